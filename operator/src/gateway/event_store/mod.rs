//! The durable event store: agent events, telemetry and connection history in SQLite (a file,
//! the default) or PostgreSQL, stored once per `(robot, seq)` so that replays are harmless.

mod error;
#[cfg(test)]
mod tests;

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use sqlx::migrate::Migrator;
use sqlx::postgres::{PgConnectOptions, PgConnection, PgPool, PgPoolOptions};
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::types::Json;
use sqlx::{Connection as _, FromRow, QueryBuilder};
use tokio::task::JoinHandle;
use tokio::time::MissedTickBehavior;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

pub use self::error::{Error, Result};
/// One telemetry sample as the agent sends it; [`Store::insert_telemetry`] takes a batch.
pub use lekiwi_protocol::Sample;

static SQLITE_MIGRATIONS: Migrator = sqlx::migrate!("./src/gateway/event_store/migrations/sqlite");
static POSTGRES_MIGRATIONS: Migrator =
    sqlx::migrate!("./src/gateway/event_store/migrations/postgres");

/// How long a SQLite writer waits for another to finish before giving up.
const SQLITE_BUSY_TIMEOUT: Duration = Duration::from_secs(10);
/// SQLite serialises writers anyway; a few connections let readers run beside one writer.
const SQLITE_MAX_CONNECTIONS: u32 = 4;
const POSTGRES_MAX_CONNECTIONS: u32 = 10;
/// How long a query waits for a free connection (or for a new one to open).
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(30);
/// How long opening the first PostgreSQL connection may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// Six parameters a row keeps one statement under SQLite's 32766 and PostgreSQL's 65535.
const SAMPLES_PER_STATEMENT: usize = 1000;

/// A robot's identity.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RobotKey {
    /// Namespace of the Robot resource.
    pub namespace: String,
    /// Name of the Robot resource.
    pub name: String,
}

impl RobotKey {
    /// The robot `namespace/name`.
    pub fn new(namespace: impl Into<String>, name: impl Into<String>) -> Self {
        Self {
            namespace: namespace.into(),
            name: name.into(),
        }
    }
}

impl fmt::Display for RobotKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.namespace, self.name)
    }
}

pub use lekiwi_protocol::StoredEvent;

/// One stored telemetry sample.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredSample {
    /// Sequence number of the batch it arrived in.
    pub seq: u64,
    /// Metric name, e.g. `cpu_percent`.
    pub metric: String,
    /// When it was taken, Unix milliseconds.
    pub ts_ms: i64,
    /// The value.
    pub value: f64,
}

/// One agent connection to a gateway.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, FromRow)]
pub struct ConnectionRecord {
    /// Identity of the gateway replica that served it.
    pub gateway: String,
    /// Transport, e.g. `websocket`.
    pub protocol: String,
    /// The agent's address as the gateway saw it.
    pub address: Option<String>,
    /// When it was accepted, Unix milliseconds.
    pub connected_at_ms: i64,
    /// When it closed, Unix milliseconds; `None` while open.
    pub disconnected_at_ms: Option<i64>,
    /// Why it closed.
    pub reason: Option<String>,
}

/// How many records a [`Store::prune`] deleted.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PruneCounts {
    /// Events.
    pub events: u64,
    /// Telemetry samples.
    pub samples: u64,
    /// Closed connection records.
    pub connections: u64,
}

/// A handle on the event store; cheap to clone (a connection pool).
#[derive(Clone)]
pub struct Store {
    backend: Backend,
}

#[derive(Clone)]
enum Backend {
    Sqlite(SqlitePool),
    Postgres(PgPool),
}

impl fmt::Debug for Store {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Not the pool: its options may hold credentials.
        f.debug_struct("Store")
            .field("backend", &self.backend())
            .finish_non_exhaustive()
    }
}

/// Runs `$body` with `$pool` bound to the backend's pool; the SQL is written once for both
/// (`$n` placeholders and `ON CONFLICT` mean the same in each). `$begin` is the statement that
/// opens a write transaction.
macro_rules! with_pool {
    ($store:expr, $pool:ident, $begin:ident => $body:expr) => {
        match &$store.backend {
            Backend::Sqlite($pool) => {
                // Take the write lock up front, waiting for the busy timeout; a deferred
                // transaction would fail with SQLITE_BUSY if it had to upgrade.
                let $begin = "BEGIN IMMEDIATE";
                $body
            }
            Backend::Postgres($pool) => {
                let $begin = "BEGIN";
                $body
            }
        }
    };
    ($store:expr, $pool:ident => $body:expr) => {
        match &$store.backend {
            Backend::Sqlite($pool) => $body,
            Backend::Postgres($pool) => $body,
        }
    };
}

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

