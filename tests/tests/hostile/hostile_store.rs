//! A robot that floods the event store or lies about its clock (issue 12, point 9), against a
//! real operator process: past its quota its messages are refused `quota_exceeded` naming their
//! `seq`, counted, reported once on the Robot, and the robot stays Online; retention goes by the
//! gateway's receive time, whatever `ts_ms` the robot claims.

use std::time::Duration;

use futures::{SinkExt, StreamExt};
use k8s_openapi::api::events::v1::Event;
use kube::Api;
use lekiwi_agent::connection::Socket;
use lekiwi_crds::RobotPhase;
use lekiwi_protocol::{AgentMessage, ErrorCode, Sample, ServerMessage, Severity, decode, encode};
use lekiwi_tests::{
    AgentProcess, ControlPlane, connect_agent, enrollment_token, enrollment_token_file,
    gateway_operator, gateway_url, namespace, wait_for, wait_phase,
};
use tokio_tungstenite::tungstenite::Message;

const TIMEOUT: Duration = Duration::from_secs(10);
/// Far in the future (year 2096): once, never pruned.
const FUTURE_MS: i64 = 4_000_000_000_000;

/// Sends `msg` and returns the gateway's answer (skipping pings).
async fn ask(ws: &mut Socket, msg: &AgentMessage) -> ServerMessage {
    ws.send(Message::text(encode(msg))).await.expect("send");
    loop {
        match tokio::time::timeout(TIMEOUT, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => {
                return decode(t.as_str(), usize::MAX).expect("server frame decodes");
            }
            Ok(Some(Ok(Message::Ping(_) | Message::Pong(_)))) => continue,
            other => panic!("no answer: {other:?}"),
        }
    }
}

fn event(seq: u64, ts_ms: i64) -> AgentMessage {
    AgentMessage::Event {
        seq,
        ts_ms,
        kind: "note".into(),
        severity: Severity::Info,
        message: format!("event {seq}"),
        data: serde_json::Value::Null,
    }
}

fn assert_quota_refused(answer: &ServerMessage, want_seq: u64) {
    match answer {
        ServerMessage::Error {
            code: ErrorCode::QuotaExceeded,
            fatal: false,
            seq: Some(seq),
            message,
        } => {
            assert_eq!(*seq, want_seq, "{message}");
            assert!(message.contains("rows"), "{message}");
        }
        other => panic!("expected a non-fatal quota_exceeded for {want_seq}, got {other:?}"),
    }
}

#[tokio::test]
async fn past_its_quota_a_robot_is_refused_visibly_and_stays_online() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hsquota").await?;
    let op = gateway_operator(cp, &ns, "hs-quota", &["--robot-quota-rows", "4"]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;

    // Two events and a batch of two samples fill the quota of four rows.
    for seq in 1..=2 {
        assert_eq!(
            ask(&mut ws, &event(seq, FUTURE_MS)).await,
            ServerMessage::Ack { seq }
        );
    }
    let batch = AgentMessage::Telemetry {
        seq: 3,
        samples: vec![
            Sample {
                metric: "cpu_percent".into(),
                ts_ms: 0,
                value: 1.0,
            };
            2
        ],
    };
    assert_eq!(ask(&mut ws, &batch).await, ServerMessage::Ack { seq: 3 });
    // Beyond it: refused, naming the seq, not fatal; a replay of a stored one is still acked.
    for seq in 4..=6 {
        assert_quota_refused(&ask(&mut ws, &event(seq, 0)).await, seq);
    }
    assert_eq!(
        ask(&mut ws, &event(2, FUTURE_MS)).await,
        ServerMessage::Ack { seq: 2 }
    );
    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(&ns, "kiwi-1");
    let stored: Vec<u64> = store
        .events(&key, None, 100)
        .await?
        .iter()
        .map(|e| e.seq)
        .collect();
    assert_eq!(stored, [1, 2], "nothing past the quota is stored");

    // Counted by reason and by error code.
    let refused = r#"lekiwi_gateway_events_refused_total{reason="quota_rows"}"#;
    assert_eq!(op.metric(refused).await, Some(3.0));
    let frames = r#"lekiwi_gateway_error_frames_total{kind="quota_exceeded"}"#;
    assert_eq!(op.metric(frames).await, Some(3.0));

    // One Warning Event on the Robot, not one per refused message.
    let events: Api<Event> = Api::namespaced(client.clone(), &ns);
    let warning = wait_for("a quota Warning Event", TIMEOUT, || async {
        let list = events.list(&Default::default()).await.ok()?;
        list.items.into_iter().find(|e| {
            e.reason.as_deref() == Some("EventQuotaExceeded")
                && e.regarding.as_ref().and_then(|r| r.name.as_deref()) == Some("kiwi-1")
        })
    })
    .await?;
    assert_eq!(warning.type_.as_deref(), Some("Warning"));
    let note = warning.note.unwrap_or_default();
    assert!(note.contains("latest seq 4"), "{note}");
    tokio::time::sleep(Duration::from_secs(1)).await;
    let quota_events = events
        .list(&Default::default())
        .await?
        .items
        .into_iter()
        .filter(|e| e.reason.as_deref() == Some("EventQuotaExceeded"))
        .map(|e| e.series.map_or(1, |s| s.count))
        .sum::<i32>();
    assert_eq!(
        quota_events, 1,
        "rate-limited: one Event for three refusals"
    );

    // The session goes on: heartbeats are answered and the robot is Online.
    let hb = AgentMessage::Heartbeat {
        sent_at_ms: 7,
        rtt_ms: None,
        vitals: Default::default(),
        current_release: None,
        health: None,
        teleoperation: None,
    };
    assert!(matches!(
        ask(&mut ws, &hb).await,
        ServerMessage::HeartbeatAck { sent_at_ms: 7, .. }
    ));
    wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, TIMEOUT).await?;
    Ok(())
}

