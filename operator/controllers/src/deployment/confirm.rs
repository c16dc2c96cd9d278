//! Timeouts judged on the API server's present: a robot the shared store shows past its
//! rollout timeout is read fresh before the plan may count it failed, or count it as not back
//! from a rollback. Under load the store can
//! run minutes behind the API server: the soak at 10,000 robots timed a canary out on a store
//! that did not show yet the release its gateway had written it running a minute before. A
//! robot a fresh read found past its timeout is not read again for the same mark: a failed
//! robot keeps its mark while the rollout goes on, and would be read on every reconcile.

use std::collections::{HashMap, HashSet};
use std::sync::Mutex;
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

/// Per deployment (`namespace/name`), the robots a fresh read found past their timeout, by name
/// and the time of the mark it was judged on. A mark's timeout, once past, stays past; a robot
/// that reports its outcome late shows it on the store like any other change.
#[derive(Debug, Default)]
pub(super) struct Confirmed(Mutex<HashMap<String, HashSet<(String, Timestamp)>>>);

impl Confirmed {
    fn take(&self, key: &str) -> HashSet<(String, Timestamp)> {
        self.lock().remove(key).unwrap_or_default()
    }

    fn put(&self, key: String, robots: HashSet<(String, Timestamp)>) {
        if !robots.is_empty() {
            self.lock().insert(key, robots);
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<String, HashSet<(String, Timestamp)>>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Where fresh reads come from, and what they found before.
pub(super) struct Reads<'a> {
    pub api: &'a Api<Robot>,
    pub confirmed: &'a Confirmed,
}

/// What a rollout's timeouts are judged against.
pub(super) struct Timeouts<'a> {
    /// The deployment's namespace.
    pub namespace: &'a str,
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

    /// `robot`'s mark, as [`Confirmed`] remembers it.
    fn judged(robot: &RobotView) -> Option<(String, Timestamp)> {
        Some((robot.name.clone(), robot.mark.as_ref()?.since))
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

/// Reads the robots of `robots` that are overdue on the store, and were not found so for the
/// same mark before, from the API server (at most [`MAX_READS`], within [`BUDGET`]) and puts the
/// view `rebuild` makes of each in place of the store's; an overdue robot not read (beyond the
/// cap, the budget, or a failed read) is marked [`RobotView::unconfirmed`] and does not time out
/// on this plan.
pub(super) async fn confirm(
    reads: &Reads<'_>,
    timeouts: &Timeouts<'_>,
    robots: &mut [RobotView],
    rebuild: impl Fn(&Robot) -> RobotView,
) {
    let key = format!("{}/{}", timeouts.namespace, timeouts.deployment);
    let before = reads.confirmed.take(&key);
    let due = timeouts.due(robots);
    // Found past their timeout for these very marks: judged on the store, not read again.
    let (known, due): (Vec<usize>, Vec<usize>) = due
        .into_iter()
        .partition(|&i| Timeouts::judged(&robots[i]).is_some_and(|j| before.contains(&j)));
    let mut confirmed: HashSet<_> = known
        .iter()
        .filter_map(|&i| Timeouts::judged(&robots[i]))
        .collect();
    if due.is_empty() {
        reads.confirmed.put(key, confirmed);
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
    let api = reads.api;
    let mut gets = stream::iter(names)
        .map(|(i, name)| async move { (i, api.get_opt(&name).await) })
        .buffer_unordered(CONCURRENCY);
    let deadline = tokio::time::Instant::now() + BUDGET;
    let (mut read, mut in_time) = (0, 0);
    while let Ok(Some((i, got))) = tokio::time::timeout_at(deadline, gets.next()).await {
        match got {
            Ok(Some(fresh)) => {
                let view = RobotView {
                    superseded_by: robots[i].superseded_by.take(),
                    ..rebuild(&fresh)
                };
                read += 1;
                if timeouts.overdue(&view) {
                    confirmed.extend(Timeouts::judged(&view));
                } else {
                    in_time += 1;
                }
                robots[i] = view;
            }
            // Deleted: the store drops it soon; nothing to time out.
            Ok(None) => robots[i].unconfirmed = false,
            Err(error) => warn!(robot = %robots[i].name, %error,
                "cannot read a robot past its timeout; judged on a later reconcile"),
        }
    }
    reads.confirmed.put(key, confirmed);
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

    /// A robot found past its timeout on a fresh read is not read again for the same mark (it
    /// is judged on the store, not left unconfirmed); one with a newer mark is read again. The
    /// API server here refuses every connection: a read fails and leaves its robot unconfirmed.
    #[tokio::test]
    async fn a_robot_found_past_its_timeout_is_not_read_again_for_the_same_mark() {
        let config = kube::Config::new("http://127.0.0.1:9".parse().unwrap());
        let api = Api::namespaced(kube::Client::try_from(config).unwrap(), "ns");
        let confirmed = Confirmed::default();
        let reads = Reads {
            api: &api,
            confirmed: &confirmed,
        };
        let now = Timestamp::now();
        let target = release("2");
        let t = Timeouts {
            namespace: "ns",
            deployment: "d",
            target: &target,
            timeout: SignedDuration::from_secs(60),
            now,
        };
        let (known, renewed) = (
            started("known", "d", 100, now),
            started("renewed", "d", 90, now),
        );
        let earlier = renewed.mark.as_ref().unwrap().since - SignedDuration::from_secs(200);
        confirmed.put(
            "ns/d".to_owned(),
            HashSet::from([
                Timeouts::judged(&known).unwrap(),
                ("renewed".to_owned(), earlier),
            ]),
        );
        let mut robots = vec![known, renewed];
        confirm(&reads, &t, &mut robots, |_| {
            unreachable!("no read succeeds")
        })
        .await;
        assert!(!robots[0].unconfirmed, "judged on the store");
        assert!(
            robots[1].unconfirmed,
            "read (and failed) for its newer mark"
        );
        let kept = confirmed.take("ns/d");
        assert_eq!(kept, HashSet::from([Timeouts::judged(&robots[0]).unwrap()]));
        // Once the deployment has no robot past its timeout, it holds nothing.
        confirmed.put("ns/d".to_owned(), kept);
        confirm(&reads, &t, &mut [], |_| unreachable!()).await;
        assert!(confirmed.take("ns/d").is_empty());
    }

    #[test]
    fn only_this_deployments_robots_past_their_timeout_are_due_oldest_first() {
        let now = Timestamp::now();
        let target = release("2");
        let t = Timeouts {
            namespace: "ns",
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
