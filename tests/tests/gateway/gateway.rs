//! The agent gateway end to end: real WebSocket agents against a real operator process and API
//! server — enrollment, refusals, bad frames, replacement, presence timing, durable ingest,
//! gateway death, legacy polling.

use std::time::{Duration, Instant};

use futures::SinkExt;
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams};
use lekiwi_agent::connection::{ConnectError, Credentials, Socket, connect};
use lekiwi_crds::{Robot, RobotPhase};
use lekiwi_protocol::{AgentMessage, ErrorCode, ServerMessage, Severity, encode};
use lekiwi_tests::{
    ControlPlane, connect_agent, enrollment_token, gateway_operator, gateway_url, get_robot,
    heartbeat, hello, http_get_with, namespace, recv, wait_for, wait_phase,
};
use serde_json::json;
use tokio_tungstenite::tungstenite::Message;

const TIMEOUT: Duration = Duration::from_secs(10);

fn secs(s: u64) -> Duration {
    Duration::from_secs(s)
}

async fn phase_within(
    client: &kube::Client,
    ns: &str,
    name: &str,
    phase: RobotPhase,
    within: Duration,
) -> anyhow::Result<Duration> {
    let start = Instant::now();
    wait_phase(client, ns, name, phase, within).await?;
    Ok(start.elapsed())
}

async fn send(ws: &mut Socket, msg: &AgentMessage) {
    ws.send(Message::text(encode(msg))).await.expect("send");
}

#[tokio::test]
async fn enrollment_presence_and_replacement() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gw").await?;
    let op = gateway_operator(cp, &ns, "gw-a", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);

    // Enrollment creates the Robot and hands out the robot's own token; Online within a second.
    let creds = Credentials {
        token: enroll.clone(),
        robot: format!("{ns}/kiwi-1"),
    };
    let t = Instant::now();
    let (mut ws, welcome) = connect(&url, &creds, &hello(), TIMEOUT).await?;
    assert_eq!(welcome.robot, format!("{ns}/kiwi-1"));
    let token = welcome
        .robot_token
        .clone()
        .expect("enrollment returns a robot token");
    let online = phase_within(&client, &ns, "kiwi-1", RobotPhase::Online, secs(5)).await?
        + t.elapsed().min(Duration::ZERO);
    println!("enrolled robot Online {:?} after connect", t.elapsed());
    assert!(
        t.elapsed() < Duration::from_secs(2),
        "Online took {:?}",
        online
    );
    let r = get_robot(&client, &ns, "kiwi-1").await?;
    let status = r.status.unwrap();
    assert_eq!(status.protocol.as_deref(), Some("websocket"));
    assert_eq!(status.agent_version.as_deref(), Some("0.1.0-test"));
    assert_eq!(status.system.unwrap().arch.as_deref(), Some("aarch64"));
    send(&mut ws, &heartbeat()).await;
    assert!(matches!(
        recv(&mut ws).await,
        Some(ServerMessage::HeartbeatAck { sent_at_ms: 42, .. })
    ));

    // The robot's own token works; a second connection replaces the first, which is told why.
    let own = Credentials {
        token: token.clone(),
        robot: welcome.robot.clone(),
    };
    let (mut ws2, w2) = connect(&url, &own, &hello(), TIMEOUT).await?;
    assert_eq!(w2.robot_token, None);
    match recv(&mut ws).await {
        Some(ServerMessage::Error {
            code: ErrorCode::Replaced,
            fatal: true,
            ..
        }) => {}
        other => panic!("old connection got {other:?}"),
    }
    assert!(recv(&mut ws).await.is_none(), "old connection is closed");
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        get_robot(&client, &ns, "kiwi-1")
            .await?
            .status
            .unwrap()
            .phase,
        Some(RobotPhase::Online),
        "replacement must not look like a disconnect"
    );
    send(&mut ws2, &heartbeat()).await;
    assert!(matches!(
        recv(&mut ws2).await,
        Some(ServerMessage::HeartbeatAck { .. })
    ));

    // A bare robot name enrolls into the enrollment token's namespace (from the watch cache).
    let bare = Credentials {
        token: enroll.clone(),
        robot: "kiwi-bare".into(),
    };
    let (bare_ws, bare_welcome) =
        wait_for("bare-name enrollment", Duration::from_secs(5), || async {
            connect(&url, &bare, &hello(), TIMEOUT).await.ok()
        })
        .await?;
    assert_eq!(bare_welcome.robot, format!("{ns}/kiwi-bare"));
    drop(bare_ws);

    // Enrolling again (a robot that lost its token) needs a person's permission
    // (`kubectl lekiwi robot reenroll`; refusals are in hostile_identity) and never duplicates
    // the Robot.
    drop(ws2);
    let until = jiff::Timestamp::now() + jiff::SignedDuration::from_secs(600);
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch(
            "kiwi-1",
            &PatchParams::default(),
            &Patch::Merge(json!({"metadata": {"annotations": {
                lekiwi_crds::contract::REENROLL_ANNOTATION: until.round(jiff::Unit::Second)?.to_string()
            }}})),
        )
        .await?;
    let (ws3, w3) = connect(&url, &creds, &hello(), TIMEOUT).await?;
    assert!(
        w3.robot_token.is_some() && w3.robot_token != Some(token.clone()),
        "re-enrollment rotates the token"
    );
    let robots = Api::<Robot>::namespaced(client.clone(), &ns)
        .list(&ListParams::default())
        .await?;
    assert_eq!(robots.items.len(), 2, "kiwi-1 and kiwi-bare, once each");
    // The old token no longer works.
    let err = connect(&url, &own, &hello(), TIMEOUT).await.unwrap_err();
    assert!(matches!(err, ConnectError::Unauthorized(_)), "{err}");

    // A closed connection is Offline within a second.
    drop(ws3);
    let t = Instant::now();
    phase_within(&client, &ns, "kiwi-1", RobotPhase::Offline, secs(5)).await?;
    println!("Offline {:?} after close", t.elapsed());
    assert!(
        t.elapsed() < Duration::from_millis(1500),
        "Offline took {:?}",
        t.elapsed()
    );
    Ok(())
}