const INSERT_EVENT: &str = "INSERT INTO events (namespace, robot, seq, ts_ms, kind, severity, message, data) \
     VALUES ($1, $2, $3, $4, $5, $6, $7, $8) ON CONFLICT (namespace, robot, seq) DO NOTHING";
const INSERT_BATCH: &str = "INSERT INTO telemetry_batches (namespace, robot, seq, max_ts_ms) \
     VALUES ($1, $2, $3, $4) ON CONFLICT (namespace, robot, seq) DO NOTHING";
const LAST_SEQ: &str = "SELECT MAX(seq) FROM (\
     SELECT MAX(seq) AS seq FROM events WHERE namespace = $1 AND robot = $2 \
     UNION ALL \
     SELECT MAX(seq) AS seq FROM telemetry_batches WHERE namespace = $1 AND robot = $2) AS m";
const INSERT_CONNECTION: &str = "INSERT INTO connections \
     (namespace, robot, gateway, protocol, address, connected_at_ms, disconnected_at_ms, reason) \
     VALUES ($1, $2, $3, $4, $5, $6, $7, $8) RETURNING id";
// The first disconnect wins: a late duplicate must not rewrite when or why it closed.
const CLOSE_CONNECTION: &str = "UPDATE connections SET disconnected_at_ms = $2, reason = $3 \
     WHERE id = $1 AND disconnected_at_ms IS NULL";
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
const PRUNE_EVENTS: &str = "DELETE FROM events WHERE ts_ms < $1";
const PRUNE_SAMPLES: &str = "DELETE FROM samples WHERE ts_ms < $1";
const PRUNE_BATCHES: &str = "DELETE FROM telemetry_batches WHERE max_ts_ms < $1";
const PRUNE_CONNECTIONS: &str =
    "DELETE FROM connections WHERE disconnected_at_ms IS NOT NULL AND disconnected_at_ms < $1";

impl Store {
    /// Opens the store at `url` (`sqlite:///abs/path.db`, `sqlite://rel.db`, `sqlite::memory:`
    /// or `postgres://...`) and applies pending migrations. A SQLite file (and its directory) is
    /// created if missing and runs in WAL mode with `synchronous=FULL`, so a stored record is on
    /// disk before it is acknowledged.
    pub async fn connect(url: &str) -> Result<Store> {
        let scheme = url.split_once(':').map(|(scheme, _)| scheme).filter(|s| {
            !s.is_empty()
                && s.chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.'))
        });
        match scheme {
            Some("sqlite") => Self::connect_sqlite(url).await,
            Some("postgres" | "postgresql") => Self::connect_postgres(url).await,
            Some(other) => Err(Error::UnsupportedUrl {
                reason: format!("unknown scheme {other:?}"),
            }),
            None => Err(Error::UnsupportedUrl {
                reason: "no scheme".into(),
            }),
        }
    }

    async fn connect_sqlite(url: &str) -> Result<Store> {
        let unsupported = |reason: String| Error::UnsupportedUrl { reason };
        let rest = url
            .trim_start_matches("sqlite://")
            .trim_start_matches("sqlite:");
        let (database, params) = rest.split_once('?').unwrap_or((rest, ""));
        if database.is_empty() {
            return Err(unsupported("no SQLite file path".into()));
        }
        let in_memory = database == ":memory:" || params.split('&').any(|p| p == "mode=memory");
        let options = SqliteConnectOptions::from_str(url)
            .map_err(|e| unsupported(e.to_string()))?
            .busy_timeout(SQLITE_BUSY_TIMEOUT)
            .foreign_keys(true);
        let pool = if in_memory {
            // The database lives as long as one connection to it: keep exactly one, forever.
            SqlitePoolOptions::new()
                .max_connections(1)
                .min_connections(1)
                .idle_timeout(None)
                .max_lifetime(None)
                .connect_with(options)
                .await
        } else {
            let options = options
                .create_if_missing(true)
                .journal_mode(SqliteJournalMode::Wal)
                .synchronous(SqliteSynchronous::Full);
            if let Some(dir) = options.get_filename().parent()
                && !dir.as_os_str().is_empty()
            {
                tokio::fs::create_dir_all(dir)
                    .await
                    .map_err(|source| Error::CreateDir {
                        path: dir.to_owned(),
                        source,
                    })?;
            }
            SqlitePoolOptions::new()
                .max_connections(SQLITE_MAX_CONNECTIONS)
                .acquire_timeout(ACQUIRE_TIMEOUT)
                .connect_with(options)
                .await
        }
        .map_err(|source| Error::Connect {
            backend: "sqlite",
            source,
        })?;
        SQLITE_MIGRATIONS
            .run(&pool)
            .await
            .map_err(|source| Error::Migrate {
                backend: "sqlite",
                source,
            })?;
        Ok(Store {
            backend: Backend::Sqlite(pool),
        })
    }

