//! Pure planning for the RobotDeployment controller: from the deployment, the robots it selects
//! and the time, decide which robots to start, wait for, skip or roll back, and the status.
//!
//! All rollout state that must survive an operator restart lives where it is written anyway:
//! the deployment's status (phase, rollout id, current batch) and one annotation per robot
//! ([`Mark`], written together with `spec.release`). Batch membership, start times and the
//! release a robot ran before are read back from the marks, so a new leader resumes exactly
//! where the old one stopped and never redeploys a robot that already finished.

mod abort;
mod analysis;
mod classify;
mod draft;
mod gates;
pub mod halt;
mod pause;
mod phase;
mod progress;
mod rollback;
mod status;

use std::time::Duration;

use jiff::{SignedDuration, Timestamp};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use lekiwi_crds::{ReleaseRef, RobotDeployment, RobotDeploymentStatus, RobotPhase};
use serde::{Deserialize, Serialize};

use self::classify::Fleet;
use self::draft::{Draft, Rollout};
use self::gates::Gates;

pub use lekiwi_crds::deployment::{
    ABORT_ANNOTATION, MARK_ANNOTATION, RESTART_ANNOTATION, UNDO_ANNOTATION,
};

/// Condition: the rollout is still moving (True) or has ended (False, with the outcome as reason).
pub const CONDITION_PROGRESSING: &str = "Progressing";
/// All targeted robots updated or skipped.
pub const CONDITION_COMPLETE: &str = "Complete";
/// Another deployment selects some of the same robots.
pub const CONDITION_CONFLICT: &str = "Conflict";
/// The rollout was rolled back.
pub const CONDITION_ROLLED_BACK: &str = "RolledBack";
/// The release exists in the blob store and is a valid manifest.
pub const CONDITION_RELEASE_VALID: &str = "ReleaseValid";

/// A robot's state within one rollout, kept in its [`MARK_ANNOTATION`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MarkState {
    /// Its turn came while it was teleoperated, offline or unhealthy; waiting since `since`.
    Waiting,
    /// Told to switch at `since`.
    Started,
    /// Did not succeed (reported failure or timed out); permanent for this rollout.
    Failed,
    /// Left out (unavailable when its batch started, or waited for too long); permanent too.
    Skipped,
    /// Told to switch back to `previous` at `since`.
    RollingBack,
}

/// What the controller wrote on a robot for one rollout.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Mark {
    /// The deployment that wrote it; another deployment's mark holds the robot while active.
    pub deployment: String,
    /// The rollout it belongs to: a mark of an earlier rollout of the same deployment is ignored.
    pub rollout_id: String,
    /// The batch the robot joined (0 is the canary batch).
    pub batch: i32,
    /// Where the robot stands in that rollout.
    pub state: MarkState,
    /// When `state` was entered.
    pub since: Timestamp,
    /// The release it ran before it was started (restored on rollback).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub previous: Option<ReleaseRef>,
    /// Why it failed or was skipped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// It failed before it was rolled back (kept so the count of failures survives rollback).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub failed: bool,
}

impl Mark {
    /// The mark `robot` carries for rollouts of `kind`, if it has one that parses.
    pub fn of(
        robot: &lekiwi_crds::Robot,
        kind: lekiwi_crds::deployment::RolloutKind,
    ) -> Option<Self> {
        let marks = robot.metadata.annotations.as_ref()?;
        serde_json::from_str(marks.get(kind.mark_annotation())?).ok()
    }

    /// The release (or agent build) the robot was told to run by the rollout that wrote this
    /// mark: the rollout's `target` once started (also when it then failed: only a rollback
    /// moves it), `previous` once rolling back or held back by a pause or an abort; `None` for
    /// a robot told nothing (waiting for its turn, skipped before it). A mark-only write sends
    /// it so that server-side apply keeps the field; the store is not asked, as under load it
    /// may not show the rollout's own write of a moment ago.
    pub fn told(&self, target: &ReleaseRef) -> Option<ReleaseRef> {
        let held_back = matches!(
            self.message.as_deref(),
            Some(pause::HELD_BY_PAUSE | abort::CANCELLED)
        );
        match self.state {
            MarkState::Started | MarkState::Failed => Some(target.clone()),
            MarkState::RollingBack => self.previous.clone(),
            MarkState::Waiting | MarkState::Skipped if held_back => self.previous.clone(),
            MarkState::Waiting | MarkState::Skipped => None,
        }
    }
}

