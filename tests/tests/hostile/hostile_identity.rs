//! Identity and authority against hostile peers (issue 12, points 1, 2 and 12): an enrollment
//! token creates robots but never takes over one that has credentials, never speaks for a robot
//! in a legacy poll, and robot names the gateway cannot give a token are refused up front.

use std::time::Duration;

use futures::{SinkExt, StreamExt};
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams};
use lekiwi_agent::connection::{ConnectError, Credentials, Socket, connect};
use lekiwi_crds::Robot;
use lekiwi_crds::contract::REENROLL_ANNOTATION;
use lekiwi_protocol::{ServerMessage, encode};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, bin, create_robot, enrollment_token, gateway_operator,
    gateway_url, get_robot, heartbeat, hello, http_get_with, namespace, recv, wait_for,
};
use serde_json::json;
use tokio_tungstenite::tungstenite::Message;

const TIMEOUT: Duration = Duration::from_secs(10);

/// A legacy poll with the enrollment token gets 401 and leaves the Robot's status as it was.
#[tokio::test]
async fn poll_with_the_enrollment_token_is_refused_and_fakes_nothing() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hipoll").await?;
    let op = gateway_operator(cp, &ns, "hi-poll", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let release = json!({"version": "2.0.0", "digest": format!("sha256:{}", "b".repeat(64))});
    lekiwi_tests::set_release(&client, &ns, "kiwi-1", &release).await?;
    let auth = format!("Bearer {enroll}");
    for path in [
        format!("/v1/poll?robot={ns}/kiwi-1&version=2.0.0&agent=forged"),
        "/v1/poll?robot=kiwi-1&version=2.0.0".to_owned(),
    ] {
        let (code, _, body) =
            http_get_with(op.gateway_port, &path, &[("authorization", &auth)]).await?;
        assert_eq!(code, 401, "{path}: {body}");
        assert!(body.contains("robot's own token"), "{body}");
    }
    // Presence is written within a second of a poll; give it three.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let status = get_robot(&client, &ns, "kiwi-1")
        .await?
        .status
        .unwrap_or_default();
    assert_ne!(status.connected, Some(true), "{status:?}");
    assert_eq!(status.current_release, None, "{status:?}");
    assert_eq!(status.agent_version, None, "{status:?}");
    let robots = Api::<Robot>::namespaced(client.clone(), &ns)
        .list(&ListParams::default())
        .await?;
    assert_eq!(robots.items.len(), 1);
    Ok(())
}

fn creds(token: &str, robot: &str) -> Credentials {
    Credentials {
        token: token.to_owned(),
        robot: robot.to_owned(),
    }
}

/// Connects with `creds` and expects a 403 before the upgrade whose body contains `says`.
async fn forbidden(url: &str, creds: &Credentials, says: &str) {
    match connect(url, creds, &hello(), TIMEOUT).await {
        Err(ConnectError::Forbidden(body)) => {
            let v: serde_json::Value = serde_json::from_str(&body).expect("JSON body");
            assert_eq!(v["error"], "forbidden", "{body}");
            assert!(body.contains(says), "{body}");
        }
        other => panic!("expected 403 ({says}), got {:?}", other.map(|(_, w)| w)),
    }
}

/// Sets the re-enrollment permission of `name` to hold until `offset` from now.
async fn permit(
    client: &kube::Client,
    ns: &str,
    name: &str,
    offset_secs: i64,
) -> anyhow::Result<()> {
    let until = jiff::Timestamp::now() + jiff::SignedDuration::from_secs(offset_secs);
    Api::<Robot>::namespaced(client.clone(), ns)
        .patch(
            name,
            &PatchParams::default(),
            &Patch::Merge(json!({"metadata": {"annotations": {REENROLL_ANNOTATION: until.round(jiff::Unit::Second)?.to_string()}}})),
        )
        .await?;
    Ok(())
}

