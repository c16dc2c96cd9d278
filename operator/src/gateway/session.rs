//! One agent's WebSocket session: handshake, heartbeats, durable ingest with acks, limits,
//! replacement by a newer connection. Generic over the socket halves, so unit tests drive it
//! with channels and the gateway with a real WebSocket.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes};
use futures::{Sink, SinkExt, Stream, StreamExt};
use jiff::Timestamp;
use lekiwi_protocol::{
    AgentMessage, ErrorCode, PROTOCOL_VERSION, ProgressPhase, Release, ServerMessage, decode,
    encode,
};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, debug, info, info_span, warn};

use super::auth::{Authenticator, Grant};
use super::presence::{ConnectInfo, HeartbeatInfo, Presence, UpdateOutcome};
use crate::gateway::event_store::{ConnectionRecord, RobotKey, Store, StoredEvent};
use crate::metrics::{KindLabels, Metrics};

/// Limits one session enforces.
#[derive(Clone, Debug)]
pub struct Limits {
    /// Largest frame accepted; larger ones get an error frame.
    pub max_frame_bytes: usize,
    /// Messages per second sustained.
    pub rate: u32,
    /// Messages at once.
    pub burst: u32,
    /// Net refused frames (each refusal adds one, each accepted frame takes one away) above
    /// which the session is closed as abusive.
    pub abuse_threshold: u32,
    /// Time allowed for the `hello`.
    pub handshake_timeout: Duration,
    /// Heartbeat interval announced in `welcome`.
    pub heartbeat_interval: Duration,
    /// Silent intervals after which the session is closed.
    pub missed_heartbeats: u32,
}

/// Control messages to a running session.
#[derive(Debug)]
pub enum Control {
    /// A newer connection of the same robot took over.
    Replaced,
    /// Send this to the agent.
    /// Boxed: the channel's slots are allocated per connection, so keep them pointer-sized.
    Send(Box<ServerMessage>),
    /// The robot's `spec.release` changed to this.
    Desired(Option<Box<Release>>),
}

/// The sessions of this gateway, one per robot.
#[derive(Default)]
pub struct Registry {
    next: AtomicU64,
    sessions: Mutex<HashMap<RobotKey, (u64, mpsc::Sender<Control>)>>,
}

impl Registry {
    /// Registers a new session for `key`, telling an older one that it was replaced.
    fn register(&self, key: &RobotKey) -> (u64, mpsc::Receiver<Control>) {
        let id = self.next.fetch_add(1, Ordering::Relaxed) + 1;
        let (tx, rx) = mpsc::channel(16);
        let old = self
            .sessions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(key.clone(), (id, tx));
        if let Some((_, old)) = old {
            let _ = old.try_send(Control::Replaced);
        }
        (id, rx)
    }

    /// Removes the session unless a newer one replaced it already.
    fn unregister(&self, key: &RobotKey, id: u64) {
        let mut sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        if sessions.get(key).is_some_and(|(current, _)| *current == id) {
            sessions.remove(key);
        }
    }

    /// Tells a robot's session that its desired release changed, if it has a session.
    pub fn desire(&self, key: &RobotKey, release: Option<Release>) -> bool {
        let sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        sessions
            .get(key)
            .is_some_and(|(_, tx)| tx.try_send(Control::Desired(release.map(Box::new))).is_ok())
    }

    /// Sends a message to a robot's session, if it has one.
    pub fn send(&self, key: &RobotKey, msg: ServerMessage) -> bool {
        let sessions = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        sessions
            .get(key)
            .is_some_and(|(_, tx)| tx.try_send(Control::Send(Box::new(msg))).is_ok())
    }

    /// Sessions open now.
    pub fn len(&self) -> usize {
        self.sessions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .len()
    }

