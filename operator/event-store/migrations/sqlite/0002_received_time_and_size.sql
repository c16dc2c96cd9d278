-- Retention by the gateway's receive time, not the robot's clock; and each record's size, for
-- the per-robot quota. `ts_ms` stays the robot's claim, shown as it was sent.

ALTER TABLE events ADD COLUMN received_ms INTEGER NOT NULL DEFAULT 0;
ALTER TABLE events ADD COLUMN bytes INTEGER NOT NULL DEFAULT 0;
ALTER TABLE telemetry_batches ADD COLUMN received_ms INTEGER NOT NULL DEFAULT 0;
ALTER TABLE telemetry_batches ADD COLUMN bytes INTEGER NOT NULL DEFAULT 0;
ALTER TABLE samples ADD COLUMN received_ms INTEGER NOT NULL DEFAULT 0;

-- Rows stored before this migration were received no later than now and, at best, when the
-- robot said: its claim clamped to now.
UPDATE events SET
    received_ms = MIN(ts_ms, CAST(strftime('%s', 'now') AS INTEGER) * 1000),
    bytes = length(CAST(kind AS BLOB)) + length(CAST(severity AS BLOB))
          + length(CAST(message AS BLOB)) + length(CAST(data AS BLOB));
UPDATE telemetry_batches SET
    received_ms = MIN(max_ts_ms, CAST(strftime('%s', 'now') AS INTEGER) * 1000);
UPDATE telemetry_batches SET bytes = (
    SELECT COALESCE(SUM(length(CAST(metric AS BLOB)) + 16), 0) FROM samples s
    WHERE s.namespace = telemetry_batches.namespace AND s.robot = telemetry_batches.robot
      AND s.seq = telemetry_batches.seq);
UPDATE samples SET
    received_ms = MIN(ts_ms, CAST(strftime('%s', 'now') AS INTEGER) * 1000);

DROP INDEX events_ts;
DROP INDEX telemetry_batches_ts;
DROP INDEX samples_ts;
-- Retention deletes by receive time.
CREATE INDEX events_received ON events (received_ms);
CREATE INDEX telemetry_batches_received ON telemetry_batches (received_ms);
CREATE INDEX samples_received ON samples (received_ms);
