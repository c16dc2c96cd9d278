//! The `RobotDeployment` resource: roll one release (or one `lekiwi-agent` version) out to the
//! robots a selector picks.

use k8s_openapi::apimachinery::pkg::apis::meta::v1::{LabelSelector, Time};
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use kube::CustomResource;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::agent::AgentRef;
use crate::condition::Condition;
use crate::contract::managers;
use crate::release::ReleaseRef;

/// Annotation on a RobotDeployment whose change restarts the rollout from its first batch
/// (`kubectl lekiwi rollout restart`): failed and skipped robots are tried again.
pub const RESTART_ANNOTATION: &str = "fleet.lekiwi.io/restartedAt";
/// Annotation on a RobotDeployment, an RFC 3339 time, asking to roll every robot it updated back
/// to the release it ran before (`kubectl lekiwi rollout undo`).
pub const UNDO_ANNOTATION: &str = "fleet.lekiwi.io/undoRequestedAt";
/// Annotation on a RobotDeployment, an RFC 3339 time, asking to stop its rollout where it
/// stands (`kubectl lekiwi rollout abort`): no robot starts, robots not yet switched are told to
/// stay on the release they run, switched robots keep the new one; the phase ends `Aborted`.
pub const ABORT_ANNOTATION: &str = "fleet.lekiwi.io/abortRequestedAt";
/// Annotation on a Robot holding, as JSON, its state in the release rollout that last touched it.
pub const MARK_ANNOTATION: &str = "fleet.lekiwi.io/rollout";
/// The same for agent rollouts (deployments with `spec.agent`): a robot's release and agent
/// rollouts keep separate marks, so neither overwrites the other's.
pub const AGENT_MARK_ANNOTATION: &str = "fleet.lekiwi.io/agent-rollout";

/// Most per-robot results kept in status; the event store keeps the full history.
pub const MAX_ROBOT_RESULTS: usize = 500;

/// Rolls a release (or a `lekiwi-agent` version) out to the robots a label selector picks,
/// batch by batch, skipping robots that are teleoperated, offline or unhealthy, and rolling back
/// when a batch fails.
#[derive(CustomResource, Clone, Debug, Deserialize, Serialize, JsonSchema, PartialEq)]
#[kube(
    group = "fleet.lekiwi.io",
    version = "v1alpha1",
    kind = "RobotDeployment",
    plural = "robotdeployments",
    shortname = "rdeploy",
    category = "lekiwi",
    namespaced,
    status = "RobotDeploymentStatus",
    derive = "PartialEq",
    doc = "Rolls a release (or a lekiwi-agent version) out to the robots a label selector picks, in batches, with automatic rollback.",
    printcolumn = r#"{"name":"Release","type":"string","jsonPath":".spec.release.version"}"#,
    printcolumn = r#"{"name":"Agent","type":"string","jsonPath":".spec.agent.version"}"#,
    printcolumn = r#"{"name":"Phase","type":"string","jsonPath":".status.phase"}"#,
    printcolumn = r#"{"name":"Progress","type":"string","jsonPath":".status.progress"}"#,
    printcolumn = r#"{"name":"Batch","type":"string","jsonPath":".status.batchProgress","priority":1}"#,
    printcolumn = r#"{"name":"Failed","type":"integer","jsonPath":".status.failed"}"#,
    printcolumn = r#"{"name":"Superseded","type":"integer","jsonPath":".status.superseded"}"#,
    printcolumn = r#"{"name":"Paused","type":"boolean","jsonPath":".spec.paused","priority":1}"#,
    printcolumn = r#"{"name":"Age","type":"date","jsonPath":".metadata.creationTimestamp"}"#
)]
#[serde(rename_all = "camelCase")]
#[schemars(extend("oneOf" = [{"required": ["release"]}, {"required": ["agent"]}]))]
pub struct RobotDeploymentSpec {
    /// Which robots of this namespace to update, by label. An empty selector (`{}`) selects
    /// every robot of the namespace.
    pub selector: LabelSelector,

    /// The release to roll out. Exactly one of `release` and `agent` is set.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub release: Option<ReleaseRef>,

    /// The `lekiwi-agent` version to roll out instead of a release (the builds pushed with
    /// `kubectl lekiwi agent push`). Each started robot gets it in its `spec.agent`, installs the
    /// build for its own architecture beside the running agent and restarts into it; a new
    /// agent that does not come back is undone by the robot itself and counts as failed.
    /// Rolling back sets each updated robot's `spec.agent` to the version and digest it ran
    /// before, which it switches back to from its own disk. Robots whose architecture has no
    /// build are skipped with that reason. Agent and release rollouts of a robot are
    /// independent: each kind only competes with deployments of its own kind for a robot.
    /// `analysis` applies to releases only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent: Option<AgentRef>,

    /// How fast to go and when to stop.
    #[serde(default)]
    pub strategy: RolloutStrategy,

    /// Pauses the rollout: no new robot starts until this is set back to false. Robots told
    /// to switch that have not switched yet are told to stay on the release they run (their
    /// download or pre-switch command is cancelled; the download resumes after the pause);
    /// robots that switched already finish.
    #[serde(default)]
    pub paused: bool,