    /// Whether no session is open.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// What every session shares.
#[derive(Clone)]
pub struct Shared {
    /// Presence tracker.
    pub presence: Presence,
    /// Event store.
    pub store: Store,
    /// Token checks and registration.
    pub auth: Authenticator,
    /// Open sessions.
    pub registry: Arc<Registry>,
    /// Limits.
    pub limits: Limits,
    /// Metrics.
    pub metrics: Metrics,
    /// This gateway's name.
    pub gateway: String,
    /// Fires on shutdown.
    pub cancel: CancellationToken,
    /// The robots' desired releases (`spec.release`), when this gateway watches Robots.
    pub desired: Option<DesiredReleases>,
}

/// Looks up a robot's `spec.release` in the gateway's Robot cache.
#[derive(Clone)]
pub struct DesiredReleases(pub kube::runtime::reflector::Store<lekiwi_crds::Robot>);

impl DesiredReleases {
    /// The release `key` should run, if its Robot names one.
    pub fn get(&self, key: &RobotKey) -> Option<Release> {
        let obj = kube::runtime::reflector::ObjectRef::new(&key.name).within(&key.namespace);
        self.0
            .get(&obj)
            .and_then(|r| r.spec.release.as_ref().map(Release::from))
    }
}

/// A short id of this gateway process, different after every restart.
fn boot_id() -> &'static str {
    static BOOT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    BOOT.get_or_init(|| format!("{:x}", Timestamp::now().as_millisecond()))
}

/// What a session knows about the robot's release and the deploy command it sent.
struct Rollout {
    current: Option<Release>,
    desired: Option<Release>,
    /// The last deploy command: its id and release. Not repeated within the session; a new
    /// session (reconnect) sends it again if the robot still does not run it.
    sent: Option<(String, Release)>,
    counter: u32,
}

impl Rollout {
    /// The deploy command to send now, if the robot should run another release.
    fn command(&mut self, gateway: &str, session: u64) -> Option<ServerMessage> {
        let desired = self.desired.clone()?;
        if self.current.as_ref() == Some(&desired)
            || self.sent.as_ref().is_some_and(|(_, r)| *r == desired)
        {
            return None;
        }
        self.counter += 1;
        // Unique across gateway restarts too: agents remember finished command ids and do not
        // run one twice, and session numbers start over with every process.
        let command_id = format!("{gateway}-{}-{session}-{}", boot_id(), self.counter);
        self.sent = Some((command_id.clone(), desired.clone()));
        Some(ServerMessage::Command {
            command_id,
            command: lekiwi_protocol::Command::Deploy {
                manifest_url: lekiwi_protocol::release::blob_path(&desired.digest),
                release: desired,
            },
        })
    }
}

/// WebSocket close code for a session ended by policy (limits, replacement).
const CLOSE_POLICY: u16 = 1008;
/// WebSocket close code "going away" (shutdown, silence).
const CLOSE_AWAY: u16 = 1001;

enum End {
    Closed,
    Replaced,
    HeartbeatTimeout,
    Abuse,
    Shutdown,
}

impl End {
    fn label(&self) -> &'static str {
        match self {
            End::Closed => "closed",
            End::Replaced => "replaced",
            End::HeartbeatTimeout => "heartbeat_timeout",
            End::Abuse => "rate_limit_abuse",
            End::Shutdown => "shutdown",
        }
    }
}

struct Conn<W> {
    sink: W,
    metrics: Metrics,
}

impl<W: Sink<Message> + Unpin> Conn<W> {
    async fn send(&mut self, msg: &ServerMessage) -> bool {
        self.sink
            .send(Message::Text(Utf8Bytes::from(encode(msg))))
            .await
            .is_ok()
    }

    async fn error(&mut self, code: ErrorCode, message: impl Into<String>, fatal: bool) -> bool {
        let label = serde_json::to_value(code)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_default();
        let label: &'static str = ERROR_LABELS
            .iter()
            .find(|l| **l == label)
            .copied()
            .unwrap_or("other");
        self.metrics
            .gateway
            .errors
            .get_or_create(&KindLabels { kind: label })
            .inc();
        self.send(&ServerMessage::Error {
            code,
            message: message.into(),
            fatal,
            seq: None,
        })
        .await
    }