#[tokio::test]
async fn bad_credentials_are_refused_before_the_upgrade() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwauth").await?;
    let op = gateway_operator(cp, &ns, "gw-auth", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);
    let cases = [
        (
            "wrong token",
            Credentials {
                token: "lkr_not-a-token".into(),
                robot: format!("{ns}/kiwi-1"),
            },
        ),
        (
            "enrollment token of another namespace",
            Credentials {
                token: enroll.clone(),
                robot: "default/kiwi-1".into(),
            },
        ),
        (
            "invalid robot name",
            Credentials {
                token: enroll.clone(),
                robot: "Kiwi_1".into(),
            },
        ),
        (
            "empty token",
            Credentials {
                token: String::new(),
                robot: format!("{ns}/kiwi-1"),
            },
        ),
    ];
    for (what, creds) in cases {
        match connect(&url, &creds, &hello(), TIMEOUT).await {
            Err(ConnectError::Unauthorized(body)) => {
                let v: serde_json::Value = serde_json::from_str(&body)
                    .unwrap_or_else(|_| panic!("{what}: body not JSON: {body}"));
                assert_eq!(v["error"], "unauthorized", "{what}: {body}");
            }
            other => panic!("{what}: expected 401, got {:?}", other.map(|(_, w)| w)),
        }
    }
    // No Robot was created, and the log never contains a token.
    assert!(
        Api::<Robot>::namespaced(client.clone(), &ns)
            .list(&ListParams::default())
            .await?
            .items
            .is_empty()
    );
    let log = op.log_text();
    assert!(
        !log.contains("lkr_not-a-token") && !log.contains(&enroll),
        "a token leaked into the log"
    );
    assert!(log.contains("refused an agent request"), "{log}");
    Ok(())
}

