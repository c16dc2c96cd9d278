//! The agent's side of a gateway session: open the WebSocket with the right credentials, send
//! `hello`, read `welcome`. Shared by the agent and the fleet simulator.

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use futures::{Sink, SinkExt, Stream, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, MAX_FRAME_BYTES, ROBOT_HEADER, ServerMessage, decode, encode,
};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::handshake::client::Request;
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;
use tokio_tungstenite::tungstenite::{Error as WsError, Message};
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// An open WebSocket to the gateway.
pub type Socket = WebSocketStream<MaybeTlsStream<TcpStream>>;

/// A connection attempt: the open connection and the gateway's `welcome`, or why not.
pub type Connecting<S> = Pin<Box<dyn Future<Output = Result<(S, Welcome), ConnectError>>>>;

/// Starts a connection attempt with these credentials and this `hello`.
pub type Connector<S> = Box<dyn FnMut(Credentials, AgentMessage) -> Connecting<S>>;

/// A connection to the gateway as a session uses it: WebSocket messages in and out. The real
/// [`Socket`] in production; unit tests use channels.
pub trait Transport:
    Sink<Message, Error = WsError> + Stream<Item = Result<Message, WsError>> + Unpin
{
}

impl<T> Transport for T where
    T: Sink<Message, Error = WsError> + Stream<Item = Result<Message, WsError>> + Unpin
{
}

