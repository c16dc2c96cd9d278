//! The downloads reading each blob now, so that garbage collection never removes a blob in the
//! middle of one: a download holds a [`ReadGuard`] while it streams, and a blob counts as busy
//! for a grace period (default [`RECENT`]) after its last read ended too, for a robot that
//! resumes a broken download or fetches the next file of the same release.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// How long a blob stays busy after its last download ended by default: a robot resuming by
/// byte range comes back within its retry backoff, well inside this.
pub const RECENT: Duration = Duration::from_secs(300);

#[derive(Default)]
struct Reads {
    /// Downloads streaming the blob now.
    open: usize,
    /// When the last of them ended.
    ended: Option<Instant>,
}

/// Open and recent reads per blob digest; cheap to clone (shared).
#[derive(Clone)]
pub struct Readers {
    reads: Arc<Mutex<HashMap<String, Reads>>>,
    grace: Duration,
}

impl Default for Readers {
    fn default() -> Self {
        Self::new(RECENT)
    }
}

impl Readers {
    /// Reads that keep a blob busy for `grace` after they end.
    pub fn new(grace: Duration) -> Self {
        Self {
            reads: Arc::default(),
            grace,
        }
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<String, Reads>> {
        self.reads.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Marks `digest` as read until the guard drops.
    pub fn begin(&self, digest: &str) -> ReadGuard {
        let mut reads = self.lock();
        // Forget blobs whose last read is long over; the map stays as small as recent reads.
        let grace = self.grace;
        reads.retain(|_, r| r.open > 0 || r.ended.is_some_and(|e| e.elapsed() < grace));
        reads.entry(digest.to_owned()).or_default().open += 1;
        ReadGuard {
            readers: self.clone(),
            digest: digest.to_owned(),
        }
    }

    /// Whether a download reads `digest` now or ended less than the grace period ago.
    pub fn busy(&self, digest: &str) -> bool {
        self.busy_in(&self.lock(), digest)
    }

    fn busy_in(&self, reads: &HashMap<String, Reads>, digest: &str) -> bool {
        reads
            .get(digest)
            .is_some_and(|r| r.open > 0 || r.ended.is_some_and(|e| e.elapsed() < self.grace))
    }

    /// Runs `remove` for `digest` unless it is busy, with new reads held off meanwhile;
    /// returns `None` when it was busy.
    pub fn unless_busy<T>(&self, digest: &str, remove: impl FnOnce() -> T) -> Option<T> {
        let reads = self.lock();
        (!self.busy_in(&reads, digest)).then(remove)
    }
}

/// A download in progress; dropping it ends the read.
pub struct ReadGuard {
    readers: Readers,
    digest: String,
}

impl Drop for ReadGuard {
    fn drop(&mut self) {
        let mut reads = self.readers.lock();
        if let Some(r) = reads.get_mut(&self.digest) {
            r.open = r.open.saturating_sub(1);
            r.ended = Some(Instant::now());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_blob_is_busy_while_read_and_for_a_while_after() {
        let readers = Readers::default();
        assert!(!readers.busy("a"));
        let guard = readers.begin("a");
        assert!(readers.busy("a"));
        assert_eq!(readers.unless_busy("a", || ()), None);
        drop(guard);
        // Ended just now: a resuming robot is still protected.
        assert!(readers.busy("a"));
        assert_eq!(readers.unless_busy("b", || 1), Some(1));
    }
}
