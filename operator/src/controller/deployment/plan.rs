//! Pure planning for the RobotDeployment controller: from the deployment, the robots it selects
//! and the time, decide which robots to start, wait for, skip or roll back, and the status.
//!
//! All rollout state that must survive an operator restart lives where it is written anyway:
//! the deployment's status (phase, rollout id, current batch) and one annotation per robot
//! ([`Mark`], written together with `spec.release`). Batch membership, start times and the
//! release a robot ran before are read back from the marks, so a new leader resumes exactly
//! where the old one stopped and never redeploys a robot that already finished.

use std::collections::BTreeMap;
use std::time::Duration;

use jiff::{SignedDuration, Timestamp};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use lekiwi_crds::condition::merge_conditions;
use lekiwi_crds::deployment::{
    MAX_ROBOT_RESULTS, RobotResult, RobotRolloutState, RolloutPhase, UnavailablePolicy,
};
use lekiwi_crds::{
    Condition, ConditionStatus, ReleaseRef, RobotDeployment, RobotDeploymentStatus, RobotPhase,
};
use serde::{Deserialize, Serialize};

pub use lekiwi_crds::deployment::{MARK_ANNOTATION, RESTART_ANNOTATION, UNDO_ANNOTATION};

/// Condition types of a RobotDeployment.
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
    /// Left out.
    Skipped,
    /// Told to switch back to `previous` at `since`.
    RollingBack,
}

/// What the controller wrote on a robot for one rollout.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Mark {
    /// The deployment.
    pub deployment: String,
    /// Its rollout id at the time.
    pub rollout_id: String,
    /// Batch index.
    pub batch: i32,
    /// Where the robot stands.
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

/// The facts about one selected robot that a rollout needs.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RobotView {
    /// Robot name.
    pub name: String,
    /// `spec.maintenance`.
    pub maintenance: bool,
    /// `status.phase`.
    pub phase: Option<RobotPhase>,
    /// Health reported (absent counts as healthy).
    pub healthy: bool,
    /// Teleoperation reported.
    pub teleoperated: bool,
    /// `spec.release`.
    pub desired: Option<ReleaseRef>,
    /// `status.currentRelease`.
    pub current: Option<ReleaseRef>,
    /// `status.lastUpdate`: release, phase (`done`, `failed`, `rolled_back`), message, time.
    pub last_update: Option<(ReleaseRef, String, Option<String>, Option<Timestamp>)>,
    /// Its mark, if any (of any deployment).
    pub mark: Option<Mark>,
}