    async fn refuse(&mut self, code: ErrorCode, message: String, seq: Option<u64>) -> bool {
        if seq.is_none() {
            return self.error(code, message, false).await;
        }
        self.metrics
            .gateway
            .errors
            .get_or_create(&KindLabels {
                kind: "store_unavailable",
            })
            .inc();
        self.send(&ServerMessage::Error {
            code,
            message,
            fatal: false,
            seq,
        })
        .await
    }

    async fn close(&mut self, code: u16, reason: &str) {
        let _ = self
            .sink
            .send(Message::Close(Some(CloseFrame {
                code,
                reason: Utf8Bytes::from(reason),
            })))
            .await;
        let _ = self.sink.close().await;
    }
}

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
    "shutting_down",
    "internal",
];

fn frame_label(msg: &AgentMessage) -> &'static str {
    match msg {
        AgentMessage::Hello { .. } => "hello",
        AgentMessage::Heartbeat { .. } => "heartbeat",
        AgentMessage::Event { .. } => "event",
        AgentMessage::Telemetry { .. } => "telemetry",
        AgentMessage::Progress { .. } => "progress",
    }
}

/// Runs one session to its end.
pub async fn run<W, R, E>(
    shared: Arc<Shared>,
    grant: Grant,
    address: Option<String>,
    sink: W,
    stream: R,
) where
    W: Sink<Message> + Unpin + Send,
    R: Stream<Item = Result<Message, E>> + Unpin + Send,
    E: std::fmt::Display,
{
    let key = grant.robot().clone();
    let span = info_span!("session", robot = %key.name, namespace = %key.namespace);
    run_inner(shared, grant, address, sink, stream)
        .instrument(span)
        .await;
}