#[tokio::test]
async fn bad_frames_get_error_frames_and_the_session_survives() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwframes").await?;
    let op = gateway_operator(
        cp,
        &ns,
        "gw-frames",
        &["--agent-rate", "2", "--agent-burst", "5"],
    )
    .await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;

    let cases: Vec<(Message, ErrorCode)> = vec![
        (Message::text("this is not json"), ErrorCode::Malformed),
        (
            Message::text(r#"{"type":"teleport","to":"mars"}"#),
            ErrorCode::UnknownMessage,
        ),
        (
            Message::text(r#"{"type":"event","seq":1}"#),
            ErrorCode::UnknownMessage,
        ),
        (
            Message::text(format!(
                r#"{{"type":"heartbeat","sent_at_ms":1,"pad":"{}"}}"#,
                "x".repeat(300 * 1024)
            )),
            ErrorCode::FrameTooLarge,
        ),
        (Message::binary(vec![0u8, 1, 2]), ErrorCode::Malformed),
        (
            Message::text(encode(&hello())),
            ErrorCode::UnexpectedMessage,
        ),
    ];
    for (frame, code) in cases {
        ws.send(frame).await?;
        match recv(&mut ws).await {
            Some(ServerMessage::Error {
                code: got,
                fatal: false,
                ..
            }) => assert_eq!(got, code),
            other => panic!("expected a non-fatal {code:?} error frame, got {other:?}"),
        }
        tokio::time::sleep(Duration::from_millis(600)).await; // stay under the rate limit (2/s)
    }
    send(&mut ws, &heartbeat()).await;
    assert!(
        matches!(
            recv(&mut ws).await,
            Some(ServerMessage::HeartbeatAck { .. })
        ),
        "session still serves"
    );

    // A burst over the limit (2/s, burst 5) is refused message by message; sustained abuse (net
    // refusals above 2 x burst) closes the session. 40 frames exceed it however slowly they go out.
    tokio::time::sleep(Duration::from_millis(2600)).await; // a full bucket to start from
    for _ in 0..40 {
        send(&mut ws, &heartbeat()).await;
    }
    let mut limited = 0;
    let mut closed = false;
    while let Some(msg) = recv(&mut ws).await {
        match msg {
            ServerMessage::Error {
                code: ErrorCode::RateLimited,
                fatal: true,
                ..
            } => {
                closed = recv(&mut ws).await.is_none();
                break;
            }
            ServerMessage::Error {
                code: ErrorCode::RateLimited,
                ..
            } => limited += 1,
            other => eprintln!("burst answer: {other:?}"),
        }
    }
    assert!(limited > 0 && closed, "limited {limited}, closed {closed}");
    Ok(())
}

#[tokio::test]
async fn durable_events_are_stored_once_and_acked_again() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwevents").await?;
    let op = gateway_operator(cp, &ns, "gw-ev", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, welcome) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;
    assert_eq!(welcome.stored_seq, None);
    let event = |seq| AgentMessage::Event {
        seq,
        ts_ms: 1_763_800_000_000 + seq as i64,
        kind: "teleoperation_started".into(),
        severity: Severity::Info,
        message: format!("event {seq}"),
        data: json!({"port": 5555}),
    };
    for seq in [1, 2, 2, 1, 3] {
        send(&mut ws, &event(seq)).await;
        assert_eq!(recv(&mut ws).await, Some(ServerMessage::Ack { seq }));
    }
    send(
        &mut ws,
        &AgentMessage::Telemetry {
            seq: 4,
            samples: vec![lekiwi_protocol::Sample {
                metric: "cpu_percent".into(),
                ts_ms: 1,
                value: 5.0,
            }],
        },
    )
    .await;
    assert_eq!(recv(&mut ws).await, Some(ServerMessage::Ack { seq: 4 }));
    // One sequence for all three kinds: a seq stored as one kind, sent again as another, is a
    // replay (acked, not stored).
    let samples = |seq| AgentMessage::Telemetry {
        seq,
        samples: vec![lekiwi_protocol::Sample {
            metric: "temperature_c".into(),
            ts_ms: 2,
            value: 50.0,
        }],
    };
    let progress = |seq| AgentMessage::Progress {
        seq,
        command_id: "c1".into(),
        phase: "downloading".into(),
        percent: None,
        message: String::new(),
    };
    for (seq, msg) in [
        (2, samples(2)),
        (4, event(4)),
        (4, progress(4)),
        (3, progress(3)),
    ] {
        send(&mut ws, &msg).await;
        assert_eq!(recv(&mut ws).await, Some(ServerMessage::Ack { seq }));
    }
    drop(ws);

    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(ns.clone(), "kiwi-1");
    let events = store.events(&key, None, 100).await?;
    assert_eq!(
        events.iter().map(|e| e.seq).collect::<Vec<_>>(),
        [1, 2, 3],
        "each seq stored exactly once"
    );
    assert_eq!(events[0].data["port"], 5555);
    assert_eq!(
        (events[2].kind.as_str(), events[2].message.as_str()),
        ("teleoperation_started", "event 3"),
        "the first copy of seq 3 kept"
    );
    let samples = store.samples(&key, None, 0, 100).await?;
    assert_eq!(
        samples
            .iter()
            .map(|s| (s.seq, s.metric.as_str()))
            .collect::<Vec<_>>(),
        [(4, "cpu_percent")]
    );
    assert_eq!(store.last_seq(&key).await?, Some(4));

    // A reconnecting agent learns what is stored already.
    let (_ws, welcome) = connect_agent(&op, &welcome.robot_token.unwrap(), &welcome.robot).await?;
    assert_eq!(welcome.stored_seq, Some(4));
    let conns = store.connections(&key, 10).await?;
    assert!(
        conns.len() >= 2 && conns.iter().any(|c| c.disconnected_at_ms.is_some()),
        "{conns:?}"
    );
    Ok(())
}

