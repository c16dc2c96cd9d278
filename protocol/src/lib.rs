//! Wire types of the agent-gateway protocol: versioned JSON messages in WebSocket text frames.
//!
//! This first version carries registration and heartbeats; telemetry, events and deployment
//! commands join it with the gateway.

use serde::{Deserialize, Serialize};

/// Protocol version spoken by this crate. A peer with another major version is refused.
pub const PROTOCOL_VERSION: u32 = 1;

/// Largest frame either side accepts, in bytes.
pub const MAX_FRAME_BYTES: usize = 256 * 1024;

/// Errors decoding a frame.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The frame is larger than [`MAX_FRAME_BYTES`].
    #[error("frame of {size} bytes exceeds the limit of {limit} bytes")]
    FrameTooLarge { size: usize, limit: usize },
    /// The frame is not a message this version understands.
    #[error("malformed frame: {0}")]
    Malformed(#[from] serde_json::Error),
}

/// Machine-readable error codes carried by [`Message::Error`].
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// The frame could not be parsed.
    Malformed,
    /// The frame exceeded the size limit.
    FrameTooLarge,
    /// The peer speaks an incompatible protocol version.
    UnsupportedVersion,
}

/// One protocol message.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Message {
    /// First frame from the agent.
    Hello {
        protocol_version: u32,
        robot: String,
        agent_version: String,
    },
    /// The gateway's answer to `hello`.
    Welcome {
        protocol_version: u32,
        heartbeat_interval_seconds: u32,
    },
    /// Periodic liveness signal from the agent.
    Heartbeat { seq: u64, sent_at_ms: u64 },
    /// The gateway's acknowledgement, echoing the agent's clock so it can measure round-trip time.
    HeartbeatAck { seq: u64, sent_at_ms: u64 },
    /// A refused frame or a fatal condition.
    Error { code: ErrorCode, message: String },
}

impl Message {
    /// Decodes one text frame, enforcing the size limit before parsing.
    pub fn decode(frame: &str) -> Result<Self, Error> {
        if frame.len() > MAX_FRAME_BYTES {
            return Err(Error::FrameTooLarge {
                size: frame.len(),
                limit: MAX_FRAME_BYTES,
            });
        }
        Ok(serde_json::from_str(frame)?)
    }

    /// Encodes the message as one text frame.
    pub fn encode(&self) -> String {
        // Serializing these plain enums cannot fail: no maps with non-string keys, no I/O.
        serde_json::to_string(self).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hello_has_a_type_tag_and_round_trips() {
        let hello = Message::Hello {
            protocol_version: PROTOCOL_VERSION,
            robot: "kiwi-01".into(),
            agent_version: "0.1.0".into(),
        };
        let frame = hello.encode();
        assert!(frame.starts_with(r#"{"type":"hello""#), "{frame}");
        assert_eq!(Message::decode(&frame).unwrap(), hello);
    }

    #[test]
    fn unknown_and_oversized_frames_are_errors_not_panics() {
        assert!(matches!(
            Message::decode(r#"{"type":"teleport"}"#),
            Err(Error::Malformed(_))
        ));
        assert!(matches!(
            Message::decode("not json"),
            Err(Error::Malformed(_))
        ));
        let big = format!(
            r#"{{"type":"heartbeat","pad":"{}"}}"#,
            "x".repeat(MAX_FRAME_BYTES)
        );
        assert!(matches!(
            Message::decode(&big),
            Err(Error::FrameTooLarge { .. })
        ));
    }
}
