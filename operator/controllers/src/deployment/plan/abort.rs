//! A user's `rollout abort`: the rollout stops where it stands. No robot starts any more; a
//! robot told to switch that has not switched yet is told to stay on the release it ran (its
//! `spec.release` goes back to the mark's `previous`, so its gateway sends `cancel` to a download
//! in flight, as a pause does); a robot waited for is left out; switched robots keep the new
//! release. The rollout ends `Aborted`: `rollout restart` goes on, `rollout undo` rolls back.

use lekiwi_crds::deployment::RolloutPhase;

use super::classify::{Fleet, RobotState};
use super::draft::{Draft, Rollout};
use super::{MarkState, time};

/// The mark message of a robot whose update an abort cancelled.
pub(super) const CANCELLED: &str = "aborted before it switched; its update was cancelled";

/// Whether an abort asked for now stops a rollout in `phase`: one that is still going forward
/// (or failed on an invalid release, and would go on once it is valid). A rollback goes on; a
/// finished rollout has nothing to stop.
pub(super) fn applies(phase: RolloutPhase) -> bool {
    matches!(
        phase,
        RolloutPhase::Pending
            | RolloutPhase::Progressing
            | RolloutPhase::Paused
            | RolloutPhase::Failed
    )
}

/// Stops the rollout: marks and cancellations for the robots it had not finished, the phase,
/// the message and a Warning.
pub(super) fn stop(rollout: &Rollout<'_>, fleet: &Fleet<'_>, draft: &mut Draft) {
    let (mut cancelled, mut kept) = (0, 0);
    for (robot, state) in &fleet.robots {
        let (switching, waiting) = match state {
            RobotState::Updating(..) => (!robot.runs(rollout.target), false),
            RobotState::Waiting(..) => (false, true),
            _ => (false, false),
        };
        if !(switching || waiting) {
            continue;
        }
        let Some(mut mark) = robot.mark.clone() else {
            continue;
        };
        // A robot that ran no release before has nothing to stay on: it goes on switching.
        let back = mark.previous.clone().filter(|_| switching);
        if switching && back.is_none() {
            continue;
        }
        mark.state = MarkState::Skipped;
        mark.since = rollout.now;
        mark.message = Some(if switching {
            CANCELLED.to_owned()
        } else {
            "aborted before its turn came".to_owned()
        });
        cancelled += usize::from(switching);
        kept += usize::from(waiting);
        draft.writes.retain(|w| w.robot != robot.name);
        draft.write(&robot.name, mark, back);
    }
    draft.phase = RolloutPhase::Aborted;
    draft.status.completion_time = Some(time(rollout.now));
    draft.message = format!(
        "aborted by a user (kubectl lekiwi rollout abort): robots that switched keep {}; {cancelled} update(s) cancelled, {kept} robot(s) waited for left out",
        rollout.target
    );
    draft.warning("RolloutAborted", draft.message.clone());
}
