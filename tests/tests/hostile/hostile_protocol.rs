//! Hostile and odd protocol input against a real operator process (issue 12, points 7, 10 and
//! 13; issue 40, points 2 and 3): bounded sequence numbers, short error frames, a future
//! version's `hello`, what the document says about whitespace, `null`, severities and
//! out-of-range numbers, an agent's Close frame, and a real agent that keeps working after
//! someone forged a huge `seq` for its robot.

use std::time::Duration;

use futures::{SinkExt, StreamExt};
use lekiwi_agent::connection::Socket;
use lekiwi_protocol::{AgentMessage, ErrorCode, MAX_SEQ, ServerMessage, Severity, decode, encode};
use lekiwi_tests::{
    AgentProcess, ControlPlane, connect_agent, enrollment_token, enrollment_token_file,
    gateway_operator, gateway_url, namespace, recv, wait_for,
};
use serde_json::json;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::protocol::CloseFrame;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::{Error as WsError, Message};

const TIMEOUT: Duration = Duration::from_secs(10);

/// Sends `text` as one frame and returns the answer.
async fn ask(ws: &mut Socket, text: String) -> ServerMessage {
    ws.send(Message::text(text)).await.expect("send");
    recv(ws).await.expect("an answer")
}

fn event(seq: u64, severity: Severity) -> String {
    encode(&AgentMessage::Event {
        seq,
        ts_ms: 1_763_800_000_000,
        kind: "note".into(),
        severity,
        message: String::new(),
        data: serde_json::Value::Null,
    })
}

/// A non-fatal refusal with `code` (and `seq`), or a panic naming what came instead.
fn assert_refused(answer: &ServerMessage, want: ErrorCode, want_seq: Option<u64>) {
    match answer {
        ServerMessage::Error {
            code,
            fatal: false,
            seq,
            message,
        } => {
            assert_eq!((*code, *seq), (want, want_seq), "{message}");
            assert!(message.len() <= 256, "{} bytes: {message}", message.len());
        }
        other => panic!("expected a non-fatal {want:?} error, got {other:?}"),
    }
}