    async fn connect_postgres(url: &str) -> Result<Store> {
        let options = PgConnectOptions::from_str(url).map_err(|e| Error::UnsupportedUrl {
            reason: e.to_string(),
        })?;
        // One connection first, so a wrong host, password or database fails now with its own
        // message; a pool would retry a refused connection until it timed out.
        let mut conn = tokio::time::timeout(CONNECT_TIMEOUT, PgConnection::connect_with(&options))
            .await
            .map_err(|_| Error::ConnectTimeout {
                backend: "postgres",
                after: CONNECT_TIMEOUT,
            })?
            .map_err(|source| Error::Connect {
                backend: "postgres",
                source,
            })?;
        // Migrations take an advisory lock, so replicas starting together apply them once.
        POSTGRES_MIGRATIONS
            .run(&mut conn)
            .await
            .map_err(|source| Error::Migrate {
                backend: "postgres",
                source,
            })?;
        // Best effort: the session ends when the socket closes either way.
        let _ = conn.close().await;
        let pool = PgPoolOptions::new()
            .max_connections(POSTGRES_MAX_CONNECTIONS)
            .acquire_timeout(ACQUIRE_TIMEOUT)
            .connect_lazy_with(options);
        Ok(Store {
            backend: Backend::Postgres(pool),
        })
    }

