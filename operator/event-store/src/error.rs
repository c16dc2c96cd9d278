//! The event store's error type.

use std::path::PathBuf;

/// Everything that can fail in the event store. Messages never contain the database URL, which
/// may hold a password.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The URL names no backend we support, or is malformed.
    #[error(
        "unsupported event store URL ({reason}); expected sqlite:///abs/path.db, sqlite://rel.db, sqlite::memory: or postgres://user@host/db"
    )]
    UnsupportedUrl {
        /// What is wrong with it.
        reason: String,
    },
    /// The directory for the SQLite file could not be created.
    #[error("cannot create directory {path} for the SQLite event store: {source}")]
    CreateDir {
        /// The directory the SQLite URL's file lives in.
        path: PathBuf,
        /// The operating system's error, e.g. permission denied.
        source: std::io::Error,
    },
    /// Opening the database failed.
    #[error("cannot connect to the {backend} event store: {source}")]
    Connect {
        /// `sqlite` or `postgres`.
        backend: &'static str,
        /// The database driver's error.
        source: sqlx::Error,
    },
    /// The database did not answer in time.
    #[error("cannot connect to the {backend} event store: no answer within {after:?}")]
    ConnectTimeout {
        /// `sqlite` or `postgres`.
        backend: &'static str,
        /// How long we waited.
        after: std::time::Duration,
    },
    /// Applying the schema migrations failed.
    #[error("cannot migrate the {backend} event store: {source}")]
    Migrate {
        /// `sqlite` or `postgres`.
        backend: &'static str,
        /// Which migration failed, and the database's error.
        source: sqlx::migrate::MigrateError,
    },
    /// Storing something failed; it was not stored and must not be acknowledged.
    #[error("cannot store {what} of robot {robot}: {source}")]
    Insert {
        /// What was being stored, e.g. `event`.
        what: &'static str,
        /// `namespace/name` of the robot.
        robot: String,
        /// The database driver's error.
        source: sqlx::Error,
    },
    /// Updating a stored record failed.
    #[error("cannot update {what}: {source}")]
    Update {
        /// What was being updated.
        what: &'static str,
        /// The database driver's error.
        source: sqlx::Error,
    },
    /// Reading failed.
    #[error("cannot read {what} from the event store: {source}")]
    Query {
        /// What was being read.
        what: &'static str,
        /// The database driver's error.
        source: sqlx::Error,
    },
    /// Deleting old records failed.
    #[error("cannot prune the event store: {0}")]
    Prune(#[source] sqlx::Error),
    /// Storing the message would take the robot over its quota; it was not stored.
    #[error(
        "robot {robot} is over its event store quota of {rows} rows and {bytes} bytes ({which} exceeded)",
        rows = quota.rows,
        bytes = quota.bytes,
        which = limit.as_str()
    )]
    QuotaExceeded {
        /// `namespace/name` of the robot.
        robot: String,
        /// Which limit the message would exceed.
        limit: super::QuotaLimit,
        /// The quota in force.
        quota: super::Quota,
    },
    /// A second copy of a message (a resend) waited in the same batch as the first, whose
    /// insert failed: it was not stored either, and must not be acknowledged.
    #[error("message {seq} of robot {robot} was not stored: its first copy failed")]
    NotStored {
        /// `namespace/name` of the robot.
        robot: String,
        /// The message's sequence number.
        seq: i64,
    },
    /// The database has been out of reach since a write failed for want of a connection;
    /// nothing was tried: writes are refused until a probe finds the database again.
    #[error("the {backend} event store has been out of reach for {for_s} s; not stored")]
    Unavailable {
        /// `sqlite` or `postgres`.
        backend: &'static str,
        /// Seconds since the outage began.
        for_s: u64,
    },
    /// The store was closed (the gateway is stopping) before the message was stored.
    #[error("the event store is closed")]
    Closed,
    /// A sequence number too large for the database's signed 64-bit integers.
    #[error("sequence number {0} is out of range: the event store holds at most {max}", max = i64::MAX)]
    SeqOutOfRange(u64),
}

impl Error {
    /// Whether the write was refused, untried, because the database is in an outage
    /// ([`Error::Unavailable`]): the caller keeps the message and tries again later.
    pub fn is_unavailable(&self) -> bool {
        matches!(self, Error::Unavailable { .. })
    }

    /// Whether this failure says the database could not be reached at all (no connection in
    /// time, a broken socket, the server shutting down), not that it refused one statement.
    pub(crate) fn unreachable(&self) -> bool {
        match self {
            Error::Insert { source, .. }
            | Error::Update { source, .. }
            | Error::Query { source, .. }
            | Error::Prune(source) => unreachable(source),
            Error::Unavailable { .. } => true,
            _ => false,
        }
    }
}

/// No connection in time, I/O or TLS failing, or PostgreSQL's connection exceptions (class 08)
/// and shutdown codes (57P01-57P03).
fn unreachable(e: &sqlx::Error) -> bool {
    match e {
        sqlx::Error::PoolTimedOut | sqlx::Error::Io(_) | sqlx::Error::Tls(_) => true,
        sqlx::Error::Database(db) => db.code().is_some_and(|code| {
            code.starts_with("08") || matches!(code.as_ref(), "57P01" | "57P02" | "57P03")
        }),
        _ => false,
    }
}

/// Result with the event store's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