/// Whether a legacy poll with `token` for `ns/name` is answered (200) rather than refused.
async fn token_works(
    op: &OperatorProcess,
    ns: &str,
    name: &str,
    token: &str,
) -> anyhow::Result<bool> {
    let (code, _, body) = http_get_with(
        op.gateway_port,
        &format!("/v1/poll?robot={ns}/{name}&version=0"),
        &[("authorization", &format!("Bearer {token}"))],
    )
    .await?;
    assert!(code == 200 || code == 401, "{code}: {body}");
    Ok(code == 200)
}

/// An enrollment token never takes over an enrolled robot: refused before the upgrade, the
/// robot's session and token untouched. A person's permission allows one re-enrollment, which
/// uses it up; an expired permission allows none; two racing enrollments cannot both use one.
#[tokio::test]
async fn enrollment_never_takes_over_an_enrolled_robot() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hienroll").await?;
    let op = gateway_operator(cp, &ns, "hi-enroll", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);
    let full = format!("{ns}/kiwi-1");

    let (mut ws, welcome) = connect(&url, &creds(&enroll, &full), &hello(), TIMEOUT).await?;
    let own = welcome
        .robot_token
        .expect("the first enrollment issues a token");
    for robot in [full.as_str(), "kiwi-1"] {
        forbidden(&url, &creds(&enroll, robot), "already enrolled").await;
    }
    // The real robot's session was not kicked and its token still works.
    alive(&mut ws).await?;
    assert!(token_works(&op, &ns, "kiwi-1", &own).await?);

    // An expired permission allows nothing.
    permit(&client, &ns, "kiwi-1", -60).await?;
    forbidden(&url, &creds(&enroll, &full), "expired").await;

    // A person's permission (`kubectl lekiwi robot reenroll`) allows exactly one
    // re-enrollment, even to two racing connections.
    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args(["-n", &ns, "robot", "reenroll", "kiwi-1", "--for", "10m"])
        .output()?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && stderr.contains("may enroll again once"),
        "{stderr}"
    );
    let (racer, greeting) = (creds(&enroll, &full), hello());
    let (a, b) = tokio::join!(
        connect(&url, &racer, &greeting, TIMEOUT),
        connect(&url, &racer, &greeting, TIMEOUT),
    );
    let (winner, loser) = match (a, b) {
        (Ok(w), Err(e)) | (Err(e), Ok(w)) => (w, e),
        (a, b) => panic!(
            "exactly one re-enrollment: {:?} / {:?}",
            a.map(|(_, w)| w),
            b.map(|(_, w)| w)
        ),
    };
    let new = winner
        .1
        .robot_token
        .clone()
        .expect("re-enrollment issues a token");
    assert_ne!(new, own);
    assert!(
        matches!(
            &loser,
            ConnectError::Forbidden(_) | ConnectError::Refused { .. }
        ),
        "{loser}"
    );
    let robot = get_robot(&client, &ns, "kiwi-1").await?;
    let annotations = robot.metadata.annotations.unwrap_or_default();
    assert!(
        !annotations.contains_key(REENROLL_ANNOTATION),
        "{annotations:?}"
    );
    wait_for("the old token refused", TIMEOUT, || async {
        (!token_works(&op, &ns, "kiwi-1", &own).await.ok()?).then_some(())
    })
    .await?;
    assert!(token_works(&op, &ns, "kiwi-1", &new).await?);
    // The permission is used up.
    drop(winner);
    forbidden(&url, &creds(&enroll, &full), "already enrolled").await;
    Ok(())
}

