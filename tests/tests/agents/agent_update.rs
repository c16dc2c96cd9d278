//! Agent self-update with real processes (issue 19): real `lekiwi-agent` processes under a small
//! supervisor that plays systemd's part as the unit says ([`lekiwi_tests::supervisor`]), a real
//! operator, builds pushed with `kubectl-lekiwi agent push`, and `Robot.spec.agent` patched by
//! hand.
//!
//! Agent A is the workspace's `lekiwi-agent` (the "package binary"). B is A under another version
//! name: a wrapper script that sets `LEKIWI_AGENT_VERSION_OVERRIDE` and execs A (the digest,
//! download, install, switch and guard do not care what the bytes are). C exits at start. D is A
//! with a wrong gateway URL baked in: it runs but never connects.

use std::path::Path;
use std::time::{Duration, Instant};

use lekiwi_core::RobotKey;
use lekiwi_event_store::Store;
use lekiwi_tests::agent_fleet::{
    AgentFleet as Fleet, DEADLINE_S, T, agent_fleet as fleet, arch, wrapper,
};
use lekiwi_tests::supervisor::Supervised;
use lekiwi_tests::{bin, wait_for, wait_online};
use serde_json::{Value, json};
use sha2::Digest as _;

/// Queues an event in `state`'s outbox with `lekiwi-agent event` (the running agent sends it).
fn emit(state: &Path, n: u64) -> anyhow::Result<()> {
    let out = std::process::Command::new(bin("lekiwi-agent"))
        .args(["--config", "/nonexistent/lekiwi-agent.yaml"])
        .args(["--state-dir", state.to_str().unwrap()])
        .args([
            "event",
            "--kind",
            "switch_test",
            "--message",
            &format!("event {n}"),
        ])
        .args(["--data", &json!({"n": n}).to_string()])
        .output()?;
    anyhow::ensure!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(())
}

/// The stored events of robot `name`: (kind, data) in seq order.
async fn events(store: &Store, ns: &str, name: &str) -> Vec<(String, Value)> {
    let key = RobotKey::new(ns.to_owned(), name.to_owned());
    store
        .events(&key, None, 10_000)
        .await
        .unwrap_or_default()
        .into_iter()
        .map(|e| (e.kind, e.data))
        .collect()
}

fn count(events: &[(String, Value)], kind: &str) -> usize {
    events.iter().filter(|(k, _)| k == kind).count()
}