#[tokio::test]
async fn retention_goes_by_receive_time_not_the_robots_clock() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hsclock").await?;
    let op = gateway_operator(cp, &ns, "hs-clock", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;

    let before = jiff::Timestamp::now().as_millisecond() - 1;
    // A clock far ahead and a Pi without RTC stuck in 1970.
    for (seq, ts_ms) in [(1, FUTURE_MS), (2, 0)] {
        assert_eq!(
            ask(&mut ws, &event(seq, ts_ms)).await,
            ServerMessage::Ack { seq }
        );
    }
    let store = op.event_store().await?;
    let key = lekiwi_core::RobotKey::new(&ns, "kiwi-1");
    // Retention with a cutoff before they arrived keeps both, the 1970 one included.
    assert_eq!(store.prune(before).await?.events, 0);
    let kept = store.events(&key, None, 10).await?;
    // The robot's claim is still what the events API shows.
    let claims: Vec<(u64, i64)> = kept.iter().map(|e| (e.seq, e.ts_ms)).collect();
    assert_eq!(claims, [(1, FUTURE_MS), (2, 0)]);
    // A cutoff after they arrived deletes both, the far-future one included.
    let after = jiff::Timestamp::now().as_millisecond() + 1;
    assert_eq!(store.prune(after).await?.events, 2);
    assert!(store.events(&key, None, 10).await?.is_empty());
    Ok(())
}

#[tokio::test]
async fn a_real_agent_drops_what_is_over_quota_and_keeps_sending() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hsagent").await?;
    // Room for its start event and not much more: telemetry and events soon go over.
    let op = gateway_operator(cp, &ns, "hs-agent", &["--robot-quota-rows", "2"]).await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enrollment-token");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let state = dir.path().join("state");
    let agent = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/kiwi-1"),
        &token_file,
        &state,
        &[],
    )?;
    agent.wait_connected(TIMEOUT).await?;
    let mut seqs = Vec::new();
    for i in 0..3 {
        seqs.push(agent.emit("flood", &format!("event {i}"), &serde_json::json!({}))?);
    }
    // Each refused one is dropped from the outbox with a warning, never resent in a loop.
    let last = *seqs.last().expect("three seqs");
    wait_for("the agent to drop its refused event", TIMEOUT, || async {
        agent
            .log_lines()
            .iter()
            .any(|l| {
                l["fields"]["message"]
                    .as_str()
                    .is_some_and(|m| m.starts_with("durable message dropped"))
                    && l["fields"]["seq"].as_u64() == Some(last)
            })
            .then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;
    let refused = r#"lekiwi_gateway_events_refused_total{reason="quota_rows"}"#;
    let counted = op.metric(refused).await.unwrap_or(0.0);
    assert!(counted >= 2.0, "{counted} refused");
    let status = agent.status().await?;
    assert_eq!(status["connected"], true, "{status}");
    wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, TIMEOUT).await?;
    // Past a resend interval (a heartbeat), no refused event came back: each was dropped once
    // (of three, at most the first fit in the quota beside the agent's start event).
    tokio::time::sleep(Duration::from_secs(3)).await;
    let lines = agent.log_lines();
    let drops = |seq: u64| {
        lines
            .iter()
            .filter(|l| {
                l["fields"]["message"]
                    .as_str()
                    .is_some_and(|m| m.starts_with("durable message dropped"))
                    && l["fields"]["seq"].as_u64() == Some(seq)
            })
            .count()
    };
    let per_seq: Vec<usize> = seqs.iter().map(|s| drops(*s)).collect();
    assert!(per_seq.iter().all(|n| *n <= 1), "{per_seq:?}");
    assert!(per_seq.iter().sum::<usize>() >= 2, "{per_seq:?}");
    Ok(())
}
