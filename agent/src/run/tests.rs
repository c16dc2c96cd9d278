//! The run loop driven over channels instead of a WebSocket: a test plays the gateway and
//! checks the frames the agent sends.

use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use futures::channel::{mpsc, oneshot};
use futures::{Sink, Stream, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, MAX_FRAME_BYTES, PROTOCOL_VERSION, ServerMessage, decode, encode,
};
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

use super::{AGENT_VERSION, Agent};
use crate::config::Config;
use crate::connection::Connector;
use crate::connection::{Credentials, handshake};
use crate::outbox::Outbox;
use crate::state;

const ROBOT: &str = "lekiwi-demo/kiwi";
/// Long enough for a few heartbeats at the shortest interval (1 s).
const PATIENCE: Duration = Duration::from_secs(5);

/// The agent's end of a connection: what it sends goes to the [`Gateway`], and back.
struct Duplex {
    tx: mpsc::UnboundedSender<Message>,
    rx: mpsc::UnboundedReceiver<Message>,
}

impl Sink<Message> for Duplex {
    type Error = WsError;

    fn poll_ready(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), WsError>> {
        Poll::Ready(Ok(()))
    }

    fn start_send(self: Pin<&mut Self>, item: Message) -> Result<(), WsError> {
        self.tx
            .unbounded_send(item)
            .map_err(|_| WsError::ConnectionClosed)
    }

    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), WsError>> {
        Poll::Ready(Ok(()))
    }

    fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), WsError>> {
        Poll::Ready(Ok(()))
    }
}

impl Stream for Duplex {
    type Item = Result<Message, WsError>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        self.rx.poll_next_unpin(cx).map(|m| m.map(Ok))
    }
}

/// The test's end of one connection, with the credentials the agent connected with.
struct Gateway {
    creds: Credentials,
    tx: mpsc::UnboundedSender<Message>,
    rx: mpsc::UnboundedReceiver<Message>,
}

impl Gateway {
    fn send(&self, msg: &ServerMessage) {
        self.send_text(&encode(msg));
    }

    fn send_text(&self, text: &str) {
        self.tx.unbounded_send(Message::text(text)).unwrap();
    }

    /// The next frame from the agent; `None` when nothing came within `wait`.
    async fn recv_within(&mut self, wait: Duration) -> Option<AgentMessage> {
        loop {
            match tokio::time::timeout(wait, self.rx.next()).await {
                Err(_) => return None,
                Ok(None) => panic!("the agent dropped the connection"),
                Ok(Some(Message::Text(t))) => return Some(decode(t.as_str(), usize::MAX).unwrap()),
                Ok(Some(Message::Close(_))) => panic!("the agent closed the session"),
                Ok(Some(_)) => {}
            }
        }
    }

    async fn recv(&mut self) -> AgentMessage {
        self.recv_within(PATIENCE)
            .await
            .expect("a frame from the agent")
    }

    /// The next frame that is not a heartbeat, acknowledging heartbeats on the way as the
    /// gateway does; `None` when none came within `wait`.
    async fn durable_within(&mut self, wait: Duration) -> Option<AgentMessage> {
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            let left = deadline.saturating_duration_since(tokio::time::Instant::now());
            match self.recv_within(left).await? {
                AgentMessage::Heartbeat { sent_at_ms, .. } => self.send(&heartbeat_ack(sent_at_ms)),
                other => return Some(other),
            }
        }
    }

    /// Waits for the agent to close the session (a close frame or the end of the stream).
    async fn closed(&mut self) {
        let closing = async {
            while let Some(m) = self.rx.next().await {
                if matches!(m, Message::Close(_)) {
                    return;
                }
            }
        };
        tokio::time::timeout(PATIENCE, closing)
            .await
            .expect("the agent closes the session");
    }

    /// Reads `hello`, answers `welcome` (with a robot token when `token` is given), and returns
    /// the `hello`.
    async fn welcome(&mut self, token: Option<&str>) -> AgentMessage {
        let hello = self.recv().await;
        self.send(&ServerMessage::Welcome {
            protocol_version: PROTOCOL_VERSION,
            robot: ROBOT.into(),
            heartbeat_interval_s: 1,
            max_frame_bytes: MAX_FRAME_BYTES,
            max_messages_per_second: 100,
            stored_seq: None,
            robot_token: token.map(str::to_owned),
        });
        hello
    }
}

