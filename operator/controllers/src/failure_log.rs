//! How many failed reconciles get a log line of their own. When the API server is away every
//! object fails at once: 10,000 robots wrote 14,000 warnings in the 8 seconds of one API server
//! restart. Each failure is still counted (`lekiwi_controller_reconcile_errors_total`) and
//! backed off alone; the lines are budgeted, the rest logged at debug, and the next line that is
//! written says how many were left out.

use std::sync::atomic::{AtomicU64, Ordering};

use lekiwi_core::rate::SharedBucket;

/// Failure lines written per second, sustained.
pub const LINES_PER_SECOND: f64 = 1.0;
/// Failure lines written at once before that rate applies.
pub const LINES_BURST: u32 = 10;

/// The budget of failure lines, shared by both controllers of a process.
pub struct FailureLog {
    budget: SharedBucket,
    left_out: AtomicU64,
}

impl Default for FailureLog {
    fn default() -> Self {
        Self {
            budget: SharedBucket::new(LINES_PER_SECOND, LINES_BURST),
            left_out: AtomicU64::new(0),
        }
    }
}

impl FailureLog {
    /// Whether this failure gets a line of its own: `Some(n)` with the `n` failures left out
    /// since the last line, or `None` (log it at debug) when the budget is spent.
    pub fn admit(&self) -> Option<u64> {
        if self.budget.try_take() {
            Some(self.left_out.swap(0, Ordering::Relaxed))
        } else {
            self.left_out.fetch_add(1, Ordering::Relaxed);
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn a_burst_of_failures_writes_a_few_lines_and_the_next_says_how_many_were_left_out() {
        let log = FailureLog::default();
        let admitted = (0..10_000).filter(|_| log.admit().is_some()).count();
        assert_eq!(admitted, LINES_BURST as usize);
        tokio::time::advance(std::time::Duration::from_secs(1)).await;
        assert_eq!(log.admit(), Some(10_000 - u64::from(LINES_BURST)));
        assert_eq!(
            log.admit(),
            None,
            "one line a second once the burst is spent"
        );
    }
}
