//! Agent discovery as a user sees it: the mDNS advertisement found by another process (the
//! `mdns-browse` binary, plain mdns-sd), updates and withdrawal of it, and the local status
//! endpoint over real sockets, garbage included.

use std::io::{BufRead as _, BufReader};
use std::net::{IpAddr, SocketAddr};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context as _, Result, bail, ensure};
use lekiwi_agent::discovery::{self, Advertiser, MAX_CONNECTIONS, StatusSnapshot, instance_name};
use lekiwi_protocol::{Release, Teleoperation};
use serde_json::Value;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;

/// Built by Cargo with this package's tests, so it needs no workspace build.
const BROWSER: &str = env!("CARGO_BIN_EXE_mdns-browse");

/// A robot name no other test run uses, so that advertisements on the LAN cannot interfere.
fn unique_robot() -> String {
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or_default();
    format!("disc-{}-{nanos:x}/kiwi", std::process::id())
}

fn snapshot(robot: &str, release: Option<&str>) -> StatusSnapshot {
    StatusSnapshot {
        robot: robot.to_owned(),
        agent_version: "0.1.0-test".into(),
        release: release.map(|v| Release {
            version: v.into(),
            digest: format!("sha256:{:0>64}", v.len()),
        }),
        gateway: "wss://fleet.example.test/v1/agent".into(),
        connected: false,
        teleoperation: Some(Teleoperation {
            active: false,
            score: Some(0.1),
        }),
        outbox_pending: 0,
        last_rtt_ms: None,
        bytes_sent: 0,
        started_at_ms: 1_700_000_000_000,
    }
}

/// A running `mdns-browse`, its JSON lines read as they come.
struct Browser {
    child: Child,
    lines: mpsc::Receiver<Value>,
    seen: Vec<Value>,
}