/// A robot name longer than a token Secret's label can hold is refused up front, by the gateway
/// and by `kubectl lekiwi robot add`, and nothing is created.
#[tokio::test]
async fn overlong_robot_names_are_refused_and_create_nothing() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hiname").await?;
    let op = gateway_operator(cp, &ns, "hi-name", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let name = "k".repeat(70);
    match connect(
        &gateway_url(&op),
        &creds(&enroll, &format!("{ns}/{name}")),
        &hello(),
        TIMEOUT,
    )
    .await
    {
        Err(ConnectError::Unauthorized(body)) => {
            assert!(body.contains("at most 63 characters"), "{body}")
        }
        other => panic!("expected 401, got {:?}", other.map(|(_, w)| w)),
    }
    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args([
            "-n",
            &ns,
            "robot",
            "add",
            &name,
            "--gateway",
            "ws://127.0.0.1:1/v1/agent",
        ])
        .output()?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("at most 63"),
        "{stderr}"
    );
    let robots = Api::<Robot>::namespaced(client.clone(), &ns)
        .list(&ListParams::default())
        .await?;
    assert!(robots.items.is_empty(), "{:?}", robots.items);
    // 63 characters is fine. `namespace/name`: a bare name is matched only against the
    // gateway's Secret watch, which may not have the token created a moment ago yet (a CI
    // failure); the agent would retry, this test connects once.
    let name = "k".repeat(63);
    let (_ws, welcome) = connect(
        &gateway_url(&op),
        &creds(&enroll, &format!("{ns}/{name}")),
        &hello(),
        TIMEOUT,
    )
    .await?;
    assert_eq!(welcome.robot, format!("{ns}/{name}"));
    Ok(())
}

/// Enrolls robot `robot` (`ns/name`) with the enrollment token; the robot's own token.
async fn enrolled(url: &str, enroll: &str, robot: &str) -> anyhow::Result<String> {
    let (_ws, welcome) = connect(url, &creds(enroll, robot), &hello(), TIMEOUT).await?;
    Ok(welcome.robot_token.expect("enrollment issues a token"))
}

/// Reads frames until the gateway closes the session; the close frame's code and reason.
async fn closed(ws: &mut Socket, within: Duration) -> anyhow::Result<(u16, String)> {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        let frame = tokio::time::timeout_at(deadline, ws.next())
            .await
            .map_err(|_| anyhow::anyhow!("the session is still open after {within:?}"))?;
        match frame {
            Some(Ok(Message::Close(Some(f)))) => return Ok((f.code.into(), f.reason.to_string())),
            Some(Ok(Message::Close(None))) | None => return Ok((0, String::new())),
            Some(Ok(_)) => continue,
            Some(Err(e)) => anyhow::bail!("the session broke instead of closing: {e}"),
        }
    }
}

/// Sends a heartbeat and expects its ack: the session is alive.
async fn alive(ws: &mut Socket) -> anyhow::Result<()> {
    ws.send(Message::text(encode(&heartbeat()))).await?;
    loop {
        match recv(ws).await {
            Some(ServerMessage::HeartbeatAck { .. }) => return Ok(()),
            Some(_) => continue,
            None => anyhow::bail!("the robot's session ended"),
        }
    }
}

/// A stolen token stops working at once when a person rotates it or deletes its Secret: the
/// session it opened is closed (1008 `token revoked`), not left running until it disconnects.
/// The robot's own enrollment, which writes its Secret while the session is open, does not.
#[tokio::test]
async fn a_rotated_or_deleted_token_ends_the_session_it_opened() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hirevoke").await?;
    let op = gateway_operator(cp, &ns, "hi-revoke", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);
    let full = format!("{ns}/kiwi-1");

    // Enrollment writes the robot's token Secret during the session: that is no revocation.
    let (mut ws, welcome) = connect(&url, &creds(&enroll, &full), &hello(), TIMEOUT).await?;
    let own = welcome.robot_token.expect("enrollment issues a token");
    tokio::time::sleep(Duration::from_secs(2)).await;
    alive(&mut ws).await?;
    drop(ws);

    // A session opened with the robot's token ends when a person rotates the token.
    let (mut stolen, _) = connect(&url, &creds(&own, &full), &hello(), TIMEOUT).await?;
    alive(&mut stolen).await?;
    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args(["-n", &ns, "robot", "add", "kiwi-1", "--rotate-token"])
        .args(["--gateway", "ws://127.0.0.1:9/v1/agent"])
        .output()?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (code, reason) = closed(&mut stolen, TIMEOUT).await?;
    assert_eq!((code, reason.as_str()), (1008, "token revoked"));
    assert!(!token_works(&op, &ns, "kiwi-1", &own).await?);

    // The new token works, until its Secret is deleted.
    let printed = String::from_utf8_lossy(&out.stdout).to_string();
    let new = printed
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .find(|w| w.starts_with("lkr_"))
        .unwrap_or_else(|| panic!("no new token in the output:\n{printed}"))
        .to_owned();
    let (mut ws, _) = connect(&url, &creds(&new, &full), &hello(), TIMEOUT).await?;
    alive(&mut ws).await?;
    let deleted = cp.kubectl(&["-n", &ns, "delete", "secret", "kiwi-1-agent-token"]);
    assert!(deleted.status.success(), "{deleted:?}");
    let (code, reason) = closed(&mut ws, TIMEOUT).await?;
    assert_eq!((code, reason.as_str()), (1008, "token revoked"));
    // Counted as the session is cleaned up, just after its close frame went out.
    wait_for("both ends counted", TIMEOUT, || async {
        let ended = op
            .metric(r#"lekiwi_gateway_sessions_ended_total{kind="token_revoked"}"#)
            .await;
        (ended == Some(2.0)).then_some(())
    })
    .await?;
    Ok(())
}

