//! `kubectl lekiwi discover` finds agents that run on other hosts: two real `lekiwi-agent`
//! processes, each in a network namespace of its own, linked by veth pairs to a bridge in the
//! root namespace (10.77.0.0/24), found by mDNS and by probing the subnet, each exactly once.
//! Skipped, with a message saying why, where network namespaces cannot be made.

use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Result, ensure};
use lekiwi_tests::netns::{Lab, have_ip};
use lekiwi_tests::{ControlPlane, bin, create_robot, namespace, wait_for};
use serde_json::Value;

/// The lab's subnet is 10.77.0.0/24.
const NET: u8 = 77;
const SUBNET: &str = "10.77.0.0/24";

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
    Ok((lekiwi_tests::list_items(&out.stdout)?, took))
}

#[tokio::test]
async fn discover_finds_agents_in_other_network_namespaces() -> Result<()> {
    if !have_ip() {
        eprintln!("skipped: `ip` (iproute2) is not installed");
        return Ok(());
    }
    let mut lab = match Lab::build(2, NET) {
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
        lab.start_agent(i + 1, robot, true)?;
    }
    lab.wait_status(2, Duration::from_secs(20)).await?;

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
