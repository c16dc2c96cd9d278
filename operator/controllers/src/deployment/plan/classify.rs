//! First step of the rollout planner: where each selected robot stands in the current rollout,
//! read from its mark and its reports, and the batch arithmetic that follows.

use jiff::{SignedDuration, Timestamp};
use lekiwi_crds::{ReleaseRef, RobotPhase};

use super::analysis::{Settled, switched};
use super::draft::Rollout;
use super::{MarkState, RobotView, batch_size, total_batches};

/// Why a robot cannot be started right now.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Unavailable {
    Teleoperated,
    Offline,
    Unhealthy,
}

impl Unavailable {
    pub fn as_str(self) -> &'static str {
        match self {
            Unavailable::Teleoperated => "teleoperated",
            Unavailable::Offline => "offline",
            Unavailable::Unhealthy => "unhealthy",
        }
    }
}

impl RobotView {
    /// Whether the robot can be started now; teleoperation is checked first so that a
    /// teleoperated robot follows the teleoperation policy even when it is also unhealthy.
    pub(super) fn available(&self) -> Result<(), Unavailable> {
        if self.teleoperated {
            return Err(Unavailable::Teleoperated);
        }
        if self.phase != Some(RobotPhase::Online) {
            return Err(Unavailable::Offline);
        }
        if !self.healthy {
            return Err(Unavailable::Unhealthy);
        }
        Ok(())
    }

    /// Whether the robot reports running `release`.
    pub(crate) fn runs(&self, release: &ReleaseRef) -> bool {
        self.current.as_ref() == Some(release)
    }

    /// Whether a robot told something at `since` is past `timeout` at `now`: never on a view
    /// that should have been read fresh and was not ([`RobotView::unconfirmed`]). The one
    /// timeout rule of a switch and of a switch back, and of which robots to read fresh.
    pub(crate) fn timed_out(
        &self,
        since: Timestamp,
        timeout: SignedDuration,
        now: Timestamp,
    ) -> bool {
        now.duration_since(since) > timeout && !self.unconfirmed
    }

    /// The release to record as a robot's `previous` (what a rollback returns it to) when a
    /// rollout starts it or marks it waiting: the release it runs, unless it is on its way back
    /// to another: its mark (rolling back, or waiting as recorded while it was) names a release
    /// it does not run yet that its spec still asks for (a rollback in flight, or a store that
    /// does not show it back yet). Then that release: recording the one it still runs would
    /// let a later rollback return it to the release an earlier rollback took it off.
    pub(super) fn before_start(&self) -> Option<ReleaseRef> {
        let headed = self
            .mark
            .as_ref()
            .filter(|m| matches!(m.state, MarkState::RollingBack | MarkState::Waiting))
            .and_then(|m| m.previous.clone())
            .filter(|p| self.asks_for(p));
        match headed {
            Some(release) if !self.runs(&release) => Some(release),
            _ => self.current.clone(),
        }
    }

    /// Whether the robot's spec asks for `release`: `spec.release`, or for an agent rollout
    /// `spec.agent`'s version (an agent release is known by its version).
    fn asks_for(&self, release: &ReleaseRef) -> bool {
        self.desired.as_ref() == Some(release)
            || self
                .desired_agent
                .as_ref()
                .is_some_and(|a| a.version == release.version.as_str())
    }

    /// The message of a robot waited for: why it is not available.
    pub(super) fn waiting_reason(&self) -> String {
        match self.available() {
            Err(u) => format!("waiting: {}", u.as_str()),
            Ok(()) => "waiting".to_owned(),
        }
    }
}

/// Where a robot stands in the current rollout, derived from its mark and reports.
#[derive(Clone, Debug, PartialEq)]
pub(super) enum RobotState {
    /// Excluded: in maintenance.
    Maintenance,
    /// Held by another active deployment's mark.
    HeldBy(String),
    /// Excluded: owned by another deployment (newer, or of higher priority).
    Superseded(String),
    /// Runs the release, healthy, without being started by this rollout (or finished).
    Updated,
    /// Not yet in a batch.
    Pending,
    /// In batch `b`, waiting since `t`.
    Waiting(i32, Timestamp),
    /// In batch `b`, updating since `t`.
    Updating(i32, Timestamp),
    /// In batch `b`, finished: updated.
    Succeeded(i32),
    /// In batch `b`, failed, why.
    Failed(i32, String),
    /// In batch `b` (or none), skipped, why.
    Skipped(i32, String),
    /// Told to switch back at `t`.
    RollingBack(i32, Timestamp),
}

impl RobotState {
    /// The batch the robot is in, if it joined one in this rollout.
    pub fn batch(&self) -> Option<i32> {
        match self {
            RobotState::Waiting(b, _)
            | RobotState::Updating(b, _)
            | RobotState::Succeeded(b)
            | RobotState::Failed(b, _)
            | RobotState::Skipped(b, _)
            | RobotState::RollingBack(b, _) => Some(*b),
            _ => None,
        }
    }
}

