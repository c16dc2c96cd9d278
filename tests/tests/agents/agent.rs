//! The real `lekiwi-agent` against the real gateway on the local control plane: enrollment and
//! its saved token, reconnect with backoff and jitter after the gateway dies and comes back,
//! and zero loss of events across a gateway outage and agent crashes.

use std::os::unix::fs::PermissionsExt;
use std::path::PathBuf;
use std::time::Duration;

use lekiwi_core::RobotKey;
use lekiwi_crds::RobotPhase;
use lekiwi_event_store::Store;
use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, enrollment_token_file, gateway_url, get_robot,
    namespace, wait_for,
};
use serde_json::{Value, json};

const T: Duration = Duration::from_secs(30);

async fn online(client: &kube::Client, ns: &str, name: &str) -> anyhow::Result<bool> {
    let robot = get_robot(client, ns, name).await?;
    Ok(robot.status.and_then(|s| s.phase) == Some(RobotPhase::Online))
}

fn fields(line: &Value) -> &Value {
    &line["fields"]
}

fn lines_with<'a>(lines: &'a [Value], message: &str) -> Vec<&'a Value> {
    lines
        .iter()
        .filter(|l| fields(l)["message"] == message)
        .collect()
}

/// A namespace of the test's own with an operator, and where its agent keeps things.
struct Setup {
    client: kube::Client,
    ns: String,
    op: OperatorProcess,
    /// Holds the token file and the state directory.
    dir: tempfile::TempDir,
    token_file: PathBuf,
    state: PathBuf,
}

async fn setup(prefix: &str, identity: &str) -> anyhow::Result<Setup> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, prefix).await?;
    let mut op = OperatorProcess::start(cp, &ns, identity, &[])?;
    op.wait_ready().await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let state = dir.path().join("state");
    Ok(Setup {
        client,
        ns,
        op,
        dir,
        token_file,
        state,
    })
}

