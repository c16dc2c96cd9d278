//! The `Robot` resource: one LeKiwi robot, what its lab wants of it and what it last reported.

use k8s_openapi::apimachinery::pkg::apis::meta::v1::{MicroTime, Time};
use kube::CustomResource;
use lekiwi_protocol::rules;

use crate::text::Text;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::agent::{AgentRef, AgentUpdateReport};
use crate::condition::Condition;
use crate::release::ReleaseRef;

/// Condition type: the robot's agent holds a live connection to a gateway.
pub const CONDITION_CONNECTED: &str = "Connected";
/// Condition type: the agent's own health check passes.
pub const CONDITION_HEALTHY: &str = "Healthy";
/// Condition type: somebody is teleoperating the robot right now.
pub const CONDITION_TELEOPERATING: &str = "Teleoperating";
/// Condition type: the robot runs the release its spec asks for.
pub const CONDITION_UP_TO_DATE: &str = "UpToDate";

/// A LeKiwi robot of the fleet. The spec is what the lab sets; the status is what the robot's
/// agent last reported through a gateway, and what the Robot controller concluded from it.
#[derive(CustomResource, Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[kube(
    group = "fleet.lekiwi.io",
    version = "v1alpha1",
    kind = "Robot",
    plural = "robots",
    shortname = "rb",
    category = "lekiwi",
    namespaced,
    status = "RobotStatus",
    derive = "Default",
    derive = "PartialEq",
    doc = "A LeKiwi robot: the release it should run, and its connection, health and telemetry as reported by its agent.",
    printcolumn = r#"{"name":"Display Name","type":"string","jsonPath":".spec.displayName","priority":1}"#,
    printcolumn = r#"{"name":"Phase","type":"string","jsonPath":".status.phase"}"#,
    printcolumn = r#"{"name":"Release","type":"string","jsonPath":".status.currentRelease.version"}"#,
    printcolumn = r#"{"name":"Desired","type":"string","jsonPath":".spec.release.version"}"#,
    printcolumn = r#"{"name":"Teleop","type":"string","jsonPath":".status.conditions[?(@.type==\"Teleoperating\")].status"}"#,
    printcolumn = r#"{"name":"Heartbeat","type":"date","jsonPath":".status.lastHeartbeatTime"}"#,
    printcolumn = r#"{"name":"Agent","type":"string","jsonPath":".status.agentVersion","priority":1}"#,
    printcolumn = r#"{"name":"Desired Agent","type":"string","jsonPath":".spec.agent.version","priority":1}"#,
    printcolumn = r#"{"name":"Gateway","type":"string","jsonPath":".status.gateway","priority":1}"#,
    printcolumn = r#"{"name":"Age","type":"date","jsonPath":".metadata.creationTimestamp"}"#
)]
#[serde(rename_all = "camelCase")]
pub struct RobotSpec {
    /// Name people use for the robot, for example `Kiwi 7 (lab bench 2)`. Free text, at most
    /// 253 characters; the resource name stays the stable identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = 253))]
    pub display_name: Option<String>,

    /// What the robot is built from. Informational: rollouts do not read it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hardware: Option<Hardware>,

    /// Cordons the robot: while true no rollout touches it and its phase is `Maintenance`.
    /// The agent stays connected and keeps reporting.
    #[serde(default)]
    pub maintenance: bool,

    /// The release this robot should run. Set by a RobotDeployment while it rolls out, or by
    /// hand; the robot's agent downloads and switches to it. Unset: keep whatever runs now.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub release: Option<ReleaseRef>,

    /// The `lekiwi-agent` version this robot should run, with one build per architecture.
    /// The gateway sends the robot's agent the build for its own architecture; the agent
    /// installs it beside itself and restarts into it, and switches back by itself when the
    /// new agent does not reach the gateway in time. Unset: keep the agent that runs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent: Option<AgentRef>,
}

/// Description of a robot's hardware.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct Hardware {
    /// Hardware model, for example `LeKiwi v1`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// Serial number or asset tag.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub serial: Option<String>,
    /// Single-board computer, for example `Raspberry Pi 5 8GB`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub computer: Option<String>,
    /// Cameras attached, for example `front` and `wrist`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cameras: Vec<String>,
    /// Free-form notes, for example which arm or gripper is mounted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub notes: Option<String>,
}

