-- One sequence per robot, shared by events, telemetry and progress (PROTOCOL.md §6 rule 1): each
-- seq is claimed here by the first durable message stored under it, whatever its kind, and a
-- message of any kind under a claimed seq is a replay (acknowledged, not stored). A claim is
-- deleted by retention with the record it stands for.
CREATE TABLE seqs (
    namespace   TEXT    NOT NULL,
    robot       TEXT    NOT NULL,
    seq         BIGINT  NOT NULL CHECK (seq >= 0),
    received_ms BIGINT  NOT NULL,
    PRIMARY KEY (namespace, robot, seq)
);

-- The records stored so far claim their seqs. A seq stored under two kinds before keeps both
-- records; its claim lasts as long as the later one.
INSERT INTO seqs (namespace, robot, seq, received_ms)
SELECT namespace, robot, seq, MAX(received_ms) FROM (
    SELECT namespace, robot, seq, received_ms FROM events
    UNION ALL
    SELECT namespace, robot, seq, received_ms FROM telemetry_batches
) AS stored
GROUP BY namespace, robot, seq;

-- Retention deletes by receive time.
CREATE INDEX seqs_received ON seqs (received_ms);
