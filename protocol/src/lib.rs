//! Wire types of the agent-gateway protocol: versioned JSON messages in WebSocket text frames.
//!
//! `PROTOCOL.md` beside this crate is the specification; this module is its Rust rendering.
//! Pure types: no kube, no axum, no I/O.

use serde::{Deserialize, Serialize};

pub mod release;

/// Protocol version spoken by this crate. A peer with another version is refused.
pub const PROTOCOL_VERSION: u32 = 1;

/// Largest frame either side accepts by default, in bytes. The gateway may announce a smaller
/// limit in `welcome`.
pub const MAX_FRAME_BYTES: usize = 256 * 1024;

/// Path of the WebSocket endpoint on the gateway.
pub const AGENT_PATH: &str = "/v1/agent";

/// Header naming the robot when enrolling with a fleet enrollment token.
pub const ROBOT_HEADER: &str = "x-lekiwi-robot";

/// Errors decoding a frame.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The frame is larger than the limit.
    #[error("frame of {size} bytes exceeds the limit of {limit} bytes")]
    FrameTooLarge {
        /// Size of the frame.
        size: usize,
        /// The limit.
        limit: usize,
    },
    /// The frame is not valid JSON of a known message type.
    #[error("malformed frame: {0}")]
    Malformed(#[from] serde_json::Error),
}

impl Error {
    /// The error code to answer this decoding error with.
    pub fn code(&self) -> ErrorCode {
        match self {
            Error::FrameTooLarge { .. } => ErrorCode::FrameTooLarge,
            Error::Malformed(e) if e.is_data() => ErrorCode::UnknownMessage,
            Error::Malformed(_) => ErrorCode::Malformed,
        }
    }
}

/// Machine-readable error codes carried by [`ServerMessage::Error`] and by close frames.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// The frame is not JSON.
    Malformed,
    /// JSON, but not a message of this protocol version (unknown `type` or missing fields).
    UnknownMessage,
    /// The frame exceeded the size limit.
    FrameTooLarge,
    /// The `hello` asked for a protocol version the gateway does not speak. Fatal.
    UnsupportedVersion,
    /// A message that is not allowed at this point, e.g. a second `hello`.
    UnexpectedMessage,
    /// Too many messages per second; the message was dropped. Sustained abuse is fatal.
    RateLimited,
    /// No `hello` within the handshake timeout. Fatal.
    HandshakeTimeout,
    /// A newer connection of the same robot replaced this one. Fatal.
    Replaced,
    /// The gateway could not store a durable message; the agent must resend it later.
    StoreUnavailable,
    /// The gateway is shutting down; reconnect (to another replica). Fatal.
    ShuttingDown,
    /// Anything else on the gateway's side.
    Internal,
    /// A code this version does not know (sent by a newer gateway); honour `fatal`.
    #[serde(other)]
    Unknown,
}

/// A release as the agent reports or is told to run it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
pub struct Release {
    /// Version name.
    pub version: String,
    /// `sha256:<hex>` digest of the release manifest.
    pub digest: String,
}

/// Facts about the robot's computer, sent once in `hello`.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct SystemFacts {
    /// Host name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hostname: Option<String>,
    /// Operating system name and version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub os: Option<String>,
    /// Kernel version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kernel: Option<String>,
    /// CPU architecture, e.g. `aarch64`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arch: Option<String>,
    /// Logical CPUs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpus: Option<u32>,
    /// Total memory in bytes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_bytes: Option<u64>,
}

/// The agent's health verdict.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct Health {
    /// Whether every check passes.
    pub healthy: bool,
    /// Why not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

/// The agent's teleoperation verdict.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Teleoperation {
    /// Whether somebody operates the robot.
    pub active: bool,
    /// Weighted indicator score, 0 to 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<f64>,
}

/// Current readings sent with every heartbeat; all optional.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Vitals {
    /// Seconds since boot.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uptime_s: Option<u64>,
    /// CPU use, percent of all cores.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cpu_percent: Option<f64>,
    /// Memory in use, percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub memory_percent: Option<f64>,
    /// One-minute load average.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub load1: Option<f64>,
    /// Root file system use, percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disk_percent: Option<f64>,
    /// SoC temperature, degrees Celsius.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub temperature_c: Option<f64>,
    /// Battery charge, percent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub battery_percent: Option<f64>,
}