    /// Watches each robot for a while after its switch and fails it when its telemetry got
    /// worse than before by more than the given ratios. Unset: a robot counts as updated as
    /// soon as it runs the release and reports healthy. Costs each started robot one Robot
    /// status write more, when its window ends.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub analysis: Option<crate::analysis::AnalysisSpec>,
    /// Which deployment owns a robot that several deployments of the namespace select: the one
    /// with the highest priority, and among equal priorities the newest (latest creation time,
    /// then the greater name). The others leave the robot alone and show it `Superseded`.
    /// From -1000 to 1000; default 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    #[schemars(range(min = -1000, max = 1000))]
    pub priority: i32,
}

fn is_zero(n: &i32) -> bool {
    *n == 0
}

/// What a RobotDeployment rolls out: a release (`spec.release`) or an agent (`spec.agent`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RolloutKind {
    /// A software release of the robot's own programs.
    Release,
    /// A `lekiwi-agent` version.
    Agent,
}

impl RolloutKind {
    /// The Robot annotation holding a robot's mark in rollouts of this kind.
    pub fn mark_annotation(self) -> &'static str {
        match self {
            RolloutKind::Release => MARK_ANNOTATION,
            RolloutKind::Agent => AGENT_MARK_ANNOTATION,
        }
    }

    /// The field manager of this kind's Robot writes (`spec.release` or `spec.agent`, and the
    /// mark): separate, so applying one never drops the field the other owns.
    pub fn manager(self) -> &'static str {
        match self {
            RolloutKind::Release => managers::ROLLOUT,
            RolloutKind::Agent => managers::AGENT_ROLLOUT,
        }
    }
}

impl RobotDeploymentSpec {
    /// What this deployment rolls out; `agent` only when it alone is set (a spec with both or
    /// neither is refused by the controller, and by the API server's schema).
    pub fn kind(&self) -> RolloutKind {
        if self.release.is_none() && self.agent.is_some() {
            RolloutKind::Agent
        } else {
            RolloutKind::Release
        }
    }

    /// What is rolled out, in words: `release 1.2.0` or `agent 0.3.0`.
    pub fn what(&self) -> String {
        match (&self.release, &self.agent) {
            (Some(r), _) => format!("release {}", r.version),
            (None, Some(a)) => format!("agent {}", a.version),
            (None, None) => "nothing".to_owned(),
        }
    }
}

/// What to do with a robot that cannot be updated right now.
#[derive(Clone, Copy, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq, Eq)]
pub enum UnavailablePolicy {
    /// Wait for the robot, up to `waitTimeoutSeconds`, then skip it.
    #[default]
    Wait,
    /// Skip the robot at once and count it as skipped.
    Skip,
}

/// Batching, thresholds and timeouts of a rollout.
#[derive(Clone, Debug, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct RolloutStrategy {
    /// Robots per batch after the canary batch: a count (`5`) or a percentage of the targeted
    /// robots (`20%`, rounded up). Default `25%`.
    #[serde(default = "default_batch_size")]
    #[schemars(schema_with = "crate::schema::batch_size")]
    pub batch_size: IntOrString,

    /// Number of robots in the first (canary) batch; 0 disables the canary batch. Default 1.
    #[serde(default = "default_canary")]
    #[schemars(range(min = 0))]
    pub canary: i32,

    /// Share of a batch, from 0 to 1, that must succeed; below it every robot updated so far
    /// is rolled back to the release it ran before. Default 0.8.
    #[serde(default = "default_success_threshold")]
    #[schemars(range(min = 0.0, max = 1.0))]
    pub success_threshold: f64,

    /// How long one robot may take to download, switch and report healthy before it counts as
    /// failed, counted from the write that started it (a batch's robots are written a few at a
    /// time). Default 600.
    #[serde(default = "default_robot_timeout")]
    #[schemars(range(min = 1))]
    pub robot_timeout_seconds: i64,

    /// Pause after each successful batch, to watch the fleet before going on. Default 0.
    #[serde(default)]
    #[schemars(range(min = 0))]
    pub pause_between_batches_seconds: i64,

    /// What to do with a robot being teleoperated: `Wait` until it is idle (never interrupt
    /// it) or `Skip` it. Default `Wait`.
    #[serde(default)]
    pub teleoperated: UnavailablePolicy,

    /// What to do with a robot that is offline or unhealthy when its turn comes: `Wait` for
    /// it or `Skip` it. Default `Skip`.
    #[serde(default = "default_unavailable")]
    pub unavailable: UnavailablePolicy,

    /// How long to wait for a teleoperated, offline or unhealthy robot before skipping it.
    /// Default 1800.
    #[serde(default = "default_wait_timeout")]
    #[schemars(range(min = 0))]
    pub wait_timeout_seconds: i64,
}

