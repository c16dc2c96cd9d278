//! A reconcile plans only from stores that show the previous reconcile's own writes (of the
//! same deployment). It does not wait for them holding a worker: it returns at once, to be run
//! again when the watch that brings the writes wakes the deployment (or, at the latest, when
//! [`CATCH_UP`] has passed, and then it plans on). A worker that slept in a reconcile for the
//! watches kept every other deployment waiting behind it.

use std::collections::HashMap;
use std::hash::Hash;
use std::sync::Mutex;
use std::time::Duration;

use tokio::time::Instant;
use tracing::warn;

/// Longest a deployment waits for the stores to show its own writes.
pub const CATCH_UP: Duration = Duration::from_secs(5);

/// Each key's last writes (`W`) and when they were made, until the stores show them.
pub struct CatchUp<K, W> {
    pending: Mutex<HashMap<K, (Instant, W)>>,
}

impl<K, W> Default for CatchUp<K, W> {
    fn default() -> Self {
        Self {
            pending: Mutex::new(HashMap::new()),
        }
    }
}

impl<K: Eq + Hash, W> CatchUp<K, W> {
    /// `key`'s reconcile wrote `writes` just now.
    pub fn wrote(&self, key: K, writes: W) {
        self.lock().insert(key, (Instant::now(), writes));
    }

    /// How long to wait before planning `key` again, or `None` to plan now: its last writes are
    /// in the stores (`seen`), or were made [`CATCH_UP`] ago and the plan goes on without.
    pub fn behind(&self, key: &K, seen: impl FnOnce(&W) -> bool) -> Option<Duration> {
        let mut pending = self.lock();
        let (at, writes) = pending.get(key)?;
        let left = CATCH_UP.saturating_sub(at.elapsed());
        if seen(writes) {
            pending.remove(key);
            return None;
        }
        if left.is_zero() {
            pending.remove(key);
            warn!("the stores do not show the last reconcile's writes yet; planning on");
            return None;
        }
        Some(left)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<K, (Instant, W)>> {
        self.pending.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Behind while the stores lack the writes, for CATCH_UP at most; never behind once seen.
    #[tokio::test(start_paused = true)]
    async fn a_plan_waits_for_its_own_writes_without_sleeping_and_for_catch_up_at_most() {
        let catch_up: CatchUp<&str, u32> = CatchUp::default();
        assert_eq!(catch_up.behind(&"d1", |_| false), None, "nothing written");
        catch_up.wrote("d1", 7);
        assert_eq!(catch_up.behind(&"d1", |w| *w == 7), None, "seen");
        assert_eq!(
            catch_up.behind(&"d1", |_| false),
            None,
            "forgotten once seen"
        );
        catch_up.wrote("d1", 8);
        tokio::time::advance(Duration::from_secs(1)).await;
        assert_eq!(
            catch_up.behind(&"d1", |_| false),
            Some(CATCH_UP - Duration::from_secs(1))
        );
        assert_eq!(catch_up.behind(&"d2", |_| false), None, "others plan on");
        tokio::time::advance(CATCH_UP).await;
        assert_eq!(catch_up.behind(&"d1", |_| false), None, "gave up waiting");
    }
}
