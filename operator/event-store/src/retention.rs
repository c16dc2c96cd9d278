//! Retention: deleting records older than the configured age, now and periodically.

use std::time::Duration;

use tokio::task::JoinHandle;
use tokio::time::MissedTickBehavior;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::{Error, PruneCounts, Result, Store};

// By the gateway's receive time: a robot's clock (`ts_ms`) in the future or stuck in 1970 must
// neither keep its records forever nor lose fresh ones.
const PRUNE_EVENTS: &str = "DELETE FROM events WHERE received_ms < $1";
const PRUNE_SAMPLES: &str = "DELETE FROM samples WHERE received_ms < $1";
const PRUNE_BATCHES: &str = "DELETE FROM telemetry_batches WHERE received_ms < $1";
// A seq's claim goes with its record: the seq counts as stored exactly as long as that does.
const PRUNE_SEQS: &str = "DELETE FROM seqs WHERE received_ms < $1";
const PRUNE_CONNECTIONS: &str =
    "DELETE FROM connections WHERE disconnected_at_ms IS NOT NULL AND disconnected_at_ms < $1";

impl Store {
    /// Deletes events and telemetry received before `older_than_ms` (the gateway's clock, not
    /// the robot's `ts_ms`) and connection records closed before it, in one transaction. Open
    /// connections are kept however old. Quota counts are read from the store again afterwards.
    pub async fn prune(&self, older_than_ms: i64) -> Result<PruneCounts> {
        with_pool!(self, pool, begin => async {
            let mut tx = pool.begin_with(begin).await?;
            let mut counts = PruneCounts::default();
            for (sql, count) in [
                (PRUNE_EVENTS, Some(&mut counts.events)),
                (PRUNE_SAMPLES, Some(&mut counts.samples)),
                (PRUNE_BATCHES, None),
                (PRUNE_SEQS, None),
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
        .inspect(|_| self.ledger.forget())
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