fn heartbeat_ack(sent_at_ms: i64) -> ServerMessage {
    ServerMessage::HeartbeatAck {
        sent_at_ms,
        server_time_ms: lekiwi_protocol::now_ms(),
    }
}

fn error_frame(code: ErrorCode, fatal: bool, seq: Option<u64>) -> ServerMessage {
    ServerMessage::Error {
        code,
        message: format!("{code:?}"),
        fatal,
        seq,
    }
}

fn seq_of(msg: &AgentMessage) -> Option<u64> {
    match msg {
        AgentMessage::Event { seq, .. }
        | AgentMessage::Telemetry { seq, .. }
        | AgentMessage::Progress { seq, .. } => Some(*seq),
        _ => None,
    }
}

/// An agent with sensors off (no samples, no teleoperation checks) and quick reconnects.
fn config(dir: &std::path::Path) -> Config {
    Config {
        gateway: "ws://127.0.0.1:9/v1/agent".into(),
        state_dir: dir.join("state"),
        robot_name: ROBOT.into(),
        enrollment_token: Some("enrollment-token".into()),
        backoff_initial_ms: 50,
        backoff_max_ms: 200,
        status_listen: "off".into(),
        mdns: false,
        ..Config::default()
    }
    .without_sensors()
}

/// Runs an agent on `config` while `play` acts as the gateway, receiving each connection the
/// agent opens; the agent shuts down when `play` returns.
async fn with_agent<F, Fut>(config: Config, play: F)
where
    F: FnOnce(mpsc::UnboundedReceiver<Gateway>) -> Fut,
    Fut: Future<Output = ()>,
{
    let agent = Agent::new(config).await.unwrap();
    let (conn_tx, conn_rx) = mpsc::unbounded();
    let connect: Connector<Duplex> = Box::new(move |creds, hello| {
        let (to_gateway, from_agent) = mpsc::unbounded();
        let (to_agent, from_gateway) = mpsc::unbounded();
        let _ = conn_tx.unbounded_send(Gateway {
            creds,
            tx: to_agent,
            rx: from_agent,
        });
        let mut client = Duplex {
            tx: to_gateway,
            rx: from_gateway,
        };
        Box::pin(async move {
            let welcome = handshake(&mut client, &hello, PATIENCE).await?;
            Ok((client, welcome))
        })
    });
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let run = agent.run_with(
        async {
            let _ = stop_rx.await;
        },
        connect,
    );
    let play = async move {
        play(conn_rx).await;
        let _ = stop_tx.send(());
    };
    let (res, ()) = tokio::join!(run, play);
    res.unwrap();
}

/// Connects and takes the session up to the first durable message (`agent_started`, seq 1).
async fn session_up(conns: &mut mpsc::UnboundedReceiver<Gateway>) -> (Gateway, i64) {
    let mut gw = conns.next().await.unwrap();
    gw.welcome(Some("robot-token")).await;
    let AgentMessage::Heartbeat { sent_at_ms, .. } = gw.recv().await else {
        panic!("a heartbeat first")
    };
    let started = gw.recv().await;
    assert!(
        matches!(&started, AgentMessage::Event { seq: 1, kind, .. } if kind == "agent_started"),
        "{started:?}"
    );
    (gw, sent_at_ms)
}

#[tokio::test]
async fn hello_then_welcome_enrolls_and_the_next_session_uses_the_robot_token() {
    let dir = tempfile::tempdir().unwrap();
    let config = config(dir.path());
    let state_dir = config.state_dir.clone();
    with_agent(config, |mut conns| async move {
        let mut gw = conns.next().await.unwrap();
        assert_eq!(gw.creds.token, "enrollment-token");
        assert_eq!(gw.creds.robot, ROBOT);
        let hello = gw.welcome(Some("robot-token")).await;
        let AgentMessage::Hello {
            protocol_version,
            agent_version,
            last_acked_seq,
            ..
        } = hello
        else {
            panic!("hello first, got {hello:?}")
        };
        assert_eq!(protocol_version, PROTOCOL_VERSION);
        assert_eq!(agent_version, AGENT_VERSION);
        assert_eq!(last_acked_seq, None);
        assert!(matches!(gw.recv().await, AgentMessage::Heartbeat { .. }));
        assert_eq!(seq_of(&gw.recv().await), Some(1));
        let saved = state::load_credentials(&state_dir).unwrap().unwrap();
        assert_eq!(
            (saved.robot.as_str(), saved.token.as_str()),
            (ROBOT, "robot-token")
        );

        // The gateway goes away; the agent comes back with its own token.
        drop(gw);
        let mut gw = conns.next().await.unwrap();
        assert_eq!(gw.creds.token, "robot-token");
        assert!(matches!(gw.recv().await, AgentMessage::Hello { .. }));
    })
    .await;
}