/// Phase of a command in `progress.phase` (§12). The agent sends these; the gateway and the
/// rollout planner match on them instead of on strings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProgressPhase {
    /// Fetching the manifest and missing blobs.
    Downloading,
    /// Checking the blobs already held.
    Verifying,
    /// Building `releases/<version>/`.
    Assembling,
    /// Running the pre-switch command.
    PreSwitch,
    /// Pointing `current` at a release.
    Switching,
    /// Running the restart command.
    Restarting,
    /// Waiting for the health command to pass.
    HealthCheck,
    /// Finished: the release runs.
    Done,
    /// Finished: nothing was switched (or the switch was interrupted before it happened).
    Failed,
    /// Finished: the release was switched to, failed, and the previous one runs again.
    RolledBack,
}

impl ProgressPhase {
    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            ProgressPhase::Downloading => "downloading",
            ProgressPhase::Verifying => "verifying",
            ProgressPhase::Assembling => "assembling",
            ProgressPhase::PreSwitch => "pre_switch",
            ProgressPhase::Switching => "switching",
            ProgressPhase::Restarting => "restarting",
            ProgressPhase::HealthCheck => "health_check",
            ProgressPhase::Done => "done",
            ProgressPhase::Failed => "failed",
            ProgressPhase::RolledBack => "rolled_back",
        }
    }
}

impl std::fmt::Display for ProgressPhase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl ProgressPhase {
    /// Every phase, in the order a deploy goes through them.
    pub const ALL: [ProgressPhase; 10] = [
        ProgressPhase::Downloading,
        ProgressPhase::Verifying,
        ProgressPhase::Assembling,
        ProgressPhase::PreSwitch,
        ProgressPhase::Switching,
        ProgressPhase::Restarting,
        ProgressPhase::HealthCheck,
        ProgressPhase::Done,
        ProgressPhase::Failed,
        ProgressPhase::RolledBack,
    ];

    /// The phase a wire name stands for; `None` for a name this version does not know.
    pub fn parse(name: &str) -> Option<ProgressPhase> {
        Self::ALL.into_iter().find(|p| p.as_str() == name)
    }

    /// Whether the command is over (`done`, `failed` or `rolled_back`).
    pub fn is_final(self) -> bool {
        matches!(
            self,
            ProgressPhase::Done | ProgressPhase::Failed | ProgressPhase::RolledBack
        )
    }

    /// Whether the command ended without its release running (`failed` or `rolled_back`).
    pub fn is_failure(self) -> bool {
        matches!(self, ProgressPhase::Failed | ProgressPhase::RolledBack)
    }
}

/// One stored agent event as the gateway's events endpoint answers it (and as its store keeps
/// it): durable `event` frames, and `progress` frames with kind `progress`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoredEvent {
    /// The robot's sequence number, shared with telemetry.
    pub seq: u64,
    /// When it happened on the robot, Unix milliseconds.
    pub ts_ms: i64,
    /// What happened, e.g. `teleoperation_started` or `progress`.
    pub kind: String,
    /// `info`, `warning` or `error`.
    pub severity: String,
    /// Human-readable text.
    pub message: String,
    /// Structured details; `null` when there are none.
    #[serde(default)]
    pub data: serde_json::Value,
}

/// Milliseconds since the Unix epoch by this machine's clock (0 before 1970; saturates).
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
        .unwrap_or_default()
}

/// Severity of an agent event.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Severity {
    /// Routine.
    Info,
    /// Worth a look.
    Warning,
    /// Something failed.
    Error,
    /// A severity this version does not know (from a newer agent); stored as `unknown`.
    #[serde(other)]
    Unknown,
}

/// One telemetry sample.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Sample {
    /// Metric name, e.g. `cpu_percent`.
    pub metric: String,
    /// When it was taken, Unix milliseconds.
    pub ts_ms: i64,
    /// The value.
    pub value: f64,
}

/// A deployment command's payload.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "action", rename_all = "snake_case")]
pub enum Command {
    /// Download and switch to a release.
    Deploy {
        /// The release.
        release: Release,
        /// Where to fetch the manifest, relative to the gateway's base URL.
        manifest_url: String,
    },
    /// Stop a deployment in progress.
    Cancel,
    /// Switch back to the release that ran before.
    Rollback {
        /// The release to return to.
        release: Release,
    },
}

