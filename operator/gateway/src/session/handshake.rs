//! The start of a session: the agent's `hello` within the handshake timeout, and the robot's
//! own token when it enrolls. A refused start sends a fatal error frame and closes the socket.

use axum::extract::ws::Message;
use futures::{Sink, Stream, StreamExt};
use lekiwi_protocol::rules::{self, FieldError};
use lekiwi_protocol::{AgentMessage, ErrorCode, PROTOCOL_VERSION, decode, hello_version};
use tracing::{info, warn};

use super::SessionContext;
use super::conn::{CLOSE_AWAY, CLOSE_POLICY, Conn};
use crate::auth::Grant;
use crate::enroll;
use lekiwi_metrics::KindLabels;
use lekiwi_presence::ConnectInfo;

/// The session was refused (and its socket closed, if the agent had not closed it already).
pub(super) struct Refused;

/// A `hello` as presence records it, and the fields the status rules refused (to be named in
/// `invalid_field` errors once the agent is welcomed).
pub(super) struct Hello {
    /// What it says about the robot, without the peer address.
    pub(super) info: ConnectInfo,
    /// Fields dropped from `info` by [`lekiwi_protocol::rules::sanitize`].
    pub(super) refused: Vec<FieldError>,
    /// The optional features the agent listed (e.g. `update_agent`).
    pub(super) features: Vec<String>,
}

/// Waits for the agent's `hello`: what it says about the robot, for presence, or [`Refused`]
/// when it came late, was something else or spoke another protocol version.
pub(super) async fn hello<W, R, E>(
    shared: &SessionContext,
    conn: &mut Conn<W>,
    stream: &mut R,
) -> Result<Hello, Refused>
where
    W: Sink<Message> + Unpin,
    R: Stream<Item = Result<Message, E>> + Unpin,
{
    let text = first_text(shared, conn, stream).await?;
    let mut decoded = decode::<AgentMessage>(&text, shared.limits.max_frame_bytes);
    let refused = decoded.as_mut().map(rules::sanitize).unwrap_or_default();
    // Another version's hello may carry fields this version reads differently (§13).
    let other_version = match &decoded {
        Ok(AgentMessage::Hello {
            protocol_version, ..
        }) => Some(*protocol_version),
        Ok(_) => None,
        Err(_) if text.len() <= shared.limits.max_frame_bytes => hello_version(&text),
        Err(_) => None,
    }
    .filter(|v| *v != PROTOCOL_VERSION);
    if let Some(protocol_version) = other_version {
        conn.fail(
            ErrorCode::UnsupportedVersion,
            format!(
                "this gateway speaks protocol version {PROTOCOL_VERSION}, not {protocol_version}"
            ),
            (CLOSE_POLICY, "unsupported protocol version"),
        )
        .await;
        return Err(Refused);
    }
    match decoded {
        Ok(AgentMessage::Hello {
            agent_version,
            agent_digest,
            system,
            current_release,
            health,
            teleoperation,
            features,
            ..
        }) => Ok(Hello {
            info: ConnectInfo {
                protocol: "websocket",
                agent_version,
                agent_digest,
                release: current_release,
                health,
                teleoperation,
                system,
                address: None,
            },
            refused,
            features,
        }),
        Ok(_) => {
            conn.fail(
                ErrorCode::UnexpectedMessage,
                "the first message must be hello",
                (CLOSE_POLICY, "expected hello"),
            )
            .await;
            Err(Refused)
        }
        Err(e) => {
            conn.fail(
                e.code(),
                format!("first frame: {e}"),
                (CLOSE_POLICY, "bad hello"),
            )
            .await;
            Err(Refused)
        }
    }
}

/// The first text frame, within the handshake timeout; [`Refused`] when none came in time (said
/// to the agent and counted) or the socket closed.
async fn first_text<W, R, E>(
    shared: &SessionContext,
    conn: &mut Conn<W>,
    stream: &mut R,
) -> Result<String, Refused>
where
    W: Sink<Message> + Unpin,
    R: Stream<Item = Result<Message, E>> + Unpin,
{
    let timeout = shared.limits.handshake_timeout;
    match tokio::time::timeout(timeout, next_text(stream)).await {
        Ok(Ok(text)) => Ok(text),
        Ok(Err(NoText::Close)) => {
            conn.answer_close().await;
            Err(Refused)
        }
        Ok(Err(NoText::Gone)) => Err(Refused),
        Err(_) => {
            conn.fail(
                ErrorCode::HandshakeTimeout,
                format!("no hello within {timeout:?}"),
                (CLOSE_POLICY, "handshake timeout"),
            )
            .await;
            shared
                .metrics
                .gateway
                .sessions_ended
                .get_or_create(&KindLabels {
                    kind: "handshake_timeout",
                })
                .inc();
            Err(Refused)
        }
    }
}

/// What ended the wait for a text frame instead of one.
enum NoText {
    /// The agent's Close frame, to be answered.
    Close,
    /// The socket ended or failed.
    Gone,
}

/// The next text frame (a binary one reads as empty text); pings and pongs are skipped.
async fn next_text<R, E>(stream: &mut R) -> Result<String, NoText>
where
    R: Stream<Item = Result<Message, E>> + Unpin,
{
    loop {
        match stream.next().await {
            Some(Ok(Message::Text(t))) => return Ok(t.as_str().to_owned()),
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
            Some(Ok(Message::Binary(_))) => return Ok(String::new()),
            Some(Ok(Message::Close(_))) => return Err(NoText::Close),
            Some(Err(_)) | None => return Err(NoText::Gone),
        }
    }
}

/// Enrollment mints the robot's own token (sent in `welcome`); a robot that has its own token
/// gets `None`. [`Refused`] when the token cannot be made.
pub(super) async fn enroll<W>(
    shared: &SessionContext,
    grant: &Grant,
    conn: &mut Conn<W>,
) -> Result<Option<String>, Refused>
where
    W: Sink<Message> + Unpin,
{
    let Grant::Enroll(robot) = grant else {
        return Ok(None);
    };
    match Box::pin(shared.auth.register(robot)).await {
        Ok(token) => {
            info!("robot enrolled; issued its own token");
            Ok(Some(token))
        }
        Err(enroll::Error::Refused(r)) => {
            warn!(reason = r.as_str(), "enrollment refused");
            conn.fail(
                ErrorCode::Internal,
                r.message(robot),
                (CLOSE_POLICY, "enrollment refused"),
            )
            .await;
            Err(Refused)
        }
        Err(enroll::Error::Kube(e)) => {
            warn!(error = %e, "enrollment failed");
            conn.fail(
                ErrorCode::Internal,
                "enrollment failed; try again later",
                (CLOSE_AWAY, "enrollment failed"),
            )
            .await;
            Err(Refused)
        }
    }
}
