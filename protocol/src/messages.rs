//! The messages themselves: agent to gateway, gateway to agent, commands and error codes.

use serde::{Deserialize, Deserializer, Serialize};

use crate::types::{Health, Release, Sample, Severity, SystemFacts, Teleoperation, Vitals};

/// Reads an optional field whose `null` means the same as its absence (PROTOCOL.md §2): the
/// type's default. For fields that are no `Option` (a list, an object, a string, a flag), which
/// serde's `default` alone fills only when the field is missing.
fn null_as_default<'de, D, T>(deserializer: D) -> Result<T, D::Error>
where
    D: Deserializer<'de>,
    T: Default + Deserialize<'de>,
{
    Ok(Option::<T>::deserialize(deserializer)?.unwrap_or_default())
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
    /// The robot is over its event store quota: the durable message named by `seq` was not
    /// stored and never will be; the agent drops it, like `malformed` with a `seq`.
    QuotaExceeded,
    /// The gateway is shutting down; reconnect (to another replica). Fatal.
    ShuttingDown,
    /// Anything else on the gateway's side.
    Internal,
    /// A `hello` or `heartbeat` field breaks the status rules (PROTOCOL.md §5.4); the message
    /// names the field, which was ignored while the rest of the message took effect. Not fatal.
    InvalidField,
    /// A code this version does not know (sent by a newer gateway); honour `fatal`.
    #[serde(other)]
    Unknown,
}

/// A deployment command's payload.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "action", rename_all = "snake_case")]
pub enum Command {
    /// Download and switch to a release.
    Deploy {
        /// The release to run once the command is done.
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
    /// Replace the agent itself by another build (PROTOCOL.md §12.1). Sent only to an agent
    /// whose `hello` lists the [`FEATURE_UPDATE_AGENT`](crate::FEATURE_UPDATE_AGENT) feature.
    UpdateAgent {
        /// Version of the new agent build.
        version: String,
        /// `sha256:<hex>` digest of the agent binary, for the robot's architecture.
        digest: String,
        /// Where to fetch the binary, relative to the gateway's base URL.
        url: String,
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
        /// `sha256:<hex>` digest of the agent build that runs: the file the service manager
        /// started (an A/B slot's binary, or the package's own). A rollback of an agent update
        /// names it, and the robot switches back to it from its own disk.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        agent_digest: Option<String>,
        /// Facts about the computer; `null` like omitted.
        #[serde(default, deserialize_with = "null_as_default")]
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
        /// Optional protocol features this agent implements, e.g.
        /// [`FEATURE_UPDATE_AGENT`](crate::FEATURE_UPDATE_AGENT); unknown names are ignored.
        /// `null` (an empty list as Go encodes it) like omitted.
        #[serde(
            default,
            deserialize_with = "null_as_default",
            skip_serializing_if = "Vec::is_empty"
        )]
        features: Vec<String>,
    },
    /// Liveness and current state, every `heartbeat_interval_s`.
    Heartbeat {
        /// The agent's clock, Unix milliseconds; echoed in the ack for round-trip time.
        sent_at_ms: i64,
        /// Round-trip time of the previous heartbeat, milliseconds.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rtt_ms: Option<f64>,
        /// Readings taken for this heartbeat; `null` like omitted.
        #[serde(default, deserialize_with = "null_as_default")]
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
        /// Per-robot sequence number, shared with `telemetry` and `progress`; at most
        /// [`MAX_SEQ`](crate::MAX_SEQ), a larger one is refused `malformed`.
        seq: u64,
        /// When it happened, Unix milliseconds.
        ts_ms: i64,
        /// Short machine-readable kind, e.g. `teleoperation_started`.
        kind: String,
        /// How much it matters; an unknown one is stored as `unknown`.
        severity: Severity,
        /// Human-readable text; `null` like omitted.
        #[serde(default, deserialize_with = "null_as_default")]
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
        /// Phase: a [`ProgressPhase`](crate::ProgressPhase) wire name (`downloading`, ..., `done`, `failed`,
        /// `rolled_back`); kept as text so a newer agent's phase is still stored.
        phase: String,
        /// Percent done, 0 to 100.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        percent: Option<f64>,
        /// Human-readable details of this step (e.g. what failed); `null` like omitted.
        #[serde(default, deserialize_with = "null_as_default")]
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
        /// Whether the gateway closes the connection after this frame; `null` like omitted.
        #[serde(default, deserialize_with = "null_as_default")]
        fatal: bool,
        /// The sequence number of the durable message this refuses, if it was one; the agent
        /// keeps that message and resends it later.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        seq: Option<u64>,
    },
}

#[cfg(test)]
mod tests {
    use serde::de::DeserializeOwned;
    use serde_json::{Value, json};

    use super::*;

