//! The forward path of the rollout planner: form the current batch (canary first, pending
//! robots in name order), or resolve it once every member succeeded, failed or was skipped,
//! and judge it against the success threshold.

use jiff::{SignedDuration, Timestamp};
use lekiwi_crds::RobotDeploymentStatus;
use lekiwi_crds::deployment::{RolloutPhase, UnavailablePolicy};

use super::classify::{Fleet, RobotState, Unavailable};
use super::draft::{Draft, Rollout};
use super::{Mark, MarkState, RobotView, pause, rollback, secs, time};

/// How far the current batch got in this plan.
enum Outcome {
    /// Still forming or resolving it; the message says why.
    Continue(String),
    /// Batch `b` met the threshold with this success ratio.
    BatchSucceeded(i32, f64),
    /// Batch `b` fell below the threshold with this success ratio; why.
    BatchFailed(i32, f64, String),
    /// No robot is left to update.
    Completed,
}

/// Rolls a pending, progressing or paused rollout forward and turns the batch's outcome into
/// the phase, the message and the Events.
pub(super) fn roll_forward(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) {
    let target = rollout.target;
    if draft.phase == RolloutPhase::Failed {
        draft.normal(
            "ReleaseValid",
            format!("{target} is valid now; rolling out"),
        );
    }
    if matches!(draft.phase, RolloutPhase::Pending | RolloutPhase::Failed) {
        draft.normal(
            "RolloutStarted",
            format!(
                "rolling {target} out to {} robot(s) in {} batch(es)",
                fleet.targeted, fleet.total_batches
            ),
        );
    }
    draft.phase = if rollout.paused {
        RolloutPhase::Paused
    } else {
        RolloutPhase::Progressing
    };
    let batch = draft.current_batch;
    let members: Vec<&(&RobotView, RobotState)> = fleet
        .robots
        .iter()
        .filter(|(_, s)| s.batch() == Some(batch))
        .collect();
    let mut outcome = if members.is_empty() {
        form_batch(rollout, fleet, draft)
    } else {
        resolve_batch(rollout, &members, draft)
    };
    if let Outcome::BatchSucceeded(b, ratio) = outcome {
        draft.batch_result = Some((b, ratio));
        // No pause to wait for: the next batch starts in this plan, so a batch costs one
        // status write and one reconcile, not one to close it and one to open the next. Unless
        // robots' marks show it started already (the status is older than the marks: a
        // restarted leader): the next plan resolves it then.
        let next_started = fleet.robots.iter().any(|(_, s)| s.batch() == Some(b + 1));
        if !rollout.paused && !next_started && pause_ends(rollout, &draft.status).is_none() {
            outcome = form_batch(rollout, fleet, draft);
        }
    }
    match outcome {
        Outcome::Continue(message) => draft.message = message,
        Outcome::BatchSucceeded(b, _) => {
            draft.message = format!("batch {b} succeeded; next batch after the pause");
        }
        Outcome::Completed => {
            draft.phase = RolloutPhase::Completed;
            draft.status.completion_time = Some(time(rollout.now));
            draft.message = format!("{target} rolled out");
            draft.normal("RolloutCompleted", draft.message.clone());
        }
        Outcome::BatchFailed(b, ratio, why) => {
            draft.batch_result = Some((b, ratio));
            draft.phase = RolloutPhase::RollingBack;
            draft.message = format!("batch {b} failed: {why}");
            draft.warning(
                "RollbackStarted",
                format!("{}; rolling back every updated robot", draft.message),
            );
            rollback::start_rollback(rollout, fleet, draft);
            draft.wake_at(rollout.now + SignedDuration::from_secs(2));
        }
    }
}

/// When the pause after the last batch ends, if it has not yet.
fn pause_ends(rollout: &Rollout<'_>, status: &RobotDeploymentStatus) -> Option<Timestamp> {
    let done = status.last_batch_completion_time.as_ref()?;
    let resume = done.0 + secs(rollout.strategy.pause_between_batches_seconds);
    (resume > rollout.now).then_some(resume)
}