impl Default for RolloutStrategy {
    fn default() -> Self {
        Self {
            batch_size: default_batch_size(),
            canary: default_canary(),
            success_threshold: default_success_threshold(),
            robot_timeout_seconds: default_robot_timeout(),
            pause_between_batches_seconds: 0,
            teleoperated: UnavailablePolicy::Wait,
            unavailable: default_unavailable(),
            wait_timeout_seconds: default_wait_timeout(),
        }
    }
}

fn default_batch_size() -> IntOrString {
    IntOrString::String("25%".to_owned())
}
fn default_canary() -> i32 {
    1
}
fn default_success_threshold() -> f64 {
    0.8
}
fn default_robot_timeout() -> i64 {
    600
}
fn default_unavailable() -> UnavailablePolicy {
    UnavailablePolicy::Skip
}
fn default_wait_timeout() -> i64 {
    1800
}

/// Where a rollout stands.
#[derive(Clone, Copy, Debug, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
pub enum RolloutPhase {
    /// Accepted, not started yet.
    Pending,
    /// Updating robots.
    Progressing,
    /// `spec.paused` is true.
    Paused,
    /// Every targeted robot was updated or skipped.
    Completed,
    /// A batch fell below the success threshold; updated robots are being rolled back.
    RollingBack,
    /// The rollback finished.
    RolledBack,
    /// The rollout cannot proceed, for example because its release is invalid.
    Failed,
    /// A user stopped it (`kubectl lekiwi rollout abort`): switched robots keep the new release,
    /// the others stay on the one they ran; `rollout restart` goes on, `rollout undo` rolls back.
    Aborted,
}

/// Outcome for one robot of the rollout.
#[derive(Clone, Copy, Debug, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
pub enum RobotRolloutState {
    /// Not started yet.
    Pending,
    /// Waiting because the robot is teleoperated, offline or unhealthy.
    Waiting,
    /// Told to switch; waiting for its report.
    Updating,
    /// Runs the release and reports healthy.
    Updated,
    /// Did not reach the release, healthy, in time.
    Failed,
    /// Left out (teleoperated, offline, unhealthy or in maintenance).
    Skipped,
    /// Left alone: another deployment owns it (newer, or of higher `priority`); the message
    /// names it.
    Superseded,
    /// Switched back to the release it ran before.
    RolledBack,
}

/// One robot's part in the rollout.
#[derive(Clone, Debug, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct RobotResult {
    /// Name of the Robot.
    pub robot: String,
    /// Batch the robot belongs to, counting from 0 (the canary batch when `canary` > 0).
    pub batch: i32,
    /// Where this robot stands.
    pub state: RobotRolloutState,
    /// The release the robot ran before, restored on rollback.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub previous_release: Option<ReleaseRef>,
    /// Why the robot failed or was skipped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// When the robot was told to switch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_at: Option<Time>,
    /// When its outcome was known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finished_at: Option<Time>,
}

/// Observed state of a rollout, written by the RobotDeployment controller.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct RobotDeploymentStatus {
    /// Where the rollout stands.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<RolloutPhase>,
    /// Updated robots out of targeted ones, as `updated/targeted`, for `kubectl get`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub progress: Option<String>,
    /// Current batch out of all batches, as `current/total`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub batch_progress: Option<String>,
    /// Index of the batch being rolled out, counting from 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_batch: Option<i32>,
    /// Number of batches.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_batches: Option<i32>,
    /// Robots the selector picked when the rollout started.
    #[serde(default)]
    pub targeted: i32,
    /// Robots running the release and healthy.
    #[serde(default)]
    pub updated: i32,
    /// Robots that did not reach the release in time.
    #[serde(default)]
    pub failed: i32,
    /// Robots left out.
    #[serde(default)]
    pub skipped: i32,
    /// Robots not yet done.
    #[serde(default)]
    pub pending: i32,
    /// Robots the selector picks that another deployment owns (newer, or of higher
    /// `priority`): not targeted, left alone, listed in `robots` as `Superseded`.
    #[serde(default)]
    pub superseded: i32,
    /// Per-robot outcomes: robots in progress and failures first; at most 500 entries.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schemars(length(max = 500))]
    pub robots: Vec<RobotResult>,
    /// `Progressing`, `Available`, `Conflict`, `RolledBack`, ...
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schemars(extend("x-kubernetes-list-type" = "map", "x-kubernetes-list-map-keys" = ["type"]))]
    pub conditions: Vec<Condition>,
    /// The `metadata.generation` the controller last acted on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observed_generation: Option<i64>,
    /// When the rollout started.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_time: Option<Time>,
    /// When it completed, rolled back or failed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub completion_time: Option<Time>,
    /// A sentence on the current state, for people.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// Identifies the rollout in progress: derived from the release and the last restart. The
    /// robots of this rollout carry it in their `fleet.lekiwi.io/rollout` annotation, which is
    /// how the controller resumes after a restart without redeploying finished robots.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rollout_id: Option<String>,
    /// When the current batch started.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_batch_start_time: Option<Time>,
    /// When the last batch ended successfully (the next one waits
    /// `pauseBetweenBatchesSeconds` after it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_batch_completion_time: Option<Time>,
}
