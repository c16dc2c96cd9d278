//! Writing and reading the store's records: events, telemetry batches and connections, each
//! stored once per `(robot, seq)` (one seq space for every kind, claimed in table `seqs`) or
//! connection id.

use sqlx::QueryBuilder;
use sqlx::types::Json;
use sqlx_macros::FromRow;

use super::{
    ConnectionRecord, Error, Result, RobotKey, Sample, Store, StoredEvent, StoredSample,
    from_db_seq, storable_ms, to_db_seq,
};

/// Seven parameters a row keeps one statement under SQLite's 32766 and PostgreSQL's 65535.
const SAMPLES_PER_STATEMENT: usize = 1000;

#[derive(FromRow)]
struct EventRow {
    seq: i64,
    ts_ms: i64,
    kind: String,
    severity: String,
    message: String,
    data: Json<serde_json::Value>,
}

impl From<EventRow> for StoredEvent {
    fn from(row: EventRow) -> Self {
        StoredEvent {
            seq: from_db_seq(row.seq),
            ts_ms: row.ts_ms,
            kind: row.kind,
            severity: row.severity,
            message: row.message,
            data: row.data.0,
        }
    }
}

#[derive(FromRow)]
struct SampleRow {
    seq: i64,
    metric: String,
    ts_ms: i64,
    value: f64,
}

impl From<SampleRow> for StoredSample {
    fn from(row: SampleRow) -> Self {
        StoredSample {
            seq: from_db_seq(row.seq),
            metric: row.metric,
            ts_ms: row.ts_ms,
            value: row.value,
        }
    }
}

const INSERT_EVENT: &str = "INSERT INTO events \
     (namespace, robot, seq, ts_ms, kind, severity, message, data, received_ms, bytes) \
     VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10) ON CONFLICT (namespace, robot, seq) DO NOTHING";
const INSERT_BATCH: &str = "INSERT INTO telemetry_batches \
     (namespace, robot, seq, max_ts_ms, received_ms, bytes) \
     VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (namespace, robot, seq) DO NOTHING";
/// Claims a seq for one durable message of any kind (PROTOCOL.md §6 rule 1: one sequence per
/// robot); no row affected means another message, of this kind or another, holds it.
pub(super) const CLAIM_SEQ: &str = "INSERT INTO seqs (namespace, robot, seq, received_ms) \
     VALUES ($1, $2, $3, $4) ON CONFLICT (namespace, robot, seq) DO NOTHING";
const IS_STORED: &str =
    "SELECT COUNT(*) FROM seqs WHERE namespace = $1 AND robot = $2 AND seq = $3";
const LAST_SEQ: &str = "SELECT MAX(seq) FROM (\
     SELECT MAX(seq) AS seq FROM events WHERE namespace = $1 AND robot = $2 \
     UNION ALL \
     SELECT MAX(seq) AS seq FROM telemetry_batches WHERE namespace = $1 AND robot = $2) AS m";
const INSERT_CONNECTION: &str = "INSERT INTO connections \
     (namespace, robot, gateway, protocol, address, connected_at_ms, disconnected_at_ms, reason) \
     VALUES ($1, $2, $3, $4, $5, $6, $7, $8) RETURNING id";
const CLOSE_GATEWAY_CONNECTIONS: &str = "UPDATE connections SET disconnected_at_ms = $2, reason = $3 \
     WHERE gateway = $1 AND disconnected_at_ms IS NULL";
const SELECT_EVENTS: &str = "SELECT seq, ts_ms, kind, severity, message, data FROM events \
     WHERE namespace = $1 AND robot = $2 AND seq > $3 ORDER BY seq LIMIT $4";
const SELECT_SAMPLES: &str = "SELECT seq, metric, ts_ms, value FROM samples \
     WHERE namespace = $1 AND robot = $2 AND ts_ms >= $3 ORDER BY ts_ms, seq, id LIMIT $4";
const SELECT_METRIC_SAMPLES: &str = "SELECT seq, metric, ts_ms, value FROM samples \
     WHERE namespace = $1 AND robot = $2 AND ts_ms >= $3 AND metric = $4 \
     ORDER BY ts_ms, seq, id LIMIT $5";
const SELECT_CONNECTIONS: &str = "SELECT gateway, protocol, address, connected_at_ms, disconnected_at_ms, reason \
     FROM connections WHERE namespace = $1 AND robot = $2 \
     ORDER BY connected_at_ms DESC, id DESC LIMIT $3";

impl Store {
    /// Stores an event received now; `Ok(true)` if newly stored, `Ok(false)` if `(robot, seq)`
    /// was already stored, by an event, telemetry or progress (a replay, never a second row). Once this returns `Ok`, the event is
    /// durable. `Err(QuotaExceeded)`: not stored, the robot is over its quota.
    pub async fn insert_event(&self, robot: &RobotKey, ev: &StoredEvent) -> Result<bool> {
        self.insert_event_at(robot, ev, jiff::Timestamp::now().as_millisecond())
            .await
    }

