//! Timeouts judged on the API server's present: a robot the shared store shows past its
//! rollout timeout is read fresh before the plan may count it failed, or count it as not back
//! from a rollback. Under load the store can
//! run minutes behind the API server: the soak at 10,000 robots timed a canary out on a store
//! that did not show yet the release its gateway had written it running a minute before.

use std::time::Duration;

use futures::{StreamExt, stream};
use jiff::{SignedDuration, Timestamp};
use kube::Api;
use lekiwi_crds::{ReleaseRef, Robot};
use tracing::{debug, info, warn};

use super::plan::{MarkState, RobotView};

/// Robots read fresh in one reconcile at most; the others wait for a later reconcile (the
/// plan looks again within a second while one waits).
const MAX_READS: usize = 200;
/// Reads in flight at once.
const CONCURRENCY: usize = 16;
/// How long the reads of one reconcile may take together.
const BUDGET: Duration = Duration::from_secs(10);

/// What a rollout's timeouts are judged against.
pub(super) struct Timeouts<'a> {
    /// The deployment whose marks count.
    pub deployment: &'a str,
    /// What its robots should end up running.
    pub target: &'a ReleaseRef,
    /// `spec.strategy.robotTimeoutSeconds`.
    pub timeout: SignedDuration,
    pub now: Timestamp,
}

impl Timeouts<'_> {
    /// Whether `robot`, on this view, is past its timeout since this deployment told it to
    /// switch without running the target healthy, or since it told it to switch back without
    /// running the release it returns to.
    pub(super) fn overdue(&self, robot: &RobotView) -> bool {
        let Some(m) = robot.mark.as_ref() else {
            return false;
        };
        if m.deployment != self.deployment || !robot.timed_out(m.since, self.timeout, self.now) {
            return false;
        }
        match m.state {
            MarkState::Started => !(robot.runs(self.target) && robot.healthy),
            MarkState::RollingBack => m.previous.as_ref().is_some_and(|back| !robot.runs(back)),
            _ => false,
        }
    }

    /// The robots among `robots` that are overdue on the store, most overdue first.
    fn due(&self, robots: &[RobotView]) -> Vec<usize> {
        let mut due: Vec<usize> = (0..robots.len())
            .filter(|&i| self.overdue(&robots[i]))
            .collect();
        due.sort_by_key(|&i| robots[i].mark.as_ref().map(|m| m.since));
        due
    }
}

/// Reads the robots of `robots` that are overdue on the store from the API server (at most
/// [`MAX_READS`], within [`BUDGET`]) and puts the view `rebuild` makes of each in place of the
/// store's; an overdue robot not read (beyond the cap, the budget, or a failed read) is marked
/// [`RobotView::unconfirmed`] and does not time out on this plan.
pub(super) async fn confirm(
    api: &Api<Robot>,
    timeouts: &Timeouts<'_>,
    robots: &mut [RobotView],
    rebuild: impl Fn(&Robot) -> RobotView,
) {
    let due = timeouts.due(robots);
    if due.is_empty() {
        return;
    }
    for &i in &due {
        robots[i].unconfirmed = true;
    }
    let names: Vec<(usize, String)> = due
        .iter()
        .take(MAX_READS)
        .map(|&i| (i, robots[i].name.clone()))
        .collect();
    let mut reads = stream::iter(names)
        .map(|(i, name)| async move { (i, api.get_opt(&name).await) })
        .buffer_unordered(CONCURRENCY);
    let deadline = tokio::time::Instant::now() + BUDGET;
    let (mut read, mut in_time) = (0, 0);
    while let Ok(Some((i, got))) = tokio::time::timeout_at(deadline, reads.next()).await {
        match got {
            Ok(Some(fresh)) => {
                let view = RobotView {
                    superseded_by: robots[i].superseded_by.take(),
                    ..rebuild(&fresh)
                };
                read += 1;
                in_time += usize::from(!timeouts.overdue(&view));
                robots[i] = view;
            }
            // Deleted: the store drops it soon; nothing to time out.
            Ok(None) => robots[i].unconfirmed = false,
            Err(error) => warn!(robot = %robots[i].name, %error,
                "cannot read a robot past its timeout; judged on a later reconcile"),
        }
    }
    let waiting = robots.iter().filter(|r| r.unconfirmed).count();
    // Routine when robots really time out; worth a line when the store misled or reads wait.
    if in_time > 0 || waiting > 0 {
        info!(
            due = due.len(),
            read, in_time, waiting, "robots past their timeout on the store read fresh"
        );
    } else {
        debug!(
            due = due.len(),
            read, "robots past their timeout on the store read fresh"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deployment::plan::Mark;

    fn release(v: &str) -> ReleaseRef {
        ReleaseRef {
            version: v.to_owned().into(),
            digest: format!("sha256:{}", v.repeat(64)).into(),
        }
    }

    fn started(name: &str, deployment: &str, age_s: i64, now: Timestamp) -> RobotView {
        RobotView {
            name: name.to_owned(),
            healthy: true,
            current: Some(release("1")),
            mark: Some(Mark {
                deployment: deployment.to_owned(),
                rollout_id: "r".to_owned(),
                batch: 0,
                state: MarkState::Started,
                since: now - SignedDuration::from_secs(age_s),
                previous: None,
                message: None,
                failed: false,
            }),
            ..RobotView::default()
        }
    }

    #[test]
    fn only_this_deployments_robots_past_their_timeout_are_due_oldest_first() {
        let now = Timestamp::now();
        let target = release("2");
        let t = Timeouts {
            deployment: "d",
            target: &target,
            timeout: SignedDuration::from_secs(60),
            now,
        };
        let mut on_target = started("on-target", "d", 100, now);
        on_target.current = Some(target.clone());
        let mut unhealthy = started("unhealthy", "d", 90, now);
        unhealthy.current = Some(target.clone());
        unhealthy.healthy = false;
        let mut waiting = started("waiting", "d", 100, now);
        waiting.mark.as_mut().unwrap().state = MarkState::Waiting;
        let rolling_back = |name, previous: &str, age_s| {
            let mut r = started(name, "d", age_s, now);
            let mark = r.mark.as_mut().unwrap();
            mark.state = MarkState::RollingBack;
            mark.previous = Some(release(previous));
            r
        };
        let robots = vec![
            started("young", "d", 30, now),
            started("old", "d", 61, now),
            started("older", "d", 300, now),
            started("other", "e", 300, now),
            on_target,
            unhealthy,
            waiting,
            rolling_back("not-back", "0", 200),
            rolling_back("back", "1", 200),
            rolling_back("not-back-young", "0", 30),
            RobotView::default(),
        ];
        let names: Vec<&str> = t
            .due(&robots)
            .iter()
            .map(|&i| robots[i].name.as_str())
            .collect();
        assert_eq!(names, ["older", "not-back", "unhealthy", "old"]);
    }
}