async fn run_inner<W, R, E>(
    shared: Arc<Shared>,
    grant: Grant,
    address: Option<String>,
    sink: W,
    mut stream: R,
) where
    W: Sink<Message> + Unpin + Send,
    R: Stream<Item = Result<Message, E>> + Unpin + Send,
    E: std::fmt::Display,
{
    let limits = shared.limits.clone();
    let key = grant.robot().clone();
    let mut conn = Conn {
        sink,
        metrics: shared.metrics.clone(),
    };

    // 1. The hello, within the handshake timeout.
    let hello = match tokio::time::timeout(limits.handshake_timeout, next_text(&mut stream)).await {
        Err(_) => {
            conn.error(
                ErrorCode::HandshakeTimeout,
                format!("no hello within {:?}", limits.handshake_timeout),
                true,
            )
            .await;
            conn.close(CLOSE_POLICY, "handshake timeout").await;
            shared
                .metrics
                .gateway
                .sessions_ended
                .get_or_create(&KindLabels {
                    kind: "handshake_timeout",
                })
                .inc();
            return;
        }
        Ok(None) => return,
        Ok(Some(text)) => decode::<AgentMessage>(&text, limits.max_frame_bytes),
    };
    let (agent_version, system, release, health, teleoperation) = match hello {
        Ok(AgentMessage::Hello {
            protocol_version,
            agent_version,
            system,
            current_release,
            health,
            teleoperation,
            ..
        }) => {
            if protocol_version != PROTOCOL_VERSION {
                conn.error(
                    ErrorCode::UnsupportedVersion,
                    format!("this gateway speaks protocol version {PROTOCOL_VERSION}, not {protocol_version}"),
                    true,
                )
                .await;
                conn.close(CLOSE_POLICY, "unsupported protocol version")
                    .await;
                return;
            }
            (
                agent_version,
                system,
                current_release,
                health,
                teleoperation,
            )
        }
        Ok(_) => {
            conn.error(
                ErrorCode::UnexpectedMessage,
                "the first message must be hello",
                true,
            )
            .await;
            conn.close(CLOSE_POLICY, "expected hello").await;
            return;
        }
        Err(e) => {
            conn.error(e.code(), format!("first frame: {e}"), true)
                .await;
            conn.close(CLOSE_POLICY, "bad hello").await;
            return;
        }
    };

    // 2. Enrollment mints the robot's own token.
    let robot_token = match &grant {
        Grant::Enroll(robot) => match Box::pin(shared.auth.register(robot)).await {
            Ok(token) => {
                info!("robot enrolled; issued its own token");
                Some(token)
            }
            Err(e) => {
                warn!(error = %e, "enrollment failed");
                conn.error(
                    ErrorCode::Internal,
                    "enrollment failed; try again later",
                    true,
                )
                .await;
                conn.close(CLOSE_AWAY, "enrollment failed").await;
                return;
            }
        },
        Grant::Robot(_) => None,
    };

    // 3. Take over from an older session, record the connection, tell presence.
    let (id, mut control) = shared.registry.register(&key);
    let now_ms = Timestamp::now().as_millisecond();
    let record = ConnectionRecord {
        gateway: shared.gateway.clone(),
        protocol: "websocket".into(),
        address: address.clone(),
        connected_at_ms: now_ms,
        disconnected_at_ms: None,
        reason: None,
    };
    let record_id = match Box::pin(shared.store.record_connect(&key, &record)).await {
        Ok(id) => Some(id),
        Err(e) => {
            warn!(error = %e, "cannot record the connection in the event store");
            None
        }
    };
    let stored_seq = Box::pin(shared.store.last_seq(&key))
        .await
        .unwrap_or_else(|e| {
            warn!(error = %e, "cannot read the last stored sequence number");
            None
        });
    let release_at_hello = release.clone();
    shared.presence.connect(
        &key,
        id,
        ConnectInfo {
            protocol: "websocket",
            agent_version,
            release,
            health,
            teleoperation,
            system,
            address,
        },
    );
    shared.metrics.gateway.connections.inc();
    info!(session = id, ?stored_seq, "agent connected");

    let welcome = ServerMessage::Welcome {
        protocol_version: PROTOCOL_VERSION,
        robot: format!("{}/{}", key.namespace, key.name),
        heartbeat_interval_s: limits.heartbeat_interval.as_secs().max(1) as u32,
        max_frame_bytes: limits.max_frame_bytes,
        max_messages_per_second: limits.rate,
        stored_seq,
        robot_token,
    };
    let mut rollout = Box::new(Rollout {
        current: release_at_hello,
        desired: shared.desired.as_ref().and_then(|d| d.get(&key)),
        sent: None,
        counter: 0,
    });
    let end = if conn.send(&welcome).await {
        serve(
            &shared,
            &key,
            id,
            &mut conn,
            &mut stream,
            &mut control,
            &mut rollout,
        )
        .await
    } else {
        End::Closed
    };
    if !matches!(end, End::Closed) {
        // We sent a Close frame. Read (and drop) what the agent still sends until its Close, for
        // at most a second: closing a socket with unread data makes the kernel send RST, which
        // destroys the error frame and close reason we just sent before the agent reads them.
        let _ = tokio::time::timeout(Duration::from_secs(1), async {
            while let Some(Ok(frame)) = stream.next().await {
                if matches!(frame, Message::Close(_)) {
                    break;
                }
            }
        })
        .await;
    }

    // 4. Clean up: a replaced session leaves presence to its successor.
    shared.registry.unregister(&key, id);
    if !matches!(end, End::Replaced) {
        shared.presence.disconnect(&key, id);
    }
    shared.metrics.gateway.connections.dec();
    shared
        .metrics
        .gateway
        .sessions_ended
        .get_or_create(&KindLabels { kind: end.label() })
        .inc();
    if let Some(record_id) = record_id
        && let Err(e) = Box::pin(shared.store.record_disconnect(
            record_id,
            Timestamp::now().as_millisecond(),
            end.label(),
        ))
        .await
    {
        warn!(error = %e, "cannot record the disconnect");
    }
    info!(session = id, reason = end.label(), "agent disconnected");
}

