//! `kubectl lekiwi discover` finds agents that run on other hosts: two real `lekiwi-agent`
//! processes, each in a network namespace of its own, linked by veth pairs to a bridge in the
//! root namespace (10.77.0.0/24), found by mDNS and by probing the subnet, each exactly once.
//! Skipped, with a message saying why, where network namespaces cannot be made.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail, ensure};
use lekiwi_tests::{ControlPlane, bin, create_robot, log_dir, namespace, wait_for};
use serde_json::Value;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

const BRIDGE_ADDR: &str = "10.77.0.1/24";
const SUBNET: &str = "10.77.0.0/24";

/// Runs `ip` with `args`; an error carries its stderr.
fn ip(args: &[&str]) -> Result<()> {
    let out = Command::new("ip")
        .args(args)
        .output()
        .context("run ip (iproute2)")?;
    if !out.status.success() {
        bail!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

/// The namespaces, links and agent processes of the test; all removed when dropped.
struct Lab {
    bridge: String,
    namespaces: Vec<String>,
    host_links: Vec<String>,
    agents: Vec<Child>,
    states: Vec<tempfile::TempDir>,
}

impl Drop for Lab {
    fn drop(&mut self) {
        for agent in &mut self.agents {
            let _ = agent.kill();
            let _ = agent.wait();
        }
        // Deleting a namespace deletes the veth end inside it and so its peer.
        for ns in &self.namespaces {
            let _ = ip(&["netns", "del", ns]);
        }
        for link in &self.host_links {
            let _ = ip(&["link", "del", link]);
        }
        let _ = ip(&["link", "del", &self.bridge]);
    }
}

impl Lab {
    /// A bridge with `n` namespaces on it, or why it cannot be made.
    fn build(n: usize) -> Result<Lab> {
        let id = std::process::id() % 10_000;
        let mut lab = Lab {
            bridge: format!("lkbr{id}"),
            namespaces: Vec::new(),
            host_links: Vec::new(),
            agents: Vec::new(),
            states: Vec::new(),
        };
        // The first namespace tells whether we may make them at all.
        let first = format!("lkd{id}-1");
        ip(&["netns", "add", &first])?;
        lab.namespaces.push(first);
        // Snooping off: without an IGMP querier on this bridge, mDNS multicast is flooded.
        ip(&[
            "link",
            "add",
            "name",
            &lab.bridge,
            "type",
            "bridge",
            "mcast_snooping",
            "0",
        ])?;
        ip(&["addr", "add", BRIDGE_ADDR, "dev", &lab.bridge])?;
        ip(&["link", "set", &lab.bridge, "up"])?;
        for i in 1..=n {
            let ns = format!("lkd{id}-{i}");
            if i > 1 {
                ip(&["netns", "add", &ns])?;
                lab.namespaces.push(ns.clone());
            }
            let host = format!("lkv{id}h{i}");
            let inner = format!("lkv{id}n{i}");
            ip(&["link", "add", &host, "type", "veth", "peer", "name", &inner])?;
            lab.host_links.push(host.clone());
            ip(&["link", "set", &inner, "netns", &ns])?;
            ip(&["link", "set", &host, "master", &lab.bridge])?;
            ip(&["link", "set", &host, "up"])?;
            let addr = format!("10.77.0.{}/24", 10 + i);
            ip(&["-n", &ns, "addr", "add", &addr, "dev", &inner])?;
            ip(&["-n", &ns, "link", "set", &inner, "up"])?;
            ip(&["-n", &ns, "link", "set", "lo", "up"])?;
        }
        Ok(lab)
    }

    /// Starts a real agent for `robot` in namespace `i` (1-based), serving `/status` on all
    /// its addresses and advertising over mDNS. Its gateway is unreachable from there.
    fn start_agent(&mut self, i: usize, robot: &str) -> Result<()> {
        let ns = self.namespaces[i - 1].clone();
        let state = tempfile::tempdir()?;
        let log = log_dir().join(format!("netns-agent-{ns}.log"));
        let file = std::fs::File::create(&log)?;
        let child = Command::new("ip")
            .args(["netns", "exec", &ns])
            .arg(bin("lekiwi-agent"))
            .args(["--config", "/nonexistent/lekiwi-agent.yaml"])
            .args(["--gateway", "ws://10.77.0.1:9/v1/agent"])
            // Not loopback, and never reached: plain text must be allowed explicitly.
            .arg("--insecure-allow-plaintext")
            .args(["--robot-name", robot])
            .args(["--enrollment-token", "lke_unused-gateway-unreachable"])
            .arg("--state-dir")
            .arg(state.path())
            .args(["--status-listen", "0.0.0.0:9477", "--mdns", "true"])
            .args(["--backoff-initial-ms", "200", "--backoff-max-ms", "2000"])
            .args(["--log-format", "json"])
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .context("spawn lekiwi-agent in a network namespace")?;
        self.agents.push(child);
        self.states.push(state);
        Ok(())
    }
}

/// `GET /status` of an address in the lab, from the root namespace.
async fn status(addr: &str) -> Option<Value> {
    let connect = tokio::net::TcpStream::connect(addr);
    let mut stream = tokio::time::timeout(Duration::from_millis(500), connect)
        .await
        .ok()?
        .ok()?;
    stream
        .write_all(b"GET /status HTTP/1.0\r\nHost: lab\r\n\r\n")
        .await
        .ok()?;
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await.ok()?;
    let text = String::from_utf8_lossy(&buf);
    serde_json::from_str(text.split_once("\r\n\r\n")?.1).ok()
}

fn discover(kubeconfig: &std::path::Path, args: &[&str]) -> Result<(Vec<Value>, Duration)> {
    let start = Instant::now();
    let out = Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(kubeconfig)
        .args(["discover", "-o", "json"])
        .args(args)
        .output()?;
    let took = start.elapsed();
    let stderr = String::from_utf8_lossy(&out.stderr);
    ensure!(out.status.success(), "discover failed: {stderr}");
    eprintln!("discover {args:?} took {took:?}; stderr: {stderr}");
    Ok((serde_json::from_slice(&out.stdout)?, took))
}

#[tokio::test]
async fn discover_finds_agents_in_other_network_namespaces() -> Result<()> {
    if Command::new("ip").arg("-V").output().is_err() {
        eprintln!("skipped: `ip` (iproute2) is not installed");
        return Ok(());
    }
    let mut lab = match Lab::build(2) {
        Ok(lab) => lab,
        Err(e) => {
            eprintln!("skipped: cannot create network namespaces here ({e:#})");
            return Ok(());
        }
    };
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "netns").await?;
    // One of the two is registered, the other is not.
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let robots = [format!("{ns}/kiwi-1"), format!("{ns}/kiwi-2")];
    for (i, robot) in robots.iter().enumerate() {
        lab.start_agent(i + 1, robot)?;
    }
    for i in 1..=2 {
        let addr = format!("10.77.0.{}:9477", 10 + i);
        wait_for(
            &format!("the status endpoint at {addr}"),
            Duration::from_secs(20),
            || {
                let addr = addr.clone();
                async move { status(&addr).await }
            },
        )
        .await?;
    }

    // Probing the subnet finds both, each once, in under 2 s.
    let (found, took) = discover(&cp.kubeconfig(), &["--no-mdns", "--probe", SUBNET])?;
    for (i, robot) in robots.iter().enumerate() {
        let mine: Vec<&Value> = found.iter().filter(|f| f["robot"] == *robot).collect();
        ensure!(mine.len() == 1, "{robot} not found exactly once: {found:?}");
        assert_eq!(
            mine[0]["addresses"],
            serde_json::json!([format!("10.77.0.{}:9477", 11 + i)])
        );
        assert_eq!(mine[0]["registered"], i == 0, "{robot}");
    }
    assert!(took < Duration::from_secs(2), "discover took {took:?}");

    // mDNS alone finds both across the bridge; with the probe too, still once each.
    let (found, took) = wait_for(
        "both agents by mDNS and probe",
        Duration::from_secs(20),
        || async {
            let (found, took) = discover(&cp.kubeconfig(), &["--probe", SUBNET]).ok()?;
            robots
                .iter()
                .all(|robot| {
                    let mine: Vec<&Value> = found.iter().filter(|f| f["robot"] == *robot).collect();
                    mine.len() == 1 && mine[0]["via"] == serde_json::json!(["mdns", "probe"])
                })
                .then_some((found, took))
        },
    )
    .await?;
    assert_eq!(
        found
            .iter()
            .filter(|f| robots.iter().any(|r| f["robot"] == *r))
            .count(),
        2
    );
    assert!(took < Duration::from_secs(2), "discover took {took:?}");
    Ok(())
}
