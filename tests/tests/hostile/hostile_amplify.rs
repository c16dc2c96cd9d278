//! API-server amplification (issue 12, point 8): guessed tokens for unknown robots and
//! namespaces cost the API server a bounded number of reads, while a real agent stays Online
//! and the gateway's Lease keeps renewing; a Secret with a robot's name but not made by us
//! grants nothing; a robot added after a remembered miss connects at once.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result};
use k8s_openapi::ByteString;
use k8s_openapi::api::coordination::v1::Lease;
use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use kube::api::{ObjectMeta, PostParams};
use lekiwi_crds::RobotPhase;
use lekiwi_crds::contract::{
    HASH_KEY, KIND_ROBOT, ROBOT_LABEL, TOKEN_LABEL, hash_token, new_token, robot_secret_name,
};
use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, create_robot, enrollment_token_file,
    gateway_operator, gateway_url, namespace, robot_token, wait_for, wait_phase,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// Requests in the flood, and how many are in flight at once.
const FLOOD: usize = 2_000;
const WORKERS: usize = 40;

/// Secret reads (`GET` and `LIST`) the API server has served since it started, from its
/// `/metrics`.
fn secret_reads(cp: &ControlPlane) -> Result<f64> {
    let out = cp.kubectl(&["get", "--raw", "/metrics"]);
    anyhow::ensure!(out.status.success(), "kubectl get --raw /metrics failed");
    let text = String::from_utf8(out.stdout)?;
    Ok(text
        .lines()
        .filter(|l| l.starts_with("apiserver_request_total{"))
        .filter(|l| l.contains("resource=\"secrets\""))
        .filter(|l| l.contains("verb=\"GET\"") || l.contains("verb=\"LIST\""))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum())
}

/// Sends one raw request and reads only the response head: status and `Retry-After`.
async fn head(port: u16, request: String) -> Result<(u16, Option<String>)> {
    let mut stream = tokio::net::TcpStream::connect(("127.0.0.1", port)).await?;
    stream.write_all(request.as_bytes()).await?;
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    while !buf.windows(4).any(|w| w == b"\r\n\r\n") {
        let n = stream.read(&mut chunk).await?;
        anyhow::ensure!(n > 0, "closed before the response head");
        buf.extend_from_slice(&chunk[..n]);
    }
    let text = String::from_utf8_lossy(&buf).into_owned();
    let code = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let retry_after = text.lines().find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.eq_ignore_ascii_case("retry-after")
            .then(|| v.trim().to_owned())
    });
    Ok((code, retry_after))
}

/// Guess `i`: a random token for an unknown robot (in the test's namespace, or in one of many
/// unknown namespaces) at `/v1/agent`, `/v1/poll`, `/v1/blobs` or `/v1/releases`.
fn guess(i: usize, ns: &str) -> String {
    let token = new_token("lkr_");
    let ns = if i.is_multiple_of(2) {
        ns.to_owned()
    } else {
        format!("guess-{i}")
    };
    let robot = format!("{ns}/robot-{i}");
    let digest = format!("sha256:{}", "a".repeat(64));
    let common =
        format!("Host: 127.0.0.1\r\nAuthorization: Bearer {token}\r\nx-lekiwi-robot: {robot}\r\n");
    match i % 4 {
        0 => format!(
            "GET /v1/agent HTTP/1.1\r\n{common}Connection: Upgrade\r\nUpgrade: websocket\r\n\
             Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n"
        ),
        1 => format!(
            "GET /v1/poll?robot={robot}&version=1 HTTP/1.1\r\n{common}Connection: close\r\n\r\n"
        ),
        2 => format!("GET /v1/blobs/{digest} HTTP/1.1\r\n{common}Connection: close\r\n\r\n"),
        _ => format!("GET /v1/releases/{digest} HTTP/1.1\r\n{common}Connection: close\r\n\r\n"),
    }
}

/// Sends [`FLOOD`] guesses, [`WORKERS`] at a time; returns how many got 401 and how many 503
/// (each 503 with `Retry-After`).
async fn flood(port: u16, ns: &str) -> Result<(usize, usize)> {
    let mut workers = tokio::task::JoinSet::new();
    for w in 0..WORKERS {
        let ns = ns.to_owned();
        workers.spawn(async move {
            let mut codes = Vec::new();
            for i in (w..FLOOD).step_by(WORKERS) {
                codes.push(head(port, guess(i, &ns)).await?);
            }
            anyhow::Ok(codes)
        });
    }
    let (mut unauthorized, mut unavailable) = (0, 0);
    while let Some(codes) = workers.join_next().await {
        for (code, retry_after) in codes?? {
            match code {
                401 => unauthorized += 1,
                503 => {
                    assert_eq!(retry_after.as_deref(), Some("1"), "503 without Retry-After");
                    unavailable += 1;
                }
                other => panic!("a guess got {other}"),
            }
        }
    }
    Ok((unauthorized, unavailable))
}

/// When the gateway's Lease was last renewed.
async fn renewed(client: &kube::Client, ns: &str, op: &str) -> Option<jiff::Timestamp> {
    let lease = Api::<Lease>::namespaced(client.clone(), ns)
        .get(&format!("gw-{op}"))
        .await
        .ok()?;
    Some(lease.spec?.renew_time?.0)
}

