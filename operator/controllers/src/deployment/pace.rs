//! Deployments' status written at a bounded rate however many robots move and however many
//! deployments roll at once: a change that leaves a deployment's phase, rollout, generation and
//! conditions' verdicts alone (counts, rows, the batch, the message) waits until its period has
//! passed since this process last wrote that deployment's status; a change of those is written
//! at once, and so is the end of the rollout. The period is [`STATUS_PERIOD`], or longer when
//! many deployments roll at once: they share [`PROGRESS_WRITES_PER_SECOND`], so 100 rollouts
//! at once cost the API server no more progress writes a second than 6 do. A held status is kept
//! here and the next plan starts from it, not from the stored one, so nothing is planned twice
//! (no batch closed again, no Event published again) while the write waits. Robot writes are not
//! held: the marks on robots are what a rollout resumes from, also when this process stops with
//! a status held.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Duration;

use lekiwi_crds::{RobotDeployment, RobotDeploymentStatus};
use tokio::time::Instant;

use super::plan::Plan;

/// The least time between two status writes of one deployment that change no verdict.
pub const STATUS_PERIOD: Duration = Duration::from_secs(3);

/// The progress writes (ones that change no verdict) a second all deployments share: with `n`
/// deployments rolling, each waits `n / PROGRESS_WRITES_PER_SECOND` seconds between two, at
/// least [`STATUS_PERIOD`].
pub const PROGRESS_WRITES_PER_SECOND: u32 = 2;

/// A deployment counts as rolling while this process wrote or held its status this recently.
const ROLLING: Duration = Duration::from_secs(60);

/// Per deployment (by namespace and name): when this process last wrote its status, and the
/// status planned since but held.
#[derive(Debug, Default)]
pub struct Pace {
    last: Mutex<HashMap<(String, String), Entry>>,
}

#[derive(Debug, Default)]
struct Entry {
    written: Option<Instant>,
    /// When a status was last planned for it, written or held.
    planned: Option<Instant>,
    held: Option<RobotDeploymentStatus>,
}

impl Pace {
    /// The status the next plan of `deployment` starts from: the one held for it, if planned
    /// for its current generation; else `None` (the stored one).
    pub fn held(
        &self,
        key: (&str, &str),
        deployment: &RobotDeployment,
    ) -> Option<RobotDeploymentStatus> {
        let last = self.lock();
        let held = last.get(&owned(key))?.held.as_ref()?;
        (held.observed_generation == deployment.metadata.generation).then(|| held.clone())
    }

    /// How long the status of `plan` waits before it is written (it is then held), or `None`
    /// to write it now.
    pub fn wait(
        &self,
        key: (&str, &str),
        stored: Option<&RobotDeploymentStatus>,
        plan: &Plan,
        now: Instant,
    ) -> Option<Duration> {
        let stored = stored?;
        if plan.finished || !same_verdicts(stored, &plan.status) {
            return None;
        }
        let mut last = self.lock();
        let period = period(&last, now);
        let entry = last.get_mut(&owned(key))?;
        let since = now.duration_since(entry.written?);
        entry.planned = Some(now);
        let left = period.checked_sub(since).filter(|left| !left.is_zero())?;
        entry.held = Some(plan.status.clone());
        Some(left)
    }

