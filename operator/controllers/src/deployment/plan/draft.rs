//! What every step of the rollout planner shares: what the plan is about ([`Rollout`], fixed
//! for one plan) and what it has decided so far ([`Draft`], grown step by step).

use std::collections::BTreeMap;

use jiff::{SignedDuration, Timestamp};
use lekiwi_crds::deployment::{RolloutPhase, RolloutStrategy};
use lekiwi_crds::{Condition, ReleaseRef, RobotDeployment, RobotDeploymentStatus};

use super::{
    ABORT_ANNOTATION, Facts, Mark, Overlap, PlannedEvent, RESTART_ANNOTATION, ReleaseCheck,
    RobotView, RobotWrite, UNDO_ANNOTATION, rollout_id, rollout_id_at, rollout_start, same_rollout,
    secs, time,
};

/// Events of one reason a reconcile publishes at most; the rest are counted in one more.
pub(super) const EVENTS_PER_REASON: usize = 10;

/// The facts of one plan that no step changes: the deployment's spec, the rollout it is in,
/// the time and the robots it selects.
pub(super) struct Rollout<'a> {
    /// The deployment's name, written into every mark.
    pub name: String,
    /// This rollout's id: the spec key (see [`rollout_id`]), `-`, and its start time.
    pub id: String,
    /// Whether this plan starts the rollout (a new release or a restart).
    pub is_new: bool,
    /// The release to roll out.
    pub target: &'a ReleaseRef,
    /// Batching, thresholds, timeouts and unavailability policies.
    pub strategy: &'a RolloutStrategy,
    /// `spec.paused`: no robot is started while set.
    pub paused: bool,
    /// `metadata.generation`, for `observedGeneration` and the conditions.
    pub generation: Option<i64>,
    /// When a user asked for `rollout undo`, if they did.
    pub undo_at: Option<Timestamp>,
    /// When a user asked for `rollout abort`, if they did.
    pub abort_at: Option<Timestamp>,
    /// When this rollout started, to the millisecond (from its id; `status.startTime` keeps
    /// whole seconds only, so an undo of the previous rollout in the same second would look
    /// newer than this one).
    pub started: Option<Timestamp>,
    /// The status as read (transition times and finish times are kept from it).
    pub previous: RobotDeploymentStatus,
    /// Whether the status as read was of an unfinished rollout (so finishing now is news).
    pub was_active: bool,
    /// The current time.
    pub now: Timestamp,
    /// How long a started robot may take before it counts as failed.
    pub robot_timeout: SignedDuration,
    /// How long an unavailable robot is waited for before it is skipped.
    pub wait_timeout: SignedDuration,
    /// `spec.analysis`: what a switched robot's metrics must stay within.
    pub analysis: Option<&'a lekiwi_crds::analysis::AnalysisSpec>,
    /// The selected robots, maintenance ones included.
    pub robots: &'a [RobotView],
    /// Validity of the release.
    pub release: &'a ReleaseCheck,
    /// Other active deployments selecting some of the same robots.
    pub overlaps: &'a [Overlap],
    /// Active deployments of the namespace, ours included: their marks hold robots.
    pub active_deployments: &'a [String],
}

impl<'a> Rollout<'a> {
    /// Reads the rollout from the deployment: the same one as its status names, or a new one
    /// when the release or the restart annotation changed.
    pub fn new(deployment: &'a RobotDeployment, facts: &'a Facts) -> Self {
        let now = facts.now;
        let spec = &deployment.spec;
        let annotations = deployment.metadata.annotations.as_ref();
        let annotation = |key: &str| annotations.and_then(|a| a.get(key)).map(String::as_str);
        let key = rollout_id(&facts.target, annotation(RESTART_ANNOTATION));
        let previous = deployment.status.clone().unwrap_or_default();
        let is_new = !same_rollout(previous.rollout_id.as_deref(), &key);
        let id = if is_new {
            rollout_id_at(&key, now)
        } else {
            previous.rollout_id.clone().unwrap_or_default()
        };
        let started = rollout_start(&id);
        let was_active = matches!(
            previous.phase,
            None | Some(
                RolloutPhase::Pending
                    | RolloutPhase::Progressing
                    | RolloutPhase::Paused
                    | RolloutPhase::RollingBack
            )
        );
        Self {
            name: deployment.metadata.name.clone().unwrap_or_default(),
            id,
            is_new,
            target: &facts.target,
            strategy: &spec.strategy,
            paused: spec.paused,
            generation: deployment.metadata.generation,
            undo_at: annotation(UNDO_ANNOTATION).and_then(|v| v.parse::<Timestamp>().ok()),
            abort_at: annotation(ABORT_ANNOTATION).and_then(|v| v.parse::<Timestamp>().ok()),
            started,
            previous,
            was_active,
            now,
            robot_timeout: secs(spec.strategy.robot_timeout_seconds),
            wait_timeout: secs(spec.strategy.wait_timeout_seconds),
            analysis: spec.analysis.as_ref(),
            robots: &facts.robots,
            release: &facts.release,
            overlaps: &facts.overlaps,
            active_deployments: &facts.active_deployments,
        }
    }

