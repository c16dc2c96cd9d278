//! One agent's WebSocket session: handshake, heartbeats, durable ingest with acks, limits,
//! replacement by a newer connection. Generic over the socket halves, so unit tests drive it
//! with channels and the gateway with a real WebSocket.

mod agent_update;
mod commands;
mod conn;
mod frames;
mod handshake;
mod serve;

use std::sync::Arc;
use std::time::Duration;

use crate::mailbox::Receiver;
use axum::extract::ws::Message;
use futures::{Sink, Stream, StreamExt};
use jiff::Timestamp;
use lekiwi_protocol::{MAX_SEQ, PROTOCOL_VERSION, ServerMessage};
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, info, info_span, warn};

use self::agent_update::AgentLedger;
use self::commands::CommandLedger;
use self::conn::{Conn, End, Flow};
use super::auth::{Authenticator, Grant};
use super::quota_warnings::QuotaWarnings;
use super::registry::{Control, Registry};
use lekiwi_core::RobotKey;
use lekiwi_event_store::{ConnectionRecord, Store};
use lekiwi_metrics::{KindLabels, Metrics};
use lekiwi_presence::holder::next_epoch;
use lekiwi_presence::watched::WatchedRobots;
use lekiwi_presence::{ConnectInfo, Presence};

/// Limits one session enforces.
#[derive(Clone, Debug)]
pub struct Limits {
    /// Largest frame accepted; larger ones get an error frame.
    pub max_frame_bytes: usize,
    /// Messages per second sustained; more are refused with a `rate_limited` error frame.
    pub rate: u32,
    /// Messages accepted at once above the sustained rate.
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
    /// Time one frame may take to be written; a session whose agent stopped reading is closed
    /// after it, and its connection slot freed.
    pub send_timeout: Duration,
}

/// What every session shares.
#[derive(Clone)]
pub struct SessionContext {
    /// Each robot's connection state in memory, written to `Robot` status sparingly.
    pub presence: Presence,
    /// Where durable agent messages and connection records are stored before they are acked.
    pub store: Store,
    /// Token checks and registration.
    pub auth: Authenticator,
    /// Open sessions, so a newer connection replaces an older one.
    pub registry: Arc<Registry>,
    /// What each session enforces.
    pub limits: Limits,
    /// Where sessions count frames, errors and ends.
    pub metrics: Metrics,
    /// This gateway's name: in connection records and deploy command ids.
    pub gateway: String,
    /// Fires on shutdown: every session says so to its agent and closes.
    pub cancel: CancellationToken,
    /// The robots' desired releases (`spec.release`), when this gateway watches Robots.
    pub desired: Option<WatchedRobots>,
    /// Which robots' desired release is held (a rollout a user stopped), alongside `desired`.
    pub holds: Option<crate::halt::Holds>,
    /// Warning Events on Robots whose agents send past their event store quota.
    pub quota_warnings: QuotaWarnings,
}

/// A session past its handshake: what its loop and its frame handlers work with.
// shape: the handshake and shared state here; serve.rs the main loop, frames.rs one handler per
// message type, agent_update.rs agent-update bookkeeping.
struct Session<'a, W> {
    shared: &'a SessionContext,
    key: &'a RobotKey,
    /// This session's number in the registry.
    id: u64,
    conn: Conn<W>,
    /// Boxed: the session future lives as long as the connection, so keep it small.
    commands: Box<CommandLedger>,
    /// Boxed like `commands`.
    agent: Box<AgentLedger>,
    /// SHA-256 (hex) of the token this session speaks with: the robot's token it presented,
    /// or the one it was issued at enrollment. Rotating or deleting it ends the session.
    token_hash: String,
}

/// What opening a session left to close at its end.
struct Opened {
    /// This session's number in the registry.
    id: u64,
    /// Where the registry reaches this session.
    control: Receiver<Control>,
    /// The connection record to close, if the store took it.
    record_id: Option<i64>,
    /// The highest sequence number stored for the robot, announced in `welcome`.
    stored_seq: Option<u64>,
}

