-- The durable event store on SQLite: agent events, telemetry and connection history.
-- Every durable agent message is unique per (namespace, robot, seq), so a replay is a no-op.

CREATE TABLE events (
    id         INTEGER PRIMARY KEY,
    namespace  TEXT    NOT NULL,
    robot      TEXT    NOT NULL,
    seq        INTEGER NOT NULL CHECK (seq >= 0),
    ts_ms      INTEGER NOT NULL,
    kind       TEXT    NOT NULL,
    severity   TEXT    NOT NULL,
    message    TEXT    NOT NULL,
    data       TEXT    NOT NULL CHECK (json_valid(data)),
    UNIQUE (namespace, robot, seq)
);
-- Retention deletes by age.
CREATE INDEX events_ts ON events (ts_ms);

-- One row per telemetry batch, the unit a seq acknowledges.
CREATE TABLE telemetry_batches (
    id         INTEGER PRIMARY KEY,
    namespace  TEXT    NOT NULL,
    robot      TEXT    NOT NULL,
    seq        INTEGER NOT NULL CHECK (seq >= 0),
    -- Newest sample of the batch: once it is older than the retention cutoff, so are all samples.
    max_ts_ms  INTEGER NOT NULL,
    UNIQUE (namespace, robot, seq)
);
CREATE INDEX telemetry_batches_ts ON telemetry_batches (max_ts_ms);

CREATE TABLE samples (
    id         INTEGER PRIMARY KEY,
    namespace  TEXT    NOT NULL,
    robot      TEXT    NOT NULL,
    seq        INTEGER NOT NULL CHECK (seq >= 0),
    metric     TEXT    NOT NULL,
    ts_ms      INTEGER NOT NULL,
    value      REAL    NOT NULL
);
CREATE INDEX samples_robot_metric_ts ON samples (namespace, robot, metric, ts_ms);
CREATE INDEX samples_robot_ts ON samples (namespace, robot, ts_ms);
CREATE INDEX samples_ts ON samples (ts_ms);

CREATE TABLE connections (
    id                  INTEGER PRIMARY KEY,
    namespace           TEXT    NOT NULL,
    robot               TEXT    NOT NULL,
    gateway             TEXT    NOT NULL,
    protocol            TEXT    NOT NULL,
    address             TEXT,
    connected_at_ms     INTEGER NOT NULL,
    disconnected_at_ms  INTEGER,
    reason              TEXT
);
CREATE INDEX connections_robot ON connections (namespace, robot, connected_at_ms);
CREATE INDEX connections_closed ON connections (disconnected_at_ms);
-- A restarted gateway closes the records its previous run left open.
CREATE INDEX connections_open ON connections (gateway) WHERE disconnected_at_ms IS NULL;
