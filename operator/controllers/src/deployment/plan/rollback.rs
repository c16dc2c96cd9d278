//! Rollbacks in the rollout planner: every robot this rollout started is told to switch back
//! to the release it ran before (on a failed batch, a user's undo, or marks that record a
//! rollback the status does not yet say), and the rollout is RolledBack once they all run it.

use jiff::SignedDuration;
use lekiwi_crds::deployment::RolloutPhase;

use super::classify::{Fleet, RobotState};
use super::draft::{Draft, Rollout};
use super::{MarkState, time};

/// Whether a user's undo asked for now starts a rollback of a rollout in `phase`: any but one
/// rolling back or rolled back already.
pub(super) fn undo_applies(phase: RolloutPhase) -> bool {
    !matches!(phase, RolloutPhase::RollingBack | RolloutPhase::RolledBack)
}

/// Tells every robot this rollout started to switch back to the release it ran before.
pub(super) fn start_rollback(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) {
    for (robot, state) in &fleet.robots {
        let started = matches!(
            state,
            RobotState::Updating(..) | RobotState::Succeeded(_) | RobotState::Failed(..)
        );
        if !started {
            continue;
        }
        let Some(mark) = robot.mark.as_ref().filter(|m| m.rollout_id == rollout.id) else {
            continue;
        };
        let mut mark = mark.clone();
        mark.deployment = rollout.name.clone();
        if let RobotState::Failed(_, why) = state {
            mark.failed = true;
            mark.message = Some(why.clone());
        }
        mark.state = MarkState::RollingBack;
        mark.since = rollout.now;
        // A robot that ran nothing before keeps the new release: there is nothing to return to.
        let release = mark.previous.clone();
        draft.writes.retain(|w| w.robot != robot.name);
        draft.write(&robot.name, mark, release);
    }
}

/// Robots are written before the status: a robot told to switch back while the status still
/// says the rollout goes forward (the controller stopped between the two writes, or planned
/// from a status older than its last write) means a rollback was decided. It goes on, and any
/// started robot not yet told is told now; judging the batch again would count robots that
/// are switching back as successes and start the next batch.
pub(super) fn resume_recorded_rollback(
    rollout: &Rollout<'_>,
    fleet: &Fleet<'_>,
    draft: &mut Draft,
) {
    let recorded = fleet
        .robots
        .iter()
        .any(|(_, s)| matches!(s, RobotState::RollingBack(..)));
    let settled = matches!(
        draft.phase,
        RolloutPhase::RollingBack | RolloutPhase::RolledBack
    );
    if recorded && !settled {
        draft.phase = RolloutPhase::RollingBack;
        draft.message = "rolling back, as the robots' marks record".to_owned();
        start_rollback(rollout, fleet, draft);
    }
}

/// Waits until every robot told to switch back runs its previous release, or is past its
/// timeout on a fresh view (one past it on a store not read fresh is waited for).
pub(super) fn await_rollback(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) {
    let now = rollout.now;
    let (mut outstanding, mut not_back) = (0, Vec::new());
    for (robot, state) in &fleet.robots {
        let RobotState::RollingBack(_, since) = state else {
            continue;
        };
        let back = robot.mark.as_ref().and_then(|m| m.previous.as_ref());
        let done = back.is_none_or(|p| robot.runs(p));
        if done {
            continue;
        }
        if robot.timed_out(*since, rollout.robot_timeout, now) {
            not_back.push(robot.name.as_str());
        } else {
            outstanding += 1;
            draft.wake_at(*since + rollout.robot_timeout + SignedDuration::from_secs(1));
        }
    }
    if outstanding == 0 {
        draft.phase = RolloutPhase::RolledBack;
        draft.status.completion_time = Some(time(now));
        let verdict = match not_back.as_slice() {
            [] => "every updated robot is back on its previous release".to_owned(),
            [first, ..] => format!(
                "{} updated robot(s) did not run their previous release within {}s of being told \
                 to switch back (first: {first}); the others are back",
                not_back.len(),
                rollout.robot_timeout.as_secs()
            ),
        };
        let message = format!("{verdict}: {}", draft.message);
        if !not_back.is_empty() {
            // Said in the status too: robots to see to, as long as the rollout shows.
            draft.message.clone_from(&message);
        }
        draft.warning("RolledBack", message);
    } else {
        draft.wake_at(now + SignedDuration::from_secs(10));
    }
}
