//! Slowloris (issue 12, point 6): a thousand stalled connections (idle after connecting, headers
//! dripped one byte a second, a 400 KiB header that never ends, a request line and nothing more)
//! do not stop `/healthz`, a legacy poll or a real agent session; the gateway closes them after
//! its header timeout, keeps its memory bounded, and closes at once what is over the per-address
//! limit of unauthenticated connections.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use lekiwi_crds::RobotPhase;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, connect_agent, create_robot, enrollment_token, http_get,
    http_get_with, namespace, robot_token, wait_phase,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// Seconds the test's gateway allows for a request's headers.
const HEADER_TIMEOUT: u64 = 3;
/// Attackers' source addresses (all loopback): 50 stalled connections from each.
const ATTACKERS: u8 = 20;
const PER_ATTACKER: usize = 50;

/// How a stalled connection misbehaves.
#[derive(Clone, Copy, Debug)]
enum Stall {
    /// Connects and sends nothing.
    Idle,
    /// Sends a request's headers one byte a second.
    Drip,
    /// Sends 400 KiB of one header that never ends.
    Huge,
    /// Sends a request line, then nothing.
    Half,
}

/// The gateway process's resident memory, in KiB.
fn rss_kib(pid: u32) -> anyhow::Result<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let line = status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .context("no VmRSS")?;
    Ok(line
        .split_whitespace()
        .nth(1)
        .context("VmRSS value")?
        .parse()?)
}

/// A TCP connection to the gateway from source address `from`.
async fn connect_from(from: [u8; 4], port: u16) -> anyhow::Result<TcpStream> {
    let socket = TcpSocket::new_v4()?;
    socket.bind(SocketAddr::from((from, 0)))?;
    Ok(socket
        .connect(SocketAddr::from(([127, 0, 0, 1], port)))
        .await?)
}

/// Misbehaves as `stall` on `stream` until the gateway closes it; returns how long that took.
async fn stall(mut stream: TcpStream, how: Stall) -> Duration {
    let start = Instant::now();
    let head = b"GET /v1/poll?robot=a/b HTTP/1.1\r\nHost: gateway\r\nX-Pad: ";
    let mut drip = head.iter().copied().chain(std::iter::repeat(b'a'));
    match how {
        Stall::Idle | Stall::Drip => {}
        Stall::Half => {
            let _ = stream.write_all(b"GET /healthz HTTP/1.1\r\n").await;
        }
        Stall::Huge => {
            let mut big = head.to_vec();
            big.resize(400 * 1024, b'a');
            let _ = tokio::time::timeout(Duration::from_secs(5), stream.write_all(&big)).await;
        }
    }
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(Duration::from_secs(1), stream.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return start.elapsed(),
            Ok(Ok(_)) => {} // a 408/431 answer: the close follows
            Err(_) => {
                if let Stall::Drip = how {
                    let byte = [drip.next().unwrap_or(b'a')];
                    if stream.write_all(&byte).await.is_err() {
                        return start.elapsed();
                    }
                }
            }
        }
        if start.elapsed() > Duration::from_secs(60) {
            return start.elapsed();
        }
    }
}

/// Opens the thousand stalled connections (50 from each of 20 loopback addresses) and returns
/// their tasks.
async fn open_stalled(port: u16) -> anyhow::Result<Vec<tokio::task::JoinHandle<Duration>>> {
    let kinds = [Stall::Idle, Stall::Drip, Stall::Huge, Stall::Half];
    let mut tasks = Vec::new();
    for a in 0..ATTACKERS {
        for i in 0..PER_ATTACKER {
            let stream = connect_from([127, 0, 1, a + 1], port).await?;
            tasks.push(tokio::spawn(stall(stream, kinds[i % kinds.len()])));
        }
    }
    Ok(tasks)
}