/// A robot's token in a reconnect loop (stolen, or a broken agent) is slowed before the upgrade:
/// past the burst (10) it gets 429 with `Retry-After`, so its connects cost the API server no
/// status writes, controller work or Events; other robots connect as usual.
#[tokio::test]
async fn a_token_in_a_reconnect_loop_is_slowed_before_the_upgrade() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hiloop").await?;
    let op = gateway_operator(cp, &ns, "hi-loop", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);
    let full = format!("{ns}/kiwi-1");

    let own = enrolled(&url, &enroll, &full).await?;
    for _ in 1..10 {
        let (ws, _) = connect(&url, &creds(&own, &full), &hello(), TIMEOUT).await?;
        drop(ws);
    }
    match connect(&url, &creds(&own, &full), &hello(), TIMEOUT).await {
        Err(ConnectError::TooManySessions { retry_after }) => {
            assert!(
                retry_after >= Duration::from_secs(1) && retry_after <= Duration::from_secs(10),
                "{retry_after:?}"
            );
        }
        other => panic!("expected 429, got {:?}", other.map(|(_, w)| w)),
    }
    let refused = op
        .metric(r#"lekiwi_gateway_refused_total{kind="too_many_sessions"}"#)
        .await;
    assert_eq!(refused, Some(1.0));
    // Another robot is not slowed by it.
    let (mut other, _) = connect(
        &url,
        &creds(&enroll, &format!("{ns}/kiwi-2")),
        &hello(),
        TIMEOUT,
    )
    .await?;
    alive(&mut other).await?;
    Ok(())
}

/// A token Secret deleted while the gateway's watch is down (its API server restarting) never
/// reaches the gateway as a deletion, only as a Secret missing from the relist that follows:
/// that relist still ends the session the token opened.
#[tokio::test]
async fn a_token_deleted_while_the_watch_is_down_ends_its_session_after_the_relist()
-> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "hirelist").await?;
    let op = gateway_operator(&cp, &ns, "hi-relist", &[]).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let url = gateway_url(&op);
    let full = format!("{ns}/kiwi-1");
    let own = enrolled(&url, &enroll, &full).await?;
    let (mut ws, _) = connect(&url, &creds(&own, &full), &hello(), TIMEOUT).await?;
    alive(&mut ws).await?;

    // The API server goes; behind its back, the Secret is deleted in etcd.
    cp.kill_apiserver()?;
    let key = format!("/registry/secrets/{ns}/kiwi-1-agent-token");
    assert_eq!(cp.etcd_delete(&key).await?, 1, "{key} deleted in etcd");
    alive(&mut ws).await?;
    cp.up()?;
    let (code, reason) = closed(&mut ws, Duration::from_secs(60))
        .await
        .map_err(|e| anyhow::anyhow!("{e}\noperator log:\n{}", op.log_text()))?;
    assert_eq!((code, reason.as_str()), (1008, "token revoked"));
    assert!(!token_works(&op, &ns, "kiwi-1", &own).await?);
    Ok(())
}