/// An `agent_update_succeeded` event stored by a session that ended before it could tell
/// presence (its robot reconnected meanwhile, or the store answered an error after it had
/// committed) is sent again by the agent, which never got its ack: the resend is a duplicate
/// for the store, and still the step reaches `status.agentUpdate` (in CI a robot's update
/// stayed `Started` for good in such a case).
#[tokio::test]
async fn an_agent_update_step_stored_before_reaches_the_status_when_sent_again()
-> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwstep").await?;
    let op = gateway_operator(cp, &ns, "gw-step", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;
    wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, secs(20)).await?;
    let succeeded = lekiwi_event_store::StoredEvent {
        seq: 7,
        ts_ms: 1_763_800_000_000,
        kind: "agent_update_succeeded".into(),
        severity: "info".into(),
        message: "now running 9.9.9".into(),
        data: json!({"version": "9.9.9"}),
    };
    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(ns.clone(), "kiwi-1");
    assert!(store.insert_event(&key, &succeeded).await?, "stored first");
    let resend = AgentMessage::Event {
        seq: 7,
        ts_ms: succeeded.ts_ms,
        kind: succeeded.kind.clone(),
        severity: Severity::Info,
        message: succeeded.message.clone(),
        data: succeeded.data.clone(),
    };
    send(&mut ws, &resend).await;
    assert_eq!(recv(&mut ws).await, Some(ServerMessage::Ack { seq: 7 }));
    let report = wait_for("status.agentUpdate Succeeded", secs(20), || async {
        let status = get_robot(&client, &ns, "kiwi-1").await.ok()?.status?;
        let report = status.agent_update?;
        (report.phase.as_deref() == Some("Succeeded")).then_some(report)
    })
    .await?;
    assert_eq!(report.version.as_deref(), Some("9.9.9"));
    assert_eq!(report.message.as_deref(), Some("now running 9.9.9"));
    // Counted once (no Robot names 9.9.9 in `spec.agent`: version `other`), and a step
    // presence has already is acked again but not counted again.
    let series = r#"lekiwi_gateway_agent_updates_total{kind="succeeded",version="other"}"#;
    assert_eq!(op.metric(series).await, Some(1.0), "counted once");
    send(&mut ws, &resend).await;
    assert_eq!(recv(&mut ws).await, Some(ServerMessage::Ack { seq: 7 }));
    assert_eq!(
        op.metric(series).await,
        Some(1.0),
        "a resend of a known step"
    );
    let kinds: Vec<String> = store
        .events(&key, None, 100)
        .await?
        .into_iter()
        .map(|e| e.kind)
        .collect();
    assert_eq!(kinds, ["agent_update_succeeded"], "stored once");
    Ok(())
}

