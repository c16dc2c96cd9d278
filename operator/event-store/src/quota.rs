//! Per-robot quotas: how many rows (events and telemetry samples) and bytes one robot may keep
//! in the store within the retention window. Usage is counted in memory and re-read from the
//! store once per robot per [`REFRESH`] (and after each prune), never per message.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::{Error, Quota, QuotaLimit, Result, RobotKey, Store};

/// How long a robot's usage counted in memory is trusted before it is read from the store
/// again (other gateway replicas store for the same robot, retention deletes).
const REFRESH: Duration = Duration::from_secs(300);

/// Bytes a telemetry sample counts besides its metric name: its timestamp and value.
pub(super) const SAMPLE_OVERHEAD_BYTES: u64 = 16;

const USAGE: &str = "SELECT \
     (SELECT COUNT(*) FROM events WHERE namespace = $1 AND robot = $2) \
     + (SELECT COUNT(*) FROM samples WHERE namespace = $1 AND robot = $2), \
     CAST((SELECT COALESCE(SUM(bytes), 0) FROM events WHERE namespace = $1 AND robot = $2) AS BIGINT) \
     + CAST((SELECT COALESCE(SUM(bytes), 0) FROM telemetry_batches WHERE namespace = $1 AND robot = $2) AS BIGINT)";

#[derive(Clone, Copy)]
struct Usage {
    rows: u64,
    bytes: u64,
    read_at: Instant,
}

/// The quota and each robot's usage as last counted.
pub(super) struct Ledger {
    quota: Quota,
    robots: Mutex<HashMap<RobotKey, Usage>>,
}

impl Ledger {
    pub(super) fn new(quota: Quota) -> Self {
        Self {
            quota,
            robots: Mutex::default(),
        }
    }

    /// Forgets every count, e.g. after retention deleted records.
    pub(super) fn forget(&self) {
        self.lock().clear();
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<RobotKey, Usage>> {
        // A panic while holding it leaves plain counters behind, still usable.
        self.robots.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Store {
    /// The quota this store enforces.
    pub fn quota(&self) -> Quota {
        self.ledger.quota
    }

    /// This store enforcing `quota` per robot (clones share the counts).
    pub fn with_quota(mut self, quota: Quota) -> Store {
        self.ledger = std::sync::Arc::new(Ledger::new(quota));
        self
    }

    /// `Err(QuotaExceeded)` when storing `rows` more rows of `bytes` would take `robot` over
    /// its quota.
    pub(super) async fn check_quota(&self, robot: &RobotKey, rows: u64, bytes: u64) -> Result<()> {
        let quota = self.ledger.quota;
        if quota == Quota::UNLIMITED {
            return Ok(());
        }
        let known = self.ledger.lock().get(robot).copied();
        let usage = match known.filter(|u| u.read_at.elapsed() < REFRESH) {
            Some(usage) => usage,
            None => {
                let usage = self.read_usage(robot).await?;
                self.ledger.lock().insert(robot.clone(), usage);
                usage
            }
        };
        let limit = if usage.rows.saturating_add(rows) > quota.rows {
            QuotaLimit::Rows
        } else if usage.bytes.saturating_add(bytes) > quota.bytes {
            QuotaLimit::Bytes
        } else {
            return Ok(());
        };
        Err(Error::QuotaExceeded {
            robot: robot.to_string(),
            limit,
            quota,
        })
    }

    /// Counts `rows` and `bytes` just stored for `robot`.
    pub(super) fn count_stored(&self, robot: &RobotKey, rows: u64, bytes: u64) {
        if let Some(usage) = self.ledger.lock().get_mut(robot) {
            usage.rows = usage.rows.saturating_add(rows);
            usage.bytes = usage.bytes.saturating_add(bytes);
        }
    }

    async fn read_usage(&self, robot: &RobotKey) -> Result<Usage> {
        let (rows, bytes): (i64, i64) = with_pool!(self, pool => {
            sqlx::query_as(USAGE)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .fetch_one(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "quota usage",
            source,
        })?;
        Ok(Usage {
            rows: u64::try_from(rows).unwrap_or_default(),
            bytes: u64::try_from(bytes).unwrap_or_default(),
            read_at: Instant::now(),
        })
    }
}