#[tokio::test]
async fn a_durable_event_is_resent_until_acked() {
    let dir = tempfile::tempdir().unwrap();
    let config = config(dir.path());
    let state_dir = config.state_dir.clone();
    with_agent(config, |mut conns| async move {
        let (mut gw, _) = session_up(&mut conns).await;
        // Unacknowledged for more than a heartbeat interval: sent again.
        let again = gw.durable_within(PATIENCE).await.expect("a resend");
        assert_eq!(seq_of(&again), Some(1), "{again:?}");
        gw.send(&ServerMessage::Ack { seq: 1 });
        // Acknowledged: never again, and gone from the outbox.
        assert_eq!(gw.durable_within(Duration::from_millis(2500)).await, None);
        let outbox = Outbox::open(&state_dir, 1 << 20).unwrap();
        assert_eq!(outbox.all().unwrap(), vec![]);
        assert_eq!(outbox.last_acked_seq().unwrap(), 1);
        assert!(conns.try_recv().is_err(), "the session held");
    })
    .await;
}

#[tokio::test]
async fn a_heartbeat_ack_sets_the_rtt_of_the_next_heartbeat() {
    let dir = tempfile::tempdir().unwrap();
    with_agent(config(dir.path()), |mut conns| async move {
        let (mut gw, sent_at_ms) = session_up(&mut conns).await;
        gw.send(&ServerMessage::Ack { seq: 1 });
        // Echo a send time 300 ms earlier than the real one: the agent measures >= 300 ms.
        gw.send(&heartbeat_ack(sent_at_ms - 300));
        // Heartbeats sent before the ack was read (e.g. when the start-up recovery ends) carry
        // no round trip yet.
        let mut heartbeats = 0;
        let rtt = loop {
            heartbeats += 1;
            assert!(heartbeats < 5, "no heartbeat carries the round trip");
            let next = gw.recv().await;
            let AgentMessage::Heartbeat { rtt_ms, .. } = next else {
                panic!("a heartbeat, got {next:?}")
            };
            if let Some(rtt) = rtt_ms {
                break rtt;
            }
        };
        assert!((300.0..5000.0).contains(&rtt), "{rtt}");
    })
    .await;
}