#[tokio::test]
async fn silence_closes_the_session_and_a_dead_gateway_leaves_robots_unknown() -> anyhow::Result<()>
{
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwdeath").await?;
    // Controllers and gateway in separate processes, so the gateway can die alone.
    let _ctl = gateway_operator(cp, &ns, "ctl", &["--role", "controller"]).await?;
    let mut gw = gateway_operator(
        cp,
        &ns,
        "gw",
        &[
            "--role",
            "gateway",
            "--heartbeat-interval-seconds",
            "1",
            "--gateway-lease-seconds",
            "3",
        ],
    )
    .await?;
    let enroll = enrollment_token(&client, &ns).await?;

    // Silence: closed and Offline within 3 intervals (+ write latency).
    let (ws, _) = connect_agent(&gw, &enroll, &format!("{ns}/quiet")).await?;
    phase_within(&client, &ns, "quiet", RobotPhase::Online, secs(5)).await?;
    let t = Instant::now();
    phase_within(&client, &ns, "quiet", RobotPhase::Offline, secs(8)).await?;
    println!(
        "silent robot Offline after {:?} (3 x 1 s intervals)",
        t.elapsed()
    );
    assert!(
        t.elapsed() < Duration::from_millis(4500),
        "took {:?}",
        t.elapsed()
    );
    drop(ws);

    // A live robot on a gateway that is killed: Unknown once the gateway Lease expires.
    let (mut ws, _) = connect_agent(&gw, &enroll, &format!("{ns}/busy")).await?;
    send(&mut ws, &heartbeat()).await;
    phase_within(&client, &ns, "busy", RobotPhase::Online, secs(5)).await?;
    gw.kill();
    let t = Instant::now();
    phase_within(&client, &ns, "busy", RobotPhase::Unknown, secs(10)).await?;
    println!(
        "robot Unknown {:?} after its gateway was killed (lease 3 s)",
        t.elapsed()
    );
    Ok(())
}