/// The next text frame; pings and pongs are skipped, anything else ends the wait.
async fn next_text<R, E>(stream: &mut R) -> Option<String>
where
    R: Stream<Item = Result<Message, E>> + Unpin,
{
    loop {
        match stream.next().await? {
            Ok(Message::Text(t)) => return Some(t.as_str().to_owned()),
            Ok(Message::Ping(_) | Message::Pong(_)) => continue,
            Ok(Message::Binary(_)) => return Some(String::new()),
            Ok(Message::Close(_)) | Err(_) => return None,
        }
    }
}

async fn serve<W, R, E>(
    shared: &Shared,
    key: &RobotKey,
    id: u64,
    conn: &mut Conn<W>,
    stream: &mut R,
    control: &mut mpsc::Receiver<Control>,
    rollout: &mut Rollout,
) -> End
where
    W: Sink<Message> + Unpin + Send,
    R: Stream<Item = Result<Message, E>> + Unpin + Send,
    E: std::fmt::Display,
{
    let limits = &shared.limits;
    let silence = limits.heartbeat_interval * limits.missed_heartbeats.max(1);
    let mut deadline = Instant::now() + silence;
    let mut bucket = super::rate::TokenBucket::new(f64::from(limits.rate.max(1)), limits.burst);
    let mut strikes: u32 = 0;
    if let Some(cmd) = rollout.command(&shared.gateway, id) {
        info!(release = ?rollout.desired.as_ref().map(|r| &r.version), "sending deploy command");
        if !conn.send(&cmd).await {
            return End::Closed;
        }
    }
    loop {
        let frame = tokio::select! {
            () = shared.cancel.cancelled() => {
                conn.error(ErrorCode::ShuttingDown, "gateway shutting down; reconnect", true).await;
                conn.close(CLOSE_AWAY, "gateway shutting down").await;
                return End::Shutdown;
            }
            ctl = control.recv() => match ctl {
                Some(Control::Send(msg)) => {
                    if !conn.send(&msg).await { return End::Closed; }
                    continue;
                }
                Some(Control::Desired(release)) => {
                    rollout.desired = release.map(|r| *r);
                    if let Some(cmd) = rollout.command(&shared.gateway, id) {
                        info!(release = ?rollout.desired.as_ref().map(|r| &r.version), "sending deploy command");
                        if !conn.send(&cmd).await { return End::Closed; }
                    }
                    continue;
                }
                Some(Control::Replaced) | None => {
                    conn.error(ErrorCode::Replaced, "a newer connection of this robot replaced this one", true).await;
                    conn.close(CLOSE_POLICY, "replaced by a newer connection").await;
                    return End::Replaced;
                }
            },
            () = tokio::time::sleep_until(deadline) => {
                warn!(?silence, "no frame within the missed-heartbeat limit; closing");
                conn.close(CLOSE_AWAY, "heartbeat timeout").await;
                return End::HeartbeatTimeout;
            }
            frame = stream.next() => frame,
        };
        let text = match frame {
            None => return End::Closed,
            Some(Err(e)) => {
                debug!(error = %e, "socket error");
                return End::Closed;
            }
            Some(Ok(Message::Close(_))) => return End::Closed,
            // Pings keep the socket open but are no heartbeat: they do not reset the deadline.
            Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
            Some(Ok(Message::Binary(_))) => None,
            Some(Ok(Message::Text(t))) => Some(t),
        };
        deadline = Instant::now() + silence;
        if !bucket.try_take() {
            strikes += 1;
            if strikes > limits.abuse_threshold {
                conn.error(
                    ErrorCode::RateLimited,
                    "sustained message rate above the limit; closing",
                    true,
                )
                .await;
                conn.close(CLOSE_POLICY, "rate limit exceeded").await;
                return End::Abuse;
            }
            if !conn
                .error(
                    ErrorCode::RateLimited,
                    format!(
                        "more than {} messages per second; message dropped, resend later",
                        limits.rate
                    ),
                    false,
                )
                .await
            {
                return End::Closed;
            }
            continue;
        }
        strikes = strikes.saturating_sub(1);
        let Some(text) = text else {
            if !conn
                .error(
                    ErrorCode::Malformed,
                    "binary frames are not part of the protocol; send JSON text",
                    false,
                )
                .await
            {
                return End::Closed;
            }
            continue;
        };
        let msg = match decode::<AgentMessage>(text.as_str(), limits.max_frame_bytes) {
            Ok(m) => m,
            Err(e) => {
                if !conn.error(e.code(), e.to_string(), false).await {
                    return End::Closed;
                }
                continue;
            }
        };
        shared
            .metrics
            .gateway
            .frames
            .get_or_create(&KindLabels {
                kind: frame_label(&msg),
            })
            .inc();
        let reply = match msg {
            AgentMessage::Hello { .. } => ServerMessage::Error {
                code: ErrorCode::UnexpectedMessage,
                message: "hello was already received".into(),
                fatal: false,
                seq: None,
            },
            AgentMessage::Heartbeat {
                sent_at_ms,
                rtt_ms,
                vitals,
                current_release,
                health,
                teleoperation,
            } => {
                if let Some(rtt) = rtt_ms.filter(|r| r.is_finite() && *r >= 0.0) {
                    shared.metrics.gateway.heartbeat_rtt.observe(rtt / 1000.0);
                }
                if current_release.is_some() && current_release != rollout.current {
                    rollout.current = current_release.clone();
                    // Switched elsewhere than asked (e.g. finished an older deploy): ask again.
                    if let Some(cmd) = rollout.command(&shared.gateway, id)
                        && !conn.send(&cmd).await
                    {
                        return End::Closed;
                    }
                }
                shared.presence.heartbeat(
                    key,
                    id,
                    HeartbeatInfo {
                        release: current_release,
                        health,
                        teleoperation,
                        vitals,
                    },
                );
                ServerMessage::HeartbeatAck {
                    sent_at_ms,
                    server_time_ms: Timestamp::now().as_millisecond(),
                }
            }
            AgentMessage::Event {
                seq,
                ts_ms,
                kind,
                severity,
                message,
                data,
            } => {
                let severity = serde_json::to_value(severity)
                    .ok()
                    .and_then(|v| v.as_str().map(str::to_owned))
                    .unwrap_or_default();
                let ev = StoredEvent {
                    seq,
                    ts_ms,
                    kind,
                    severity,
                    message,
                    data,
                };
                durable(
                    shared,
                    seq,
                    Box::pin(shared.store.insert_event(key, &ev)).await,
                )
            }
            AgentMessage::Telemetry { seq, samples } => durable(
                shared,
                seq,
                Box::pin(shared.store.insert_telemetry(key, seq, &samples)).await,
            ),
            AgentMessage::Progress {
                seq,
                command_id,
                phase,
                percent,
                message,
            } => {
                let known = ProgressPhase::parse(&phase);
                if known.is_some_and(ProgressPhase::is_final)
                    && let Some((sent_id, release)) = &rollout.sent
                    && *sent_id == command_id
                {
                    info!(%phase, release = %release.version, %message, "update finished");
                    if known == Some(ProgressPhase::Done) {
                        rollout.current = Some(release.clone());
                    }
                    shared.presence.update_finished(
                        key,
                        id,
                        UpdateOutcome {
                            release: release.clone(),
                            phase: phase.clone(),
                            message: (!message.is_empty()).then(|| message.clone()),
                            time: Timestamp::now(),
                        },
                    );
                }
                let ev = StoredEvent {
                    seq,
                    ts_ms: Timestamp::now().as_millisecond(),
                    kind: "progress".into(),
                    severity: if known == Some(ProgressPhase::Failed) {
                        "error".into()
                    } else {
                        "info".into()
                    },
                    message,
                    data: serde_json::json!({ "command_id": command_id, "phase": phase, "percent": percent }),
                };
                durable(
                    shared,
                    seq,
                    Box::pin(shared.store.insert_event(key, &ev)).await,
                )
            }
        };
        let sent = match reply {
            ServerMessage::Error {
                code, message, seq, ..
            } => conn.refuse(code, message, seq).await,
            other => conn.send(&other).await,
        };
        if !sent {
            return End::Closed;
        }
    }
}

