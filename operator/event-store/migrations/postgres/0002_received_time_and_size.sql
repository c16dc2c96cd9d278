-- Retention by the gateway's receive time, not the robot's clock; and each record's size, for
-- the per-robot quota. `ts_ms` stays the robot's claim, shown as it was sent.

ALTER TABLE events ADD COLUMN received_ms BIGINT NOT NULL DEFAULT 0;
ALTER TABLE events ADD COLUMN bytes BIGINT NOT NULL DEFAULT 0;
ALTER TABLE telemetry_batches ADD COLUMN received_ms BIGINT NOT NULL DEFAULT 0;
ALTER TABLE telemetry_batches ADD COLUMN bytes BIGINT NOT NULL DEFAULT 0;
ALTER TABLE samples ADD COLUMN received_ms BIGINT NOT NULL DEFAULT 0;

-- Rows stored before this migration were received no later than now and, at best, when the
-- robot said: its claim clamped to now.
UPDATE events SET
    received_ms = LEAST(ts_ms, (EXTRACT(EPOCH FROM now()) * 1000)::BIGINT),
    bytes = octet_length(kind) + octet_length(severity) + octet_length(message)
          + octet_length(data::TEXT);
UPDATE telemetry_batches SET
    received_ms = LEAST(max_ts_ms, (EXTRACT(EPOCH FROM now()) * 1000)::BIGINT);
UPDATE telemetry_batches b SET bytes = (
    SELECT COALESCE(SUM(octet_length(s.metric) + 16), 0) FROM samples s
    WHERE s.namespace = b.namespace AND s.robot = b.robot AND s.seq = b.seq);
UPDATE samples SET
    received_ms = LEAST(ts_ms, (EXTRACT(EPOCH FROM now()) * 1000)::BIGINT);

DROP INDEX events_ts;
DROP INDEX telemetry_batches_ts;
DROP INDEX samples_ts;
-- Retention deletes by receive time.
CREATE INDEX events_received ON events (received_ms);
CREATE INDEX telemetry_batches_received ON telemetry_batches (received_ms);
CREATE INDEX samples_received ON samples (received_ms);