/// The facts about one selected robot that a rollout needs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RobotView {
    /// Robot name, unique within the namespace; batches take pending robots in name order.
    pub name: String,
    /// `spec.maintenance`: such a robot is not targeted at all.
    pub maintenance: bool,
    /// `status.phase`, downgraded to Offline when the heartbeat is stale (see the controller).
    pub phase: Option<RobotPhase>,
    /// Health reported (absent counts as healthy).
    pub healthy: bool,
    /// Teleoperation reported; the strategy's `teleoperated` policy decides whether to wait.
    pub teleoperated: bool,
    /// `spec.release`: kept on mark-only writes so the rollout's field manager keeps owning it.
    pub desired: Option<ReleaseRef>,
    /// `status.currentRelease`: what the agent reports it runs.
    pub current: Option<ReleaseRef>,
    /// `status.lastUpdate`: release, phase (`done`, `failed`, `rolled_back`), message, time.
    pub last_update: Option<(ReleaseRef, String, Option<String>, Option<Timestamp>)>,
    /// Its mark, if any (of any deployment).
    pub mark: Option<Mark>,
    /// `status.analysis`: its metrics before and after its last switch.
    pub analysis: Option<lekiwi_crds::analysis::AnalysisReport>,
    /// The deployment that owns the robot instead of this one (newer, or of higher priority):
    /// this rollout leaves it alone.
    pub superseded_by: Option<String>,
    /// Agent rollouts: `spec.agent`, kept on mark-only writes like `desired` is for releases.
    pub desired_agent: Option<lekiwi_crds::AgentRef>,
    /// Agent rollouts: the robot's architecture (from its `hello`), for a rollback's build.
    pub arch: Option<lekiwi_crds::AgentArch>,
    /// Agent rollouts: why the robot cannot take the agent (no build for its architecture);
    /// such a robot is skipped with this message instead of started.
    pub no_build: Option<String>,
    /// Past its timeout on the shared store, which can run minutes behind the API server under
    /// load, and not read fresh this time (the controller reads a bounded number of such
    /// robots per reconcile): it does not time out on this view; a later reconcile reads it.
    pub unconfirmed: bool,
}

/// Whether the release can be rolled out.
#[derive(Clone, Debug, PartialEq)]
pub enum ReleaseCheck {
    /// The manifest exists, is valid and all its blobs are present.
    Valid,
    /// It is not; why.
    Invalid(String),
    /// Not checked (no blob store in this process).
    Unchecked,
}

/// Another deployment of the namespace that is still active and selects some of our robots.
#[derive(Clone, Debug, PartialEq)]
pub struct Overlap {
    /// The other deployment's name.
    pub deployment: String,
    /// Whether it was created before ours (it wins; ours waits for it).
    pub earlier: bool,
    /// Robots both select (only the first is named in the Conflict condition).
    pub robots: Vec<String>,
}

/// Everything the planner needs besides the deployment, gathered by the controller.
#[derive(Clone, Debug)]
pub struct Facts {
    /// The current time.
    pub now: Timestamp,
    /// The robots the selector picks (maintenance ones included; the plan excludes them).
    pub robots: Vec<RobotView>,
    /// What the robots move to: the release, or an agent rollout's version and identity (see
    /// the controller's `facts::target`).
    pub target: ReleaseRef,
    /// Validity of the release.
    pub release: ReleaseCheck,
    /// Other active deployments selecting some of the same robots.
    pub overlaps: Vec<Overlap>,
    /// Names of deployments of the namespace that are active (their marks are respected).
    pub active_deployments: Vec<String>,
}

/// A change to one robot: its mark and, when set, its `spec.release`.
#[derive(Clone, Debug, PartialEq)]
pub struct RobotWrite {
    /// The robot to patch (same namespace as the deployment).
    pub robot: String,
    /// The mark to write, replacing any mark the robot had.
    pub mark: Mark,
    /// The release to set, when the robot is started or rolled back.
    pub release: Option<ReleaseRef>,
}