/// Why a session could not be established.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    /// The gateway refused the credentials (HTTP 401).
    #[error("the gateway refused the credentials: {0}")]
    Unauthorized(String),
    /// The gateway refused enrollment (HTTP 403): the robot is enrolled already and no person
    /// allowed it to enroll again.
    #[error("the gateway refused enrollment: {0}")]
    Forbidden(String),
    /// The gateway is full or unavailable (HTTP 503), or admits no more enrollments for now;
    /// with a `Retry-After`, not before that.
    #[error("the gateway is unavailable: {message}")]
    Unavailable {
        /// The status and the gateway's explanation.
        message: String,
        /// The gateway's `Retry-After`, if it sent one.
        retry_after: Option<std::time::Duration>,
    },
    /// This robot opened sessions faster than the gateway allows (HTTP 429); wait at least
    /// `retry_after` before the next attempt.
    #[error("the gateway limits how often this robot connects: retry in {retry_after:?}")]
    TooManySessions {
        /// The gateway's `Retry-After`.
        retry_after: std::time::Duration,
    },
    /// The URL or a header value is invalid.
    #[error("invalid gateway request: {0}")]
    Request(String),
    /// Network or WebSocket failure.
    #[error("cannot reach the gateway: {0}")]
    Transport(#[from] WsError),
    /// The gateway answered `hello` with an error.
    #[error("the gateway refused the session ({code:?}): {message}")]
    Refused {
        /// Why, for the agent to decide whether retrying helps.
        code: ErrorCode,
        /// The gateway's explanation, for the log.
        message: String,
    },
    /// No `welcome` in time, or the connection closed first.
    #[error("no welcome from the gateway: {0}")]
    NoWelcome(&'static str),
}

impl ConnectError {
    /// The least time the gateway asked the agent to wait (`Retry-After` of a 429 or 503).
    pub fn retry_after(&self) -> Option<std::time::Duration> {
        match self {
            ConnectError::TooManySessions { retry_after } => Some(*retry_after),
            ConnectError::Unavailable { retry_after, .. } => *retry_after,
            _ => None,
        }
    }

    /// Whether retrying with the same credentials can help.
    pub fn retryable(&self) -> bool {
        !matches!(
            self,
            ConnectError::Unauthorized(_) | ConnectError::Forbidden(_) | ConnectError::Request(_)
        )
    }
}

/// What the gateway said in `welcome`.
#[derive(Clone, Debug, PartialEq)]
pub struct Welcome {
    /// `namespace/name` of this robot.
    pub robot: String,
    /// Heartbeat interval to use.
    pub heartbeat_interval: Duration,
    /// Largest frame the gateway accepts.
    pub max_frame_bytes: usize,
    /// Messages per second allowed.
    pub max_messages_per_second: u32,
    /// Highest sequence number the gateway has stored.
    pub stored_seq: Option<u64>,
    /// A new per-robot token, after enrollment.
    pub robot_token: Option<String>,
}

/// Credentials for one connection.
#[derive(Clone, Debug)]
pub struct Credentials {
    /// Per-robot or enrollment token.
    pub token: String,
    /// `namespace/name` (or just `name` when enrolling).
    pub robot: String,
}

/// Opens a session: WebSocket upgrade with credentials, `hello`, `welcome`; `wss://` URLs are
/// verified against the public web roots.
pub async fn connect(
    url: &str,
    creds: &Credentials,
    hello: &AgentMessage,
    timeout: Duration,
) -> Result<(Socket, Welcome), ConnectError> {
    connect_with_ca(url, creds, hello, timeout, None).await
}

/// TLS settings for `wss://` that trust only the CA certificates in `ca_file` (PEM).
fn tls_connector(ca_file: &std::path::Path) -> Result<tokio_tungstenite::Connector, ConnectError> {
    use rustls_pki_types::CertificateDer;
    use rustls_pki_types::pem::PemObject;
    let bad = |e: &dyn std::fmt::Display| {
        ConnectError::Request(format!("CA file {}: {e}", ca_file.display()))
    };
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_file_iter(ca_file).map_err(|e| bad(&e))? {
        roots.add(cert.map_err(|e| bad(&e))?).map_err(|e| bad(&e))?;
    }
    if roots.is_empty() {
        return Err(bad(&"no certificate in the file"));
    }
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| ConnectError::Request(e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(tokio_tungstenite::Connector::Rustls(std::sync::Arc::new(
        config,
    )))
}

/// As [`connect`], trusting only the CA in `ca_file` for `wss://` when one is given.
pub async fn connect_with_ca(
    url: &str,
    creds: &Credentials,
    hello: &AgentMessage,
    timeout: Duration,
    ca_file: Option<&std::path::Path>,
) -> Result<(Socket, Welcome), ConnectError> {
    let mut ws = open(url, creds, timeout, ca_file).await?;
    let welcome = handshake(&mut ws, hello, timeout).await?;
    Ok((ws, welcome))
}

/// The WebSocket upgrade request: the URL with the robot's token and name as headers.
fn upgrade_request(url: &str, creds: &Credentials) -> Result<Request, ConnectError> {
    let mut request = url
        .into_client_request()
        .map_err(|e| ConnectError::Request(e.to_string()))?;
    let auth = HeaderValue::from_str(&format!("Bearer {}", creds.token))
        .map_err(|e| ConnectError::Request(e.to_string()))?;
    let robot =
        HeaderValue::from_str(&creds.robot).map_err(|e| ConnectError::Request(e.to_string()))?;
    request.headers_mut().insert("authorization", auth);
    request.headers_mut().insert(ROBOT_HEADER, robot);
    Ok(request)
}

/// Opens the WebSocket (TCP, TLS for `wss://`, upgrade) within `timeout`; an HTTP answer
/// instead of the upgrade says why the gateway refused.
async fn open(
    url: &str,
    creds: &Credentials,
    timeout: Duration,
    ca_file: Option<&std::path::Path>,
) -> Result<Socket, ConnectError> {
    // tokio-tungstenite's default TLS connector needs a process-wide crypto provider.
    let _ = rustls::crypto::ring::default_provider().install_default();
    let connector = ca_file.map(tls_connector).transpose()?;
    let request = upgrade_request(url, creds)?;
    match tokio::time::timeout(
        timeout,
        tokio_tungstenite::connect_async_tls_with_config(
            request,
            Some(websocket_config()),
            false,
            connector,
        ),
    )
    .await
    {
        Err(_) => Err(ConnectError::NoWelcome("connect timed out")),
        Ok(Err(WsError::Http(resp))) => Err(refusal(&resp)),
        Ok(r) => Ok(r?.0),
    }
}

/// Bytes read from the socket at once. The gateway's frames are small (an ack, a command: a
/// few hundred bytes) and the read buffer, zero-filled to this size, stays resident for the
/// life of the connection: tungstenite's default of 128 KiB was most of a simulated robot's
/// memory. A larger frame grows the buffer as far as it needs.
const READ_BUFFER_BYTES: usize = 4096;

/// The WebSocket settings of a session.
fn websocket_config() -> WebSocketConfig {
    WebSocketConfig::default().read_buffer_size(READ_BUFFER_BYTES)
}

/// The error for an HTTP answer to the upgrade: 401 is a refused token, 403 a refused
/// enrollment, anything else means
/// the gateway cannot take the session now.
fn refusal(resp: &tokio_tungstenite::tungstenite::http::Response<Option<Vec<u8>>>) -> ConnectError {
    let body = resp
        .body()
        .as_ref()
        .map(|b| String::from_utf8_lossy(b).into_owned())
        .unwrap_or_default();
    match resp.status().as_u16() {
        401 => ConnectError::Unauthorized(body),
        403 => ConnectError::Forbidden(body),
        429 => ConnectError::TooManySessions {
            retry_after: retry_after(resp).unwrap_or(std::time::Duration::from_secs(10)),
        },
        _ => ConnectError::Unavailable {
            message: format!("HTTP {}: {body}", resp.status()),
            retry_after: retry_after(resp),
        },
    }
}

/// The `Retry-After` of an answer, in seconds (at most an hour).
fn retry_after(
    resp: &tokio_tungstenite::tungstenite::http::Response<Option<Vec<u8>>>,
) -> Option<std::time::Duration> {
    resp.headers()
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.trim().parse::<u64>().ok())
        .map(|s| std::time::Duration::from_secs(s.min(3600)))
}

/// Sends `hello` over an open connection and waits up to `timeout` for `welcome`, skipping
/// other frames. Generic over the socket so the run loop's tests can drive it with channels.
pub async fn handshake(
    ws: &mut impl Transport,
    hello: &AgentMessage,
    timeout: Duration,
) -> Result<Welcome, ConnectError> {
    ws.send(Message::text(encode(hello))).await?;
    tokio::time::timeout(timeout, async {
        while let Some(frame) = ws.next().await {
            match frame? {
                Message::Text(t) => {
                    if let Some(answer) = answer_to_hello(t.as_str()) {
                        return answer;
                    }
                }
                Message::Close(_) => break,
                _ => {}
            }
        }
        Err(ConnectError::NoWelcome("connection closed before welcome"))
    })
    .await
    .map_err(|_| ConnectError::NoWelcome("welcome timed out"))?
}

/// What a text frame during the handshake means: `welcome`, a refusal, or (`None`) nothing
/// the handshake waits for.
fn answer_to_hello(text: &str) -> Option<Result<Welcome, ConnectError>> {
    match decode::<ServerMessage>(text, MAX_FRAME_BYTES) {
        Ok(ServerMessage::Welcome {
            robot,
            heartbeat_interval_s,
            max_frame_bytes,
            max_messages_per_second,
            stored_seq,
            robot_token,
            ..
        }) => Some(Ok(Welcome {
            robot,
            heartbeat_interval: Duration::from_secs(u64::from(heartbeat_interval_s.max(1))),
            max_frame_bytes,
            max_messages_per_second,
            stored_seq,
            robot_token,
        })),
        Ok(ServerMessage::Error { code, message, .. }) => {
            Some(Err(ConnectError::Refused { code, message }))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A session's read buffer stays small: it is resident for the connection's life, in each
    /// of a simulator's 10,000 robots (tungstenite's default is 128 KiB).
    #[test]
    fn the_read_buffer_is_sized_for_small_frames() {
        assert!(websocket_config().read_buffer_size <= 4096);
        assert_eq!(
            websocket_config().max_message_size,
            WebSocketConfig::default().max_message_size,
            "frames up to the protocol's limit still arrive"
        );
    }
}