    /// The planned status is stored now: written at `now`, or `None` when it already was.
    pub fn stored(&self, key: (&str, &str), written: Option<Instant>) {
        let mut last = self.lock();
        let entry = last.entry(owned(key)).or_default();
        entry.held = None;
        if written.is_some() {
            entry.written = written;
            entry.planned = written;
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<(String, String), Entry>> {
        self.last.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The least time between two progress writes of one deployment while the deployments in
/// `last` roll: [`STATUS_PERIOD`], or their share of [`PROGRESS_WRITES_PER_SECOND`].
fn period(last: &HashMap<(String, String), Entry>, now: Instant) -> Duration {
    let rolling = last
        .values()
        .filter(|e| e.planned.is_some_and(|t| now.duration_since(t) < ROLLING))
        .count();
    let share = Duration::from_secs(1) * rolling as u32 / PROGRESS_WRITES_PER_SECOND;
    share.max(STATUS_PERIOD)
}

fn owned(key: (&str, &str)) -> (String, String) {
    (key.0.to_owned(), key.1.to_owned())
}

/// Whether `a` and `b` agree on everything a change of which is written at once: the phase,
/// the rollout, the generation, and each condition's status and reason.
fn same_verdicts(a: &RobotDeploymentStatus, b: &RobotDeploymentStatus) -> bool {
    let verdicts = |s: &RobotDeploymentStatus| {
        let conditions: Vec<_> = s
            .conditions
            .iter()
            .map(|c| (c.r#type.clone(), c.status, c.reason.clone()))
            .collect();
        (
            s.phase,
            s.rollout_id.clone(),
            s.observed_generation,
            conditions,
        )
    };
    verdicts(a) == verdicts(b)
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
            observed_generation: Some(1),
            ..RobotDeploymentStatus::default()
        }
    }

    #[test]
    fn only_a_new_verdict_is_written_at_once_the_rest_once_a_period_and_planned_from_meanwhile() {
        let (pace, key, t0) = (Pace::default(), ("ns", "fleet"), Instant::now());
        let stored = status(1, 1);
        let spec = lekiwi_crds::RobotDeploymentSpec {
            selector: Default::default(),
            release: None,
            agent: None,
            strategy: Default::default(),
            paused: false,
            analysis: None,
            priority: 0,
        };
        let mut d = RobotDeployment::new("fleet", spec);
        d.metadata.generation = Some(1);
        // Never written by this process: at once.
        assert_eq!(pace.wait(key, Some(&stored), &plan(status(2, 1)), t0), None);
        pace.stored(key, Some(t0));
        let soon = t0 + Duration::from_secs(1);
        assert_eq!(
            pace.wait(key, Some(&stored), &plan(status(3, 1)), soon),
            Some(STATUS_PERIOD - Duration::from_secs(1))
        );
        assert_eq!(
            pace.held(key, &d),
            Some(status(3, 1)),
            "the next plan starts from it"
        );
        // A new batch is held too: the next plan starts from it, so it is not opened twice.
        assert_eq!(
            pace.wait(key, Some(&stored), &plan(status(3, 2)), soon),
            Some(STATUS_PERIOD - Duration::from_secs(1))
        );
        assert_eq!(pace.held(key, &d), Some(status(3, 2)));
        d.metadata.generation = Some(2);
        assert_eq!(pace.held(key, &d), None, "planned for an older spec");
        assert_eq!(
            pace.wait(key, Some(&stored), &plan(status(3, 1)), t0 + STATUS_PERIOD),
            None
        );
        // A new phase, a condition's new verdict, the end: at once.
        let mut done = status(40, 1);
        done.phase = Some(RolloutPhase::Completed);
        assert_eq!(pace.wait(key, Some(&stored), &plan(done), soon), None);
        let mut conflict = status(3, 1);
        conflict.conditions.push(lekiwi_crds::Condition {
            r#type: "Conflict".into(),
            status: lekiwi_crds::ConditionStatus::True,
            last_transition_time: k8s_openapi::apimachinery::pkg::apis::meta::v1::Time(
                "2026-12-05T10:00:00Z".parse().unwrap(),
            ),
            reason: "OlderDeployment".into(),
            message: "".into(),
            observed_generation: None,
        });
        assert_eq!(pace.wait(key, Some(&stored), &plan(conflict), soon), None);
        let mut finished = plan(status(3, 1));
        finished.finished = true;
        assert_eq!(pace.wait(key, Some(&stored), &finished, soon), None);
        assert_eq!(pace.wait(key, None, &plan(status(3, 1)), soon), None);
        pace.stored(key, None);
        d.metadata.generation = Some(1);
        assert_eq!(pace.held(key, &d), None, "stored: nothing held");
    }

    #[test]
    fn deployments_rolling_at_once_share_the_progress_writes() {
        let (pace, t0) = (Pace::default(), Instant::now());
        let stored = status(1, 1);
        let names: Vec<String> = (0..20).map(|i| format!("d{i}")).collect();
        for name in &names {
            pace.stored(("ns", name), Some(t0));
        }
        // 20 rolling at 2 writes a second: each waits 10 s between two progress writes.
        let at = t0 + Duration::from_secs(4);
        assert_eq!(
            pace.wait(("ns", "d0"), Some(&stored), &plan(status(2, 1)), at),
            Some(Duration::from_secs(6))
        );
        // A new verdict is not held however many roll.
        let mut done = status(40, 1);
        done.phase = Some(RolloutPhase::Completed);
        assert_eq!(
            pace.wait(("ns", "d1"), Some(&stored), &plan(done), at),
            None
        );
        // Once the others have planned nothing for a while, one alone is back to the period.
        let later = t0 + ROLLING + Duration::from_secs(1);
        pace.stored(("ns", "d0"), Some(later));
        assert_eq!(
            pace.wait(
                ("ns", "d0"),
                Some(&stored),
                &plan(status(3, 1)),
                later + Duration::from_secs(1)
            ),
            Some(STATUS_PERIOD - Duration::from_secs(1))
        );
    }
}