/// (a) Ten robots on A move to B: every robot reports B; events emitted before, during and after
/// the switch are all stored exactly once.
#[tokio::test]
async fn ten_agents_update_themselves_without_losing_an_event() -> anyhow::Result<()> {
    let f = fleet("agentupd", "agud").await?;
    let names: Vec<String> = (0..10).map(|i| format!("kiwi-{i}")).collect();
    let robots: Vec<Supervised> = names.iter().map(|n| f.robot(n)).collect();
    wait_online(&f.client, &f.ns, names.len(), 2 * T).await?;
    // A reports the digest of the package binary it runs.
    let a_digest = format!(
        "sha256:{}",
        hex::encode(sha2::Sha256::digest(std::fs::read(bin("lekiwi-agent"))?))
    );
    let a_version = f.agent_status("kiwi-0").await.unwrap_or_default().0;
    assert_eq!(f.agent_digest("kiwi-0").await, Some(a_digest.clone()));
    let b = f.push("agent-b", "9.0.0-b", &wrapper("9.0.0-b", false))?;
    let store = f.op.event_store().await?;
    for r in &robots {
        for n in 1..=5 {
            emit(&r.state_dir, n)?;
        }
    }
    let t0 = Instant::now();
    for name in &names {
        f.desire(name, "9.0.0-b", arch(), &b).await?;
    }
    // During the switch: queued while the old agent downloads, exits, or the new one starts.
    for n in 6..=10 {
        for r in &robots {
            emit(&r.state_dir, n)?;
        }
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    let mut switched = Vec::new();
    for name in &names {
        let took = wait_for(&format!("{name} on B"), T, || async {
            let (version, update) = f.agent_status(name).await?;
            (version == "9.0.0-b" && update["phase"] == "Succeeded").then(|| t0.elapsed())
        })
        .await;
        let took = match took {
            Ok(t) => t,
            Err(e) => {
                let status = f.agent_status(name).await;
                anyhow::bail!("{e}; last status {status:?}");
            }
        };
        switched.push(took);
    }
    for r in &robots {
        for n in 11..=15 {
            emit(&r.state_dir, n)?;
        }
    }
    for (name, r) in names.iter().zip(&robots) {
        let stored = wait_for(&format!("{name}: 15 events stored"), T, || async {
            let ev = events(&store, &f.ns, name).await;
            (count(&ev, "switch_test") >= 15 && count(&ev, "agent_update_succeeded") >= 1)
                .then_some(ev)
        })
        .await?;
        let numbers: Vec<u64> = stored
            .iter()
            .filter(|(k, _)| k == "switch_test")
            .map(|(_, d)| d["n"].as_u64().unwrap_or_default())
            .collect();
        assert_eq!(
            numbers,
            (1..=15).collect::<Vec<_>>(),
            "{name}: each event once, in order"
        );
        assert_eq!(count(&stored, "agent_update_started"), 1, "{name}");
        assert_eq!(count(&stored, "agent_update_succeeded"), 1, "{name}");
        let started = stored
            .iter()
            .find(|(k, _)| k == "agent_update_started")
            .unwrap();
        let bytes = started.1["bytes"].as_u64().unwrap_or_default();
        let history = r.history.lock().unwrap();
        let first = &history.starts[0];
        assert_eq!(
            first.binary,
            bin("lekiwi-agent"),
            "{name}: starts on the package binary"
        );
        assert_eq!(first.exit, Some(75), "{name}: A exits 75 after switching");
        let last = history.starts.last().unwrap();
        assert!(
            last.binary.ends_with("agent/current/lekiwi-agent"),
            "{name}: runs the slot"
        );
        assert_eq!(r.current_slot().as_deref(), Some("a"), "{name}");
        eprintln!(
            "{name}: on B after {:?}, {bytes} bytes downloaded",
            switched[names.iter().position(|n| n == name).unwrap()]
        );
    }
    let max = switched.iter().max().unwrap();
    eprintln!("ten robots switched A -> B; slowest {max:?}");
    assert_eq!(
        f.op.metric(r#"lekiwi_gateway_agent_updates_total{kind="succeeded",version="9.0.0-b"}"#)
            .await,
        Some(10.0)
    );
    roll_back_to_the_package_binary(&f, &robots[0], &store, &a_version, &a_digest, &b).await?;
    Ok(())
}

/// (a, continued) kiwi-0 is rolled back to A by naming A's version and digest (from its
/// status before the update): A was never pushed; the robot switches back to its package
/// binary from its own disk, downloads nothing and commits as after any update.
async fn roll_back_to_the_package_binary(
    f: &Fleet,
    robot: &Supervised,
    store: &Store,
    a_version: &str,
    a_digest: &str,
    b_digest: &str,
) -> anyhow::Result<()> {
    let name = "kiwi-0";
    assert_eq!(f.agent_digest(name).await.as_deref(), Some(b_digest));
    let t0 = Instant::now();
    f.desire(name, a_version, arch(), a_digest).await?;
    let took = wait_for(&format!("{name} back on A"), T, || async {
        let (version, update) = f.agent_status(name).await?;
        (version == a_version && update["phase"] == "Succeeded").then(|| t0.elapsed())
    })
    .await?;
    assert_eq!(f.agent_digest(name).await.as_deref(), Some(a_digest));
    assert_eq!(
        robot.current_slot(),
        None,
        "current removed: the package runs"
    );
    let last = robot
        .history
        .lock()
        .unwrap()
        .starts
        .last()
        .map(|s| s.binary.clone());
    assert_eq!(last, Some(bin("lekiwi-agent")), "runs the package binary");
    let ev = wait_for("the rollback's events", T, || async {
        let ev = events(store, &f.ns, name).await;
        (count(&ev, "agent_update_succeeded") >= 2).then_some(ev)
    })
    .await?;
    let started: Vec<&Value> = ev
        .iter()
        .filter(|(k, _)| k == "agent_update_started")
        .map(|(_, d)| d)
        .collect();
    assert_eq!(started.len(), 2, "{ev:?}");
    assert_eq!(started[1]["version"], a_version, "{ev:?}");
    assert_eq!(started[1]["bytes"], 0, "nothing downloaded: {ev:?}");
    eprintln!("{name}: rolled back B -> A (never pushed) in {took:?}, 0 bytes downloaded");
    Ok(())
}

/// (b) C exits at start and (c) D never connects: each robot is back on A by itself within the
/// deadline, reports the failure and its reason, and is not sent the same build again; (x) a
/// robot whose architecture has no build is told so in its status, nothing else happens.
#[tokio::test]
async fn broken_agents_are_undone_by_the_robot_itself() -> anyhow::Result<()> {
    let f = fleet("agentfb", "agfb").await?;
    let (rc, rd, rx) = (f.robot("kiwi-c"), f.robot("kiwi-d"), f.robot("kiwi-x"));
    wait_online(&f.client, &f.ns, 3, 2 * T).await?;
    let c = f.push(
        "agent-c",
        "9.0.0-c",
        "#!/bin/sh\necho 'agent C: exits at start' >&2\nexit 1\n",
    )?;
    let d = f.push("agent-d", "9.0.0-d", &wrapper("9.0.0-d", true))?;
    let store = f.op.event_store().await?;
    let t0 = Instant::now();
    f.desire("kiwi-c", "9.0.0-c", arch(), &c).await?;
    f.desire("kiwi-d", "9.0.0-d", arch(), &d).await?;
    let other = if arch() == "amd64" { "arm64" } else { "amd64" };
    f.desire("kiwi-x", "9.0.0-x", other, &c).await?;

    let fell_back = |name: &'static str| {
        let f = &f;
        async move {
            wait_for(
                &format!("{name} fell back"),
                T + Duration::from_secs(DEADLINE_S),
                || async {
                    let (version, update) = f.agent_status(name).await?;
                    (version != "9.0.0-c" && update["phase"] == "FallenBack")
                        .then(|| (t0.elapsed(), version, update))
                },
            )
            .await
        }
    };
    let (c_took, c_version, c_update) = fell_back("kiwi-c")
        .await
        .map_err(|e| anyhow::anyhow!("{e}\n{}", rc.log_text()))?;
    let (d_took, d_version, d_update) = fell_back("kiwi-d")
        .await
        .map_err(|e| anyhow::anyhow!("{e}\n{}", rd.log_text()))?;
    eprintln!("C fell back after {c_took:?}: {c_update}");
    eprintln!("D fell back after {d_took:?}: {d_update}");
    let a = lekiwi_agent::selfupdate::version();
    assert_eq!(c_version, a, "back on A");
    assert_eq!(d_version, a, "back on A");
    assert!(
        c_update["message"]
            .as_str()
            .unwrap_or_default()
            .contains("crash at start"),
        "{c_update}"
    );
    assert!(
        d_update["message"]
            .as_str()
            .unwrap_or_default()
            .contains("no connection"),
        "{d_update}"
    );
    assert!(
        c_took < Duration::from_secs(DEADLINE_S),
        "C: after its starts, before the deadline: {c_took:?}"
    );
    assert!(
        d_took < Duration::from_secs(DEADLINE_S + 15),
        "D: at the deadline: {d_took:?}"
    );
    for (name, r) in [("kiwi-c", &rc), ("kiwi-d", &rd)] {
        assert_eq!(r.current_slot(), None, "{name}: the package binary again");
        let ev = wait_for(&format!("{name}: fallback reported"), T, || async {
            let ev = events(&store, &f.ns, name).await;
            (count(&ev, "agent_update_fallen_back") >= 1).then_some(ev)
        })
        .await?;
        assert_eq!(count(&ev, "agent_update_started"), 1, "{name}");
        assert_eq!(count(&ev, "agent_update_fallen_back"), 1, "{name}");
        assert_eq!(count(&ev, "agent_update_succeeded"), 0, "{name}");
        let (_, data) = ev
            .iter()
            .find(|(k, _)| k == "agent_update_fallen_back")
            .unwrap();
        assert!(
            data["reason"].as_str().is_some_and(|r| !r.is_empty()),
            "{data}"
        );
    }
    // No loop: nothing restarts any more, and the status stays.
    let starts = |r: &Supervised| r.history.lock().unwrap().starts.len();
    let before = (starts(&rc), starts(&rd), starts(&rx));
    tokio::time::sleep(Duration::from_secs(5)).await;
    assert_eq!(
        before,
        (starts(&rc), starts(&rd), starts(&rx)),
        "no further restarts"
    );
    assert_eq!(
        f.agent_status("kiwi-c").await.unwrap().1["phase"],
        "FallenBack"
    );
    // (x) no build for the robot's architecture: a status message, the agent untouched.
    let (version, update) = f.agent_status("kiwi-x").await.unwrap();
    assert_eq!(version, a);
    assert_eq!(update["phase"], "Unavailable", "{update}");
    assert!(
        update["message"]
            .as_str()
            .unwrap_or_default()
            .contains("no build for"),
        "{update}"
    );
    assert_eq!(starts(&rx), 1, "kiwi-x never restarted");
    // Labelled by the version spec.agent names (the robot's own reports cannot add series).
    for version in ["9.0.0-c", "9.0.0-d"] {
        let series = format!(
            r#"lekiwi_gateway_agent_updates_total{{kind="fallen_back",version="{version}"}}"#
        );
        assert_eq!(f.op.metric(&series).await, Some(1.0), "{series}");
    }
    Ok(())
}
