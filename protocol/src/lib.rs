//! Wire types of the agent-gateway protocol: versioned JSON messages in WebSocket text frames.
//!
//! `PROTOCOL.md` beside this crate is the specification; this module is its Rust rendering.
//! Pure types: no kube, no axum, no I/O.

use serde::Serialize;

pub mod join;
mod messages;
mod phase;
pub mod release;
pub mod rules;
pub mod transport;
mod types;

pub use messages::{AgentMessage, Command, ErrorCode, ServerMessage};
pub use phase::ProgressPhase;
pub use types::{
    Health, Release, Sample, Severity, StoredEvent, SystemFacts, Teleoperation, Vitals, now_ms,
};

/// Protocol version spoken by this crate. A peer with another version is refused.
pub const PROTOCOL_VERSION: u32 = 1;

/// The `hello` feature of an agent that handles the `update_agent` command (it replaces itself
/// by another build, PROTOCOL.md §12.1). The gateway sends that command to no other agent.
pub const FEATURE_UPDATE_AGENT: &str = "update_agent";

/// Largest frame either side accepts by default, in bytes. The gateway may announce a smaller
/// limit in `welcome`.
pub const MAX_FRAME_BYTES: usize = 256 * 1024;

/// Path of the WebSocket endpoint on the gateway.
pub const AGENT_PATH: &str = "/v1/agent";

/// Header naming the robot when enrolling with a fleet enrollment token.
pub const ROBOT_HEADER: &str = "x-lekiwi-robot";

/// Largest sequence number of a durable message, 2^53 - 1: every JSON implementation reads it
/// exactly (IEEE doubles hold integers up to it), and no counter near it can overflow.
pub const MAX_SEQ: u64 = (1 << 53) - 1;

/// Most bytes of a refused input that an error message quotes; longer quotes are cut there and
/// end with `…`.
pub const MAX_ERROR_QUOTE_BYTES: usize = 64;

/// Errors decoding a frame.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The frame is larger than the limit.
    #[error("frame of {size} bytes exceeds the limit of {limit} bytes")]
    FrameTooLarge {
        /// Size of the frame, in bytes.
        size: usize,
        /// The largest frame accepted, in bytes.
        limit: usize,
    },
    /// The frame is not valid JSON of a known message type. Its text quotes at most
    /// [`MAX_ERROR_QUOTE_BYTES`] of the frame, however long the offending value.
    #[error("malformed frame: {}", brief(.0))]
    Malformed(#[from] serde_json::Error),
}

/// A decoding error's text, cut to [`MAX_ERROR_QUOTE_BYTES`] (serde's text quotes the offending
/// value, which may be the whole frame), with its position kept.
fn brief(e: &serde_json::Error) -> String {
    let text = e.to_string();
    let cut = truncate_utf8(&text, MAX_ERROR_QUOTE_BYTES);
    if cut.len() == text.len() {
        return text;
    }
    format!("{cut}… at line {} column {}", e.line(), e.column())
}

/// The longest prefix of `text` of at most `max` bytes that ends on a character boundary.
pub fn truncate_utf8(text: &str, max: usize) -> &str {
    if text.len() <= max {
        return text;
    }
    let end = (0..=max).rev().find(|i| text.is_char_boundary(*i));
    &text[..end.unwrap_or(0)]
}

/// The `protocol_version` of a frame that is a `hello` of any version: an object with
/// `"type":"hello"` and an integer `protocol_version`, whatever its other fields hold. A gateway
/// uses it to answer a future version's `hello` it cannot decode with `unsupported_version`.
pub fn hello_version(frame: &str) -> Option<u32> {
    #[derive(serde::Deserialize)]
    struct Probe {
        #[serde(rename = "type")]
        kind: String,
        protocol_version: u32,
    }
    let probe: Probe = serde_json::from_str(frame).ok()?;
    (probe.kind == "hello").then_some(probe.protocol_version)
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
            agent_digest: Some(format!("sha256:{}", "a".repeat(64))),
            system: SystemFacts {
                arch: Some("aarch64".into()),
                cpus: Some(4),
                ..Default::default()
            },
            current_release: None,
            last_acked_seq: Some(41),
            features: vec![FEATURE_UPDATE_AGENT.into()],
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
        let err = r#"{"type":"error","code":"budget_spent","message":"x","fatal":true,"seq":7}"#;
        match decode::<ServerMessage>(err, MAX_FRAME_BYTES).unwrap() {
            ServerMessage::Error {
                code, fatal, seq, ..
            } => {
                assert_eq!((code, fatal, seq), (ErrorCode::Unknown, true, Some(7)));
            }
            other => panic!("{other:?}"),
        }
        let quota =
            r#"{"type":"error","code":"quota_exceeded","message":"x","fatal":false,"seq":7}"#;
        assert!(matches!(
            decode::<ServerMessage>(quota, MAX_FRAME_BYTES).unwrap(),
            ServerMessage::Error {
                code: ErrorCode::QuotaExceeded,
                seq: Some(7),
                ..
            }
        ));
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

    #[test]
    fn error_text_quotes_only_a_short_prefix_of_the_frame() {
        let long = format!(r#"{{"type":"{}"}}"#, "é".repeat(100_000));
        let text = decode::<AgentMessage>(&long, usize::MAX)
            .unwrap_err()
            .to_string();
        assert!(text.len() < 200, "{} bytes: {text}", text.len());
        assert!(text.contains("… at line 1 column"), "{text}");
        let short = decode::<AgentMessage>(r#"{"type":"x"}"#, 100).unwrap_err();
        assert!(short.to_string().contains("`x`"), "{short}");
        assert_eq!(truncate_utf8("aé", 2), "a");
    }

    #[test]
    fn a_future_hello_reveals_its_version() {
        let v2 = r#"{"type":"hello","protocol_version":2,"agent_version":"9","system":"new"}"#;
        assert_eq!(hello_version(v2), Some(2));
        assert_eq!(
            hello_version(r#"{"type":"heartbeat","protocol_version":2}"#),
            None
        );
        assert_eq!(
            hello_version(r#"{"type":"hello","protocol_version":"2"}"#),
            None
        );
        assert_eq!(hello_version("not json"), None);
    }
}