impl RobotView {
    fn available(&self) -> Result<(), Unavailable> {
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

    fn runs(&self, release: &ReleaseRef) -> bool {
        self.current.as_ref() == Some(release)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Unavailable {
    Teleoperated,
    Offline,
    Unhealthy,
}

impl Unavailable {
    fn as_str(self) -> &'static str {
        match self {
            Unavailable::Teleoperated => "teleoperated",
            Unavailable::Offline => "offline",
            Unavailable::Unhealthy => "unhealthy",
        }
    }
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
    /// Its name.
    pub deployment: String,
    /// Whether it was created before ours (it wins).
    pub earlier: bool,
    /// Robots both select.
    pub robots: Vec<String>,
}

/// Everything besides the deployment.
#[derive(Clone, Debug)]
pub struct Facts {
    /// The current time.
    pub now: Timestamp,
    /// The robots the selector picks (maintenance ones included; the plan excludes them).
    pub robots: Vec<RobotView>,
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
    /// Robot name.
    pub robot: String,
    /// The mark to write.
    pub mark: Mark,
    /// The release to set, when the robot is started or rolled back.
    pub release: Option<ReleaseRef>,
}

/// A Kubernetes Event to record.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedEvent {
    /// Warning rather than Normal.
    pub warning: bool,
    /// CamelCase reason.
    pub reason: &'static str,
    /// Text.
    pub note: String,
}

/// What to do.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// Robots to write, in order.
    pub writes: Vec<RobotWrite>,
    /// The status to apply.
    pub status: RobotDeploymentStatus,
    /// Events to record.
    pub events: Vec<PlannedEvent>,
    /// Look again after this long, even if nothing changes.
    pub requeue_after: Option<Duration>,
    /// Success ratio of a batch that ended in this plan, for metrics: (batch, ratio).
    pub batch_result: Option<(i32, f64)>,
    /// Whether this plan ends the rollout (Completed, RolledBack or Failed) now.
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

/// Where each robot stands in the current rollout, derived from its mark and reports.
#[derive(Clone, Debug, PartialEq)]
enum RobotState {
    /// Excluded: in maintenance.
    Maintenance,
    /// Held by another active deployment's mark.
    HeldBy(String),
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

fn classify(
    robot: &RobotView,
    d_name: &str,
    rid: &str,
    target: &ReleaseRef,
    robot_timeout: SignedDuration,
    active: &[String],
    now: Timestamp,
) -> RobotState {
    if robot.maintenance {
        return RobotState::Maintenance;
    }
    let mark = robot
        .mark
        .as_ref()
        .filter(|m| m.deployment == d_name && m.rollout_id == rid);
    let Some(mark) = mark else {
        if let Some(other) = robot.mark.as_ref()
            && other.deployment != d_name
            && active.contains(&other.deployment)
            && matches!(other.state, MarkState::Started | MarkState::RollingBack)
        {
            return RobotState::HeldBy(other.deployment.clone());
        }
        if robot.runs(target) && robot.healthy {
            return RobotState::Updated;
        }
        return RobotState::Pending;
    };
    let b = mark.batch;
    match mark.state {
        MarkState::Waiting => RobotState::Waiting(b, mark.since),
        MarkState::Failed => RobotState::Failed(b, mark.message.clone().unwrap_or_default()),
        MarkState::Skipped => RobotState::Skipped(b, mark.message.clone().unwrap_or_default()),
        MarkState::RollingBack => RobotState::RollingBack(b, mark.since),
        MarkState::Started => {
            if robot.runs(target) && robot.healthy {
                return RobotState::Succeeded(b);
            }
            if let Some((release, phase, message, at)) = &robot.last_update
                && release == target
                && lekiwi_protocol::ProgressPhase::parse(phase)
                    .is_some_and(lekiwi_protocol::ProgressPhase::is_failure)
                && at.is_none_or(|at| at >= mark.since)
            {
                return RobotState::Failed(
                    b,
                    format!(
                        "the agent reported {phase}: {}",
                        message.as_deref().unwrap_or("no details")
                    ),
                );
            }
            if now.duration_since(mark.since) > robot_timeout {
                let runs = robot
                    .current
                    .as_ref()
                    .map_or("no release".to_owned(), |r| r.version.clone());
                let why = if robot.runs(target) {
                    "unhealthy".to_owned()
                } else {
                    format!("still runs {runs}")
                };
                return RobotState::Failed(
                    b,
                    format!("timed out after {}s: {why}", robot_timeout.as_secs()),
                );
            }
            RobotState::Updating(b, mark.since)
        }
    }
}

/// Computes the plan.
pub fn plan(d: &RobotDeployment, facts: &Facts) -> Plan {
    let now = facts.now;
    let name = d.metadata.name.clone().unwrap_or_default();
    let generation = d.metadata.generation;
    let spec = &d.spec;
    let strategy = &spec.strategy;
    let target = &spec.release;
    let annotations = d.metadata.annotations.clone().unwrap_or_default();
    let key = rollout_id(
        target,
        annotations.get(RESTART_ANNOTATION).map(String::as_str),
    );
    let old = d.status.clone().unwrap_or_default();
    // A new release or a restart: a new rollout, from the canary batch.
    let new_rollout = !same_rollout(old.rollout_id.as_deref(), &key);
    let rid = if new_rollout {
        format!("{key}-{:x}", now.as_millisecond())
    } else {
        old.rollout_id.clone().unwrap_or_default()
    };
    let robot_timeout = secs(strategy.robot_timeout_seconds);
    let wait_timeout = secs(strategy.wait_timeout_seconds);

    let mut status = RobotDeploymentStatus {
        observed_generation: generation,
        ..old.clone()
    };
    let mut writes = Vec::new();
    let mut events = Vec::new();
    let mut conditions = Vec::new();
    let mut wake: Option<Timestamp> = None;
    let mut soon = |t: Timestamp| {
        wake = Some(wake.map_or(t, |w: Timestamp| w.min(t)));
    };
    let mut batch_result = None;
    let was_active = matches!(
        old.phase,
        None | Some(RolloutPhase::Pending | RolloutPhase::Progressing | RolloutPhase::Paused)
            | Some(RolloutPhase::RollingBack)
    );

    if new_rollout {
        status.rollout_id = Some(rid.clone());
        status.phase = Some(RolloutPhase::Pending);
        status.current_batch = Some(0);
        status.current_batch_start_time = None;
        status.last_batch_completion_time = None;
        status.start_time = Some(time(now));
        status.completion_time = None;
        if old.rollout_id.is_some() {
            events.push(PlannedEvent {
                warning: false,
                reason: "RolloutRestarted",
                note: format!("new rollout {rid} of {target}: starting over from the first batch"),
            });
        }
    }

    // Classify every selected robot.
    let states: Vec<(usize, RobotState)> = facts
        .robots
        .iter()
        .enumerate()
        .map(|(i, r)| {
            (
                i,
                classify(
                    r,
                    &name,
                    &rid,
                    target,
                    robot_timeout,
                    &facts.active_deployments,
                    now,
                ),
            )
        })
        .collect();
    let targeted = states
        .iter()
        .filter(|(_, s)| *s != RobotState::Maintenance)
        .count();
    let canary = usize::try_from(strategy.canary).unwrap_or(0);
    let size = batch_size(&strategy.batch_size, targeted);
    let total = total_batches(canary, size, targeted);
    status.targeted = targeted as i32;
    status.total_batches = Some(total as i32);

    // Robots whose failure became known now get a permanent mark.
    for (i, s) in &states {
        let r = &facts.robots[*i];
        if let RobotState::Failed(b, why) = s
            && r.mark
                .as_ref()
                .is_some_and(|m| m.state == MarkState::Started)
        {
            let mut mark = r
                .mark
                .clone()
                .unwrap_or_else(|| unreachable_mark(&name, &rid));
            mark.state = MarkState::Failed;
            mark.since = now;
            mark.message = Some(why.clone());
            writes.push(RobotWrite {
                robot: r.name.clone(),
                mark,
                release: None,
            });
            events.push(PlannedEvent {
                warning: true,
                reason: "RobotUpdateFailed",
                note: format!("{} (batch {b}): {why}", r.name),
            });
        }
    }

    let release_ok = match &facts.release {
        ReleaseCheck::Invalid(why) => {
            conditions.push(Condition::new(
                CONDITION_RELEASE_VALID,
                ConditionStatus::False,
                "InvalidRelease",
                why.clone(),
                generation,
            ));
            false
        }
        ReleaseCheck::Valid => {
            conditions.push(Condition::new(
                CONDITION_RELEASE_VALID,
                ConditionStatus::True,
                "ManifestComplete",
                format!("{target}: manifest and every file present"),
                generation,
            ));
            true
        }
        ReleaseCheck::Unchecked => true,
    };
    let earlier: Vec<&Overlap> = facts.overlaps.iter().filter(|o| o.earlier).collect();
    if let Some(o) = earlier.first() {
        conditions.push(Condition::new(
            CONDITION_CONFLICT,
            ConditionStatus::True,
            "SelectorOverlap",
            format!(
                "{} robot(s) (e.g. {}) are also selected by the older active deployment {}; waiting for it to finish",
                o.robots.len(),
                o.robots.first().cloned().unwrap_or_default(),
                o.deployment
            ),
            generation,
        ));
    } else {
        conditions.push(Condition::new(
            CONDITION_CONFLICT,
            ConditionStatus::False,
            "NoOverlap",
            "",
            generation,
        ));
    }

    let undo_requested = annotations.get(UNDO_ANNOTATION).is_some_and(|v| {
        v.parse::<Timestamp>()
            .ok()
            .is_some_and(|at| status.start_time.as_ref().is_none_or(|s| at > s.0))
    });

    let mut phase = status.phase.unwrap_or(RolloutPhase::Pending);
    let mut message = status.message.clone().unwrap_or_default();
    let mut current_batch = status.current_batch.unwrap_or(0);
    let pending_exist = states.iter().any(|(_, s)| *s == RobotState::Pending);

    // A completed rollout picks up robots selected later.
    if phase == RolloutPhase::Completed && pending_exist && release_ok {
        phase = RolloutPhase::Progressing;
        status.completion_time = None;
    }
    let mut rollback_started_now = false;
    if undo_requested && !matches!(phase, RolloutPhase::RollingBack | RolloutPhase::RolledBack) {
        rollback_started_now = true;
        phase = RolloutPhase::RollingBack;
        message = "rollback requested by a user (kubectl lekiwi rollout undo)".to_owned();
        events.push(PlannedEvent {
            warning: true,
            reason: "RollbackStarted",
            note: message.clone(),
        });
        start_rollback(&facts.robots, &states, &name, &rid, now, &mut writes);
    }

    match phase {
        RolloutPhase::Completed | RolloutPhase::RolledBack | RolloutPhase::Failed
            if !(phase == RolloutPhase::Failed && release_ok) => {}
        _ if !release_ok => {
            if phase != RolloutPhase::RollingBack {
                phase = RolloutPhase::Failed;
                message = match &facts.release {
                    ReleaseCheck::Invalid(why) => format!("cannot roll out {target}: {why}"),
                    _ => String::new(),
                };
                if was_active {
                    events.push(PlannedEvent {
                        warning: true,
                        reason: "InvalidRelease",
                        note: message.clone(),
                    });
                    status.completion_time = Some(time(now));
                }
            }
        }
        _ if !earlier.is_empty() && phase != RolloutPhase::RollingBack => {
            // Wait for the older deployment; robots already started keep going.
            message = format!(
                "waiting for the older deployment {} that selects some of the same robots",
                earlier[0].deployment
            );
            soon(now + SignedDuration::from_secs(30));
        }
        RolloutPhase::RollingBack if rollback_started_now => {
            soon(now + SignedDuration::from_secs(2));
        }
        RolloutPhase::RollingBack => {
            // Wait until every robot told to switch back runs its previous release.
            let mut outstanding = 0;
            for (i, s) in &states {
                let r = &facts.robots[*i];
                if let RobotState::RollingBack(_, since) = s {
                    let back = r.mark.as_ref().and_then(|m| m.previous.as_ref());
                    let done = back.is_none_or(|p| r.runs(p));
                    if !done && now.duration_since(*since) <= robot_timeout {
                        outstanding += 1;
                        soon(*since + robot_timeout + SignedDuration::from_secs(1));
                    }
                }
            }
            if outstanding == 0 {
                phase = RolloutPhase::RolledBack;
                status.completion_time = Some(time(now));
                events.push(PlannedEvent {
                    warning: true,
                    reason: "RolledBack",
                    note: format!("every updated robot is back on its previous release: {message}"),
                });
            } else {
                soon(now + SignedDuration::from_secs(10));
            }
        }
        _ => {
            // Pending, Progressing, Paused, or Failed with a now-valid release.
            if phase == RolloutPhase::Failed {
                events.push(PlannedEvent {
                    warning: false,
                    reason: "ReleaseValid",
                    note: format!("{target} is valid now; rolling out"),
                });
            }
            if phase == RolloutPhase::Pending || phase == RolloutPhase::Failed {
                events.push(PlannedEvent {
                    warning: false,
                    reason: "RolloutStarted",
                    note: format!(
                        "rolling {target} out to {targeted} robot(s) in {total} batch(es)"
                    ),
                });
            }
            phase = if spec.paused {
                RolloutPhase::Paused
            } else {
                RolloutPhase::Progressing
            };
            let outcome = progress(
                &name,
                &rid,
                d,
                facts,
                &states,
                Batching {
                    canary,
                    size,
                    current_batch: &mut current_batch,
                },
                &mut status,
                &mut writes,
                &mut events,
                &mut soon,
                wait_timeout,
                robot_timeout,
            );
            match outcome {
                Outcome::Continue(m) => message = m,
                Outcome::BatchSucceeded(b, ratio) => {
                    batch_result = Some((b, ratio));
                    message = format!("batch {b} succeeded; next batch after the pause");
                }
                Outcome::Completed => {
                    phase = RolloutPhase::Completed;
                    status.completion_time = Some(time(now));
                    message = format!("{target} rolled out");
                    events.push(PlannedEvent {
                        warning: false,
                        reason: "RolloutCompleted",
                        note: message.clone(),
                    });
                }
                Outcome::BatchFailed(b, ratio, why) => {
                    batch_result = Some((b, ratio));
                    phase = RolloutPhase::RollingBack;
                    message = format!("batch {b} failed: {why}");
                    events.push(PlannedEvent {
                        warning: true,
                        reason: "RollbackStarted",
                        note: format!("{message}; rolling back every updated robot"),
                    });
                    start_rollback(&facts.robots, &states, &name, &rid, now, &mut writes);
                    soon(now + SignedDuration::from_secs(2));
                }
            }
        }
    }

    // Counts, from the states and the writes this plan makes.
    let mut results: Vec<RobotResult> = Vec::new();
    let (mut updated, mut failed, mut skipped) = (0, 0, 0);
    let written: BTreeMap<&str, &RobotWrite> =
        writes.iter().map(|w| (w.robot.as_str(), w)).collect();
    for (i, s) in &states {
        let r = &facts.robots[*i];
        let w = written.get(r.name.as_str());
        let mark = w.map(|w| &w.mark).or(r.mark.as_ref());
        let started_at = mark
            .filter(|m| m.state != MarkState::Waiting)
            .map(|m| time(m.since));
        let previous = mark.and_then(|m| m.previous.clone());
        let (state, batch, msg) = match (s, w.map(|w| w.mark.state)) {
            (RobotState::Maintenance, _) => continue,
            (_, Some(MarkState::Started)) => (
                RobotRolloutState::Updating,
                w.map_or(0, |w| w.mark.batch),
                None,
            ),
            (_, Some(MarkState::Skipped)) => (
                RobotRolloutState::Skipped,
                w.map_or(0, |w| w.mark.batch),
                w.and_then(|w| w.mark.message.clone()),
            ),
            (_, Some(MarkState::RollingBack)) | (RobotState::RollingBack(..), _) => {
                let b = mark.map_or(0, |m| m.batch);
                let back = previous.as_ref().is_none_or(|p| r.runs(p));
                let why = match mark.filter(|m| m.failed) {
                    Some(m) => {
                        failed += 1;
                        format!(
                            "failed ({}); ",
                            m.message.as_deref().unwrap_or("no details")
                        )
                    }
                    None => String::new(),
                };
                (
                    if back {
                        RobotRolloutState::RolledBack
                    } else {
                        RobotRolloutState::Updating
                    },
                    b,
                    Some(if back {
                        format!("{why}back on its previous release")
                    } else {
                        format!("{why}switching back to its previous release")
                    }),
                )
            }
            (_, Some(MarkState::Waiting)) | (RobotState::Waiting(..), _) => (
                RobotRolloutState::Waiting,
                mark.map_or(0, |m| m.batch),
                Some(waiting_reason(r)),
            ),
            (RobotState::HeldBy(other), _) => (
                RobotRolloutState::Pending,
                -1,
                Some(format!("held by deployment {other}")),
            ),
            (RobotState::Updated, _) => {
                updated += 1;
                continue;
            }
            (RobotState::Succeeded(b), _) => {
                updated += 1;
                (RobotRolloutState::Updated, *b, None)
            }
            (RobotState::Pending, _) => continue,
            (RobotState::Updating(b, _), _) => (RobotRolloutState::Updating, *b, None),
            (RobotState::Failed(b, why), _) => (RobotRolloutState::Failed, *b, Some(why.clone())),
            (RobotState::Skipped(b, why), _) => (RobotRolloutState::Skipped, *b, Some(why.clone())),
        };
        match state {
            RobotRolloutState::Failed => failed += 1,
            RobotRolloutState::Skipped => skipped += 1,
            _ => {}
        }
        results.push(RobotResult {
            robot: r.name.clone(),
            batch,
            state,
            previous_release: previous,
            message: msg,
            started_at,
            finished_at: None,
        });
    }
    // In progress and failures first, then by batch and name; bounded.
    let rank = |s: RobotRolloutState| match s {
        RobotRolloutState::Updating | RobotRolloutState::Waiting => 0,
        RobotRolloutState::Failed => 1,
        RobotRolloutState::RolledBack | RobotRolloutState::Skipped => 2,
        _ => 3,
    };
    results.sort_by(|a, b| {
        (rank(a.state), a.batch, &a.robot).cmp(&(rank(b.state), b.batch, &b.robot))
    });
    results.truncate(MAX_ROBOT_RESULTS);
    // Keep `startedAt`/`finishedAt` stable across reconciles.
    for r in &mut results {
        if let Some(old) = old
            .robots
            .iter()
            .find(|o| o.robot == r.robot && o.state == r.state)
        {
            r.finished_at = old.finished_at.clone();
        } else if matches!(
            r.state,
            RobotRolloutState::Updated
                | RobotRolloutState::Failed
                | RobotRolloutState::Skipped
                | RobotRolloutState::RolledBack
        ) {
            r.finished_at = Some(time(now));
        }
    }
    status.robots = results;
    status.updated = updated;
    status.failed = failed;
    status.skipped = skipped;
    status.pending = (targeted as i32 - updated - failed - skipped).max(0);
    status.progress = Some(format!("{updated}/{targeted}"));
    status.current_batch = Some(current_batch);
    status.batch_progress = Some(format!(
        "{}/{}",
        (current_batch + 1).min(total.max(1) as i32),
        total
    ));
    status.phase = Some(phase);
    status.message = Some(message.clone());

    let active = matches!(
        phase,
        RolloutPhase::Pending
            | RolloutPhase::Progressing
            | RolloutPhase::Paused
            | RolloutPhase::RollingBack
    );
    conditions.push(Condition::new(
        CONDITION_PROGRESSING,
        if active {
            ConditionStatus::True
        } else {
            ConditionStatus::False
        },
        match phase {
            RolloutPhase::Paused => "Paused",
            RolloutPhase::RollingBack => "RollingBack",
            RolloutPhase::Completed => "RolloutCompleted",
            RolloutPhase::RolledBack => "RolledBack",
            RolloutPhase::Failed => "Failed",
            _ => "Updating",
        },
        message.clone(),
        generation,
    ));
    conditions.push(Condition::new(
        CONDITION_COMPLETE,
        if phase == RolloutPhase::Completed {
            ConditionStatus::True
        } else {
            ConditionStatus::False
        },
        if phase == RolloutPhase::Completed {
            "AllRobotsDone"
        } else {
            "InProgress"
        },
        format!("{updated} updated, {failed} failed, {skipped} skipped of {targeted}"),
        generation,
    ));
    conditions.push(Condition::new(
        CONDITION_ROLLED_BACK,
        if matches!(phase, RolloutPhase::RolledBack | RolloutPhase::RollingBack) {
            ConditionStatus::True
        } else {
            ConditionStatus::False
        },
        if matches!(phase, RolloutPhase::RolledBack | RolloutPhase::RollingBack) {
            "BatchBelowThreshold"
        } else {
            "NotRolledBack"
        },
        if matches!(phase, RolloutPhase::RolledBack | RolloutPhase::RollingBack) {
            message.clone()
        } else {
            String::new()
        },
        generation,
    ));
    // Kubernetes 1.20's server-side apply turns "" into null, which the schema refuses.
    for c in &mut conditions {
        if c.message.is_empty() {
            c.message = c.reason.clone();
        }
    }
    if status.message.as_deref() == Some("") {
        status.message = None;
    }
    status.conditions = merge_conditions(&old.conditions, conditions);

    let finished = was_active
        && matches!(
            phase,
            RolloutPhase::Completed | RolloutPhase::RolledBack | RolloutPhase::Failed
        );
    let requeue_after = if active {
        Some(
            wake.map(|w| {
                Duration::try_from(w.duration_since(now)).unwrap_or(Duration::from_secs(1))
            })
            .unwrap_or(Duration::from_secs(30))
            .clamp(Duration::from_secs(1), Duration::from_secs(30)),
        )
    } else {
        None
    };
    Plan {
        writes,
        status,
        events,
        requeue_after,
        batch_result,
        finished,
    }
}

fn unreachable_mark(d: &str, rid: &str) -> Mark {
    Mark {
        deployment: d.to_owned(),
        rollout_id: rid.to_owned(),
        batch: 0,
        state: MarkState::Failed,
        since: Timestamp::UNIX_EPOCH,
        previous: None,
        message: None,
        failed: false,
    }
}

fn waiting_reason(r: &RobotView) -> String {
    match r.available() {
        Err(u) => format!("waiting: {}", u.as_str()),
        Ok(()) => "waiting".to_owned(),
    }
}

/// Tells every robot this rollout started to switch back to the release it ran before.
fn start_rollback(
    robots: &[RobotView],
    states: &[(usize, RobotState)],
    d: &str,
    rid: &str,
    now: Timestamp,
    writes: &mut Vec<RobotWrite>,
) {
    for (i, s) in states {
        let r = &robots[*i];
        let started = matches!(
            s,
            RobotState::Updating(..) | RobotState::Succeeded(_) | RobotState::Failed(..)
        );
        if !started {
            continue;
        }
        let Some(mark) = r.mark.as_ref().filter(|m| m.rollout_id == rid) else {
            continue;
        };
        let mut m = mark.clone();
        m.deployment = d.to_owned();
        if let RobotState::Failed(_, why) = s {
            m.failed = true;
            m.message = Some(why.clone());
        }
        m.state = MarkState::RollingBack;
        m.since = now;
        // A robot that ran nothing before keeps the new release: there is nothing to return to.
        let release = m.previous.clone();
        writes.retain(|w| w.robot != r.name);
        writes.push(RobotWrite {
            robot: r.name.clone(),
            mark: m,
            release,
        });
    }
}

struct Batching<'a> {
    canary: usize,
    size: usize,
    current_batch: &'a mut i32,
}

enum Outcome {
    Continue(String),
    BatchSucceeded(i32, f64),
    BatchFailed(i32, f64, String),
    Completed,
}

/// Moves a progressing rollout on: resolves the current batch, or forms the next one.
#[allow(clippy::too_many_arguments)]
fn progress(
    name: &str,
    rid: &str,
    d: &RobotDeployment,
    facts: &Facts,
    states: &[(usize, RobotState)],
    batching: Batching<'_>,
    status: &mut RobotDeploymentStatus,
    writes: &mut Vec<RobotWrite>,
    events: &mut Vec<PlannedEvent>,
    soon: &mut impl FnMut(Timestamp),
    wait_timeout: SignedDuration,
    robot_timeout: SignedDuration,
) -> Outcome {
    let now = facts.now;
    let strategy = &d.spec.strategy;
    let target = &d.spec.release;
    let paused = d.spec.paused;
    let k = *batching.current_batch;
    let members: Vec<&(usize, RobotState)> = states
        .iter()
        .filter(|(_, s)| batch_of(s) == Some(k))
        .collect();

    if members.is_empty() {
        // Form batch k.
        if paused {
            return Outcome::Continue("paused before the next batch".into());
        }
        if let Some(done) = &status.last_batch_completion_time {
            let resume = done.0 + secs(strategy.pause_between_batches_seconds);
            if resume > now {
                soon(resume);
                return Outcome::Continue(format!(
                    "pausing {}s between batches",
                    strategy.pause_between_batches_seconds
                ));
            }
        }
        let size = if k == 0 && batching.canary > 0 {
            batching.canary
        } else {
            batching.size
        };
        let mut pending: Vec<&RobotView> = states
            .iter()
            .filter(|(_, s)| *s == RobotState::Pending)
            .map(|(i, _)| &facts.robots[*i])
            .collect();
        pending.sort_by(|a, b| a.name.cmp(&b.name));
        if pending.is_empty() {
            let waiting_elsewhere = states
                .iter()
                .any(|(_, s)| matches!(s, RobotState::HeldBy(_)));
            if waiting_elsewhere {
                soon(now + SignedDuration::from_secs(30));
                return Outcome::Continue("waiting for robots held by another deployment".into());
            }
            return Outcome::Completed;
        }
        status.current_batch_start_time = Some(time(now));
        let chosen: Vec<&RobotView> = pending.into_iter().take(size).collect();
        let mut started = 0;
        for r in &chosen {
            let (state, message) = match r.available() {
                Ok(()) => (MarkState::Started, None),
                Err(u) => {
                    let policy = match u {
                        Unavailable::Teleoperated => strategy.teleoperated,
                        _ => strategy.unavailable,
                    };
                    match policy {
                        UnavailablePolicy::Wait => (MarkState::Waiting, None),
                        UnavailablePolicy::Skip => (
                            MarkState::Skipped,
                            Some(format!("skipped: {} when its batch started", u.as_str())),
                        ),
                    }
                }
            };
            if state == MarkState::Started {
                started += 1;
            }
            if state == MarkState::Waiting {
                soon(now + wait_timeout);
            }
            writes.push(RobotWrite {
                robot: r.name.clone(),
                mark: Mark {
                    deployment: name.to_owned(),
                    rollout_id: rid.to_owned(),
                    batch: k,
                    state,
                    since: now,
                    previous: r.current.clone(),
                    message,
                    failed: false,
                },
                release: (state == MarkState::Started).then(|| target.clone()),
            });
        }
        soon(now + robot_timeout + SignedDuration::from_secs(1));
        events.push(PlannedEvent {
            warning: false,
            reason: "BatchStarted",
            note: format!(
                "batch {k}: {} robot(s), {started} started now",
                chosen.len()
            ),
        });
        return Outcome::Continue(format!(
            "batch {k}: updating {started} of {} robot(s)",
            chosen.len()
        ));
    }

    // Resolve batch k.
    let mut unresolved = 0;
    let (mut ok, mut bad) = (0usize, Vec::new());
    for (i, s) in &members {
        let r = &facts.robots[*i];
        match s {
            RobotState::Succeeded(_) => ok += 1,
            RobotState::Failed(_, why) => bad.push(format!("{}: {why}", r.name)),
            RobotState::Skipped(..) => {}
            RobotState::Updating(_, since) => {
                unresolved += 1;
                soon(*since + robot_timeout + SignedDuration::from_secs(1));
            }
            RobotState::Waiting(_, since) => {
                if now.duration_since(*since) > wait_timeout {
                    let mut mark = r
                        .mark
                        .clone()
                        .unwrap_or_else(|| unreachable_mark(name, rid));
                    mark.state = MarkState::Skipped;
                    mark.message = Some(format!(
                        "skipped: still {} after {}s",
                        waiting_reason(r).trim_start_matches("waiting: "),
                        wait_timeout.as_secs()
                    ));
                    mark.since = now;
                    writes.push(RobotWrite {
                        robot: r.name.clone(),
                        mark,
                        release: None,
                    });
                } else if !paused && r.available().is_ok() {
                    let mut mark = r
                        .mark
                        .clone()
                        .unwrap_or_else(|| unreachable_mark(name, rid));
                    mark.state = MarkState::Started;
                    mark.since = now;
                    mark.previous = r.current.clone();
                    writes.push(RobotWrite {
                        robot: r.name.clone(),
                        mark,
                        release: Some(target.clone()),
                    });
                    unresolved += 1;
                    soon(now + robot_timeout + SignedDuration::from_secs(1));
                } else {
                    unresolved += 1;
                    soon(*since + wait_timeout + SignedDuration::from_secs(1));
                }
            }
            _ => {}
        }
    }
    if unresolved > 0 {
        return Outcome::Continue(format!(
            "batch {k}: {ok} updated, {} failed, {unresolved} in progress{}",
            bad.len(),
            if paused { " (paused)" } else { "" }
        ));
    }
    let attempted = ok + bad.len();
    let ratio = if attempted == 0 {
        1.0
    } else {
        ok as f64 / attempted as f64
    };
    if ratio < strategy.success_threshold {
        let why = format!(
            "{} of {attempted} robot(s) failed ({:.0}% succeeded, below the {:.0}% threshold); first: {}",
            bad.len(),
            ratio * 100.0,
            strategy.success_threshold * 100.0,
            bad.first().cloned().unwrap_or_default()
        );
        return Outcome::BatchFailed(k, ratio, why);
    }
    *batching.current_batch = k + 1;
    status.last_batch_completion_time = Some(time(now));
    status.current_batch_start_time = None;
    events.push(PlannedEvent {
        warning: false,
        reason: "BatchSucceeded",
        note: format!(
            "batch {k}: {ok} of {attempted} updated ({:.0}%)",
            ratio * 100.0
        ),
    });
    soon(now + secs(strategy.pause_between_batches_seconds));
    Outcome::BatchSucceeded(k, ratio)
}

fn batch_of(s: &RobotState) -> Option<i32> {
    match s {
        RobotState::Waiting(b, _)
        | RobotState::Updating(b, _)
        | RobotState::Succeeded(b)
        | RobotState::Failed(b, _)
        | RobotState::Skipped(b, _)
        | RobotState::RollingBack(b, _) => Some(*b),
        _ => None,
    }
}

#[cfg(test)]
mod tests;
