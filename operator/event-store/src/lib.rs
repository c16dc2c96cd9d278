//! The durable event store: agent events, telemetry and connection history in SQLite (a file,
//! the default) or PostgreSQL, stored once per `(robot, seq)` so that replays are harmless.

mod error;

#[cfg(test)]
mod tests;

use std::fmt;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use sqlx::postgres::PgPool;
use sqlx::sqlite::SqlitePool;
use sqlx_macros::FromRow;

pub use self::error::{Error, Result};
use lekiwi_core::RobotKey;
/// One telemetry sample as the agent sends it; [`Store::insert_telemetry`] takes a batch.
pub use lekiwi_protocol::Sample;

/// The most one robot may keep stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Quota {
    /// Events plus telemetry samples.
    pub rows: u64,
    /// Bytes of event kind, severity, message and data, and of samples (metric name + 16).
    pub bytes: u64,
}

impl Quota {
    /// No limit.
    pub const UNLIMITED: Quota = Quota {
        rows: u64::MAX,
        bytes: u64::MAX,
    };
}

/// Which limit of the [`Quota`] a message would exceed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QuotaLimit {
    /// [`Quota::rows`].
    Rows,
    /// [`Quota::bytes`].
    Bytes,
}

impl QuotaLimit {
    /// `rows` or `bytes`: a bounded metric label.
    pub fn as_str(self) -> &'static str {
        match self {
            QuotaLimit::Rows => "rows",
            QuotaLimit::Bytes => "bytes",
        }
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
    /// The reading as the agent sent it, in the unit its metric name says (percent for
    /// `cpu_percent`).
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
    /// Events older than the cutoff.
    pub events: u64,
    /// Telemetry samples taken before the cutoff.
    pub samples: u64,
    /// Connection records closed before the cutoff (open ones are kept).
    pub connections: u64,
}

/// A handle on the event store; cheap to clone (a connection pool).
#[derive(Clone)]
// shape: one method family per file: records.rs writes and reads, batch.rs, opens.rs and closes.rs
// the batched writes, history.rs paged reads, quota.rs quotas, retention.rs pruning, connect.rs
// opening, outage.rs refusing writes while the database is out of reach.
pub struct Store {
    backend: Backend,
    /// Each robot's usage against the quota, shared by clones.
    ledger: Arc<quota::Ledger>,
    /// Batches event inserts, session opens and connection closes (see [`batch`]); `None`
    /// outside a Tokio runtime.
    batcher: Option<batch::Batcher>,
    /// Since when the database has been out of reach, shared by clones (see [`outage`]).
    outage: Arc<outage::Outage>,
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
            $crate::Backend::Sqlite($pool) => {
                // Take the write lock up front, waiting for the busy timeout; a deferred
                // transaction would fail with SQLITE_BUSY if it had to upgrade.
                let $begin = "BEGIN IMMEDIATE";
                $body
            }
            $crate::Backend::Postgres($pool) => {
                let $begin = "BEGIN";
                $body
            }
        }
    };
    ($store:expr, $pool:ident => $body:expr) => {
        match &$store.backend {
            $crate::Backend::Sqlite($pool) => $body,
            $crate::Backend::Postgres($pool) => $body,
        }
    };
}

// Declared after `with_pool!`, which they use: a `macro_rules!` macro is in scope only below
// its definition.
mod batch;
mod closes;
mod connect;
mod drain;
mod history;
mod opens;
mod outage;
mod quota;
mod records;
mod retention;

pub use self::history::{PagedSample, SampleCursor, TimeRange};
pub use self::opens::SessionStart;

impl Store {
    /// A store on `backend` without a quota.
    fn new(backend: Backend) -> Store {
        Store {
            backend,
            ledger: Arc::new(quota::Ledger::new(Quota::UNLIMITED)),
            batcher: None,
            outage: Arc::default(),
        }
        .batched()
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
}

/// The earliest time the store keeps, Unix milliseconds: `-009999-01-02T01:59:59Z`, the first
/// that RFC 3339 (and [`jiff::Timestamp`]) can write.
pub const MIN_TIME_MS: i64 = -377_705_023_201_000;
/// The latest time the store keeps, Unix milliseconds: `9999-12-30T22:00:00Z`, the last that
/// RFC 3339 (and [`jiff::Timestamp`]) can write.
pub const MAX_TIME_MS: i64 = 253_402_207_200_000;

/// A robot's time (`ts_ms`) as the store keeps it: clamped to [`MIN_TIME_MS`]..=[`MAX_TIME_MS`],
/// so that every stored time can be written as RFC 3339, held exactly by a JSON double and
/// selected by a range of RFC 3339 times. Agents send any `i64`; beyond these bounds a clock
/// says nothing anyway.
pub fn storable_ms(ts_ms: i64) -> i64 {
    ts_ms.clamp(MIN_TIME_MS, MAX_TIME_MS)
}

/// Sequence numbers are `u64` on the wire but signed 64-bit in both databases.
fn to_db_seq(seq: u64) -> Result<i64> {
    i64::try_from(seq).map_err(|_| Error::SeqOutOfRange(seq))
}

/// The schema's `CHECK (seq >= 0)` makes this lossless.
fn from_db_seq(seq: i64) -> u64 {
    u64::try_from(seq).unwrap_or_default()
}