    /// [`Store::insert_event`] received at `received_ms` (Unix milliseconds, the gateway's
    /// clock), which retention goes by.
    pub async fn insert_event_at(
        &self,
        robot: &RobotKey,
        ev: &StoredEvent,
        received_ms: i64,
    ) -> Result<bool> {
        let seq = to_db_seq(ev.seq)?;
        self.refuse_while_down()?;
        let bytes = event_bytes(ev);
        self.noted(self.check_quota_unless_stored(robot, seq, 1, bytes).await)?;
        let inserted = self.noted(self.store_event(robot, seq, ev, bytes, received_ms).await)?;
        if inserted {
            self.count_stored(robot, 1, bytes);
        }
        Ok(inserted)
    }

    /// Inserts one event row by itself, with its seq's claim; `Ok(true)` if newly stored.
    pub(super) async fn insert_event_row(
        &self,
        robot: &RobotKey,
        seq: i64,
        ev: &StoredEvent,
        bytes: u64,
        received_ms: i64,
    ) -> Result<bool> {
        let inserted = with_pool!(self, pool, begin => async {
            let mut tx = pool.begin_with(begin).await?;
            let claimed = sqlx::query(CLAIM_SEQ)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .bind(received_ms)
                .execute(&mut *tx)
                .await?
                .rows_affected();
            if claimed == 0 {
                return Ok(0);
            }
            let inserted = sqlx::query(INSERT_EVENT)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .bind(storable_ms(ev.ts_ms))
                .bind(&ev.kind)
                .bind(&ev.severity)
                .bind(&ev.message)
                .bind(Json(&ev.data))
                .bind(received_ms)
                .bind(i64::try_from(bytes).unwrap_or(i64::MAX))
                .execute(&mut *tx)
                .await?
                .rows_affected();
            tx.commit().await?;
            Ok::<_, sqlx::Error>(inserted)
        }
        .await)
        .map_err(|source| Error::Insert {
            what: "event",
            robot: robot.to_string(),
            source,
        })?;
        Ok(inserted == 1)
    }