impl Browser {
    fn start(timeout_ms: u64) -> Result<Browser> {
        let mut child = Command::new(BROWSER)
            .args(["--timeout-ms", &timeout_ms.to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("spawn mdns-browse")?;
        let stdout = child.stdout.take().context("stdout of mdns-browse")?;
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                let value = serde_json::from_str(&line)
                    .unwrap_or_else(|_| serde_json::json!({ "unparsed": line }));
                if tx.send(value).is_err() {
                    break;
                }
            }
        });
        Ok(Browser {
            child,
            lines,
            seen: Vec::new(),
        })
    }

    /// Waits for an event of `instance` that satisfies `want`.
    fn wait_for(
        &mut self,
        instance: &str,
        within: Duration,
        what: &str,
        want: impl Fn(&Value) -> bool,
    ) -> Result<Value> {
        let deadline = Instant::now() + within;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(event) => {
                    self.seen.push(event.clone());
                    if event["instance"] == instance && want(&event) {
                        return Ok(event);
                    }
                }
                Err(_) => bail!(
                    "mdns-browse did not see {what} of {instance} within {within:?}; it printed:\n{}",
                    self.seen
                        .iter()
                        .map(Value::to_string)
                        .collect::<Vec<_>>()
                        .join("\n")
                ),
            }
        }
    }

    /// Waits for the browser to exit by its own timeout and returns everything it printed.
    fn finish(mut self) -> Result<Vec<Value>> {
        let status = self.child.wait()?;
        ensure!(status.success(), "mdns-browse exited with {status}");
        self.seen.extend(self.lines.try_iter());
        Ok(std::mem::take(&mut self.seen))
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A GET over a fresh connection: status code and body.
async fn get(addr: SocketAddr, path: &str) -> Result<(u16, String)> {
    let answer = exchange(
        addr,
        format!("GET {path} HTTP/1.1\r\nHost: lekiwi\r\n\r\n").as_bytes(),
    )
    .await?;
    let code = answer
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = answer
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default();
    Ok((code, body))
}

/// Sends `request`, closes the write side and reads the whole answer.
async fn exchange(addr: SocketAddr, request: &[u8]) -> Result<String> {
    let mut stream = TcpStream::connect(addr).await?;
    stream.write_all(request).await?;
    stream.shutdown().await?;
    let mut answer = Vec::new();
    tokio::time::timeout(Duration::from_secs(10), stream.read_to_end(&mut answer))
        .await
        .context("no answer within 10s")??;
    Ok(String::from_utf8_lossy(&answer).into_owned())
}

fn is_lan(ip: &IpAddr) -> bool {
    matches!(ip, IpAddr::V4(v4) if !v4.is_loopback() && !v4.is_unspecified())
}

#[test]
fn another_process_finds_the_robot_and_follows_its_updates() -> Result<()> {
    let robot = unique_robot();
    let instance = instance_name(&robot);
    let runtime = tokio::runtime::Runtime::new()?;
    // The status endpoint on every interface, so the advertised addresses lead to it.
    let listener = runtime.block_on(TcpListener::bind("0.0.0.0:0"))?;
    let port = listener.local_addr()?.port();
    let mut status = snapshot(&robot, Some("v1"));
    let (status_tx, status_rx) = watch::channel(status.clone());
    runtime.spawn(discovery::serve_status(listener, status_rx));

    let mut advertiser = Advertiser::start(&status, port)?;
    assert_eq!(advertiser.instance(), instance);

    // A browser started after the advertisement: it has to ask, and the agent has to answer.
    let found = Browser::start(3000)?.finish()?;
    // mdns-sd reports a service as soon as it has one address record and again as more
    // arrive (one per interface and IP version), so the last report is the complete one.
    let resolved: Vec<&Value> = found
        .iter()
        .filter(|e| e["event"] == "resolved" && e["instance"] == instance.as_str())
        .collect();
    let event = resolved
        .last()
        .with_context(|| format!("mdns-browse did not find {instance}; it printed {found:?}"))?;
    for event in &resolved {
        assert_eq!(event["port"], port);
        assert_eq!(event["host"], format!("{instance}.local."));
        let txt = &event["txt"];
        assert_eq!(txt["robot"], robot.as_str());
        assert_eq!(txt["agent_version"], "0.1.0-test");
        assert_eq!(txt["release"], "v1");
        assert_eq!(txt["gateway"], "wss://fleet.example.test/v1/agent");
        assert_eq!(txt["status_port"], port.to_string());
    }
    let addresses: Vec<IpAddr> = serde_json::from_value(event["addresses"].clone())?;
    let lan = addresses
        .iter()
        .copied()
        .find(is_lan)
        .with_context(|| format!("no LAN IPv4 address advertised: {resolved:?}"))?;

    // What `kubectl lekiwi discover` will do next: ask the robot found for its status.
    let (code, body) = runtime.block_on(get(SocketAddr::new(lan, port), "/status"))?;
    assert_eq!(code, 200, "{body}");
    assert_eq!(serde_json::from_str::<StatusSnapshot>(&body)?, status);

    // A browser that watches across the change sees the re-announced TXT records.
    let mut watcher = Browser::start(20_000)?;
    watcher.wait_for(&instance, Duration::from_secs(5), "release v1", |e| {
        e["event"] == "resolved" && e["txt"]["release"] == "v1"
    })?;
    status.connected = true;
    status.bytes_sent = 4096;
    advertiser.update(&status)?; // live state only: nothing to announce
    status.release = Some(Release {
        version: "v2".into(),
        digest: "sha256:02".into(),
    });
    advertiser.update(&status)?;
    status_tx.send_replace(status.clone());
    let event = watcher.wait_for(&instance, Duration::from_secs(5), "release v2", |e| {
        e["event"] == "resolved" && e["txt"]["release"] == "v2"
    })?;
    assert_eq!(event["txt"]["robot"], robot.as_str());
    assert_eq!(event["port"], port);

    // The library's own browser, fresh, gets the new records too.
    let found = discovery::browse(Duration::from_secs(3))?;
    let agent = found
        .iter()
        .find(|f| f.instance == instance)
        .with_context(|| format!("browse() did not find {instance}: {found:?}"))?;
    assert_eq!(agent.robot, robot);
    assert_eq!(agent.release.as_deref(), Some("v2"));
    assert_eq!(agent.agent_version, "0.1.0-test");
    assert_eq!(agent.gateway, "wss://fleet.example.test/v1/agent");
    assert_eq!(agent.port, port);
    assert!(agent.addresses.contains(&lan), "{agent:?}");
    let (code, body) = runtime.block_on(get(SocketAddr::new(lan, port), "/status"))?;
    assert_eq!(code, 200, "{body}");
    assert_eq!(serde_json::from_str::<StatusSnapshot>(&body)?, status);

    // Stopping the agent withdraws the advertisement at once (goodbye), not after the TTL.
    drop(advertiser);
    watcher.wait_for(&instance, Duration::from_secs(5), "removal", |e| {
        e["event"] == "removed"
    })?;
    Ok(())
}

#[tokio::test]
async fn status_endpoint_answers_and_survives_garbage() -> Result<()> {
    // The default (current-thread) runtime, as the agent runs it.
    let listener = TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    let robot = unique_robot();
    let (tx, rx) = watch::channel(snapshot(&robot, None));
    let server = tokio::spawn(discovery::serve_status(listener, rx));

    let (code, headers, body) = lekiwi_tests::http_get_with(addr.port(), "/status", &[]).await?;
    assert_eq!(code, 200, "{body}");
    let header = |name: &str| {
        headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    };
    assert_eq!(header("content-type"), Some("application/json"));
    assert_eq!(header("connection"), Some("close"));
    assert_eq!(
        header("content-length"),
        Some(body.len().to_string().as_str())
    );
    assert_eq!(
        serde_json::from_str::<StatusSnapshot>(&body)?,
        snapshot(&robot, None)
    );
    let json: Value = serde_json::from_str(&body)?;
    assert_eq!(json["agentVersion"], "0.1.0-test");
    assert_eq!(json["startedAtMs"], 1_700_000_000_000_i64);

    // The endpoint follows the watch channel.
    tx.send_modify(|s| {
        s.connected = true;
        s.outbox_pending = 3;
        s.last_rtt_ms = Some(12.5);
        s.release = Some(Release {
            version: "v7".into(),
            digest: "sha256:07".into(),
        });
    });
    let (code, body) = lekiwi_tests::http_get(addr.port(), "/status?pretty=1").await?;
    assert_eq!(code, 200, "{body}");
    assert_eq!(serde_json::from_str::<StatusSnapshot>(&body)?, *tx.borrow());

    assert_eq!(get(addr, "/healthz").await?, (200, "ok".into()));
    let answer = exchange(addr, b"HEAD /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await?;
    assert!(answer.starts_with("HTTP/1.1 200 OK\r\n"), "{answer}");
    assert!(answer.contains("Content-Length: 2\r\n"), "{answer}");
    assert!(answer.ends_with("\r\n\r\n"), "HEAD has no body: {answer}");

    let (code, body) = get(addr, "/metrics").await?;
    assert_eq!(code, 404);
    assert_eq!(serde_json::from_str::<Value>(&body)?["error"], "not found");

    let answer = exchange(
        addr,
        b"POST /status HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\n\r\nhello",
    )
    .await?;
    assert!(answer.starts_with("HTTP/1.1 405 "), "{answer}");
    assert!(answer.contains("Allow: GET, HEAD\r\n"), "{answer}");
    assert!(
        answer.contains(r#"{"error":"method not allowed"}"#),
        "{answer}"
    );

    let big = format!(
        "GET /status HTTP/1.1\r\nHost: x\r\nX-Filler: {}\r\n\r\n",
        "a".repeat(10_000)
    );
    let answer = exchange(addr, big.as_bytes()).await?;
    assert!(answer.starts_with("HTTP/1.1 431 "), "{answer}");
    // A head without line breaks is cut off the same way.
    let answer = exchange(addr, &[b'x'; 20_000]).await?;
    assert!(answer.starts_with("HTTP/1.1 431 "), "{answer}");

    // Garbage: a TLS ClientHello, binary noise, a bare empty head, half a request, nothing.
    let garbage: [&[u8]; 7] = [
        b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n",
        b"\x00\xff\xfe\x80\n\n",
        b"\r\n\r\n",
        b"GET /status HTTP/9.9\r\n\r\n",
        b"GET /healthz HTTP/1.1\r\nHost",
        b"\xf0\x9f\x92\xa9 /status HTTP/1.1\r\n\r\n",
        b"",
    ];
    for request in garbage {
        let answer = exchange(addr, request).await?;
        assert!(
            answer.is_empty()
                || answer.starts_with("HTTP/1.1 400 ")
                || answer.starts_with("HTTP/1.1 505 "),
            "{request:?} -> {answer}"
        );
    }
    // A client that resets the connection mid-request.
    {
        let mut stream = TcpStream::connect(addr).await?;
        stream.set_zero_linger()?;
        stream.write_all(b"GET /sta").await?;
    }
    assert!(!server.is_finished(), "the server is still running");
    assert_eq!(get(addr, "/healthz").await?, (200, "ok".into()));
    server.abort();
    Ok(())
}

#[tokio::test]
async fn slow_clients_time_out_and_free_their_slots() -> Result<()> {
    let listener = TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    let (_tx, rx) = watch::channel(snapshot(&unique_robot(), None));
    let server = tokio::spawn(discovery::serve_status(listener, rx));

    // Fill every slot with a client that starts a request and then stalls.
    let mut stalled = Vec::new();
    for _ in 0..MAX_CONNECTIONS {
        let mut stream = TcpStream::connect(addr).await?;
        stream.write_all(b"GET /sta").await?;
        stalled.push(stream);
    }
    tokio::time::sleep(Duration::from_millis(200)).await;

    // One more client waits until the read timeout frees a slot, then gets its answer.
    let start = Instant::now();
    let (code, _) = get(addr, "/healthz").await?;
    let waited = start.elapsed();
    assert_eq!(code, 200);
    assert!(
        waited >= Duration::from_secs(4),
        "answered after {waited:?}: the connection cap did not hold"
    );

    // The stalled clients were told why they were dropped.
    for mut stream in stalled {
        let mut answer = Vec::new();
        stream.read_to_end(&mut answer).await?;
        let answer = String::from_utf8_lossy(&answer);
        assert!(answer.starts_with("HTTP/1.1 408 "), "{answer}");
    }
    server.abort();
    Ok(())
}
