//! Protocol-valid input that the Robot CRD would refuse (issue 12, point 11): each example of the
//! issue is refused with an `invalid_field` error naming the field or stored normalised, the
//! robot is Online with a status the API server accepted, and Offline soon after it disconnects.
//! And a status the API server refuses anyway (validation bypassed) is not retried forever:
//! presence is written without it and a Warning Event names the field.

use std::time::Duration;

use futures::SinkExt;
use k8s_openapi::api::core::v1::Event;
use kube::Api;
use kube::api::ListParams;
use lekiwi_agent::connection::{Credentials, Socket, connect};
use lekiwi_core::RobotKey;
use lekiwi_crds::RobotPhase;
use lekiwi_presence::{ConnectInfo, Presence, PresenceConfig};
use lekiwi_protocol::{AgentMessage, ErrorCode, Release, ServerMessage, encode};
use lekiwi_tests::{
    ControlPlane, create_robot, enrollment_token, gateway_operator, gateway_url, get_robot, hello,
    namespace, recv, wait_for, wait_phase,
};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

const TIMEOUT: Duration = Duration::from_secs(10);

/// A digest of 64 hex digits, `hex` repeated.
fn digest(hex: &str) -> String {
    format!("sha256:{}", hex.repeat(64 / hex.len()))
}

/// The frames the gateway sends up to and including the next heartbeat ack.
async fn until_ack(ws: &mut Socket) -> Vec<ServerMessage> {
    let mut frames = Vec::new();
    while let Some(m) = recv(ws).await {
        let done = matches!(m, ServerMessage::HeartbeatAck { .. });
        frames.push(m);
        if done {
            break;
        }
    }
    frames
}

/// The fields named by the `invalid_field` errors among `frames` (each non-fatal).
fn refused_fields(frames: &[ServerMessage]) -> Vec<String> {
    frames
        .iter()
        .filter_map(|m| match m {
            ServerMessage::Error {
                code: ErrorCode::InvalidField,
                message,
                fatal,
                ..
            } => {
                assert!(!fatal, "{message}");
                Some(message.split('`').nth(1).unwrap_or_default().to_owned())
            }
            _ => None,
        })
        .collect()
}

/// One example of the issue: a `hello` (and heartbeats) carrying it, the field it must be
/// refused as (if any), and what `status` must then show at `pointer`.
struct Example {
    robot: &'static str,
    release: Option<Release>,
    memory_bytes: Option<u64>,
    refused: Option<&'static str>,
    pointer: &'static str,
    shows: Value,
}

fn examples() -> Vec<Example> {
    let release = |version: &str, digest: String| {
        Some(Release {
            version: version.into(),
            digest,
        })
    };
    vec![
        Example {
            robot: "short-digest",
            release: release("1.0", "sha256:11".into()),
            memory_bytes: None,
            refused: Some("current_release.digest"),
            pointer: "/currentRelease",
            shows: Value::Null,
        },
        Example {
            robot: "upper-digest",
            release: release("1.0", digest("AB")),
            memory_bytes: None,
            refused: None,
            pointer: "/currentRelease",
            shows: json!({ "version": "1.0", "digest": digest("ab") }),
        },
        Example {
            robot: "empty-version",
            release: release("", digest("ab")),
            memory_bytes: None,
            refused: Some("current_release.version"),
            pointer: "/currentRelease",
            shows: Value::Null,
        },
        Example {
            robot: "spaced-version",
            release: release("1.0 beta", digest("ab")),
            memory_bytes: None,
            refused: Some("current_release.version"),
            pointer: "/currentRelease",
            shows: Value::Null,
        },
        Example {
            robot: "huge-memory",
            release: None,
            memory_bytes: Some(u64::MAX),
            refused: Some("system.memory_bytes"),
            pointer: "/system",
            shows: json!({ "arch": "aarch64", "cpus": 4 }),
        },
    ]
}

/// Enrolls `ex.robot` with its `hello`, sends a heartbeat with the same release and checks the
/// documented answers; returns the open socket.
async fn connect_example(url: &str, token: &str, ns: &str, ex: &Example) -> Socket {
    let mut msg = hello();
    if let AgentMessage::Hello {
        system,
        current_release,
        ..
    } = &mut msg
    {
        system.memory_bytes = ex.memory_bytes;
        *current_release = ex.release.clone();
    }
    let creds = Credentials {
        token: token.into(),
        robot: format!("{ns}/{}", ex.robot),
    };
    let (mut ws, _) = connect(url, &creds, &msg, TIMEOUT).await.expect("welcomed");
    let heartbeat = AgentMessage::Heartbeat {
        sent_at_ms: 1,
        rtt_ms: None,
        vitals: Default::default(),
        current_release: ex.release.clone(),
        health: None,
        teleoperation: None,
    };
    ws.send(Message::text(encode(&heartbeat)))
        .await
        .expect("send");
    let frames = until_ack(&mut ws).await;
    let mut want: Vec<String> = ex.refused.map(String::from).into_iter().collect();
    if ex.release.is_some() {
        // The heartbeat repeats the release: refused again.
        want.extend(
            ex.refused
                .filter(|f| f.starts_with("current_release"))
                .map(String::from),
        );
    }
    assert_eq!(refused_fields(&frames), want, "{}: {frames:?}", ex.robot);
    ws
}

