//! The Robot controller against a real API server: status follows presence, Events only on
//! transitions, `observedGeneration` tracks the spec, and `/metrics` scrapes cleanly.

use std::time::{Duration, Instant};

use k8s_openapi::api::events::v1::Event;
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams};
use lekiwi_crds::{ConditionStatus, Robot, RobotPhase};
use lekiwi_tests::{
    ControlPlane, GatewayStandIn, OperatorProcess, create_robot, get_robot, namespace, wait_for,
    wait_phase,
};
use serde_json::json;

/// The operator's heartbeat grace. Everything the test does after the robot's last heartbeat
/// (maintenance, a release, the condition and Event checks, the idle second and a half) must fit
/// in it, or the robot expires a second time: 4 s did not on a loaded 2-core CI machine (one run
/// counted 6 `RobotOnline` and 3 `RobotOffline`).
const GRACE_SECS: u64 = 8;

fn secs(s: u64) -> Duration {
    Duration::from_secs(s)
}

fn condition(r: &Robot, t: &str) -> (ConditionStatus, String) {
    let c = r
        .condition(t)
        .unwrap_or_else(|| panic!("no {t} condition in {:?}", r.status));
    (c.status, c.reason.to_string())
}

/// Event reasons about `robot` with how often each was emitted: repeats of the same reason are
/// one Event with a growing `series.count`, as Kubernetes aggregates them.
async fn event_counts(
    client: &kube::Client,
    ns: &str,
    robot: &str,
) -> anyhow::Result<std::collections::BTreeMap<String, i32>> {
    let events: Api<Event> = Api::namespaced(client.clone(), ns);
    let mut list: Vec<Event> = events
        .list(&ListParams::default())
        .await?
        .items
        .into_iter()
        .filter(|e| e.regarding.as_ref().and_then(|r| r.name.as_deref()) == Some(robot))
        .collect();
    list.sort_by_key(|e| e.metadata.creation_timestamp.clone().map(|t| t.0));
    let mut counts = std::collections::BTreeMap::new();
    for e in list {
        let n = e.series.as_ref().map(|s| s.count).unwrap_or(1);
        *counts.entry(e.reason.unwrap_or_default()).or_insert(0) += n;
    }
    Ok(counts)
}

