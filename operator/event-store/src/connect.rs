//! Opening the event store: the backend named by the URL, its pool, and its migrations.

use std::str::FromStr;
use std::time::Duration;

use sqlx::Connection as _;
use sqlx::migrate::Migrator;
use sqlx::postgres::{PgConnectOptions, PgConnection, PgPoolOptions};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};

use super::{Backend, Error, Result, Store};

pub(super) static SQLITE_MIGRATIONS: Migrator = sqlx_macros::migrate!("./migrations/sqlite");
static POSTGRES_MIGRATIONS: Migrator = sqlx_macros::migrate!("./migrations/postgres");

/// How long a SQLite writer waits for another to finish before giving up.
const SQLITE_BUSY_TIMEOUT: Duration = Duration::from_secs(10);
/// SQLite serialises writers anyway; a few connections let readers run beside one writer.
const SQLITE_MAX_CONNECTIONS: u32 = 4;
/// Event inserts take at most four (batched, see `batch`); the rest serve a reconnect wave's
/// connection records and `last_seq` reads, and the HTTP API's queries.
const POSTGRES_MAX_CONNECTIONS: u32 = 16;
/// How long a query waits for a free connection (or for a new one to open).
const ACQUIRE_TIMEOUT: Duration = Duration::from_secs(30);
/// How long opening the first PostgreSQL connection may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

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
        Ok(Store::new(Backend::Sqlite(pool)))
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
        Ok(Store::new(Backend::Postgres(pool)))
    }
}
