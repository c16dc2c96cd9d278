//! Third step of the rollout planner: moves the rollout's phase on, from the gates and the
//! robots' states: fail on an invalid release, wait for an older deployment, roll back, stop
//! (see [`super::abort`]), or roll forward (see [`super::progress`]); rollbacks are
//! [`super::rollback`]'s.

use jiff::SignedDuration;
use lekiwi_crds::deployment::RolloutPhase;

use super::classify::{Fleet, RobotState};
use super::draft::{Draft, Rollout};
use super::gates::Gates;
use super::rollback::{self, await_rollback, resume_recorded_rollback, start_rollback};
use super::{MarkState, ReleaseCheck, abort, progress, time};

/// Robots whose failure became known now get a permanent mark (and a Warning).
pub(super) fn mark_new_failures(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) {
    for (robot, state) in &fleet.robots {
        let RobotState::Failed(batch, why) = state else {
            continue;
        };
        if !robot
            .mark
            .as_ref()
            .is_some_and(|m| m.state == MarkState::Started)
        {
            continue;
        }
        let mut mark = robot
            .mark
            .clone()
            .unwrap_or_else(|| rollout.fallback_mark());
        mark.state = MarkState::Failed;
        mark.since = rollout.now;
        mark.message = Some(why.clone());
        draft.write(&robot.name, mark, None);
        draft.warning(
            "RobotUpdateFailed",
            format!("{} (batch {batch}): {why}", robot.name),
        );
    }
}

/// Decides the phase this plan ends in, with the writes and Events that go with it.
pub(super) fn advance(
    rollout: &Rollout<'_>,
    fleet: &Fleet<'_>,
    gates: &Gates<'_>,
    draft: &mut Draft,
) {
    // A completed rollout picks up robots selected later.
    if draft.phase == RolloutPhase::Completed && fleet.any_pending() && gates.release_ok {
        draft.phase = RolloutPhase::Progressing;
        draft.status.completion_time = None;
    }
    let undo_now = gates.undo_requested && rollback::undo_applies(draft.phase);
    if undo_now {
        draft.phase = RolloutPhase::RollingBack;
        draft.message = "rollback requested by a user (kubectl lekiwi rollout undo)".to_owned();
        draft.warning("RollbackStarted", draft.message.clone());
        start_rollback(rollout, fleet, draft);
    } else {
        resume_recorded_rollback(rollout, fleet, draft);
        if gates.abort_requested && abort::applies(draft.phase) {
            abort::stop(rollout, fleet, draft);
        }
    }
    let phase = draft.phase;
    match phase {
        RolloutPhase::Completed
        | RolloutPhase::RolledBack
        | RolloutPhase::Failed
        | RolloutPhase::Aborted
            if !(phase == RolloutPhase::Failed && gates.release_ok) => {}
        RolloutPhase::RollingBack if undo_now => {
            draft.wake_at(rollout.now + SignedDuration::from_secs(2));
        }
        // A rollback goes on even if the release became invalid meanwhile.
        RolloutPhase::RollingBack => await_rollback(rollout, fleet, draft),
        _ if !gates.release_ok => fail_on_invalid_release(rollout, draft),
        _ => match gates.older_overlap {
            // Wait for the older deployment; robots already started keep going.
            Some(older) => {
                draft.message = format!(
                    "waiting for the older deployment {} that selects some of the same robots",
                    older.deployment
                );
                draft.wake_at(rollout.now + SignedDuration::from_secs(30));
            }
            // Pending, Progressing, Paused, or Failed with a now-valid release.
            None => progress::roll_forward(rollout, fleet, draft),
        },
    }
}

/// An active rollout of an invalid release fails.
fn fail_on_invalid_release(rollout: &Rollout<'_>, draft: &mut Draft) {
    draft.phase = RolloutPhase::Failed;
    draft.message = match rollout.release {
        ReleaseCheck::Invalid(why) => format!("cannot roll out {}: {why}", rollout.target),
        _ => String::new(),
    };
    if rollout.was_active {
        draft.warning("InvalidRelease", draft.message.clone());
        draft.status.completion_time = Some(time(rollout.now));
    }
}