/// Forms the current batch from the pending robots, unless paused or between batches.
fn form_batch(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) -> Outcome {
    let now = rollout.now;
    let batch = draft.current_batch;
    if rollout.paused {
        return Outcome::Continue("paused before the next batch".into());
    }
    if let Some(resume) = pause_ends(rollout, &draft.status) {
        draft.wake_at(resume);
        return Outcome::Continue(format!(
            "pausing {}s between batches",
            rollout.strategy.pause_between_batches_seconds
        ));
    }
    let size = if batch == 0 && fleet.canary > 0 {
        fleet.canary
    } else {
        fleet.batch_size
    };
    let mut pending: Vec<&RobotView> = fleet
        .robots
        .iter()
        .filter(|(_, s)| *s == RobotState::Pending)
        .map(|(robot, _)| *robot)
        .collect();
    pending.sort_by(|a, b| a.name.cmp(&b.name));
    if pending.is_empty() {
        let held_elsewhere = fleet
            .robots
            .iter()
            .any(|(_, s)| matches!(s, RobotState::HeldBy(_)));
        if held_elsewhere {
            draft.wake_at(now + SignedDuration::from_secs(30));
            return Outcome::Continue("waiting for robots held by another deployment".into());
        }
        return Outcome::Completed;
    }
    draft.status.current_batch_start_time = Some(time(now));
    let chosen: Vec<&RobotView> = pending.into_iter().take(size).collect();
    let mut started = 0;
    for robot in &chosen {
        let (state, message) = first_mark(rollout, robot);
        if state == MarkState::Started {
            started += 1;
        }
        if state == MarkState::Waiting {
            draft.wake_at(now + rollout.wait_timeout);
        }
        let mark = Mark {
            deployment: rollout.name.clone(),
            rollout_id: rollout.id.clone(),
            batch,
            state,
            since: now,
            previous: robot.before_start(),
            message,
            failed: false,
        };
        let release = (state == MarkState::Started).then(|| rollout.target.clone());
        draft.write(&robot.name, mark, release);
    }
    draft.wake_at(now + rollout.robot_timeout + SignedDuration::from_secs(1));
    draft.normal(
        "BatchStarted",
        format!(
            "batch {batch}: {} robot(s), {started} started now",
            chosen.len()
        ),
    );
    Outcome::Continue(format!(
        "batch {batch}: updating {started} of {} robot(s)",
        chosen.len()
    ))
}

/// A robot's state when its batch starts: started if available, else as the strategy's
/// policy for its kind of unavailability says (wait, or skip with a reason).
fn first_mark(rollout: &Rollout<'_>, robot: &RobotView) -> (MarkState, Option<String>) {
    let Err(unavailable) = robot.available() else {
        return (MarkState::Started, None);
    };
    let policy = match unavailable {
        Unavailable::Teleoperated => rollout.strategy.teleoperated,
        _ => rollout.strategy.unavailable,
    };
    match policy {
        UnavailablePolicy::Wait => (MarkState::Waiting, None),
        UnavailablePolicy::Skip => (
            MarkState::Skipped,
            Some(format!(
                "skipped: {} when its batch started",
                unavailable.as_str()
            )),
        ),
    }
}

/// The members of a batch by outcome so far.
#[derive(Default)]
struct Tally {
    succeeded: usize,
    /// `robot: why` of every failed member.
    failed: Vec<String>,
    /// Members still updating or waited for.
    unresolved: usize,
}