#[tokio::test]
async fn sequence_numbers_are_bounded_and_error_frames_stay_short() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hpseq").await?;
    let op = gateway_operator(cp, &ns, "hp-seq", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, enrolled) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;
    // Once enrolled, the robot speaks with its own token (enrollment never takes it over).
    let own = enrolled
        .robot_token
        .ok_or_else(|| anyhow::anyhow!("enrollment gave no robot token"))?;

    // The largest allowed seq is stored; anything above is `malformed` naming it: 2^53, the
    // 2^63-1 that once overflowed agents, and 2^63 which the store could never hold.
    let answer = ask(&mut ws, event(MAX_SEQ, Severity::Info)).await;
    assert_eq!(answer, ServerMessage::Ack { seq: MAX_SEQ });
    for seq in [MAX_SEQ + 1, i64::MAX as u64, 1 << 63] {
        let answer = ask(&mut ws, event(seq, Severity::Info)).await;
        assert_refused(&answer, ErrorCode::Malformed, Some(seq));
    }
    // Counted as what they are, not as a store failure.
    let malformed = r#"lekiwi_gateway_error_frames_total{kind="malformed"}"#;
    assert_eq!(op.metric(malformed).await, Some(3.0));
    let unavailable = r#"lekiwi_gateway_error_frames_total{kind="store_unavailable"}"#;
    assert_eq!(op.metric(unavailable).await.unwrap_or(0.0), 0.0);

    // A seq that is no u64 at all cannot be named: `unknown_message`, like any wrong type.
    let huge =
        r#"{"type":"event","seq":18446744073709551616,"ts_ms":1,"kind":"k","severity":"info"}"#;
    assert_refused(
        &ask(&mut ws, huge.into()).await,
        ErrorCode::UnknownMessage,
        None,
    );

    // A 250 KB value is quoted by a short prefix only.
    let long = format!(r#"{{"type":"{}"}}"#, "x".repeat(250_000));
    ws.send(Message::text(long)).await?;
    let raw = match tokio::time::timeout(TIMEOUT, ws.next()).await? {
        Some(Ok(Message::Text(t))) => t.as_str().to_owned(),
        other => panic!("{other:?}"),
    };
    assert!(raw.len() < 400, "{} bytes of error frame", raw.len());
    let answer: ServerMessage = decode(&raw, usize::MAX)?;
    assert_refused(&answer, ErrorCode::UnknownMessage, None);

    // JSON whitespace around the object is fine; other trailing characters are not.
    let hb = r#"{"type":"heartbeat","sent_at_ms":7}"#;
    let answer = ask(&mut ws, format!(" {hb}\r\n\t ")).await;
    assert!(
        matches!(answer, ServerMessage::HeartbeatAck { sent_at_ms: 7, .. }),
        "{answer:?}"
    );
    assert_refused(
        &ask(&mut ws, format!("{hb}x")).await,
        ErrorCode::Malformed,
        None,
    );

    // An unknown severity is stored as `unknown` (and acked), as §5.2 says.
    let critical = event(5, Severity::Info).replace(r#""info""#, r#""critical""#);
    assert_eq!(ask(&mut ws, critical).await, ServerMessage::Ack { seq: 5 });
    drop(ws);
    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(ns.clone(), "kiwi-1");
    let stored = store.events(&key, None, 10).await?;
    let seqs: Vec<(u64, &str)> = stored
        .iter()
        .map(|e| (e.seq, e.severity.as_str()))
        .collect();
    assert_eq!(seqs, [(5, "unknown"), (MAX_SEQ, "info")]);
    let (ws, welcome) = connect_agent(&op, &own, &format!("{ns}/kiwi-1")).await?;
    assert_eq!(welcome.stored_seq, Some(MAX_SEQ));
    drop(ws);

    // A seq above the bound, stored by an older gateway, is never announced to an agent.
    let mut legacy = stored[0].clone();
    legacy.seq = i64::MAX as u64;
    store.insert_event(&key, &legacy).await?;
    let (_ws, welcome) = connect_agent(&op, &own, &format!("{ns}/kiwi-1")).await?;
    assert_eq!(welcome.stored_seq, None);
    Ok(())
}

/// A WebSocket upgraded by the gateway for `robot` with `token`, before any frame.
async fn upgrade(
    op: &lekiwi_tests::OperatorProcess,
    token: &str,
    robot: &str,
) -> anyhow::Result<Socket> {
    let mut request = gateway_url(op).into_client_request()?;
    let headers = request.headers_mut();
    headers.insert("authorization", format!("Bearer {token}").parse()?);
    // With its namespace: a token created a moment ago is then looked up if the gateway's
    // watch has not delivered it yet (a bare name is only matched against the watch).
    headers.insert("x-lekiwi-robot", robot.parse()?);
    Ok(tokio_tungstenite::connect_async(request).await?.0)
}

/// An agent that writes every optional field it has no value for as `null` (as Go writes a nil
/// slice or pointer) enrolls and is served exactly like one that omits them (PROTOCOL.md §2).
#[tokio::test]
async fn null_optional_fields_count_as_omitted() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hpnull").await?;
    let op = gateway_operator(cp, &ns, "hp-null", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let mut ws = upgrade(&op, &enroll, &format!("{ns}/kiwi-go")).await?;
    let hello = json!({
        "type": "hello", "protocol_version": 1, "agent_version": "0.1.0-go",
        "agent_digest": null, "system": null, "current_release": null, "last_acked_seq": null,
        "health": null, "teleoperation": null, "features": null,
    });
    match ask(&mut ws, hello.to_string()).await {
        ServerMessage::Welcome { robot, .. } => assert_eq!(robot, format!("{ns}/kiwi-go")),
        other => panic!("expected welcome, got {other:?}"),
    }
    let heartbeat = json!({
        "type": "heartbeat", "sent_at_ms": 9, "rtt_ms": null, "vitals": null,
        "current_release": null, "health": {"healthy": true, "message": null, "reason": null},
        "teleoperation": {"active": false, "score": null},
    });
    let answer = ask(&mut ws, heartbeat.to_string()).await;
    assert!(
        matches!(answer, ServerMessage::HeartbeatAck { sent_at_ms: 9, .. }),
        "{answer:?}"
    );
    let event = json!({
        "type": "event", "seq": 1, "ts_ms": 1_763_800_000_000_i64, "kind": "note",
        "severity": "info", "message": null, "data": null,
    });
    assert_eq!(
        ask(&mut ws, event.to_string()).await,
        ServerMessage::Ack { seq: 1 }
    );
    let progress = json!({
        "type": "progress", "seq": 2, "command_id": "c1", "phase": "downloading",
        "percent": null, "message": null,
    });
    assert_eq!(
        ask(&mut ws, progress.to_string()).await,
        ServerMessage::Ack { seq: 2 }
    );
    // A required field is another matter: `null` is a wrong type.
    let no_seq = json!({"type": "event", "seq": null, "ts_ms": 1, "kind": "k", "severity": "info"});
    assert_refused(
        &ask(&mut ws, no_seq.to_string()).await,
        ErrorCode::UnknownMessage,
        None,
    );
    drop(ws);
    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(ns.clone(), "kiwi-go");
    let stored = store.events(&key, None, 10).await?;
    assert_eq!(stored.len(), 2, "{stored:?}");
    assert_eq!(
        (stored[0].message.as_str(), &stored[0].data),
        ("", &serde_json::Value::Null)
    );
    Ok(())
}

/// The gateway's answer to our Close frame: its Close, then the end of the stream. Without the
/// answer the client reads a reset (`ResetWithoutClosingHandshake`, which agents see as 1006).
async fn close_answer(ws: &mut Socket, code: CloseCode, reason: &str) -> Option<CloseFrame> {
    let ours = CloseFrame {
        code,
        reason: reason.into(),
    };
    ws.close(Some(ours)).await.expect("our Close frame sent");
    let answer = match tokio::time::timeout(TIMEOUT, ws.next()).await {
        Ok(Some(Ok(Message::Close(frame)))) => frame,
        other => panic!("expected the gateway's Close frame, got {other:?}"),
    };
    match tokio::time::timeout(TIMEOUT, ws.next()).await {
        Ok(None | Some(Err(WsError::ConnectionClosed))) => {}
        other => panic!("expected the end of the stream, got {other:?}"),
    }
    answer
}

/// An agent that closes its session cleanly, during the handshake or after it, gets the
/// gateway's Close frame echoing its code (RFC 6455 §5.5.1) before the connection ends; the
/// robot is disconnected as after any close.
#[tokio::test]
async fn an_agents_close_frame_is_answered_with_a_close_frame() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hpclose").await?;
    let op = gateway_operator(cp, &ns, "hp-close", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let robot = format!("{ns}/kiwi-c");
    let (mut ws, welcome) = connect_agent(&op, &enroll, &robot).await?;
    let answer = close_answer(&mut ws, CloseCode::Normal, "agent stopping").await;
    let answer = answer.expect("a close code");
    assert_eq!(
        (answer.code, answer.reason.as_str()),
        (CloseCode::Normal, "agent stopping")
    );
    let token = welcome.robot_token.expect("a robot token");
    let (mut ws, _) = connect_agent(&op, &token, &robot).await?;
    let answer = close_answer(&mut ws, CloseCode::Away, "").await;
    assert_eq!(answer.map(|f| f.code), Some(CloseCode::Away));
    // Before its hello, too.
    let mut ws = upgrade(&op, &token, &robot).await?;
    let answer = close_answer(&mut ws, CloseCode::Away, "restarting").await;
    assert_eq!(answer.map(|f| f.code), Some(CloseCode::Away));
    let closed = r#"lekiwi_gateway_sessions_ended_total{kind="closed"}"#;
    wait_for("both sessions counted as closed", TIMEOUT, || async {
        (op.metric(closed).await == Some(2.0)).then_some(())
    })
    .await?;
    Ok(())
}

#[tokio::test]
async fn a_future_hello_with_other_field_types_gets_unsupported_version() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hpver").await?;
    let op = gateway_operator(cp, &ns, "hp-ver", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let mut ws = upgrade(&op, &enroll, &format!("{ns}/kiwi-v2")).await?;
    let v2 = json!({
        "type": "hello", "protocol_version": 2, "agent_version": "2.0.0",
        "system": "a v2 string", "current_release": ["v2", "list"]
    });
    ws.send(Message::text(v2.to_string())).await?;
    match recv(&mut ws).await {
        Some(ServerMessage::Error {
            code: ErrorCode::UnsupportedVersion,
            fatal: true,
            ..
        }) => {}
        other => panic!("expected a fatal unsupported_version, got {other:?}"),
    }
    assert_eq!(recv(&mut ws).await, None, "closed after the refusal");
    Ok(())
}

#[tokio::test]
async fn an_agent_keeps_working_after_a_forged_seq_and_refuses_oversized_events()
-> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hpagent").await?;
    let op = gateway_operator(cp, &ns, "hp-agent", &[]).await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enrollment-token");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let state = dir.path().join("state");
    let robot = format!("{ns}/kiwi-1");
    let mut agent = AgentProcess::start(&gateway_url(&op), &robot, &token_file, &state, &[])?;
    agent.wait_connected(TIMEOUT).await?;
    agent.terminate()?;

    // Someone holding the robot's token forges the seq that used to overflow the agent.
    let creds: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(state.join("credentials.json"))?)?;
    let token = creds["token"].as_str().expect("a saved token");
    let (mut ws, _) = connect_agent(&op, token, &robot).await?;
    let forged = i64::MAX as u64;
    let answer = ask(&mut ws, event(forged, Severity::Info)).await;
    assert_refused(&answer, ErrorCode::Malformed, Some(forged));
    drop(ws);

    // The real agent comes back, is welcomed, and its next event is stored.
    let seq = agent.emit("after_forgery", "still here", &json!({}))?;
    agent.restart()?;
    agent.wait_connected(TIMEOUT).await?;
    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(ns.clone(), "kiwi-1");
    wait_for("the event after the forgery stored", TIMEOUT, || async {
        let events = store.events(&key, None, 100).await.ok()?;
        events
            .iter()
            .any(|e| e.seq == seq && e.kind == "after_forgery")
            .then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;

    // An event too large for any frame is refused at the command line, with a clear error:
    // what counts is the encoded frame (each control character takes 6 bytes in JSON).
    let err = agent
        .emit("huge", &"\u{1}".repeat(60_000), &json!({}))
        .expect_err("an oversized event is refused");
    assert!(
        err.to_string().contains("the gateway accepts at most"),
        "{err}"
    );
    Ok(())
}

/// The next `deploy` command's release version within `wait`, skipping other frames.
async fn deploy_within(ws: &mut Socket, wait: Duration) -> Option<String> {
    let deadline = tokio::time::Instant::now() + wait;
    loop {
        let frame = tokio::time::timeout_at(deadline, ws.next()).await.ok()??;
        let Ok(Message::Text(t)) = frame else {
            continue;
        };
        if let Ok(ServerMessage::Command {
            command: lekiwi_protocol::Command::Deploy { release, .. },
            ..
        }) = decode(t.as_str(), usize::MAX)
        {
            return Some(release.version);
        }
    }
}

#[tokio::test]
async fn a_switch_away_is_not_redeployed_within_the_session_but_on_reconnect() -> anyhow::Result<()>
{
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hpdeploy").await?;
    let op = gateway_operator(cp, &ns, "hp-deploy", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    lekiwi_tests::create_robot(&client, &ns, "kiwi-d", &[]).await?;
    let v2 = json!({"version": "2.0.0", "digest": format!("sha256:{}", "b".repeat(64))});
    kube::Api::<lekiwi_crds::Robot>::namespaced(client.clone(), &ns)
        .patch(
            "kiwi-d",
            &kube::api::PatchParams::default(),
            &kube::api::Patch::Merge(json!({"spec": {"release": v2}})),
        )
        .await?;
    let (mut ws, welcome) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-d")).await?;
    assert_eq!(
        deploy_within(&mut ws, TIMEOUT).await.as_deref(),
        Some("2.0.0")
    );

    // The robot reports another release (e.g. it rolled back): acked, no second deploy.
    let v1 = json!({"version": "1.0.0", "digest": format!("sha256:{}", "a".repeat(64))});
    let hb = json!({"type": "heartbeat", "sent_at_ms": 1, "current_release": v1});
    ws.send(Message::text(hb.to_string())).await?;
    assert_eq!(deploy_within(&mut ws, Duration::from_secs(3)).await, None);
    drop(ws);

    // A new session asks again.
    let token = welcome.robot_token.expect("a robot token");
    let (mut ws, _) = connect_agent(&op, &token, &welcome.robot).await?;
    assert_eq!(
        deploy_within(&mut ws, TIMEOUT).await.as_deref(),
        Some("2.0.0")
    );
    Ok(())
}