/// A Kubernetes Event to record.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedEvent {
    /// Warning (failures, rollbacks) rather than Normal.
    pub warning: bool,
    /// CamelCase reason.
    pub reason: &'static str,
    /// The message, cut to 1000 characters when published.
    pub note: String,
}

/// What one reconcile should do: robot writes first, then status, then Events.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// Robots to write, in the order planned.
    pub writes: Vec<RobotWrite>,
    /// The status to apply (written only when it differs from the one read).
    pub status: RobotDeploymentStatus,
    /// Events to record, in the order they happened in this plan.
    pub events: Vec<PlannedEvent>,
    /// Look again after this long, even if nothing changes.
    pub requeue_after: Option<Duration>,
    /// Success ratio of a batch that ended in this plan, for metrics: (batch, ratio).
    pub batch_result: Option<(i32, f64)>,
    /// Whether this plan ends the rollout (Completed, RolledBack, Failed or Aborted) now.
    pub finished: bool,
}

/// What a rollout is of: the release digest and the restart annotation, hashed. A rollout's id is
/// this key, `-`, and its start time, so rolling the same release out again later (after another
/// release, or a rollback) is a new rollout whose robots' old marks do not count.
pub fn rollout_id(release: &ReleaseRef, restart: Option<&str>) -> String {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(release.digest.as_bytes());
    h.update(b"\0");
    h.update(restart.unwrap_or_default().as_bytes());
    hex::encode(&h.finalize()[..5])
}

/// The id of a rollout of the spec whose key is `key` (see [`rollout_id`]) started at `now`:
/// the key, `-`, and the start in Unix milliseconds, hex.
pub fn rollout_id_at(key: &str, now: Timestamp) -> String {
    format!("{key}-{:x}", now.as_millisecond())
}

/// When the rollout `id` started, to the millisecond (see [`rollout_id_at`]); the status's
/// `startTime` keeps whole seconds only.
pub fn rollout_start(id: &str) -> Option<Timestamp> {
    let (_, ms) = id.rsplit_once('-')?;
    Timestamp::from_millisecond(i64::from_str_radix(ms, 16).ok()?).ok()
}

/// Whether the rollout `id` is of the spec whose key is `key` (see [`rollout_id`]).
pub fn same_rollout(id: Option<&str>, key: &str) -> bool {
    id.and_then(|id| id.strip_prefix(key))
        .is_some_and(|rest| rest.starts_with('-'))
}

/// Robots per batch after the canary: a count or a percentage of `targeted`, rounded up, at
/// least 1.
pub fn batch_size(spec: &IntOrString, targeted: usize) -> usize {
    let n = match spec {
        IntOrString::Int(n) => usize::try_from(*n).unwrap_or(1),
        IntOrString::String(s) => {
            let pct: f64 = s.trim_end_matches('%').parse().unwrap_or(25.0);
            (targeted as f64 * pct / 100.0).ceil() as usize
        }
    };
    n.max(1)
}

/// Number of batches for `targeted` robots.
pub fn total_batches(canary: usize, size: usize, targeted: usize) -> usize {
    let canary = canary.min(targeted);
    usize::from(canary > 0) + (targeted - canary).div_ceil(size.max(1))
}

fn time(t: Timestamp) -> Time {
    Time(t)
}

fn secs(n: i64) -> SignedDuration {
    SignedDuration::from_secs(n.max(0))
}

/// Computes the plan: classify the robots, note new failures, check the gates (release,
/// overlaps, undo, abort), move the phase on (forming or resolving a batch, or rolling back), and
/// derive the status from where every robot ends up.
pub fn plan(deployment: &RobotDeployment, facts: &Facts) -> Plan {
    let rollout = Rollout::new(deployment, facts);
    let mut draft = Draft::begin(&rollout);
    let fleet = Fleet::classify(&rollout);
    draft.status.targeted = fleet.targeted as i32;
    draft.status.total_batches = Some(fleet.total_batches as i32);
    phase::mark_new_failures(&rollout, &fleet, &mut draft);
    let gates = Gates::check(&rollout, &mut draft);
    phase::advance(&rollout, &fleet, &gates, &mut draft);
    status::finish(&rollout, &fleet, draft)
}
#[cfg(test)]
mod tests;