    /// A mark of this rollout, for a robot whose own mark is unexpectedly missing.
    pub fn fallback_mark(&self) -> Mark {
        Mark {
            deployment: self.name.clone(),
            rollout_id: self.id.clone(),
            batch: 0,
            state: super::MarkState::Failed,
            since: Timestamp::UNIX_EPOCH,
            previous: None,
            message: None,
            failed: false,
        }
    }
}

/// What the plan has decided so far; each step reads and extends it.
pub(super) struct Draft {
    /// The status being built (phase, message and batch are set from the fields below last).
    pub status: RobotDeploymentStatus,
    /// Robot writes, in the order planned.
    pub writes: Vec<RobotWrite>,
    /// Events, in the order they happened, at most [`EVENTS_PER_REASON`] of each reason.
    pub events: Vec<PlannedEvent>,
    /// Events left out past [`EVENTS_PER_REASON`], by reason (and whether they warn).
    pub left_out: BTreeMap<&'static str, (bool, usize)>,
    /// Conditions decided by the gates; the status step adds the outcome conditions.
    pub conditions: Vec<Condition>,
    /// The earliest moment something is due (a timeout, the end of a pause).
    pub wake: Option<Timestamp>,
    /// A batch that ended in this plan, for metrics: (batch, success ratio).
    pub batch_result: Option<(i32, f64)>,
    /// The phase the rollout is in.
    pub phase: RolloutPhase,
    /// The human-readable state of the rollout.
    pub message: String,
    /// The batch being formed or resolved.
    pub current_batch: i32,
}

impl Draft {
    /// Starts from the status as read; a new rollout starts over from the canary batch.
    pub fn begin(rollout: &Rollout<'_>) -> Self {
        let mut status = RobotDeploymentStatus {
            observed_generation: rollout.generation,
            ..rollout.previous.clone()
        };
        let mut events = Vec::new();
        if rollout.is_new {
            status.rollout_id = Some(rollout.id.clone());
            status.phase = Some(RolloutPhase::Pending);
            status.current_batch = Some(0);
            status.current_batch_start_time = None;
            status.last_batch_completion_time = None;
            status.start_time = Some(time(rollout.now));
            status.completion_time = None;
            if rollout.previous.rollout_id.is_some() {
                events.push(PlannedEvent {
                    warning: false,
                    reason: "RolloutRestarted",
                    note: format!(
                        "new rollout {} of {}: starting over from the first batch",
                        rollout.id, rollout.target
                    ),
                });
            }
        }
        Self {
            phase: status.phase.unwrap_or(RolloutPhase::Pending),
            message: status.message.clone().unwrap_or_default(),
            current_batch: status.current_batch.unwrap_or(0),
            status,
            writes: Vec::new(),
            events,
            left_out: BTreeMap::new(),
            conditions: Vec::new(),
            wake: None,
            batch_result: None,
        }
    }

    /// Asks to be reconciled again by `at` at the latest.
    pub fn wake_at(&mut self, at: Timestamp) {
        self.wake = Some(self.wake.map_or(at, |w| w.min(at)));
    }

    /// Records a Normal Event.
    pub fn normal(&mut self, reason: &'static str, note: String) {
        self.event(false, reason, note);
    }

    /// Records a Warning Event.
    pub fn warning(&mut self, reason: &'static str, note: String) {
        self.event(true, reason, note);
    }

    /// Records an Event, or counts it as left out once [`EVENTS_PER_REASON`] of its reason
    /// are planned: a batch of a thousand robots that time out at once plans ten Events and a
    /// summary, not a thousand (each an API request made before the rollout can go on).
    fn event(&mut self, warning: bool, reason: &'static str, note: String) {
        if self.events.iter().filter(|e| e.reason == reason).count() < EVENTS_PER_REASON {
            self.events.push(PlannedEvent {
                warning,
                reason,
                note,
            });
        } else {
            self.left_out.entry(reason).or_insert((warning, 0)).1 += 1;
        }
    }

    /// The planned Events, each reason that had more than [`EVENTS_PER_REASON`] closed by one
    /// Event that says how many more there were.
    pub fn take_events(&mut self) -> Vec<PlannedEvent> {
        let mut events = std::mem::take(&mut self.events);
        for (reason, (warning, n)) in std::mem::take(&mut self.left_out) {
            events.push(PlannedEvent {
                warning,
                reason,
                note: format!(
                    "and {n} more {reason} in this step, left out of Events: the \
                     RobotDeployment's status and each Robot's rollout mark say which robots"
                ),
            });
        }
        events
    }

    /// Plans a write of `mark` (and of `spec.release` when `release` is set) to `robot`.
    pub fn write(&mut self, robot: &str, mark: Mark, release: Option<ReleaseRef>) {
        self.writes.push(RobotWrite {
            robot: robot.to_owned(),
            mark,
            release,
        });
    }
}