/// Runs one session to its end, in a `session` span naming the robot. `token_hash` is the hash
/// of the token the agent presented ([`lekiwi_crds::contract::hash_token`]). Not an `async fn`:
/// its arguments would stay in the returned future, as well as in the one they move into.
pub fn run<W, R, E>(
    shared: Arc<SessionContext>,
    grant: Grant,
    token_hash: String,
    address: Option<String>,
    sink: W,
    stream: R,
) -> impl Future<Output = ()>
where
    W: Sink<Message> + Unpin + Send,
    R: Stream<Item = Result<Message, E>> + Unpin + Send,
    E: std::fmt::Display,
{
    let span =
        info_span!("session", robot = %grant.robot().name, namespace = %grant.robot().namespace);
    run_inner(shared, grant, token_hash, address, sink, stream).instrument(span)
}

async fn run_inner<W, R, E>(
    shared: Arc<SessionContext>,
    grant: Grant,
    token_hash: String,
    address: Option<String>,
    sink: W,
    mut stream: R,
) where
    W: Sink<Message> + Unpin + Send,
    R: Stream<Item = Result<Message, E>> + Unpin + Send,
    E: std::fmt::Display,
{
    let key = grant.robot().clone();
    // Every step but the main loop is boxed, and the handshake is one function of its own:
    // this future lives (and holds its memory) as long as the connection, and a step inline,
    // or a local of the handshake, would add its size to it for that whole time.
    let conn = Conn::new(sink, &shared.metrics, shared.limits.send_timeout);
    let started = Box::pin(start(
        &shared,
        &grant,
        &key,
        token_hash,
        address,
        conn,
        &mut stream,
    ));
    let Some((mut session, mut opened, welcomed)) = started.await else {
        return;
    };
    let end = match welcomed {
        Ok(()) => session.serve(&mut stream, &mut opened.control).await,
        Err(end) => end,
    };
    // Closed: nothing left to read; SendTimeout: no Close frame went out to be answered.
    if !matches!(end, End::Closed | End::SendTimeout) {
        Box::pin(drain_until_close(&mut stream)).await;
    }
    // 4. Clean up: a replaced session leaves presence to its successor.
    Box::pin(close(&shared, &key, &opened, &end)).await;
}