/// The robot's lifecycle phase, derived by the Robot controller.
#[derive(Clone, Copy, Debug, Deserialize, Serialize, JsonSchema, PartialEq, Eq, Hash)]
pub enum RobotPhase {
    /// The robot has never connected.
    Pending,
    /// Connected, with a recent heartbeat, through a live gateway.
    Online,
    /// Disconnected, or its last heartbeat is older than the grace period.
    Offline,
    /// The gateway that held its connection stopped renewing its Lease: nobody can tell.
    Unknown,
    /// Cordoned by `spec.maintenance`.
    Maintenance,
}

impl RobotPhase {
    /// Every phase, for metrics that report a value per phase.
    pub const ALL: [RobotPhase; 5] = [
        RobotPhase::Pending,
        RobotPhase::Online,
        RobotPhase::Offline,
        RobotPhase::Unknown,
        RobotPhase::Maintenance,
    ];

    /// The phase as written in status.
    pub fn as_str(self) -> &'static str {
        match self {
            RobotPhase::Pending => "Pending",
            RobotPhase::Online => "Online",
            RobotPhase::Offline => "Offline",
            RobotPhase::Unknown => "Unknown",
            RobotPhase::Maintenance => "Maintenance",
        }
    }
}

impl std::fmt::Display for RobotPhase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Observed state of a robot. Two writers share it through server-side apply: the gateway that
/// holds the robot's connection writes the presence facts (`connected`, `gateway`,
/// `lastHeartbeatTime`, system facts, telemetry, ...) together with the `phase`, `conditions`
/// and `observedGeneration` they imply (one write per change); the Robot controller computes
/// the same three by the same rules and writes them where they differ (heartbeat expiry, a dead
/// gateway, a spec change).
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct RobotStatus {
    /// Lifecycle phase: `Pending` (never connected), `Online`, `Offline`, `Unknown` (its
    /// gateway is gone) or `Maintenance`. Derived by the Robot controller's rules; the gateway
    /// writes it with the facts it follows from, the controller when time or a Lease changes it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<RobotPhase>,

    /// Current conditions: `Connected`, `Healthy`, `Teleoperating`, `UpToDate`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    #[schemars(extend("x-kubernetes-list-type" = "map", "x-kubernetes-list-map-keys" = ["type"]))]
    pub conditions: Vec<Condition>,

    /// The `metadata.generation` of the spec the controller last acted on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observed_generation: Option<i64>,

    /// Whether the gateway named in `gateway` holds a live connection to the robot's agent.
    /// Written by the gateway.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub connected: Option<bool>,

    /// Identity of the gateway holding (or that last held) the connection; also the name of
    /// that gateway's Lease, which it renews while it is alive.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gateway: Option<Text>,

    /// How the agent talks to the gateway: `websocket`, or `poll` for legacy polling agents.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub protocol: Option<Text>,

    /// When the gateway last recorded a heartbeat. Refreshed on every change and at least every
    /// few minutes while connected, not on every heartbeat.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_heartbeat_time: Option<Time>,

    /// When the current connection was established.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub connected_since: Option<Time>,

    /// The session epoch of the connection named in `gateway`: microseconds since the Unix epoch
    /// when that session opened, raised above any epoch its gateway saw on this Robot before, so
    /// a later session of the robot, on whichever gateway replica, has a higher one (two
    /// replicas that raised theirs above the same epoch are ordered by gateway name, the name
    /// that sorts last being the later). A gateway writes the robot's status only with a
    /// `resourceVersion` precondition and never over a later session, and a gateway whose
    /// session of the robot is earlier than this closes it (`replaced`): one live session per
    /// robot across replicas. Written by the gateway.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub session_epoch: Option<i64>,

    /// Version of the agent software running on the robot.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = rules::MAX_TEXT_CHARS))]
    pub agent_version: Option<Text>,

    /// Digest of the agent build running on the robot (`sha256:` and 64 hex digits): the file
    /// its service manager starts, an A/B slot's binary or the package's own. Setting
    /// `spec.agent` back to this version and digest later switches the robot back to this
    /// build from its own disk, without a download, even if it was never pushed. Absent for
    /// agents older than 0.2 and for legacy polling robots.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(regex(pattern = rules::DIGEST_PATTERN))]
    pub agent_digest: Option<Text>,

    /// The release the robot reports it runs now.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub current_release: Option<ReleaseRef>,

    /// Network address the robot connected from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,

    /// Result of the agent's own health check.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub health: Option<HealthReport>,

    /// Whether the agent detects teleoperation right now.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub teleoperation: Option<TeleoperationReport>,

    // The larger reports below are boxed: gateways and the controller cache every Robot, and a
    // boxed report costs a pointer while unset and its own size only once written (the JSON
    // and the schema are the same).
    /// Facts about the robot's computer, reported at connect.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub system: Option<Box<SystemInfo>>,

    /// A small summary of recent telemetry; full series live in the event store.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub telemetry: Option<Box<TelemetrySummary>>,

    /// Outcome of the agent's latest release update, as it reported it. Written by the gateway
    /// when an update ends; rollouts read it to see failures without waiting for a timeout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_update: Option<Box<UpdateReport>>,

    /// The gateway's summary of the robot's metrics before and after its last switch, judged
    /// by rollouts with `spec.analysis`. Written by the gateway.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub analysis: Option<Box<crate::analysis::AnalysisReport>>,
    /// How the robot's latest agent update (`spec.agent`) went. Written by the gateway.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub agent_update: Option<Box<AgentUpdateReport>>,
}