#[tokio::test]
async fn stalled_connections_are_bounded_and_closed() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hslow").await?;
    let timeout = HEADER_TIMEOUT.to_string();
    let args = [
        "--header-timeout-seconds",
        timeout.as_str(),
        "--max-unauthenticated-connections",
        "4000",
        "--heartbeat-grace-seconds",
        "60",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "hs-slow", &args)?;
    op.wait_ready().await?;
    let pid = op.pid();
    let enroll = enrollment_token(&client, &ns).await?;
    let (ws1, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-1")).await?;
    wait_phase(
        &client,
        &ns,
        "kiwi-1",
        RobotPhase::Online,
        Duration::from_secs(20),
    )
    .await?;
    create_robot(&client, &ns, "legacy-1", &[]).await?;
    let legacy = format!("Bearer {}", robot_token(&client, &ns, "legacy-1").await?);
    let poll = format!("/v1/poll?robot={ns}/legacy-1&version=1.0.0&agent=legacy-0.9");
    tokio::time::sleep(Duration::from_secs(2)).await;
    let baseline = rss_kib(pid)?;

    let opened = Instant::now();
    let tasks = open_stalled(op.gateway_port).await?;
    println!(
        "opened {} stalled connections in {:?}",
        tasks.len(),
        opened.elapsed()
    );

    // Meanwhile: health, a legacy poll and a new agent session, all from 127.0.0.1.
    let (code, _) = http_get(op.gateway_port, "/healthz").await?;
    assert_eq!(code, 200, "/healthz during the attack");
    let (code, _, body) =
        http_get_with(op.gateway_port, &poll, &[("authorization", &legacy)]).await?;
    assert_eq!(code, 200, "a legacy poll during the attack: {body}");
    let (ws2, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-2"))
        .await
        .map_err(|e| anyhow::anyhow!("an agent session during the attack: {e:?}"))?;
    wait_phase(
        &client,
        &ns,
        "kiwi-2",
        RobotPhase::Online,
        Duration::from_secs(20),
    )
    .await?;
    let attacked = rss_kib(pid)?;
    println!("gateway RSS: {baseline} KiB quiet, {attacked} KiB with 1000 stalled connections");
    assert!(
        attacked < 2 * baseline + 32 * 1024,
        "RSS {attacked} KiB under attack vs {baseline} KiB quiet"
    );

    // Over the per-address limit (64 by default): closed at once.
    let mut burst = Vec::new();
    for _ in 0..100 {
        let stream = connect_from([127, 0, 2, 1], op.gateway_port).await?;
        burst.push(tokio::spawn(stall(stream, Stall::Idle)));
    }
    let mut burst_times = Vec::new();
    for t in burst {
        burst_times.push(t.await?);
    }
    let quick = burst_times
        .iter()
        .filter(|d| **d < Duration::from_secs(2))
        .count();
    assert!(
        quick >= 36,
        "{quick} of 100 connections from one address closed at once"
    );
    let per_address = r#"lekiwi_gateway_connections_dropped_total{kind="per_address_limit"}"#;
    assert!(op.metric(per_address).await.unwrap_or(0.0) >= 36.0);

    // Every stalled connection is closed by the gateway soon after the header timeout.
    let mut longest = Duration::ZERO;
    for t in tasks {
        longest = longest.max(t.await?);
    }
    println!("the last stalled connection was closed after {longest:?}");
    if longest > Duration::from_secs(HEADER_TIMEOUT + 20) {
        bail!("a stalled connection stayed open {longest:?}");
    }
    let timeouts = r#"lekiwi_gateway_connections_dropped_total{kind="header_timeout"}"#;
    assert!(op.metric(timeouts).await.unwrap_or(0.0) >= 500.0);

    // The agents' sessions outlived the attack.
    for name in ["kiwi-1", "kiwi-2"] {
        let robot = wait_phase(
            &client,
            &ns,
            name,
            RobotPhase::Online,
            Duration::from_secs(5),
        )
        .await?;
        assert_eq!(robot.status.and_then(|s| s.connected), Some(true), "{name}");
    }
    drop((ws1, ws2));
    op.terminate()?;
    Ok(())
}

/// A TLS gateway closes connections that never finish the TLS handshake (silent ones, and ones
/// that stop after part of a ClientHello) after its handshake timeout, well before the header
/// timeout, while an agent trusting the gateway's CA connects over wss://.
#[tokio::test]
async fn half_tls_handshakes_are_closed_after_the_handshake_timeout() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hslowtls").await?;
    let dir = tempfile::tempdir()?;
    lekiwi_tests::test_ca(dir.path())?;
    let cert = dir.path().join("tls.crt");
    let key = dir.path().join("tls.key");
    let args = [
        "--tls-cert",
        cert.to_str().unwrap(),
        "--tls-key",
        key.to_str().unwrap(),
        "--tls-handshake-timeout-seconds",
        "2",
        "--header-timeout-seconds",
        "60",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "hs-tls", &args)?;
    op.wait_ready().await?;

    let mut tasks = Vec::new();
    for i in 0..100u8 {
        let mut stream = connect_from([127, 0, 3, 1 + i % 2], op.gateway_port).await?;
        if i % 2 == 1 {
            // A TLS record header announcing a 512-byte ClientHello, and 3 bytes of it.
            stream
                .write_all(&[0x16, 0x03, 0x01, 0x02, 0x00, 0x01, 0x00, 0x01])
                .await?;
        }
        tasks.push(tokio::spawn(stall(stream, Stall::Idle)));
    }
    let enroll = enrollment_token(&client, &ns).await?;
    let creds = lekiwi_agent::connection::Credentials {
        token: enroll,
        robot: format!("{ns}/kiwi-tls"),
    };
    let url = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);
    let ca = dir.path().join("ca.crt");
    let hello = lekiwi_tests::hello();
    let (_ws, welcome) = lekiwi_agent::connection::connect_with_ca(
        &url,
        &creds,
        &hello,
        Duration::from_secs(10),
        Some(&ca),
    )
    .await
    .map_err(|e| anyhow::anyhow!("wss:// agent during the half handshakes: {e:?}"))?;
    assert_eq!(welcome.robot, format!("{ns}/kiwi-tls"));

    let mut longest = Duration::ZERO;
    for t in tasks {
        longest = longest.max(t.await?);
    }
    println!("the last half handshake was closed after {longest:?}");
    assert!(longest < Duration::from_secs(15), "{longest:?}");
    // Counted just after each close, so the last few may lag the clients' EOF a moment.
    let dropped = r#"lekiwi_gateway_connections_dropped_total{kind="tls_handshake"}"#;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    let mut counted = op.metric(dropped).await.unwrap_or(0.0);
    while counted < 100.0 && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(100)).await;
        counted = op.metric(dropped).await.unwrap_or(0.0);
    }
    assert!(counted >= 100.0, "{counted} half handshakes counted");
    op.terminate()?;
    Ok(())
}
