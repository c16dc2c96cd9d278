//! The sending half of a session: JSON frames, error frames counted by code, and the Close
//! frame that ends a session with a reason.

use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes};
use futures::{Sink, SinkExt};
use lekiwi_protocol::{ErrorCode, ServerMessage, encode};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use serde::Serialize;
use tracing::warn;

use lekiwi_metrics::{KindLabels, Metrics};

/// WebSocket close code for a session ended by policy (limits, replacement).
pub(super) const CLOSE_POLICY: u16 = 1008;
/// WebSocket close code "going away" (shutdown, silence).
pub(super) const CLOSE_AWAY: u16 = 1001;

/// Why a session ended; its label is the `sessions_ended` metric's kind and the disconnect
/// record's reason.
pub(super) enum End {
    /// The agent closed the socket, or it broke.
    Closed,
    /// A newer connection of the same robot took over.
    Replaced,
    /// A later session of the robot on another gateway replica took over.
    Moved,
    /// The agent stayed silent past the missed-heartbeat limit.
    HeartbeatTimeout,
    /// The agent kept sending above its rate limit.
    Abuse,
    /// The gateway is shutting down.
    Shutdown,
    /// A frame could not be written within the send timeout: the agent stopped reading.
    SendTimeout,
    /// The token the session was opened with was rotated or its Secret deleted.
    Revoked,
}

impl End {
    pub(super) fn label(&self) -> &'static str {
        match self {
            End::Closed => "closed",
            End::Replaced => "replaced",
            End::Moved => "moved",
            End::HeartbeatTimeout => "heartbeat_timeout",
            End::Abuse => "rate_limit_abuse",
            End::Shutdown => "shutdown",
            End::SendTimeout => "send_timeout",
            End::Revoked => "token_revoked",
        }
    }
}

/// Whether the session goes on (`Ok`) or how it ended.
pub(super) type Flow = Result<(), End>;

/// Error codes counted under their own label; any other counts as `other`, so the metric's
/// labels stay bounded whatever the protocol adds.
const ERROR_LABELS: &[&str] = &[
    "malformed",
    "unknown_message",
    "frame_too_large",
    "unsupported_version",
    "unexpected_message",
    "rate_limited",
    "handshake_timeout",
    "replaced",
    "store_unavailable",
    "quota_exceeded",
    "shutting_down",
    "internal",
    "invalid_field",
];

/// How `value` is spelled on the wire (a unit enum's snake_case name), or empty.
pub(super) fn wire_name<T: Serialize>(value: &T) -> String {
    serde_json::to_value(value)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_default()
}

/// The socket's sending half, with the metrics its error frames count in.
pub(super) struct Conn<W> {
    sink: W,
    /// `lekiwi_gateway_error_frames` (only this family, not all of [`Metrics`]: the connection's
    /// memory lives as long as it does).
    errors: Family<KindLabels, Counter>,
    /// How long one frame (written and flushed) may take before the session ends.
    send_timeout: Duration,
    /// A send timed out: the socket is unusable, every later send fails at once.
    stuck: bool,
}

impl<W: Sink<Message> + Unpin> Conn<W> {
    pub(super) fn new(sink: W, metrics: &Metrics, send_timeout: Duration) -> Self {
        Self {
            sink,
            errors: metrics.gateway.errors.clone(),
            send_timeout,
            stuck: false,
        }
    }

    /// Sends one frame; `Err(Closed)` when the socket is gone, `Err(SendTimeout)` when it could
    /// not be written and flushed within the send timeout (the agent stopped reading).
    pub(super) async fn send(&mut self, msg: &ServerMessage) -> Flow {
        self.send_message(Message::Text(Utf8Bytes::from(encode(msg))))
            .await
    }

    /// Writes and flushes one message within the send timeout.
    async fn send_message(&mut self, message: Message) -> Flow {
        if self.stuck {
            return Err(End::SendTimeout);
        }
        match tokio::time::timeout(self.send_timeout, self.sink.send(message)).await {
            Ok(sent) => sent.map_err(|_| End::Closed),
            Err(_) => {
                self.stuck = true;
                warn!(
                    timeout = ?self.send_timeout,
                    "agent stopped reading: a frame could not be sent in time; closing"
                );
                Err(End::SendTimeout)
            }
        }
    }

    /// Sends an error frame without a sequence number, counted by its code.
    pub(super) async fn error(
        &mut self,
        code: ErrorCode,
        message: impl Into<String>,
        fatal: bool,
    ) -> Flow {
        self.refuse_seq(code, message.into(), fatal, None).await
    }

    /// Refuses a message (non-fatal), naming its `seq` when it was a parsed durable message;
    /// counted by its code like [`Conn::error`].
    pub(super) async fn refuse(
        &mut self,
        code: ErrorCode,
        message: String,
        seq: Option<u64>,
    ) -> Flow {
        self.refuse_seq(code, message, false, seq).await
    }

    async fn refuse_seq(
        &mut self,
        code: ErrorCode,
        message: String,
        fatal: bool,
        seq: Option<u64>,
    ) -> Flow {
        let label = wire_name(&code);
        let label: &'static str = ERROR_LABELS
            .iter()
            .find(|l| **l == label)
            .copied()
            .unwrap_or("other");
        self.count_error(label);
        self.send(&ServerMessage::Error {
            code,
            message,
            fatal,
            seq,
        })
        .await
    }

    /// Ends the session: a fatal error frame, then a Close frame with `close` code and reason.
    pub(super) async fn fail(
        &mut self,
        code: ErrorCode,
        message: impl Into<String>,
        close: (u16, &str),
    ) {
        let _ = self.error(code, message, true).await;
        self.close(close.0, close.1).await;
    }

    /// Sends a Close frame and closes the sink, each within the send timeout; errors mean the
    /// socket is gone already.
    pub(super) async fn close(&mut self, code: u16, reason: &str) {
        let frame = Message::Close(Some(CloseFrame {
            code,
            reason: Utf8Bytes::from(reason),
        }));
        if self.send_message(frame).await.is_ok() {
            let _ = tokio::time::timeout(self.send_timeout, self.sink.close()).await;
        }
    }

    /// Answers the agent's Close frame with one of ours (RFC 6455 §5.5.1) and closes the sink,
    /// within the send timeout. The WebSocket layer queued the answer, echoing the agent's code
    /// and reason, when it read the agent's Close; closing the sink writes it out. Dropped
    /// unsent, the agent would see its clean close end as an abnormal one (1006).
    pub(super) async fn answer_close(&mut self) {
        if !self.stuck {
            let _ = tokio::time::timeout(self.send_timeout, self.sink.close()).await;
        }
    }

    fn count_error(&self, kind: &'static str) {
        self.errors.get_or_create(&KindLabels { kind }).inc();
    }
}