/// Messages from the agent to the gateway.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum AgentMessage {
    /// First frame of every connection.
    Hello {
        /// Protocol version the agent speaks.
        protocol_version: u32,
        /// Version of the agent software.
        agent_version: String,
        /// Facts about the computer.
        #[serde(default)]
        system: SystemFacts,
        /// Release running now.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        current_release: Option<Release>,
        /// Highest sequence number the gateway acknowledged on an earlier connection.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        last_acked_seq: Option<u64>,
        /// Health at connect time.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        health: Option<Health>,
        /// Teleoperation at connect time.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        teleoperation: Option<Teleoperation>,
    },
    /// Liveness and current state, every `heartbeat_interval_s`.
    Heartbeat {
        /// The agent's clock, Unix milliseconds; echoed in the ack for round-trip time.
        sent_at_ms: i64,
        /// Round-trip time of the previous heartbeat, milliseconds.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rtt_ms: Option<f64>,
        /// Readings.
        #[serde(default)]
        vitals: Vitals,
        /// Release running now.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        current_release: Option<Release>,
        /// Health now.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        health: Option<Health>,
        /// Teleoperation now.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        teleoperation: Option<Teleoperation>,
    },
    /// A durable event; acknowledged by `ack` once stored.
    Event {
        /// Per-robot sequence number, shared with `telemetry` and `progress`.
        seq: u64,
        /// When it happened, Unix milliseconds.
        ts_ms: i64,
        /// Short machine-readable kind, e.g. `teleoperation_started`.
        kind: String,
        /// Severity.
        severity: Severity,
        /// Human-readable text.
        #[serde(default)]
        message: String,
        /// Free-form details.
        #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
        data: serde_json::Value,
    },
    /// A durable batch of telemetry samples.
    Telemetry {
        /// Per-robot sequence number.
        seq: u64,
        /// The samples, at most 1000.
        samples: Vec<Sample>,
    },
    /// Durable progress of a command.
    Progress {
        /// Per-robot sequence number.
        seq: u64,
        /// The command this reports on.
        command_id: String,
        /// Phase: a [`ProgressPhase`] wire name (`downloading`, ..., `done`, `failed`,
        /// `rolled_back`); kept as text so a newer agent's phase is still stored.
        phase: String,
        /// Percent done, 0 to 100.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        percent: Option<f64>,
        /// Details.
        #[serde(default)]
        message: String,
    },
}

impl AgentMessage {
    /// The sequence number of a durable message.
    pub fn seq(&self) -> Option<u64> {
        match self {
            AgentMessage::Event { seq, .. }
            | AgentMessage::Telemetry { seq, .. }
            | AgentMessage::Progress { seq, .. } => Some(*seq),
            AgentMessage::Hello { .. } | AgentMessage::Heartbeat { .. } => None,
        }
    }
}

/// Messages from the gateway to the agent.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    /// Answer to `hello`: the session is established.
    Welcome {
        /// Protocol version the gateway speaks.
        protocol_version: u32,
        /// The robot's namespace and name as the gateway knows it.
        robot: String,
        /// Seconds between heartbeats.
        heartbeat_interval_s: u32,
        /// Largest frame the gateway accepts.
        max_frame_bytes: usize,
        /// Messages per second the gateway accepts (sustained).
        max_messages_per_second: u32,
        /// Highest sequence number stored for this robot; the agent may drop everything up to it.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        stored_seq: Option<u64>,
        /// A new per-robot token, sent once after enrollment. The agent must persist it and
        /// use it instead of the enrollment token from now on.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        robot_token: Option<String>,
    },
    /// Answer to `heartbeat`.
    HeartbeatAck {
        /// The agent's `sent_at_ms`, echoed.
        sent_at_ms: i64,
        /// The gateway's clock, Unix milliseconds.
        server_time_ms: i64,
    },
    /// A durable message is stored (or was already stored).
    Ack {
        /// Its sequence number.
        seq: u64,
    },
    /// Something to do.
    Command {
        /// Unique id, echoed in `progress`.
        command_id: String,
        /// What to do.
        #[serde(flatten)]
        command: Command,
    },
    /// A refused frame or a fatal condition.
    Error {
        /// Machine-readable code.
        code: ErrorCode,
        /// Human-readable text.
        message: String,
        /// Whether the gateway closes the connection after this frame.
        #[serde(default)]
        fatal: bool,
        /// The sequence number of the durable message this refuses, if it was one; the agent
        /// keeps that message and resends it later.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seq: Option<u64>,
    },
}