/// The handshake: the hello, enrollment, taking over from an older session, `welcome` and the
/// hello's refused fields. `None` when the agent never got as far as a session (it was told
/// why); else the session, what opening it left to close, and how the welcome went.
async fn start<'a, W, R, E>(
    shared: &'a SessionContext,
    grant: &Grant,
    key: &'a RobotKey,
    token_hash: String,
    address: Option<String>,
    mut conn: Conn<W>,
    stream: &mut R,
) -> Option<(Session<'a, W>, Opened, Flow)>
where
    W: Sink<Message> + Unpin + Send,
    R: Stream<Item = Result<Message, E>> + Unpin + Send,
    E: std::fmt::Display,
{
    // 1. The hello, within the handshake timeout.
    let hello = Box::pin(handshake::hello(shared, &mut conn, stream))
        .await
        .ok()?;
    // 2. Enrollment mints the robot's own token.
    let robot_token = Box::pin(handshake::enroll(shared, grant, &mut conn))
        .await
        .ok()?;
    let token_hash = robot_token
        .as_deref()
        .map(lekiwi_crds::contract::hash_token)
        .unwrap_or(token_hash);
    // 3. Take over from an older session, record the connection, tell presence.
    let handshake::Hello {
        info: hello,
        refused,
        features,
    } = hello;
    let current = hello.release.clone();
    let agent = AgentLedger::new(
        hello.agent_version.clone(),
        hello.system.arch.clone(),
        &features,
        shared.desired.as_ref().and_then(|d| d.agent(key)),
    );
    let opened = Box::pin(open(shared, key, ConnectInfo { address, ..hello })).await;
    let mut commands =
        CommandLedger::new(current, shared.desired.as_ref().and_then(|d| d.get(key)));
    if let Some(release) = held_release(shared, key) {
        // Nothing is in flight in a new session: no cancel to send.
        let _ = commands.halt(release, &shared.gateway, opened.id);
    }
    let mut session = Session {
        shared,
        key,
        id: opened.id,
        conn,
        commands: Box::new(commands),
        agent: Box::new(agent),
        token_hash,
    };
    let welcome = welcome(&shared.limits, key, opened.stored_seq, robot_token);
    let welcomed = match session.conn.send(&welcome).await {
        Ok(()) => session.invalid_fields(refused).await,
        Err(end) => Err(end),
    };
    Some((session, opened, welcomed))
}

/// The robot's desired release when it is held (see [`crate::halt::Holds`]): a session that
/// opens does not deploy it.
fn held_release(shared: &SessionContext, key: &RobotKey) -> Option<lekiwi_protocol::Release> {
    let robots = shared.desired.as_ref()?;
    let robot = robots.robot(key)?;
    if !shared.holds.as_ref()?.held(&robot) {
        return None;
    }
    robot
        .spec
        .release
        .as_ref()
        .map(lekiwi_protocol::Release::from)
}

/// Registers the session (replacing an older one) with an epoch above the one the robot's
/// status shows, tells presence (whether the robot moved here), then records the connection.
async fn open(shared: &SessionContext, key: &RobotKey, hello: ConnectInfo) -> Opened {
    let holder = shared.desired.as_ref().and_then(|d| d.holder(key));
    let seen = holder.as_ref().and_then(|h| h.epoch);
    // Its status names another gateway: it moved here (that gateway may have died).
    let moved = holder
        .and_then(|h| h.gateway)
        .is_some_and(|g| g != shared.gateway);
    let epoch = next_epoch(Timestamp::now(), seen);
    let (id, control) = shared.registry.register(key, epoch);
    let record = ConnectionRecord {
        gateway: shared.gateway.clone(),
        protocol: "websocket".into(),
        address: hello.address.clone(),
        connected_at_ms: Timestamp::now().as_millisecond(),
        disconnected_at_ms: None,
        reason: None,
    };
    // Presence first, and with it the claim of a moved robot: in a reconnect storm the event
    // store can take seconds to answer, and the Robot controller marks a dead gateway's robots
    // `Unknown` once the live gateways' Leases renewed after its expiry (the claims they list).
    // A claim that waited for the store missed that renewal (42 of 5,000 in a kill benchmark).
    shared.presence.connect_moved(key, id, epoch, hello, moved);
    let start = Box::pin(shared.store.open_session(key, &record)).await;
    let record_id = start
        .record_id
        .inspect_err(|e| {
            shared.metrics.gateway.event_store_error("open_session");
            warn!(error = %e, "cannot record the connection in the event store");
        })
        .ok();
    let stored_seq = start
        .last_seq
        .unwrap_or_else(|e| {
            warn!(error = %e, "cannot read the last stored sequence number");
            None
        })
        // Stored before seqs were bounded: not a number to tell an agent; say nothing.
        .filter(|s| *s <= MAX_SEQ);
    shared.metrics.gateway.connections.inc();
    info!(session = id, epoch, ?stored_seq, "agent connected");
    Opened {
        id,
        control,
        record_id,
        stored_seq,
    }
}

/// The `welcome` frame: the limits the agent must keep and what the gateway already stored.
fn welcome(
    limits: &Limits,
    key: &RobotKey,
    stored_seq: Option<u64>,
    robot_token: Option<String>,
) -> ServerMessage {
    ServerMessage::Welcome {
        protocol_version: PROTOCOL_VERSION,
        robot: format!("{}/{}", key.namespace, key.name),
        heartbeat_interval_s: limits.heartbeat_interval.as_secs().max(1) as u32,
        max_frame_bytes: limits.max_frame_bytes,
        max_messages_per_second: limits.rate,
        stored_seq,
        robot_token,
    }
}

/// After we sent a Close frame, reads (and drops) what the agent still sends until its Close,
/// for at most a second: closing a socket with unread data makes the kernel send RST, which
/// destroys the error frame and close reason we just sent before the agent reads them.
async fn drain_until_close<R, E>(stream: &mut R)
where
    R: Stream<Item = Result<Message, E>> + Unpin,
{
    let _ = tokio::time::timeout(Duration::from_secs(1), async {
        while let Some(Ok(frame)) = stream.next().await {
            if matches!(frame, Message::Close(_)) {
                break;
            }
        }
    })
    .await;
}

/// Unregisters the session, tells presence (unless a newer session took over: here, it has the
/// presence entry; on another gateway, the status), counts the end and closes the connection
/// record.
async fn close(shared: &SessionContext, key: &RobotKey, opened: &Opened, end: &End) {
    shared.registry.unregister(key, opened.id);
    match end {
        End::Replaced => {}
        End::Moved => shared.presence.forget(key, opened.id),
        _ => shared.presence.disconnect(key, opened.id),
    }
    shared.metrics.gateway.connections.dec();
    shared
        .metrics
        .gateway
        .sessions_ended
        .get_or_create(&KindLabels { kind: end.label() })
        .inc();
    if let Some(record_id) = opened.record_id
        && let Err(e) = Box::pin(shared.store.record_disconnect(
            record_id,
            Timestamp::now().as_millisecond(),
            end.label(),
        ))
        .await
    {
        shared.metrics.gateway.event_store_error("close_session");
        warn!(error = %e, "cannot record the disconnect");
    }
    info!(
        session = opened.id,
        reason = end.label(),
        "agent disconnected"
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::auth::Authenticator;
    use lekiwi_core::RobotKey;
    use lekiwi_presence::{Presence, PresenceConfig};

    #[tokio::test]
    async fn an_idle_session_is_small() {
        let client =
            kube::Client::try_from(kube::Config::new("http://127.0.0.1:1".parse().unwrap()))
                .unwrap();
        let metrics = Metrics::default();
        let shared = Arc::new(SessionContext {
            presence: Presence::new(
                PresenceConfig {
                    gateway: "gw".into(),
                    status_refresh: Duration::from_secs(300),
                    poll_grace: Duration::from_secs(180),
                    qps: 1.0,
                    adaptive: None,
                    burst: 1,
                    concurrency: 1,
                },
                metrics.clone(),
            ),
            store: Store::connect("sqlite::memory:").await.unwrap(),
            auth: Authenticator::new(
                client.clone(),
                Arc::new(crate::tokens::TokenIndex::listed([])),
            ),
            registry: Arc::default(),
            limits: Limits {
                max_frame_bytes: 1024,
                rate: 10,
                burst: 10,
                abuse_threshold: 20,
                handshake_timeout: Duration::from_secs(1),
                heartbeat_interval: Duration::from_secs(1),
                missed_heartbeats: 3,
                send_timeout: Duration::from_secs(10),
            },
            metrics,
            gateway: "gw".into(),
            cancel: CancellationToken::new(),
            desired: None,
            holds: None,
            quota_warnings: QuotaWarnings::new(client, "gw", Duration::from_secs(300)),
        });
        let (sink, _rx) = futures::channel::mpsc::channel::<Message>(1);
        let (_tx, stream) = futures::channel::mpsc::channel::<Result<Message, std::io::Error>>(1);
        let grant = Grant::Robot(RobotKey {
            namespace: "lab".into(),
            name: "kiwi".into(),
        });
        let session = run(shared, grant, String::new(), None, sink, stream);
        let size = std::mem::size_of_val(&session);
        println!("session future: {size} bytes");
        // Every connection holds one of these for its whole life: each step but the main loop
        // is boxed, the handshake's locals with it, and `run` is no `async fn` (976 bytes in
        // debug and release builds; 2,256 while the handshake was inline).
        assert!(size < 1280, "session future is {size} bytes");
    }
}