/// Every selected robot with its state, and how the targeted ones split into batches.
pub(super) struct Fleet<'a> {
    /// The selected robots in the order the controller listed them, with their states.
    pub robots: Vec<(&'a RobotView, RobotState)>,
    /// Robots not in maintenance.
    pub targeted: usize,
    /// Size of the canary batch (0: none).
    pub canary: usize,
    /// Size of every batch after the canary.
    pub batch_size: usize,
    /// Number of batches for the targeted robots.
    pub total_batches: usize,
}

impl<'a> Fleet<'a> {
    /// Classifies the rollout's robots.
    pub fn classify(rollout: &Rollout<'a>) -> Self {
        let robots: Vec<(&RobotView, RobotState)> = rollout
            .robots
            .iter()
            .map(|robot| (robot, classify(robot, rollout)))
            .collect();
        let targeted = robots
            .iter()
            .filter(|(_, s)| !matches!(s, RobotState::Maintenance | RobotState::Superseded(_)))
            .count();
        let canary = usize::try_from(rollout.strategy.canary).unwrap_or(0);
        let size = batch_size(&rollout.strategy.batch_size, targeted);
        Self {
            robots,
            targeted,
            canary,
            batch_size: size,
            total_batches: total_batches(canary, size, targeted),
        }
    }

    /// Whether some robot has not joined a batch yet.
    pub fn any_pending(&self) -> bool {
        self.robots.iter().any(|(_, s)| *s == RobotState::Pending)
    }
}

/// Reads one robot's state; a mark of another rollout or deployment does not count, except
/// that an active deployment's started robot is held by it.
fn classify(robot: &RobotView, rollout: &Rollout<'_>) -> RobotState {
    if robot.maintenance {
        return RobotState::Maintenance;
    }
    if let Some(owner) = &robot.superseded_by {
        return RobotState::Superseded(owner.clone());
    }
    let ours = robot
        .mark
        .as_ref()
        .filter(|m| m.deployment == rollout.name && m.rollout_id == rollout.id);
    let Some(mark) = ours else {
        if let Some(other) = robot.mark.as_ref()
            && other.deployment != rollout.name
            && rollout.active_deployments.contains(&other.deployment)
            && matches!(other.state, MarkState::Started | MarkState::RollingBack)
        {
            return RobotState::HeldBy(other.deployment.clone());
        }
        if robot.runs(rollout.target) && robot.healthy {
            return RobotState::Updated;
        }
        if let Some(why) = &robot.no_build {
            return RobotState::Skipped(-1, why.clone());
        }
        return RobotState::Pending;
    };
    let batch = mark.batch;
    match mark.state {
        MarkState::Waiting => RobotState::Waiting(batch, mark.since),
        MarkState::Failed => RobotState::Failed(batch, mark.message.clone().unwrap_or_default()),
        MarkState::Skipped => RobotState::Skipped(batch, mark.message.clone().unwrap_or_default()),
        MarkState::RollingBack => RobotState::RollingBack(batch, mark.since),
        MarkState::Started => started(robot, batch, mark.since, rollout),
    }
}

/// A started robot: succeeded once it runs the release healthy; failed when its agent reports
/// a failure since it was started, or when it is still not there after the robot timeout.
fn started(robot: &RobotView, batch: i32, since: Timestamp, rollout: &Rollout<'_>) -> RobotState {
    let target = rollout.target;
    match switched(robot, since, rollout) {
        Some(Settled::Updated) => return RobotState::Succeeded(batch),
        Some(Settled::Failed(why)) => return RobotState::Failed(batch, why),
        None => {}
    }
    if let Some((release, phase, message, at)) = &robot.last_update
        && release == target
        && lekiwi_protocol::ProgressPhase::parse(phase)
            .is_some_and(lekiwi_protocol::ProgressPhase::is_failure)
        // The report's time is the gateway's, to the microsecond: a failure reported in the
        // second the robot was started is this start's when it came after it, and the outcome
        // of an update cancelled just before (a pause and a resume in one second) when before.
        && at.is_none_or(|at| at >= since)
    {
        return RobotState::Failed(
            batch,
            format!(
                "the agent reported {phase}: {}",
                message.as_deref().unwrap_or("no details")
            ),
        );
    }
    let timeout = rollout.robot_timeout;
    if robot.timed_out(since, timeout, rollout.now) {
        let runs = robot
            .current
            .as_ref()
            .map_or("no release".to_owned(), |r| r.version.to_string());
        let why = if robot.runs(target) && !robot.healthy {
            "unhealthy".to_owned()
        } else if robot.runs(target) {
            // Healthy on the release, but `spec.analysis` never saw its window: no gateway
            // saw the switch's `done` (e.g. it was reported while the robot's gateway restarted).
            format!(
                "runs {} healthy, but no analysis window of its switch",
                target.version
            )
        } else {
            format!("still runs {runs}")
        };
        return RobotState::Failed(
            batch,
            format!("timed out after {}s: {why}", timeout.as_secs()),
        );
    }
    RobotState::Updating(batch, since)
}