#[tokio::test]
async fn a_malformed_frame_from_the_gateway_does_not_end_the_session() {
    let dir = tempfile::tempdir().unwrap();
    with_agent(config(dir.path()), |mut conns| async move {
        let (mut gw, _) = session_up(&mut conns).await;
        gw.send_text("{not json");
        gw.send_text(r#"{"type":"no_such_frame","seq":1}"#);
        gw.send_text(&"x".repeat(MAX_FRAME_BYTES + 1));
        // Still read and handled: the ack stops the resend of seq 1.
        gw.send(&ServerMessage::Ack { seq: 1 });
        assert_eq!(gw.durable_within(Duration::from_millis(2500)).await, None);
        let hb = gw.recv().await;
        assert!(matches!(hb, AgentMessage::Heartbeat { .. }), "{hb:?}");
        assert!(conns.try_recv().is_err(), "no second connection");
    })
    .await;
}

#[tokio::test]
async fn a_refused_durable_message_is_sent_again_after_a_pause() {
    let dir = tempfile::tempdir().unwrap();
    with_agent(config(dir.path()), |mut conns| async move {
        let (mut gw, _) = session_up(&mut conns).await;
        gw.send(&error_frame(ErrorCode::RateLimited, false, Some(1)));
        // Held for a second, not resent at once...
        assert_eq!(gw.durable_within(Duration::from_millis(500)).await, None);
        // ...then sent again.
        let again = gw.durable_within(PATIENCE).await.expect("a resend");
        assert_eq!(seq_of(&again), Some(1), "{again:?}");
        assert!(conns.try_recv().is_err(), "the session held");
    })
    .await;
}

#[tokio::test]
async fn a_fatal_error_ends_the_session_and_the_agent_comes_back() {
    let dir = tempfile::tempdir().unwrap();
    with_agent(config(dir.path()), |mut conns| async move {
        let (mut gw, _) = session_up(&mut conns).await;
        gw.send(&error_frame(ErrorCode::Replaced, true, None));
        gw.closed().await;
        let mut gw = tokio::time::timeout(PATIENCE, conns.next())
            .await
            .expect("a new connection")
            .unwrap();
        let hello = gw.welcome(Some("robot-token")).await;
        assert!(matches!(hello, AgentMessage::Hello { .. }), "{hello:?}");
        // Not acknowledged in the first session: sent again in the second.
        let again = gw.durable_within(PATIENCE).await.expect("the event again");
        assert_eq!(seq_of(&again), Some(1), "{again:?}");
    })
    .await;
}

#[tokio::test]
async fn a_durable_message_refused_as_malformed_is_dropped_not_resent() {
    refused_durable_message_is_dropped_not_resent(ErrorCode::Malformed).await;
}

#[tokio::test]
async fn a_durable_message_over_the_robots_quota_is_dropped_not_resent() {
    refused_durable_message_is_dropped_not_resent(ErrorCode::QuotaExceeded).await;
}

async fn refused_durable_message_is_dropped_not_resent(code: ErrorCode) {
    let dir = tempfile::tempdir().unwrap();
    let config = config(dir.path());
    let state_dir = config.state_dir.clone();
    with_agent(config, |mut conns| async move {
        let (mut gw, _) = session_up(&mut conns).await;
        gw.send(&error_frame(code, false, Some(1)));
        // Past the resend interval (a heartbeat, 1 s): never sent again.
        assert_eq!(gw.durable_within(Duration::from_millis(2500)).await, None);
        let outbox = Outbox::open(&state_dir, 1 << 20).unwrap();
        assert_eq!(outbox.all().unwrap(), vec![]);
        assert_eq!(outbox.last_acked_seq().unwrap(), 0, "dropped, not acked");
        assert!(conns.try_recv().is_err(), "the session held");
    })
    .await;
}

#[tokio::test]
async fn a_stored_seq_above_the_maximum_is_ignored_and_the_agent_keeps_sending() {
    let dir = tempfile::tempdir().unwrap();
    with_agent(config(dir.path()), |mut conns| async move {
        let mut gw = conns.next().await.unwrap();
        gw.recv().await; // hello
        gw.send(&ServerMessage::Welcome {
            protocol_version: PROTOCOL_VERSION,
            robot: ROBOT.into(),
            heartbeat_interval_s: 1,
            max_frame_bytes: MAX_FRAME_BYTES,
            max_messages_per_second: 100,
            stored_seq: Some(i64::MAX as u64),
            robot_token: Some("robot-token".into()),
        });
        // Its own numbering goes on: agent_started is still seq 1, and is sent.
        let first = gw
            .durable_within(PATIENCE)
            .await
            .expect("a durable message");
        assert_eq!(seq_of(&first), Some(1), "{first:?}");
        assert!(conns.try_recv().is_err(), "the session held");
    })
    .await;
}

/// A robot whose own token is refused and whose enrollment is refused (403: it is enrolled
/// already) alternates between the two, and never hammers the gateway.
#[tokio::test]
async fn a_refused_enrollment_goes_back_to_the_robot_token() {
    let dir = tempfile::tempdir().unwrap();
    let config = config(dir.path());
    state::ensure_dir(&config.state_dir).unwrap();
    let own = state::Credentials {
        robot: ROBOT.into(),
        token: "robot-token".into(),
    };
    state::save_credentials(&config.state_dir, &own).unwrap();
    let agent = Agent::new(config).await.unwrap();
    let (tokens_tx, mut tokens_rx) = mpsc::unbounded::<String>();
    let connect: Connector<Duplex> = Box::new(move |creds: Credentials, _hello| {
        let _ = tokens_tx.unbounded_send(creds.token.clone());
        Box::pin(async move {
            Err(if creds.token == "robot-token" {
                crate::connection::ConnectError::Unauthorized("invalid token".into())
            } else {
                crate::connection::ConnectError::Forbidden("already enrolled".into())
            })
        })
    });
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let run = agent.run_with(
        async {
            let _ = stop_rx.await;
        },
        connect,
    );
    let watch = async move {
        let mut seen = Vec::new();
        for _ in 0..4 {
            seen.push(tokens_rx.next().await.unwrap());
        }
        let _ = stop_tx.send(());
        seen
    };
    let (res, seen) = tokio::join!(run, watch);
    res.unwrap();
    assert_eq!(
        seen,
        [
            "robot-token",
            "enrollment-token",
            "robot-token",
            "enrollment-token"
        ]
    );
}