#[tokio::test]
async fn the_issues_examples_leave_a_true_status() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hstatus").await?;
    let op = gateway_operator(cp, &ns, "hs-examples", &[]).await?;
    let token = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);
    let mut sockets = Vec::new();
    for ex in &examples() {
        sockets.push(connect_example(&url, &token, &ns, ex).await);
    }
    for ex in &examples() {
        let robot = wait_for(
            &format!("{} Online with its status", ex.robot),
            TIMEOUT * 3,
            || async {
                let r = get_robot(&client, &ns, ex.robot).await.ok()?;
                let status = serde_json::to_value(r.status.as_ref()?).ok()?;
                let online = status["phase"] == "Online" && status["agentVersion"] == "0.1.0-test";
                let shown = status.pointer(ex.pointer).cloned().unwrap_or(Value::Null);
                (online && shown == ex.shows).then_some(status)
            },
        )
        .await;
        robot.map_err(|e| anyhow::anyhow!("{e}; log:\n{}", op.log_text()))?;
    }
    // Disconnected: Offline promptly, not after the heartbeat grace (60 s here, 360 s default).
    for ws in &mut sockets {
        ws.close(None).await.ok();
    }
    for ex in &examples() {
        wait_phase(
            &client,
            &ns,
            ex.robot,
            RobotPhase::Offline,
            Duration::from_secs(20),
        )
        .await?;
    }
    Ok(())
}

#[tokio::test]
async fn a_refused_status_falls_back_to_presence_and_a_warning_event() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hsrefused").await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let presence = Presence::new(
        PresenceConfig {
            gateway: "hs-injected".into(),
            status_refresh: Duration::from_secs(60),
            poll_grace: Duration::from_secs(60),
            qps: 50.0,
            adaptive: None,
            burst: 50,
            concurrency: 4,
        },
        lekiwi_metrics::Metrics::new(false),
    );
    let cancel = tokio_util::sync::CancellationToken::new();
    let writer = tokio::spawn(
        presence
            .clone()
            .run_writer(client.clone(), None, cancel.clone()),
    );
    // Injected past the boundary validation: a digest the CRD refuses.
    let key = RobotKey::new(&ns, "kiwi-1");
    let bad = Release {
        version: "1.0".into(),
        digest: "sha256:11".into(),
    };
    presence.connect(
        &key,
        1,
        1,
        ConnectInfo {
            protocol: "websocket",
            agent_version: "0.1.0-test".into(),
            release: Some(bad),
            ..ConnectInfo::default()
        },
    );
    let status = |want: bool| {
        let client = client.clone();
        let ns = ns.clone();
        async move {
            let r = get_robot(&client, &ns, "kiwi-1").await.ok()?;
            let s = r.status?;
            (s.connected == Some(want) && s.gateway.as_deref() == Some("hs-injected")).then_some(s)
        }
    };
    let s = wait_for("presence without the refused fields", TIMEOUT, || {
        status(true)
    })
    .await?;
    assert_eq!(s.current_release, None);
    let events: Api<Event> = Api::namespaced(client.clone(), &ns);
    let warning = wait_for("a Warning Event naming the field", TIMEOUT, || async {
        let list = events.list(&ListParams::default()).await.ok()?;
        list.items.into_iter().find(|e| {
            e.reason.as_deref() == Some("StatusFieldRefused")
                && e.type_.as_deref() == Some("Warning")
                && e.involved_object.name.as_deref() == Some("kiwi-1")
        })
    })
    .await?;
    let note = warning.message.unwrap_or_default();
    assert!(note.contains("currentRelease.digest"), "{note}");
    // The disconnect is written too (presence only), not retried forever.
    presence.disconnect(&key, 1);
    wait_for("the disconnect written", TIMEOUT, || status(false)).await?;
    assert_eq!(presence.queued(), 0);
    cancel.cancel();
    writer.await?;
    Ok(())
}