    /// Every optional field named by `paths` (dotted, into nested objects) decodes the same
    /// whether it is `null` or omitted (PROTOCOL.md §2), and the frame with all of them `null`
    /// decodes like the one with none of them.
    fn null_is_omitted<T: DeserializeOwned + PartialEq + std::fmt::Debug>(
        full: Value,
        paths: &[&str],
    ) {
        let edit = |mut frame: Value, path: &str, null: bool| {
            let (parent, field) = path.rsplit_once('.').unwrap_or(("", path));
            let mut object = &mut frame;
            for part in parent.split('.').filter(|p| !p.is_empty()) {
                object = &mut object[part];
            }
            let object = object.as_object_mut().expect("an object");
            assert!(object.contains_key(field), "{path} not in the sample");
            if null {
                object.insert(field.to_owned(), Value::Null);
            } else {
                object.remove(field);
            }
            frame
        };
        let decode = |frame: &Value| -> T {
            serde_json::from_value(frame.clone()).unwrap_or_else(|e| panic!("{frame}: {e}"))
        };
        for path in paths {
            let nulled = edit(full.clone(), path, true);
            let omitted = edit(full.clone(), path, false);
            assert_eq!(decode(&nulled), decode(&omitted), "{path}");
        }
        // Top-level fields at once (a nested path's parent may be among them).
        let top: Vec<&str> = paths.iter().copied().filter(|p| !p.contains('.')).collect();
        let (mut nulled, mut omitted) = (full.clone(), full);
        for path in top {
            nulled = edit(nulled, path, true);
            omitted = edit(omitted, path, false);
        }
        assert_eq!(decode(&nulled), decode(&omitted), "all at once");
    }

    fn release() -> Value {
        json!({"version": "1.1.0", "digest": format!("sha256:{}", "1".repeat(64))})
    }

    #[test]
    fn hello_takes_null_like_omitted() {
        let hello = json!({
            "type": "hello", "protocol_version": 1, "agent_version": "0.1.0",
            "agent_digest": format!("sha256:{}", "a".repeat(64)),
            "system": {"hostname": "kiwi-1", "os": "Debian", "kernel": "6.6", "arch": "aarch64",
                       "cpus": 4, "memory_bytes": 8},
            "current_release": release(), "last_acked_seq": 41,
            "health": {"healthy": false, "message": "no arm", "reason": "SerialDeviceMissing"},
            "teleoperation": {"active": true, "score": 0.5},
            "features": ["update_agent"],
        });
        null_is_omitted::<AgentMessage>(
            hello,
            &[
                "agent_digest",
                "system",
                "system.hostname",
                "system.os",
                "system.kernel",
                "system.arch",
                "system.cpus",
                "system.memory_bytes",
                "current_release",
                "last_acked_seq",
                "health",
                "health.message",
                "health.reason",
                "teleoperation",
                "teleoperation.score",
                "features",
            ],
        );
    }

    #[test]
    fn heartbeat_takes_null_like_omitted() {
        let vitals = json!({
            "uptime_s": 1, "cpu_percent": 2.0, "memory_percent": 3.0, "load1": 0.5,
            "disk_percent": 4.0, "temperature_c": 50.0, "battery_percent": 90.0,
            "host_rss_bytes": 1000, "host_cpu_percent": 1.5,
        });
        let heartbeat = json!({
            "type": "heartbeat", "sent_at_ms": 7, "rtt_ms": 3.2, "vitals": vitals,
            "current_release": release(), "health": {"healthy": true},
            "teleoperation": {"active": false},
        });
        let mut paths = vec![
            "rtt_ms".to_owned(),
            "vitals".into(),
            "current_release".into(),
            "health".into(),
            "teleoperation".into(),
        ];
        for field in vitals.as_object().expect("an object").keys() {
            paths.push(format!("vitals.{field}"));
        }
        let paths: Vec<&str> = paths.iter().map(String::as_str).collect();
        null_is_omitted::<AgentMessage>(heartbeat, &paths);
    }

    #[test]
    fn durable_messages_take_null_like_omitted() {
        let event = json!({
            "type": "event", "seq": 42, "ts_ms": 1, "kind": "k", "severity": "info",
            "message": "m", "data": {"a": 1},
        });
        null_is_omitted::<AgentMessage>(event, &["message", "data"]);
        let progress = json!({
            "type": "progress", "seq": 44, "command_id": "c1", "phase": "downloading",
            "percent": 35.0, "message": "3 of 8",
        });
        null_is_omitted::<AgentMessage>(progress, &["percent", "message"]);
        // Telemetry has no optional field; its samples none either.
    }

    #[test]
    fn gateway_messages_take_null_like_omitted() {
        let welcome = json!({
            "type": "welcome", "protocol_version": 1, "robot": "lab/kiwi-1",
            "heartbeat_interval_s": 30, "max_frame_bytes": 262144,
            "max_messages_per_second": 20, "stored_seq": 41, "robot_token": "lkr_x",
        });
        null_is_omitted::<ServerMessage>(welcome, &["stored_seq", "robot_token"]);
        let error = json!({
            "type": "error", "code": "store_unavailable", "message": "m", "fatal": true,
            "seq": 42,
        });
        null_is_omitted::<ServerMessage>(error, &["fatal", "seq"]);
    }
}
