//! Pausing a rollout mid-batch: a robot told to switch that has not switched yet is told to
//! stay on the release it ran (its `spec.release` goes back to the mark's `previous`, which
//! makes its gateway send `cancel` to a download or pre-switch command in flight) and waits in
//! its batch; resuming starts it again, and its agent resumes the partial download.

use super::draft::{Draft, Rollout};
use super::{MarkState, RobotView};

/// The mark message of a robot held by a pause; such a robot is not skipped for waiting long.
pub(super) const HELD_BY_PAUSE: &str = "paused before it switched; its update was cancelled";

/// Holds an updating robot of a paused rollout that does not run the target yet; false when
/// it cannot be held (it switched already, or ran no release before: nothing to stay on).
pub(super) fn hold(rollout: &Rollout<'_>, robot: &RobotView, draft: &mut Draft) -> bool {
    if !rollout.paused || robot.runs(rollout.target) {
        return false;
    }
    let Some(mut mark) = robot.mark.clone() else {
        return false;
    };
    let Some(previous) = mark.previous.clone() else {
        return false;
    };
    mark.state = MarkState::Waiting;
    mark.since = rollout.now;
    mark.message = Some(HELD_BY_PAUSE.to_owned());
    draft.write(&robot.name, mark, Some(previous));
    true
}

/// Whether a waiting robot was held by a pause (while the pause lasts, and until it is
/// started again or begins an ordinary wait: its wait does not time out meanwhile).
pub(super) fn held(robot: &RobotView) -> bool {
    robot
        .mark
        .as_ref()
        .is_some_and(|m| m.message.as_deref() == Some(HELD_BY_PAUSE))
}