/// Decodes one text frame, enforcing `limit` before parsing.
pub fn decode<T: serde::de::DeserializeOwned>(frame: &str, limit: usize) -> Result<T, Error> {
    if frame.len() > limit {
        return Err(Error::FrameTooLarge {
            size: frame.len(),
            limit,
        });
    }
    Ok(serde_json::from_str(frame)?)
}

/// Encodes a message as one text frame.
pub fn encode<T: Serialize>(msg: &T) -> String {
    // These types hold only strings, numbers, JSON values and string-keyed maps: cannot fail.
    serde_json::to_string(msg).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hello_has_a_type_tag_and_round_trips() {
        let hello = AgentMessage::Hello {
            protocol_version: PROTOCOL_VERSION,
            agent_version: "0.1.0".into(),
            system: SystemFacts {
                arch: Some("aarch64".into()),
                cpus: Some(4),
                ..Default::default()
            },
            current_release: None,
            last_acked_seq: Some(41),
            health: None,
            teleoperation: None,
        };
        let frame = encode(&hello);
        assert!(frame.starts_with(r#"{"type":"hello""#), "{frame}");
        assert_eq!(
            decode::<AgentMessage>(&frame, MAX_FRAME_BYTES).unwrap(),
            hello
        );
    }

    #[test]
    fn spec_examples_decode() {
        // The frames shown in PROTOCOL.md, verbatim.
        let hb = r#"{"type":"heartbeat","sent_at_ms":1763800000000,"rtt_ms":3.2,"vitals":{"cpu_percent":12.5,"temperature_c":51.0},"teleoperation":{"active":false}}"#;
        assert!(matches!(
            decode::<AgentMessage>(hb, MAX_FRAME_BYTES).unwrap(),
            AgentMessage::Heartbeat { .. }
        ));
        let ev = r#"{"type":"event","seq":42,"ts_ms":1763800000123,"kind":"teleoperation_started","severity":"info","message":"operator connected on :5555"}"#;
        assert_eq!(
            decode::<AgentMessage>(ev, MAX_FRAME_BYTES).unwrap().seq(),
            Some(42)
        );
        let cmd = r#"{"type":"command","command_id":"c1","action":"deploy","release":{"version":"1.2.0","digest":"sha256:00"},"manifest_url":"/v1/blobs/sha256:00"}"#;
        assert!(matches!(
            decode::<ServerMessage>(cmd, MAX_FRAME_BYTES).unwrap(),
            ServerMessage::Command {
                command: Command::Deploy { .. },
                ..
            }
        ));
    }

    #[test]
    fn newer_enum_values_still_decode() {
        let err = r#"{"type":"error","code":"quota_exceeded","message":"x","fatal":true,"seq":7}"#;
        match decode::<ServerMessage>(err, MAX_FRAME_BYTES).unwrap() {
            ServerMessage::Error {
                code, fatal, seq, ..
            } => {
                assert_eq!((code, fatal, seq), (ErrorCode::Unknown, true, Some(7)));
            }
            other => panic!("{other:?}"),
        }
        let ev = r#"{"type":"event","seq":1,"ts_ms":1,"kind":"k","severity":"critical"}"#;
        assert!(matches!(
            decode::<AgentMessage>(ev, MAX_FRAME_BYTES).unwrap(),
            AgentMessage::Event {
                severity: Severity::Unknown,
                ..
            }
        ));
    }

    #[test]
    fn unknown_malformed_and_oversized_frames_are_errors_not_panics() {
        let unknown =
            decode::<AgentMessage>(r#"{"type":"teleport"}"#, MAX_FRAME_BYTES).unwrap_err();
        assert_eq!(unknown.code(), ErrorCode::UnknownMessage);
        let missing =
            decode::<AgentMessage>(r#"{"type":"event","seq":1}"#, MAX_FRAME_BYTES).unwrap_err();
        assert_eq!(missing.code(), ErrorCode::UnknownMessage);
        assert_eq!(
            decode::<AgentMessage>("not json", MAX_FRAME_BYTES)
                .unwrap_err()
                .code(),
            ErrorCode::Malformed
        );
        let big = format!(r#"{{"type":"heartbeat","pad":"{}"}}"#, "x".repeat(100));
        assert_eq!(
            decode::<AgentMessage>(&big, 64).unwrap_err().code(),
            ErrorCode::FrameTooLarge
        );
    }
}