/// Resolves the current batch: starts members that became available, skips members waited for
/// too long, and judges the batch once none is unresolved.
fn resolve_batch(
    rollout: &Rollout<'_>,
    members: &[&(&RobotView, RobotState)],
    draft: &mut Draft,
) -> Outcome {
    let batch = draft.current_batch;
    let mut tally = Tally::default();
    for (robot, state) in members {
        match state {
            RobotState::Succeeded(_) => tally.succeeded += 1,
            RobotState::Failed(_, why) => tally.failed.push(format!("{}: {why}", robot.name)),
            RobotState::Updating(_, since) => {
                tally.unresolved += 1;
                if !pause::hold(rollout, robot, draft) {
                    draft.wake_at(*since + rollout.robot_timeout + SignedDuration::from_secs(1));
                }
            }
            RobotState::Waiting(_, since) => {
                tally.unresolved += usize::from(resolve_waiting(rollout, robot, *since, draft));
            }
            _ => {}
        }
    }
    if tally.unresolved > 0 {
        return Outcome::Continue(format!(
            "batch {batch}: {} updated, {} failed, {} in progress{}",
            tally.succeeded,
            tally.failed.len(),
            tally.unresolved,
            if rollout.paused { " (paused)" } else { "" }
        ));
    }
    judge_batch(rollout, tally, draft)
}

/// A member waited for since `since`: skipped once the wait timed out, started once available
/// (unless paused). Returns whether it is still unresolved.
fn resolve_waiting(
    rollout: &Rollout<'_>,
    robot: &RobotView,
    since: Timestamp,
    draft: &mut Draft,
) -> bool {
    let now = rollout.now;
    let mut mark = robot
        .mark
        .clone()
        .unwrap_or_else(|| rollout.fallback_mark());
    let held = pause::held(robot);
    if held && rollout.paused {
        true
    } else if !held && now.duration_since(since) > rollout.wait_timeout {
        mark.state = MarkState::Skipped;
        mark.message = Some(format!(
            "skipped: still {} after {}s",
            robot.waiting_reason().trim_start_matches("waiting: "),
            rollout.wait_timeout.as_secs()
        ));
        mark.since = now;
        draft.write(&robot.name, mark, None);
        false
    } else if !rollout.paused && robot.available().is_ok() {
        mark.state = MarkState::Started;
        mark.since = now;
        mark.message = None;
        mark.previous = robot.before_start();
        draft.write(&robot.name, mark, Some(rollout.target.clone()));
        draft.wake_at(now + rollout.robot_timeout + SignedDuration::from_secs(1));
        true
    } else if held {
        // Resumed while unavailable: an ordinary wait starts now.
        mark.since = now;
        mark.message = None;
        draft.write(&robot.name, mark, None);
        draft.wake_at(now + rollout.wait_timeout + SignedDuration::from_secs(1));
        true
    } else {
        draft.wake_at(since + rollout.wait_timeout + SignedDuration::from_secs(1));
        true
    }
}

/// A resolved batch succeeds when the share of succeeded members (skipped ones do not count)
/// reaches the threshold; then the next batch comes after the pause.
fn judge_batch(rollout: &Rollout<'_>, tally: Tally, draft: &mut Draft) -> Outcome {
    let batch = draft.current_batch;
    let threshold = rollout.strategy.success_threshold;
    let attempted = tally.succeeded + tally.failed.len();
    let ratio = if attempted == 0 {
        1.0
    } else {
        tally.succeeded as f64 / attempted as f64
    };
    if ratio < threshold {
        let why = format!(
            "{} of {attempted} robot(s) failed ({:.0}% succeeded, below the {:.0}% threshold); first: {}",
            tally.failed.len(),
            ratio * 100.0,
            threshold * 100.0,
            tally.failed.first().cloned().unwrap_or_default()
        );
        return Outcome::BatchFailed(batch, ratio, why);
    }
    draft.current_batch = batch + 1;
    draft.status.last_batch_completion_time = Some(time(rollout.now));
    draft.status.current_batch_start_time = None;
    draft.normal(
        "BatchSucceeded",
        format!(
            "batch {batch}: {} of {attempted} updated ({:.0}%)",
            tally.succeeded,
            ratio * 100.0
        ),
    );
    draft.wake_at(rollout.now + secs(rollout.strategy.pause_between_batches_seconds));
    Outcome::BatchSucceeded(batch, ratio)
}