/// How an agent's release update ended. Every field is optional: a gateway that restarts forgets
/// the report, and Kubernetes 1.20's server-side apply then nulls the fields it owned.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct UpdateReport {
    /// The release the agent was told to run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub release: Option<ReleaseRef>,
    /// `done`, `failed` (nothing switched), `rolled_back` (switched, unhealthy, switched
    /// back) or `cancelled` (stopped because the robot should no longer run it: a pause, an
    /// undo or an automatic rollback; before the switch, or after it and switched back).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<String>,
    /// The agent's explanation.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// When the gateway received the outcome, to the microsecond (a rollout tells the outcome
    /// of the update it started from that of an update it cancelled a moment before).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time: Option<MicroTime>,
}

/// The agent's own health verdict.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct HealthReport {
    /// Whether every health check passes.
    pub healthy: bool,
    /// Why not, when `healthy` is false.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = rules::MAX_MESSAGE_CHARS))]
    pub message: Option<String>,
    /// Which check failed, as one CamelCase word (e.g. `HostProcessNotRunning`, `DiskFull`);
    /// the `Healthy` condition's reason. Absent from agents that do not send one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(min = 1, max = rules::MAX_HEALTH_REASON_CHARS), regex(pattern = rules::HEALTH_REASON_PATTERN))]
    pub reason: Option<String>,
}

/// The agent's teleoperation verdict.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct TeleoperationReport {
    /// Whether the robot is being teleoperated.
    pub active: bool,
    /// Weighted indicator score behind the verdict, 0 to 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(range(min = 0.0, max = 1.0))]
    pub score: Option<f64>,
    /// When `active` last changed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub since: Option<Time>,
}

/// Facts about the robot's computer.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct SystemInfo {
    /// Host name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = rules::MAX_TEXT_CHARS))]
    pub hostname: Option<String>,
    /// Operating system and version, for example `Debian GNU/Linux 12 (bookworm)`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = rules::MAX_TEXT_CHARS))]
    pub os: Option<Text>,
    /// Kernel version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = rules::MAX_TEXT_CHARS))]
    pub kernel: Option<Text>,
    /// CPU architecture, for example `aarch64`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(length(max = rules::MAX_TEXT_CHARS))]
    pub arch: Option<Text>,
    /// Number of logical CPUs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpus: Option<u32>,
    /// Total memory in bytes; at most 2^63 - 1 (`int64`, as Kubernetes stores integers).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(extend("format" = "int64"))]
    pub memory_bytes: Option<u64>,
}

/// Latest telemetry values, refreshed together with the heartbeat time.
#[derive(Clone, Debug, Default, Deserialize, Serialize, JsonSchema, PartialEq)]
#[serde(rename_all = "camelCase")]
pub struct TelemetrySummary {
    /// CPU use in percent of all cores.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpu_percent: Option<f64>,
    /// Memory in use, percent of total.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_percent: Option<f64>,
    /// SoC temperature in degrees Celsius.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature_celsius: Option<f64>,
    /// Battery charge in percent, when the robot reports one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub battery_percent: Option<f64>,
    /// Resident memory of the LeKiwi host process (the agent's `hostProcessPattern`), bytes; at
    /// most 2^63 - 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(extend("format" = "int64"))]
    pub host_memory_bytes: Option<u64>,
    /// CPU use of the LeKiwi host process, percent of all cores.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_cpu_percent: Option<f64>,
}

impl Robot {
    /// The condition of the given type, if the status has one.
    pub fn condition(&self, r#type: &str) -> Option<&Condition> {
        self.status
            .as_ref()
            .and_then(|s| crate::condition::find(&s.conditions, r#type))
    }
}