    /// Checks the quota for a new message; a replay of one already stored passes (it stores
    /// nothing), so a robot at its quota still gets its lost acks.
    async fn check_quota_unless_stored(
        &self,
        robot: &RobotKey,
        seq: i64,
        rows: u64,
        bytes: u64,
    ) -> Result<()> {
        let Err(over) = self.check_quota(robot, rows, bytes).await else {
            return Ok(());
        };
        let stored: i64 = with_pool!(self, pool => {
            sqlx::query_scalar(IS_STORED)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .fetch_one(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "stored seq",
            source,
        })?;
        if stored > 0 { Ok(()) } else { Err(over) }
    }

    /// Stores one telemetry batch received now under its `seq`, all samples or none;
    /// `Ok(false)` if that seq was already stored, by any kind of durable message (a replay:
    /// nothing is inserted twice).
    /// `Err(QuotaExceeded)`: not stored, the robot is over its quota.
    pub async fn insert_telemetry(
        &self,
        robot: &RobotKey,
        seq: u64,
        samples: &[Sample],
    ) -> Result<bool> {
        let now = jiff::Timestamp::now().as_millisecond();
        self.insert_telemetry_at(robot, seq, samples, now).await
    }

    /// [`Store::insert_telemetry`] received at `received_ms` (Unix milliseconds, the gateway's
    /// clock), which retention goes by.
    pub async fn insert_telemetry_at(
        &self,
        robot: &RobotKey,
        seq: u64,
        samples: &[Sample],
        received_ms: i64,
    ) -> Result<bool> {
        let seq = to_db_seq(seq)?;
        self.refuse_while_down()?;
        let rows = samples.len() as u64;
        let bytes = samples.iter().map(sample_bytes).sum::<u64>();
        self.noted(
            self.check_quota_unless_stored(robot, seq, rows, bytes)
                .await,
        )?;
        // An empty batch still claims its seq; retention drops it like any other.
        let max_ts_ms = samples
            .iter()
            .map(|s| storable_ms(s.ts_ms))
            .max()
            .unwrap_or(0);
        let inserted = with_pool!(self, pool, begin => async {
            let mut tx = pool.begin_with(begin).await?;
            let claimed = sqlx::query(CLAIM_SEQ)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .bind(received_ms)
                .execute(&mut *tx)
                .await?
                .rows_affected();
            if claimed == 0 {
                // Held by an earlier message of any kind: a replay. Dropping the transaction
                // rolls it back; nothing was written anyway.
                return Ok(false);
            }
            let claimed = sqlx::query(INSERT_BATCH)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .bind(max_ts_ms)
                .bind(received_ms)
                .bind(i64::try_from(bytes).unwrap_or(i64::MAX))
                .execute(&mut *tx)
                .await?
                .rows_affected();
            if claimed == 0 {
                // Dropping the transaction rolls it back; nothing was written anyway.
                return Ok(false);
            }
            for chunk in samples.chunks(SAMPLES_PER_STATEMENT) {
                let mut insert = QueryBuilder::new(
                    "INSERT INTO samples (namespace, robot, seq, metric, ts_ms, value, received_ms) ",
                );
                insert.push_values(chunk, |mut row, s| {
                    row.push_bind(&robot.namespace)
                        .push_bind(&robot.name)
                        .push_bind(seq)
                        .push_bind(&s.metric)
                        .push_bind(storable_ms(s.ts_ms))
                        .push_bind(s.value)
                        .push_bind(received_ms);
                });
                insert.build().execute(&mut *tx).await?;
            }
            tx.commit().await?;
            Ok::<_, sqlx::Error>(true)
        }
        .await)
        .map_err(|source| Error::Insert {
            what: "telemetry",
            robot: robot.to_string(),
            source,
        });
        let inserted = self.noted(inserted)?;
        if inserted {
            self.count_stored(robot, rows, bytes);
        }
        Ok(inserted)
    }

    /// Highest seq stored for the robot across events and telemetry; `None` if nothing is
    /// (retention may have deleted it).
    pub async fn last_seq(&self, robot: &RobotKey) -> Result<Option<u64>> {
        let seq: Option<i64> = with_pool!(self, pool => {
            sqlx::query_scalar(LAST_SEQ)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .fetch_one(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "last seq",
            source,
        })?;
        Ok(seq.map(from_db_seq))
    }

    /// Records a new connection; returns its id for [`Store::record_disconnect`].
    pub async fn record_connect(&self, robot: &RobotKey, rec: &ConnectionRecord) -> Result<i64> {
        with_pool!(self, pool => {
            sqlx::query_scalar(INSERT_CONNECTION)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(&rec.gateway)
                .bind(&rec.protocol)
                .bind(&rec.address)
                .bind(rec.connected_at_ms)
                .bind(rec.disconnected_at_ms)
                .bind(&rec.reason)
                .fetch_one(pool)
                .await
        })
        .map_err(|source| Error::Insert {
            what: "connection",
            robot: robot.to_string(),
            source,
        })
    }

    /// Closes every record `gateway` left open, e.g. when it restarts after a crash; returns how
    /// many it closed.
    pub async fn close_open_connections(
        &self,
        gateway: &str,
        at_ms: i64,
        reason: &str,
    ) -> Result<u64> {
        with_pool!(self, pool => {
            sqlx::query(CLOSE_GATEWAY_CONNECTIONS)
                .bind(gateway)
                .bind(at_ms)
                .bind(reason)
                .execute(pool)
                .await
                .map(|r| r.rows_affected())
        })
        .map_err(|source| Error::Update {
            what: "open connections",
            source,
        })
    }

    /// Up to `limit` events with seq above `after_seq` (all if `None`), in ascending seq.
    pub async fn events(
        &self,
        robot: &RobotKey,
        after_seq: Option<u64>,
        limit: u32,
    ) -> Result<Vec<StoredEvent>> {
        let after = match after_seq.map(i64::try_from) {
            None => -1,
            Some(Ok(seq)) => seq,
            // Nothing storable comes after it.
            Some(Err(_)) => return Ok(Vec::new()),
        };
        let rows: Vec<EventRow> = with_pool!(self, pool => {
            sqlx::query_as(SELECT_EVENTS)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(after)
                .bind(i64::from(limit))
                .fetch_all(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "events",
            source,
        })?;
        Ok(rows.into_iter().map(StoredEvent::from).collect())
    }

    /// Up to `limit` samples taken at or after `since_ms`, of one metric or all, oldest first.
    pub async fn samples(
        &self,
        robot: &RobotKey,
        metric: Option<&str>,
        since_ms: i64,
        limit: u32,
    ) -> Result<Vec<StoredSample>> {
        let rows: Vec<SampleRow> = with_pool!(self, pool => {
            let query = match metric {
                None => sqlx::query_as(SELECT_SAMPLES)
                    .bind(&robot.namespace)
                    .bind(&robot.name)
                    .bind(since_ms),
                Some(metric) => sqlx::query_as(SELECT_METRIC_SAMPLES)
                    .bind(&robot.namespace)
                    .bind(&robot.name)
                    .bind(since_ms)
                    .bind(metric),
            };
            query.bind(i64::from(limit)).fetch_all(pool).await
        })
        .map_err(|source| Error::Query {
            what: "samples",
            source,
        })?;
        Ok(rows.into_iter().map(StoredSample::from).collect())
    }

    /// Up to `limit` connection records of the robot, newest first.
    pub async fn connections(&self, robot: &RobotKey, limit: u32) -> Result<Vec<ConnectionRecord>> {
        with_pool!(self, pool => {
            sqlx::query_as(SELECT_CONNECTIONS)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(i64::from(limit))
                .fetch_all(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "connections",
            source,
        })
    }
}

/// What an event counts against the byte quota: its kind, severity, message and data as JSON.
pub(super) fn event_bytes(ev: &StoredEvent) -> u64 {
    let data = serde_json::to_string(&ev.data).map_or(0, |d| d.len());
    (ev.kind.len() + ev.severity.len() + ev.message.len() + data) as u64
}

/// What a sample counts against the byte quota: its metric name, timestamp and value.
fn sample_bytes(s: &Sample) -> u64 {
    s.metric.len() as u64 + super::quota::SAMPLE_OVERHEAD_BYTES
}