#[tokio::test]
async fn status_follows_presence() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "presence").await?;
    let mut op = OperatorProcess::start(
        cp,
        &ns,
        "op-a",
        &["--heartbeat-grace-seconds", &GRACE_SECS.to_string()],
    )?;
    op.wait_ready().await?;

    // Never connected: Pending, with every condition present and observedGeneration set.
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let r = wait_phase(&client, &ns, "kiwi-1", RobotPhase::Pending, secs(20)).await?;
    assert_eq!(r.status.as_ref().unwrap().observed_generation, Some(1));
    assert_eq!(
        condition(&r, "Connected"),
        (ConditionStatus::False, "NeverConnected".into())
    );
    for t in ["Healthy", "Teleoperating", "UpToDate"] {
        condition(&r, t);
    }

    // A gateway connects the robot: Online, healthy, idle.
    let mut gw = GatewayStandIn::start(&client, &ns, "gateway-a", 3).await?;
    gw.connect("kiwi-1").await?;
    let r = wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, secs(5)).await?;
    assert_eq!(
        condition(&r, "Connected"),
        (ConditionStatus::True, "Connected".into())
    );
    assert_eq!(condition(&r, "Healthy").0, ConditionStatus::True);
    assert_eq!(
        condition(&r, "Teleoperating"),
        (ConditionStatus::False, "Idle".into())
    );
    let connected_at = r
        .condition("Connected")
        .unwrap()
        .last_transition_time
        .clone();

    // Teleoperation and a failing health check show as conditions; phase stays Online and the
    // Connected condition keeps its transition time.
    gw.report("kiwi-1", json!({"teleoperation": {"active": true, "score": 0.9}, "health": {"healthy": false, "message": "lekiwi_host not responding"}})).await?;
    let r = wait_for(
        "teleoperating condition",
        Duration::from_secs(5),
        || async {
            let r = get_robot(&client, &ns, "kiwi-1").await.ok()?;
            (r.condition("Teleoperating")?.status == ConditionStatus::True).then_some(r)
        },
    )
    .await?;
    assert_eq!(
        condition(&r, "Healthy"),
        (ConditionStatus::False, "HealthCheckFailed".into())
    );
    assert_eq!(
        r.condition("Healthy").unwrap().message,
        "lekiwi_host not responding"
    );
    assert_eq!(
        r.condition("Connected").unwrap().last_transition_time,
        connected_at
    );
    gw.report(
        "kiwi-1",
        json!({"teleoperation": {"active": false}, "health": {"healthy": true}}),
    )
    .await?;

    // No heartbeat for longer than the grace: Offline, without any write from the gateway.
    let stale_since = Instant::now();
    let r = wait_phase(
        &client,
        &ns,
        "kiwi-1",
        RobotPhase::Offline,
        secs(GRACE_SECS + 5),
    )
    .await?;
    assert!(
        stale_since.elapsed() <= Duration::from_secs(GRACE_SECS + 3),
        "Offline came {:?} after the last heartbeat",
        stale_since.elapsed()
    );
    assert_eq!(
        condition(&r, "Connected"),
        (ConditionStatus::False, "HeartbeatExpired".into())
    );

    // A heartbeat brings it back; a closed connection makes it Offline within a second or so.
    gw.heartbeat("kiwi-1").await?;
    wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, secs(5)).await?;
    gw.disconnect("kiwi-1").await?;
    let t = Instant::now();
    let r = wait_phase(&client, &ns, "kiwi-1", RobotPhase::Offline, secs(5)).await?;
    assert!(
        t.elapsed() < Duration::from_secs(2),
        "disconnect took {:?} to show",
        t.elapsed()
    );
    assert_eq!(condition(&r, "Connected").1, "Disconnected");

    // The gateway dies (stops renewing its Lease) while holding the robot: Unknown.
    gw.connect("kiwi-1").await?;
    wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, secs(5)).await?;
    gw.stop_renewing();
    let r = wait_phase(&client, &ns, "kiwi-1", RobotPhase::Unknown, secs(10)).await?;
    assert_eq!(
        condition(&r, "Connected"),
        (ConditionStatus::Unknown, "GatewayLost".into())
    );
    // It comes back: Online again.
    gw.resume_renewing(3);
    gw.heartbeat("kiwi-1").await?;
    wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, secs(5)).await?;

    // Maintenance is a spec change: Maintenance phase, observedGeneration follows the spec.
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    robots
        .patch(
            "kiwi-1",
            &PatchParams::default(),
            &Patch::Merge(json!({"spec": {"maintenance": true}})),
        )
        .await?;
    let r = wait_phase(&client, &ns, "kiwi-1", RobotPhase::Maintenance, secs(5)).await?;
    assert_eq!(r.status.as_ref().unwrap().observed_generation, Some(2));
    assert_eq!(
        condition(&r, "Connected").0,
        ConditionStatus::True,
        "a cordoned robot stays connected"
    );
    let release = json!({"version": "2.0.0", "digest": format!("sha256:{}", "a".repeat(64))});
    robots
        .patch(
            "kiwi-1",
            &PatchParams::default(),
            &Patch::Merge(json!({"spec": {"maintenance": false, "release": release}})),
        )
        .await?;
    let r = wait_phase(&client, &ns, "kiwi-1", RobotPhase::Online, secs(5)).await?;
    assert_eq!(r.status.as_ref().unwrap().observed_generation, Some(3));
    assert_eq!(
        condition(&r, "UpToDate"),
        (ConditionStatus::False, "ReleaseUnknown".into())
    );
    gw.report("kiwi-1", json!({"currentRelease": release}))
        .await?;
    wait_for("UpToDate", Duration::from_secs(5), || async {
        let r = get_robot(&client, &ns, "kiwi-1").await.ok()?;
        (r.condition("UpToDate")?.status == ConditionStatus::True).then_some(())
    })
    .await?;

    // The gateway's fields and the controller's are owned by separate field managers.
    let r = get_robot(&client, &ns, "kiwi-1").await?;
    let managers: Vec<String> = r
        .metadata
        .managed_fields
        .unwrap_or_default()
        .into_iter()
        .filter_map(|m| m.manager)
        .collect();
    assert!(
        managers.contains(&"lekiwi-gateway".to_owned())
            && managers.contains(&"lekiwi-robot-controller".to_owned()),
        "{managers:?}"
    );

    // Events: one per transition, nothing for the initial Pending.
    let expected: std::collections::BTreeMap<String, i32> = [
        ("RobotOnline", 5),
        ("RobotOffline", 2),
        ("RobotUnknown", 1),
        ("RobotMaintenance", 1),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_owned(), v))
    .collect();
    let counts = wait_for("events", Duration::from_secs(10), || async {
        let c = event_counts(&client, &ns, "kiwi-1").await.ok()?;
        (c == expected).then_some(c)
    })
    .await;
    assert!(
        counts.is_ok(),
        "events: {:?}",
        event_counts(&client, &ns, "kiwi-1").await?
    );

    // Idle for a while: no more writes, no more events (the requeue only re-checks).
    let rv = get_robot(&client, &ns, "kiwi-1")
        .await?
        .metadata
        .resource_version;
    gw.stop_renewing(); // keep the gateway from touching anything; its Lease is still valid for 3 s
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(
        get_robot(&client, &ns, "kiwi-1")
            .await?
            .metadata
            .resource_version,
        rv,
        "an unchanged robot was written"
    );
    assert_eq!(event_counts(&client, &ns, "kiwi-1").await?, expected);
    assert!(op.running());
    Ok(())
}

