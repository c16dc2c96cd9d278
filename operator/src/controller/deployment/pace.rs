//! A deployment's status written at a bounded rate however many robots move: a change of its
//! counters alone (updated, failed, pending, the per-robot rows, the message) waits until
//! [`STATUS_PERIOD`] has passed since this process last wrote it; anything else (phase, batch,
//! conditions, generation, an Event, the end of the rollout) is written at once. Robot writes
//! are not held: the marks on robots are what a rollout resumes from.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Duration;

use lekiwi_crds::RobotDeploymentStatus;
use tokio::time::Instant;

use super::plan::Plan;

/// The least time between two status writes of one deployment that only count robots.
pub const STATUS_PERIOD: Duration = Duration::from_secs(3);

/// When this process last wrote each deployment's status, by namespace and name.
#[derive(Debug, Default)]
pub struct Pace {
    last: Mutex<HashMap<(String, String), Instant>>,
}

impl Pace {
    /// How long the status of `plan` waits before it is written, or `None` to write it now.
    pub fn wait(
        &self,
        key: (&str, &str),
        stored: Option<&RobotDeploymentStatus>,
        plan: &Plan,
        now: Instant,
    ) -> Option<Duration> {
        let stored = stored?;
        if !plan.events.is_empty() || plan.finished || !only_counts(stored, &plan.status) {
            return None;
        }
        let last = self.lock();
        let since = now.duration_since(*last.get(&(key.0.to_owned(), key.1.to_owned()))?);
        STATUS_PERIOD
            .checked_sub(since)
            .filter(|left| !left.is_zero())
    }

    /// The status was written at `now`.
    pub fn written(&self, key: (&str, &str), now: Instant) {
        self.lock()
            .insert((key.0.to_owned(), key.1.to_owned()), now);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Instant>> {
        self.last.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Whether `a` and `b` differ at most in what counts robots as they move.
fn only_counts(a: &RobotDeploymentStatus, b: &RobotDeploymentStatus) -> bool {
    let strip = |s: &RobotDeploymentStatus| {
        let mut s = s.clone();
        (s.updated, s.failed, s.skipped, s.pending, s.superseded) = (0, 0, 0, 0, 0);
        (s.progress, s.message) = (None, None);
        s.robots.clear();
        for c in &mut s.conditions {
            c.message = Default::default();
        }
        s
    };
    strip(a) == strip(b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::deployment::RolloutPhase;

    fn plan(status: RobotDeploymentStatus) -> Plan {
        Plan {
            writes: Vec::new(),
            status,
            events: Vec::new(),
            requeue_after: None,
            batch_result: None,
            finished: false,
        }
    }

    fn status(updated: i32, batch: i32) -> RobotDeploymentStatus {
        RobotDeploymentStatus {
            phase: Some(RolloutPhase::Progressing),
            updated,
            pending: 40 - updated,
            progress: Some(format!("{updated}/40")),
            current_batch: Some(batch),
            ..RobotDeploymentStatus::default()
        }
    }

    #[test]
    fn counts_alone_are_written_at_most_once_a_period_anything_else_at_once() {
        let (pace, key, t0) = (Pace::default(), ("ns", "fleet"), Instant::now());
        let stored = status(1, 1);
        // Never written by this process: at once.
        assert_eq!(pace.wait(key, Some(&stored), &plan(status(2, 1)), t0), None);
        pace.written(key, t0);
        let soon = t0 + Duration::from_secs(1);
        assert_eq!(
            pace.wait(key, Some(&stored), &plan(status(3, 1)), soon),
            Some(STATUS_PERIOD - Duration::from_secs(1))
        );
        assert_eq!(
            pace.wait(key, Some(&stored), &plan(status(3, 1)), t0 + STATUS_PERIOD),
            None
        );
        // A new batch, a new phase, the end: at once.
        assert_eq!(
            pace.wait(key, Some(&stored), &plan(status(3, 2)), soon),
            None
        );
        let mut done = status(40, 1);
        done.phase = Some(RolloutPhase::Completed);
        assert_eq!(pace.wait(key, Some(&stored), &plan(done), soon), None);
        let mut finished = plan(status(3, 1));
        finished.finished = true;
        assert_eq!(pace.wait(key, Some(&stored), &finished, soon), None);
        assert_eq!(pace.wait(key, None, &plan(status(3, 1)), soon), None);
    }
}