/// A robot the Robot controller shows gone while its session here is live (its status'
/// heartbeat aged past the grace because this gateway's writes ran late, as after an API server
/// restart) is written again before anything else, not at its next refresh minutes later.
#[tokio::test]
async fn a_live_robot_shown_gone_is_written_again_at_once() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "showngone").await?;
    // Refreshes 10 minutes apart: only a write put first brings the robot back in the test's time.
    let gw = gateway_operator(cp, &ns, "op", &["--status-refresh-seconds", "600"]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, _) = connect_agent(&gw, &enroll, &format!("{ns}/kiwi")).await?;
    send(&mut ws, &heartbeat()).await;
    phase_within(&client, &ns, "kiwi", RobotPhase::Online, secs(10)).await?;
    let beats = tokio::spawn(async move {
        loop {
            send(&mut ws, &heartbeat()).await;
            tokio::time::sleep(secs(2)).await;
        }
    });
    let gone = "lekiwi_gateway_status_writes_total{priority=\"gone\",result=\"ok\"}";
    let before = gw.metric(gone).await.unwrap_or(0.0);

    // The status as a gateway whose writes run late leaves it: its heartbeat 10 minutes old.
    // The Robot controller turns the robot Offline (heartbeat expired) under the live session.
    let stale = jiff::Timestamp::now() - jiff::SignedDuration::from_mins(10);
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch_status(
            "kiwi",
            &PatchParams::default(),
            &Patch::Merge(json!({ "status": { "lastHeartbeatTime": stale.to_string() } })),
        )
        .await?;
    let t = Instant::now();
    wait_for("the robot written first", secs(20), || async {
        (gw.metric(gone).await? > before).then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", gw.log_text()))?;
    let r = phase_within(&client, &ns, "kiwi", RobotPhase::Online, secs(10)).await?;
    println!(
        "shown gone under its live session: written again {:?} after the stale status, Online {r:?} later",
        t.elapsed()
    );
    let heartbeat_age = get_robot(&client, &ns, "kiwi")
        .await?
        .status
        .and_then(|s| s.last_heartbeat_time)
        .map(|h| jiff::Timestamp::now().duration_since(h.0));
    assert!(
        heartbeat_age.is_some_and(|a| a < jiff::SignedDuration::from_secs(30)),
        "written with a fresh heartbeat: {heartbeat_age:?}"
    );
    beats.abort();
    Ok(())
}

#[tokio::test]
async fn legacy_poll_is_answered_cached_and_counts_as_heartbeat() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwpoll").await?;
    let op = gateway_operator(cp, &ns, "gw-poll", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    lekiwi_tests::create_robot(&client, &ns, "old-1", &[]).await?;
    let release = json!({"version": "2.0.0", "digest": format!("sha256:{}", "b".repeat(64))});
    lekiwi_tests::set_release(&client, &ns, "old-1", &release).await?;
    // Only the robot's own token may poll for it (an enrollment token gets 401: hostile_identity).
    let own = lekiwi_tests::robot_token(&client, &ns, "old-1").await?;
    let auth = format!("Bearer {own}");
    let path = format!("/v1/poll?robot={ns}/old-1&version=1.0.0&agent=legacy-0.9");
    let (code, headers, body) =
        http_get_with(op.gateway_port, &path, &[("authorization", &auth)]).await?;
    assert_eq!(code, 200, "{body}");
    let answer: serde_json::Value = serde_json::from_str(&body)?;
    assert_eq!(answer["update_available"], true);
    assert_eq!(answer["target_version"], "2.0.0");
    let etag = headers
        .iter()
        .find(|(k, _)| k == "etag")
        .map(|(_, v)| v.clone())
        .expect("ETag");
    assert!(
        headers
            .iter()
            .any(|(k, v)| k == "cache-control" && v.contains("no-cache"))
    );

    let (code, _, body) = http_get_with(
        op.gateway_port,
        &path,
        &[("authorization", &auth), ("if-none-match", &etag)],
    )
    .await?;
    assert_eq!(code, 304, "{body}");
    assert!(body.is_empty());

    // The poll made the robot Online, recorded as a polling robot.
    phase_within(&client, &ns, "old-1", RobotPhase::Online, secs(5)).await?;
    let status = get_robot(&client, &ns, "old-1").await?.status.unwrap();
    assert_eq!(status.protocol.as_deref(), Some("poll"));
    assert_eq!(status.agent_version.as_deref(), Some("legacy-0.9"));

    // Answers are cached: a spec change within the TTL is not seen yet (polling fleets cost
    // the API server one read per robot per minute at most).
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch("old-1", &PatchParams::default(), &Patch::Merge(json!({"spec": {"release": {"version": "3.0.0", "digest": format!("sha256:{}", "c".repeat(64))}}})))
        .await?;
    let (code, _, _) = http_get_with(
        op.gateway_port,
        &path,
        &[("authorization", &auth), ("if-none-match", &etag)],
    )
    .await?;
    assert_eq!(code, 304);
    let polls = op.metric("lekiwi_gateway_polls_total{kind=\"304\"}").await;
    assert_eq!(polls, Some(2.0));

    // Another robot's token, the enrollment token and bad tokens are refused.
    let (code, _, body) = http_get_with(
        op.gateway_port,
        &format!("/v1/poll?robot={ns}/nope&version=1"),
        &[("authorization", &auth)],
    )
    .await?;
    assert_eq!(code, 401, "{body}");
    let (code, _, body) = http_get_with(
        op.gateway_port,
        &path,
        &[("authorization", &format!("Bearer {enroll}"))],
    )
    .await?;
    assert_eq!(code, 401, "{body}");
    let (code, _, _) =
        http_get_with(op.gateway_port, &path, &[("authorization", "Bearer wrong")]).await?;
    assert_eq!(code, 401);
    Ok(())
}

#[tokio::test]
async fn handshake_timeout_connection_cap_and_tls() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gwtls").await?;

    let dir = tempfile::tempdir()?;
    lekiwi_tests::test_ca(dir.path())?;
    let d = dir.path().display().to_string();
    let cert = format!("{d}/tls.crt");
    let key = format!("{d}/tls.key");
    let op = gateway_operator(
        cp,
        &ns,
        "gw-tls",
        &[
            "--tls-cert",
            &cert,
            "--tls-key",
            &key,
            "--max-connections",
            "1",
            "--handshake-timeout-seconds",
            "1",
        ],
    )
    .await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);
    let ca = dir.path().join("ca.crt");

    // wss:// with our CA: a session as usual.
    let creds = Credentials {
        token: enroll.clone(),
        robot: format!("{ns}/kiwi-tls"),
    };
    let (mut ws, welcome) =
        lekiwi_agent::connection::connect_with_ca(&url, &creds, &hello(), TIMEOUT, Some(&ca))
            .await?;
    assert_eq!(welcome.robot, format!("{ns}/kiwi-tls"));
    send(&mut ws, &heartbeat()).await;
    assert!(matches!(
        recv(&mut ws).await,
        Some(ServerMessage::HeartbeatAck { .. })
    ));
    phase_within(&client, &ns, "kiwi-tls", RobotPhase::Online, secs(5)).await?;

    // The connection cap (1) is reached: the next agent gets 503 before any upgrade.
    let other = Credentials {
        token: enroll.clone(),
        robot: format!("{ns}/kiwi-2"),
    };
    match lekiwi_agent::connection::connect_with_ca(&url, &other, &hello(), TIMEOUT, Some(&ca))
        .await
    {
        Err(ConnectError::Unavailable { message, .. }) => {
            assert!(message.contains("503"), "{message}")
        }
        other => panic!("expected 503, got {:?}", other.map(|(_, w)| w)),
    }
    // Plain ws:// to a TLS gateway and a wss:// client that does not trust our CA both fail.
    assert!(
        connect(
            &format!("ws://127.0.0.1:{}/v1/agent", op.gateway_port),
            &other,
            &hello(),
            TIMEOUT
        )
        .await
        .is_err()
    );
    drop(ws);
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(
        connect(&url, &other, &hello(), TIMEOUT).await.is_err(),
        "an untrusted certificate was accepted"
    );

    // A client that upgrades but never says hello is told so and closed after the timeout.
    let mut request =
        tokio_tungstenite::tungstenite::client::IntoClientRequest::into_client_request(
            url.as_str(),
        )?;
    request
        .headers_mut()
        .insert("authorization", format!("Bearer {enroll}").parse()?);
    request
        .headers_mut()
        .insert("x-lekiwi-robot", format!("{ns}/kiwi-mute").parse()?);
    let tls = rustls_for(&ca);
    let (mut mute, _) =
        tokio_tungstenite::connect_async_tls_with_config(request, None, false, Some(tls)).await?;
    let t = Instant::now();
    match recv(&mut mute).await {
        Some(ServerMessage::Error {
            code: ErrorCode::HandshakeTimeout,
            fatal: true,
            ..
        }) => {}
        other => panic!("expected handshake_timeout, got {other:?}"),
    }
    assert!(
        t.elapsed() < Duration::from_secs(3),
        "took {:?}",
        t.elapsed()
    );
    Ok(())
}

fn rustls_for(ca: &std::path::Path) -> tokio_tungstenite::Connector {
    use rustls_pki_types::CertificateDer;
    use rustls_pki_types::pem::PemObject;
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_file_iter(ca).unwrap() {
        roots.add(cert.unwrap()).unwrap();
    }
    let config = rustls::ClientConfig::builder_with_provider(std::sync::Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_root_certificates(roots)
    .with_no_client_auth();
    tokio_tungstenite::Connector::Rustls(std::sync::Arc::new(config))
}