#[tokio::test]
async fn metrics_scrape_cleanly() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "metrics").await?;
    let mut op = OperatorProcess::start(cp, &ns, "op-m", &["--log-format", "json"])?;
    op.wait_ready().await?;
    for i in 0..3 {
        create_robot(&client, &ns, &format!("kiwi-{i}"), &[]).await?;
    }
    let mut gw = GatewayStandIn::start(&client, &ns, "gateway-m", 10).await?;
    gw.connect("kiwi-0").await?;
    wait_phase(&client, &ns, "kiwi-0", RobotPhase::Online, secs(20)).await?;

    let text = wait_for("robots gauge", Duration::from_secs(5), || async {
        let t = op.metrics().await.ok()?;
        (lekiwi_tests::sample(&t, "lekiwi_robots{phase=\"Pending\"}") == Some(2.0)).then_some(t)
    })
    .await?;
    assert_eq!(
        lekiwi_tests::sample(&text, "lekiwi_robots{phase=\"Online\"}"),
        Some(1.0)
    );
    assert_eq!(
        lekiwi_tests::sample(&text, "lekiwi_leader_election_is_leader"),
        Some(1.0)
    );
    let reconciles = lekiwi_tests::sample(
        &text,
        "lekiwi_controller_reconciliations_total{controller=\"robot\"}",
    )
    .unwrap_or(0.0);
    assert!(reconciles >= 4.0, "reconciles: {reconciles}");
    assert_eq!(
        lekiwi_tests::sample(
            &text,
            "lekiwi_controller_reconcile_duration_seconds_count{controller=\"robot\"}"
        ),
        Some(reconciles)
    );
    assert_eq!(
        lekiwi_tests::sample(
            &text,
            "lekiwi_robot_phase_transitions_total{phase=\"Online\"}"
        ),
        Some(1.0)
    );

    // JSON logs: every line is one JSON object with a level and a message; reconcile lines carry
    // the robot's name from the span.
    let log = op.log_text();
    let mut saw_robot_span = false;
    for line in log.lines() {
        let v: serde_json::Value =
            serde_json::from_str(line).unwrap_or_else(|e| panic!("not JSON ({e}): {line}"));
        assert!(v["level"].is_string() && v["message"].is_string(), "{line}");
        saw_robot_span |= v["span"]["robot"] == "kiwi-0";
    }
    assert!(saw_robot_span, "no log line carried the robot span:\n{log}");

    // Prometheus's own parser and linter accept the exposition.
    let mut lint = std::process::Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()?;
    use std::io::Write;
    lint.stdin.take().unwrap().write_all(text.as_bytes())?;
    let out = lint.wait_with_output()?;
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // promtool lints the classic text format, where a counter's HELP names the `_total` series;
    // OpenMetrics names the family without `_total`. That one difference is expected; a parse
    // error or any other lint is not.
    let unexpected: Vec<&str> = report
        .lines()
        .filter(|l| {
            !(l.ends_with("_total no help text")
                && text.contains(&format!(
                    "# HELP {} ",
                    l.split("_total").next().unwrap_or("")
                )))
        })
        .collect();
    assert!(unexpected.is_empty(), "promtool check metrics: {report}");
    // Every series is ours and every sample value is a number.
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        assert!(line.starts_with("lekiwi_"), "foreign series: {line}");
        let value = line.rsplit(' ').next().unwrap();
        assert!(value.parse::<f64>().is_ok(), "bad value in {line}");
    }
    Ok(())
}