/// The answer to a durable message: an ack once stored (or already stored), else an error so
/// the agent keeps it and resends.
fn durable(
    shared: &Shared,
    seq: u64,
    stored: crate::gateway::event_store::Result<bool>,
) -> ServerMessage {
    match stored {
        Ok(new) => {
            shared
                .metrics
                .gateway
                .durable
                .get_or_create(&KindLabels {
                    kind: if new { "stored" } else { "replay" },
                })
                .inc();
            ServerMessage::Ack { seq }
        }
        // A sequence number the store cannot hold will never be stored: say so, do not ask
        // for a resend.
        Err(crate::gateway::event_store::Error::SeqOutOfRange(_)) => ServerMessage::Error {
            code: ErrorCode::Malformed,
            message: format!(
                "sequence number {seq} is out of range (at most 2^63-1); this message cannot be stored"
            ),
            fatal: false,
            seq: Some(seq),
        },
        Err(e) => {
            warn!(seq, error = %e, "cannot store a durable message");
            ServerMessage::Error {
                code: ErrorCode::StoreUnavailable,
                message: format!("message {seq} was not stored; resend it later"),
                fatal: false,
                seq: Some(seq),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gateway::auth::Authenticator;
    use crate::gateway::event_store::RobotKey;
    use crate::gateway::presence::{Presence, PresenceConfig};

    #[tokio::test]
    async fn an_idle_session_is_small() {
        let client =
            kube::Client::try_from(kube::Config::new("http://127.0.0.1:1".parse().unwrap()))
                .unwrap();
        let (_writer, secrets) = {
            let (store, writer) =
                kube::runtime::reflector::store::<k8s_openapi::api::core::v1::Secret>();
            (writer, store)
        };
        let metrics = Metrics::default();
        let shared = Arc::new(Shared {
            presence: Presence::new(
                PresenceConfig {
                    gateway: "gw".into(),
                    status_refresh: Duration::from_secs(300),
                    poll_grace: Duration::from_secs(180),
                    qps: 1.0,
                    burst: 1,
                    concurrency: 1,
                },
                metrics.clone(),
            ),
            store: Store::connect("sqlite::memory:").await.unwrap(),
            auth: Authenticator::new(client, secrets),
            registry: Arc::default(),
            limits: Limits {
                max_frame_bytes: 1024,
                rate: 10,
                burst: 10,
                abuse_threshold: 20,
                handshake_timeout: Duration::from_secs(1),
                heartbeat_interval: Duration::from_secs(1),
                missed_heartbeats: 3,
            },
            metrics,
            gateway: "gw".into(),
            cancel: CancellationToken::new(),
            desired: None,
        });
        let (sink, _rx) = futures::channel::mpsc::channel::<Message>(1);
        let (_tx, stream) = futures::channel::mpsc::channel::<Result<Message, std::io::Error>>(1);
        let grant = Grant::Robot(RobotKey {
            namespace: "lab".into(),
            name: "kiwi".into(),
        });
        let session = run(shared, grant, None, sink, stream);
        let size = std::mem::size_of_val(&session);
        println!("session future: {size} bytes");
        // Every connection holds one of these for its whole life: keep it well under 8 KiB.
        assert!(size < 8 * 1024, "session future is {size} bytes");
    }
}