    /// `"sqlite"` or `"postgres"`.
    pub fn backend(&self) -> &'static str {
        match self.backend {
            Backend::Sqlite(_) => "sqlite",
            Backend::Postgres(_) => "postgres",
        }
    }

    /// Closes every connection, waiting for those in use to be returned. Clones of this store
    /// fail afterwards.
    pub async fn close(&self) {
        with_pool!(self, pool => pool.close().await);
    }

    /// Stores an event; `Ok(true)` if newly stored, `Ok(false)` if `(robot, seq)` was already
    /// stored (a replay, never a second row). Once this returns `Ok`, the event is durable.
    pub async fn insert_event(&self, robot: &RobotKey, ev: &StoredEvent) -> Result<bool> {
        let seq = to_db_seq(ev.seq)?;
        let inserted = with_pool!(self, pool => {
            sqlx::query(INSERT_EVENT)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .bind(ev.ts_ms)
                .bind(&ev.kind)
                .bind(&ev.severity)
                .bind(&ev.message)
                .bind(Json(&ev.data))
                .execute(pool)
                .await
                .map(|r| r.rows_affected())
        })
        .map_err(|source| Error::Insert {
            what: "event",
            robot: robot.to_string(),
            source,
        })?;
        Ok(inserted == 1)
    }

    /// Stores one telemetry batch under its `seq`, all samples or none; `Ok(false)` if that seq
    /// was already stored (a replay: nothing is inserted twice).
    pub async fn insert_telemetry(
        &self,
        robot: &RobotKey,
        seq: u64,
        samples: &[Sample],
    ) -> Result<bool> {
        let seq = to_db_seq(seq)?;
        // An empty batch still claims its seq; retention drops it on its next round.
        let max_ts_ms = samples.iter().map(|s| s.ts_ms).max().unwrap_or(0);
        let inserted = with_pool!(self, pool, begin => async {
            let mut tx = pool.begin_with(begin).await?;
            let claimed = sqlx::query(INSERT_BATCH)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(seq)
                .bind(max_ts_ms)
                .execute(&mut *tx)
                .await?
                .rows_affected();
            if claimed == 0 {
                // Dropping the transaction rolls it back; nothing was written anyway.
                return Ok(false);
            }
            for chunk in samples.chunks(SAMPLES_PER_STATEMENT) {
                let mut insert = QueryBuilder::new(
                    "INSERT INTO samples (namespace, robot, seq, metric, ts_ms, value) ",
                );
                insert.push_values(chunk, |mut row, s| {
                    row.push_bind(&robot.namespace)
                        .push_bind(&robot.name)
                        .push_bind(seq)
                        .push_bind(&s.metric)
                        .push_bind(s.ts_ms)
                        .push_bind(s.value);
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
        })?;
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

    /// Marks connection `id` closed at `at_ms`. A connection already closed keeps its first
    /// time and reason; an unknown id changes nothing.
    pub async fn record_disconnect(&self, id: i64, at_ms: i64, reason: &str) -> Result<()> {
        with_pool!(self, pool => {
            sqlx::query(CLOSE_CONNECTION)
                .bind(id)
                .bind(at_ms)
                .bind(reason)
                .execute(pool)
                .await
                .map(|_| ())
        })
        .map_err(|source| Error::Update {
            what: "connection",
            source,
        })?;
        Ok(())
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

    /// Deletes events, samples and closed connection records older than `older_than_ms` (each
    /// by its own timestamp: event time, sample time, disconnect time), in one transaction.
    /// Open connections are kept however old.
    pub async fn prune(&self, older_than_ms: i64) -> Result<PruneCounts> {
        with_pool!(self, pool, begin => async {
            let mut tx = pool.begin_with(begin).await?;
            let mut counts = PruneCounts::default();
            for (sql, count) in [
                (PRUNE_EVENTS, Some(&mut counts.events)),
                (PRUNE_SAMPLES, Some(&mut counts.samples)),
                (PRUNE_BATCHES, None),
                (PRUNE_CONNECTIONS, Some(&mut counts.connections)),
            ] {
                let deleted = sqlx::query(sql)
                    .bind(older_than_ms)
                    .execute(&mut *tx)
                    .await?
                    .rows_affected();
                if let Some(count) = count {
                    *count = deleted;
                }
            }
            tx.commit().await?;
            Ok(counts)
        }
        .await)
        .map_err(Error::Prune)
    }

    /// Runs `prune(now - max_age)` now and then every `every` until `cancel` fires, logging
    /// what it deleted. A failed round is logged and retried on the next.
    pub fn spawn_retention(
        &self,
        max_age: Duration,
        every: Duration,
        cancel: CancellationToken,
    ) -> JoinHandle<()> {
        let store = self.clone();
        let max_age_ms = i64::try_from(max_age.as_millis()).unwrap_or(i64::MAX);
        tokio::spawn(async move {
            // A zero period would make `interval` panic.
            let mut ticks = tokio::time::interval(every.max(Duration::from_millis(1)));
            ticks.set_missed_tick_behavior(MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    () = cancel.cancelled() => break,
                    _ = ticks.tick() => {}
                }
                let cutoff = jiff::Timestamp::now()
                    .as_millisecond()
                    .saturating_sub(max_age_ms);
                // Cancelling mid-prune rolls its transaction back: nothing half-deleted.
                let outcome = tokio::select! {
                    () = cancel.cancelled() => break,
                    outcome = store.prune(cutoff) => outcome,
                };
                match outcome {
                    Ok(counts) if counts == PruneCounts::default() => {
                        debug!(
                            cutoff_ms = cutoff,
                            "event store retention: nothing to delete"
                        );
                    }
                    Ok(counts) => info!(
                        cutoff_ms = cutoff,
                        events = counts.events,
                        samples = counts.samples,
                        connections = counts.connections,
                        "event store retention deleted old records"
                    ),
                    Err(e) => {
                        warn!(error = %e, "event store retention failed; retrying next round")
                    }
                }
            }
        })
    }
}

/// Sequence numbers are `u64` on the wire but signed 64-bit in both databases.
fn to_db_seq(seq: u64) -> Result<i64> {
    i64::try_from(seq).map_err(|_| Error::SeqOutOfRange(seq))
}

/// The schema's `CHECK (seq >= 0)` makes this lossless.
fn from_db_seq(seq: i64) -> u64 {
    u64::try_from(seq).unwrap_or_default()
}