#[tokio::test]
async fn agent_enrolls_keeps_its_token_and_reconnects_with_backoff() -> anyhow::Result<()> {
    let Setup {
        client,
        ns,
        mut op,
        dir: _dir,
        token_file,
        state,
    } = setup("agentbo", "agbo").await?;
    let robot = format!("{ns}/kiwi-a");
    let agent = AgentProcess::start(&gateway_url(&op), &robot, &token_file, &state, &[])?;

    wait_for("the robot Online", T, || async {
        online(&client, &ns, "kiwi-a").await.ok()?.then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;
    // The gateway may write Online before the agent has read its `welcome` and saved the
    // token it enrolled with: wait for the file, then check it.
    let creds = state.join("credentials.json");
    wait_for("the saved credentials", T, || async {
        creds.exists().then_some(())
    })
    .await?;
    let mode = std::fs::metadata(&creds)?.permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "the token file is private");
    let saved: Value = serde_json::from_slice(&std::fs::read(&creds)?)?;
    assert_eq!(saved["robot"], robot.as_str());
    assert!(saved["token"].as_str().is_some_and(|t| !t.is_empty()));
    let status = agent.status().await?;
    assert_eq!(status["connected"], true, "{status}");

    // The gateway dies: the agent retries with growing, jittered delays.
    op.kill();
    let failures = wait_for("four failed reconnects", T, || async {
        let lines = agent.log_lines();
        let f: Vec<(u64, u64)> = lines_with(&lines, "connection failed")
            .iter()
            .map(|l| {
                (
                    fields(l)["attempt"].as_u64().unwrap_or_default(),
                    fields(l)["retry_in_ms"].as_u64().unwrap_or_default(),
                )
            })
            .collect();
        (f.len() >= 4).then_some(f)
    })
    .await?;
    eprintln!("(attempt, delay ms): {failures:?}");
    for (attempt, delay) in &failures {
        // After the n-th failure the delay is uniform in [0, min(2000, 200 * 2^n)].
        let ceiling = (200u64 << attempt.min(&10)).min(2000);
        assert!(
            *delay <= ceiling,
            "attempt {attempt}: delay {delay} ms above the ceiling {ceiling} ms"
        );
    }
    let attempts: Vec<u64> = failures.iter().map(|f| f.0).collect();
    assert!(
        attempts.windows(2).all(|w| w[1] == w[0] + 1),
        "attempts count up: {attempts:?}"
    );
    let delays: Vec<u64> = failures.iter().map(|f| f.1).collect();
    assert!(
        delays.iter().any(|d| *d != delays[0]),
        "jittered delays: {delays:?}"
    );
    assert_eq!(agent.status().await?["connected"], false);

    // The gateway comes back on the same address: the agent reconnects with its own token.
    op.restart()?;
    op.wait_ready().await?;
    let started = std::time::Instant::now();
    agent.wait_connected(T).await?;
    let took = started.elapsed();
    eprintln!("reconnected {took:?} after the gateway was ready");
    assert!(took < Duration::from_secs(5), "the cap is 2 s: {took:?}");
    let lines = agent.log_lines();
    let connecting = lines_with(&lines, "connecting");
    assert_eq!(fields(connecting[0])["enrolling"], true);
    assert!(
        connecting[1..]
            .iter()
            .all(|l| fields(l)["enrolling"] == false),
        "later connections use the saved token"
    );
    wait_for("the robot Online again", T, || async {
        online(&client, &ns, "kiwi-a").await.ok()?.then_some(())
    })
    .await?;
    Ok(())
}

/// Events produced while the gateway is down, with the agent SIGKILLed and restarted in between
/// (and once more while it replays), all reach the event store exactly once, in order.
#[tokio::test]
async fn no_event_is_lost_across_a_gateway_outage_and_agent_crashes() -> anyhow::Result<()> {
    let Setup {
        ns,
        mut op,
        dir: _dir,
        token_file,
        state,
        ..
    } = setup("agentzl", "agzl").await?;
    let robot = format!("{ns}/kiwi-z");
    let mut agent = AgentProcess::start(
        &gateway_url(&op),
        &robot,
        &token_file,
        &state,
        &["--telemetry-batch-interval-s", "1"],
    )?;
    let store = op.event_store().await?;
    let key = RobotKey::new(ns.clone(), "kiwi-z");
    let stored_ns = |store: Store, key: RobotKey| async move {
        let events = store.events(&key, None, 10_000).await?;
        let ours: Vec<(u64, u64)> = events
            .iter()
            .filter(|e| e.kind == "zero_loss")
            .map(|e| (e.seq, e.data["n"].as_u64().unwrap_or_default()))
            .collect();
        anyhow::Ok(ours)
    };
    let mut n = 0u64;
    let mut emit = |agent: &AgentProcess, count: u64| -> anyhow::Result<()> {
        for _ in 0..count {
            n += 1;
            agent.emit("zero_loss", &format!("event {n}"), &json!({"n": n}))?;
        }
        Ok(())
    };

    // Connected: 10 events go straight through.
    agent.wait_connected(T).await?;
    emit(&agent, 10)?;
    wait_for("10 events stored", T, || async {
        (stored_ns(store.clone(), key.clone()).await.ok()?.len() == 10).then_some(())
    })
    .await?;

    // The gateway dies; 10 more; the agent is SIGKILLed; 10 more while it is dead; it comes
    // back (still no gateway); 10 more.
    op.kill();
    emit(&agent, 10)?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    agent.kill();
    emit(&agent, 10)?;
    agent.restart()?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    emit(&agent, 10)?;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let queued = agent.status().await?["outboxPending"].as_u64().unwrap_or(0);
    assert!(queued >= 30, "the outbox holds the backlog: {queued}");

    // The gateway returns; the agent is killed again while it replays (some of the backlog
    // stored, not all), and restarted.
    op.restart()?;
    op.wait_ready().await?;
    let at_kill = wait_for("the replay under way", T, || async {
        let n = stored_ns(store.clone(), key.clone()).await.ok()?.len();
        (n > 10).then_some(n)
    })
    .await?;
    agent.kill();
    eprintln!("killed the agent with {at_kill} of 40 events stored");
    assert!(at_kill < 40, "killed mid-replay: {at_kill} of 40 stored");
    agent.restart()?;
    emit(&agent, 10)?;

    let ours = wait_for("all 50 events stored", Duration::from_secs(60), || async {
        let ours = stored_ns(store.clone(), key.clone()).await.ok()?;
        (ours.len() >= 50).then_some(ours)
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;
    let numbers: Vec<u64> = ours.iter().map(|(_, n)| *n).collect();
    assert_eq!(
        numbers,
        (1..=50).collect::<Vec<_>>(),
        "every event exactly once, in the order produced (by seq)"
    );
    assert!(ours.windows(2).all(|w| w[0].0 < w[1].0), "seqs increase");
    // The outbox empties once everything is acknowledged.
    wait_for("outbox drained", T, || async {
        agent
            .status()
            .await
            .ok()
            .filter(|s| s["outboxPending"] == 0)
            .map(|_| ())
    })
    .await?;
    // Telemetry flowed too, and the agent's own lifecycle events were kept.
    let events = store.events(&key, None, 10_000).await?;
    let started = events.iter().filter(|e| e.kind == "agent_started").count();
    assert_eq!(started, 3, "one agent_started per start");
    let samples = store.samples(&key, None, 0, 10_000).await?;
    assert!(!samples.is_empty(), "telemetry stored");
    Ok(())
}