/// 2,000 guessed tokens cost the API server at most the lookup budget (burst 10 + 1/s) plus a
/// few reads, not one or two reads each; meanwhile a real agent stays connected and Online and
/// the gateway's Lease is renewed.
#[tokio::test]
async fn guessed_tokens_cost_the_api_server_a_bounded_number_of_reads() -> Result<()> {
    let cp = ControlPlane::private()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "amplify").await?;
    let mut op = OperatorProcess::start(
        &cp,
        &ns,
        "amp",
        &["--install-crds", "--heartbeat-grace-seconds", "60"],
    )?;
    op.wait_ready().await?;
    let dir = tempfile::tempdir()?;
    let enroll = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &enroll).await?;
    let agent = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/kiwi-1"),
        &enroll,
        &dir.path().join("state"),
        &[],
    )?;
    agent.wait_connected(Duration::from_secs(20)).await?;
    wait_phase(
        &client,
        &ns,
        "kiwi-1",
        RobotPhase::Online,
        Duration::from_secs(20),
    )
    .await?;

    let before = secret_reads(&cp)?;
    let lease_before = renewed(&client, &ns, "amp")
        .await
        .context("gateway Lease")?;
    let start = Instant::now();
    let (unauthorized, unavailable) = flood(op.gateway_port, &ns).await?;
    let elapsed = start.elapsed().as_secs_f64();
    let reads = secret_reads(&cp)? - before;
    println!(
        "{FLOOD} guesses in {elapsed:.1} s: {unauthorized} × 401, {unavailable} × 503, \
         {reads} secret reads at the API server"
    );
    let budget = 10.0 + 1.0 * (elapsed + 1.0) + 5.0;
    assert!(
        reads <= budget,
        "{reads} secret reads for {FLOOD} guesses in {elapsed:.1} s (budget {budget})"
    );
    assert!(unavailable > 0, "the lookup budget never ran out");
    assert!(
        op.metric("lekiwi_gateway_refused_total{kind=\"lookup_throttled\"}")
            .await
            .is_some_and(|n| n >= unavailable as f64),
        "throttled refusals are counted"
    );

    // The real robot did not notice; the Lease kept being renewed.
    let status = agent.status().await?;
    assert_eq!(status["connected"], true, "{status}");
    wait_phase(
        &client,
        &ns,
        "kiwi-1",
        RobotPhase::Online,
        Duration::from_secs(1),
    )
    .await?;
    wait_for(
        "a Lease renewal after the flood",
        Duration::from_secs(10),
        || async {
            renewed(&client, &ns, "amp")
                .await
                .filter(|t| *t > lease_before)
        },
    )
    .await?;
    Ok(())
}

/// Posts a Secret named like robot `name`'s token Secret, holding the hash of `token`, with
/// `labels`.
async fn hand_made_secret(
    client: &kube::Client,
    ns: &str,
    name: &str,
    token: &str,
    labels: &[(&str, &str)],
) -> Result<()> {
    let secret = Secret {
        metadata: ObjectMeta {
            name: Some(robot_secret_name(name)),
            labels: Some(
                labels
                    .iter()
                    .map(|(k, v)| (k.to_string(), v.to_string()))
                    .collect(),
            ),
            ..ObjectMeta::default()
        },
        data: Some(BTreeMap::from([(
            HASH_KEY.to_owned(),
            ByteString(hash_token(token).into_bytes()),
        )])),
        ..Secret::default()
    };
    Api::<Secret>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &secret)
        .await?;
    Ok(())
}

/// The status of a legacy poll for `ns/name` with `token`.
async fn poll(op: &OperatorProcess, ns: &str, name: &str, token: &str) -> Result<u16> {
    let request = format!(
        "GET /v1/poll?robot={ns}/{name}&version=1 HTTP/1.1\r\nHost: 127.0.0.1\r\n\
         Authorization: Bearer {token}\r\nConnection: close\r\n\r\n"
    );
    Ok(head(op.gateway_port, request).await?.0)
}

/// A Secret with the robot's token Secret name and the hash of the presented token, but without
/// our labels (or labelled for another robot), grants nothing; a robot given a token (as
/// `kubectl lekiwi robot add` does) right after a guess for it was remembered as a miss is
/// admitted within seconds.
#[tokio::test]
async fn only_our_token_secrets_count_and_a_new_robot_is_not_kept_out() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "amplabel").await?;
    let op = gateway_operator(cp, &ns, "amp-label", &[]).await?;

    let forged = new_token("lkr_");
    create_robot(&client, &ns, "kiwi-a", &[]).await?;
    hand_made_secret(&client, &ns, "kiwi-a", &forged, &[]).await?;
    create_robot(&client, &ns, "kiwi-b", &[]).await?;
    hand_made_secret(
        &client,
        &ns,
        "kiwi-b",
        &forged,
        &[(TOKEN_LABEL, KIND_ROBOT), (ROBOT_LABEL, "kiwi-z")],
    )
    .await?;
    // Long enough for the watch to hold the labelled one.
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(poll(&op, &ns, "kiwi-a", &forged).await?, 401, "no labels");
    assert_eq!(
        poll(&op, &ns, "kiwi-b", &forged).await?,
        401,
        "another robot's label"
    );

    // A guess for a robot that does not exist yet: the miss is remembered.
    assert_eq!(poll(&op, &ns, "kiwi-new", &new_token("lkr_")).await?, 401);
    assert_eq!(poll(&op, &ns, "kiwi-new", &new_token("lkr_")).await?, 401);
    create_robot(&client, &ns, "kiwi-new", &[]).await?;
    let token = robot_token(&client, &ns, "kiwi-new").await?;
    let added = Instant::now();
    wait_for("the new robot admitted", Duration::from_secs(5), || async {
        (poll(&op, &ns, "kiwi-new", &token).await.ok()? == 200).then_some(())
    })
    .await?;
    println!("new robot admitted {:?} after its token", added.elapsed());
    Ok(())
}
