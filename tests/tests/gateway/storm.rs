//! Fleet-scale storms (issue 14): a fleet coming Online costs the API server at most about one
//! write per robot, with its Events aggregated; enrollment beyond the gateway's admission limit
//! is told when to retry and gets through later, while connected robots stay Online.

use std::time::Duration;

use k8s_openapi::api::events::v1::Event;
use kube::Api;
use kube::api::ListParams;
use lekiwi_agent::connection::{ConnectError, Credentials, connect};
use lekiwi_crds::{Robot, RobotPhase};
use lekiwi_tests::{
    AgentProcess, ControlPlane, FleetProcess, FleetSpec, OperatorProcess, enrollment_token_file,
    gateway_operator, gateway_url, get_robot, hello, namespace, wait_for, wait_online, wait_phase,
};

/// Robots in the fleet that comes Online.
const ROBOTS: usize = 100;

/// Write requests (POST, PUT, PATCH, APPLY, DELETE) the API server has served for `resource`
/// since it started, from its own `/metrics`.
fn writes(cp: &ControlPlane, resource: &str) -> anyhow::Result<f64> {
    let out = cp.kubectl(&["get", "--raw", "/metrics"]);
    anyhow::ensure!(out.status.success(), "kubectl get --raw /metrics failed");
    let text = String::from_utf8(out.stdout)?;
    let resource = format!("resource=\"{resource}\"");
    Ok(text
        .lines()
        .filter(|l| l.starts_with("apiserver_request_total{") && l.contains(&resource))
        .filter(|l| {
            ["POST", "PUT", "PATCH", "APPLY", "DELETE"]
                .iter()
                .any(|v| l.contains(&format!("verb=\"{v}\"")))
        })
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum())
}

/// `robots` simulated robots of namespace `ns` enrolling through `gateway` with the token in
/// `token_file`, their state under `dir`, healthy, logging warnings only.
fn start_fleet(
    gateway: &str,
    token_file: &std::path::Path,
    ns: &str,
    robots: usize,
    dir: &std::path::Path,
) -> anyhow::Result<FleetProcess> {
    FleetProcess::start(FleetSpec {
        gateway,
        token_file,
        namespace: ns,
        robots,
        state_root: &dir.join("robots"),
        health_command: "true",
        report_every: "5",
        rust_log: "warn",
        extra: &[],
    })
}

/// Robots of `ns` in `phase`.
async fn count_phase(api: &Api<Robot>, phase: RobotPhase) -> usize {
    api.list(&ListParams::default())
        .await
        .map(|l| {
            l.items
                .iter()
                .filter(|r| r.status.as_ref().and_then(|s| s.phase) == Some(phase))
                .count()
        })
        .unwrap_or(0)
}

/// When an Event was last emitted: its series' last observation, else its creation.
fn last_seen(e: &Event) -> Option<jiff::Timestamp> {
    e.series
        .as_ref()
        .map(|s| s.last_observed_time.0)
        .or_else(|| e.metadata.creation_timestamp.as_ref().map(|t| t.0))
}

/// A fleet of known robots reconnecting at once (what follows a gateway restart) costs the API
/// server at most 1.2 writes per robot in all (Robot status and Events), and `kubectl get events`
/// still says what happened.
#[tokio::test]
async fn fleet_coming_online_costs_one_write_per_robot() -> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "storm").await?;
    let op = gateway_operator(&cp, &ns, "op-storm", &["--status-refresh-seconds", "600"]).await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enroll-token");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);

    // Enroll the fleet: each robot costs its Robot's creation and one status write (the
    // gateway's, as its session opens; the Robot controller does not write `Pending` first).
    let before = writes(&cp, "robots")?;
    let url = gateway_url(&op);
    let mut fleet = start_fleet(&url, &token_file, &ns, ROBOTS, dir.path())?;
    wait_online(&client, &ns, ROBOTS, Duration::from_secs(120)).await?;
    tokio::time::sleep(Duration::from_secs(5)).await;
    let enrolled = writes(&cp, "robots")? - before;
    eprintln!("Robot writes while {ROBOTS} robots enrolled and came Online: {enrolled}");
    assert!(
        enrolled <= 2.1 * ROBOTS as f64,
        "{enrolled} Robot writes for {ROBOTS} robots enrolling (a create and a status write each)"
    );

    // Then crash it: every robot is Offline.
    fleet.kill();
    wait_for("every robot Offline", Duration::from_secs(60), || async {
        (count_phase(&robots, RobotPhase::Offline).await == ROBOTS).then_some(())
    })
    .await?;
    // Let the controller and the Event recorder finish with the disconnects.
    tokio::time::sleep(Duration::from_secs(12)).await;

    // The whole fleet comes back at once.
    let before = writes(&cp, "robots")? + writes(&cp, "events")?;
    let started = jiff::Timestamp::now() - jiff::SignedDuration::from_secs(1);
    fleet.restart()?;
    wait_online(&client, &ns, ROBOTS, Duration::from_secs(120)).await?;
    // Whatever the controller and the Event aggregation still do for this transition.
    tokio::time::sleep(Duration::from_secs(12)).await;
    let robot_writes = writes(&cp, "robots")?;
    let total = robot_writes + writes(&cp, "events")? - before;
    let per_robot = total / ROBOTS as f64;
    eprintln!("API writes while {ROBOTS} robots came Online: {total} ({per_robot:.2} per robot)");
    assert!(
        per_robot <= 1.2,
        "{total} API writes (Robot status and Events) for {ROBOTS} robots coming Online"
    );

    // The Events still tell the story: one names how many robots came Online (the recorder
    // folds a repeat of the same note into the earlier Event's series).
    let events = Api::<Event>::all(client.clone())
        .list(&ListParams::default())
        .await?
        .items;
    let summary = events.iter().find(|e| {
        e.reason.as_deref() == Some("RobotsOnline")
            && e.note
                .as_deref()
                .is_some_and(|n| n.contains("robots became Online"))
            && last_seen(e).is_some_and(|t| t >= started)
    });
    assert!(
        summary.is_some(),
        "no RobotsOnline summary among {:?}",
        events
            .iter()
            .map(|e| (&e.reason, &e.note))
            .collect::<Vec<_>>()
    );
    Ok(())
}

/// The gateway's count of enrollments refused by admission.
const THROTTLED: &str = "lekiwi_gateway_refused_total{kind=\"enrollment_throttled\"}";

/// Robots enrolling in the admission test, beyond the one already connected.
const ENROLLING: usize = 8;

/// Enrollment beyond the gateway's admission rate is answered 503 with a `Retry-After` before the
/// upgrade; the agents honour it and all enroll later, while an already connected robot stays
/// Online throughout.
#[tokio::test]
async fn enrollment_beyond_admission_is_told_when_to_retry() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "admission").await?;
    let mut op = OperatorProcess::start_with_env(
        cp,
        &ns,
        "op-adm",
        &["--heartbeat-grace-seconds", "60"],
        &[("LEKIWI_ENROLL_RATE", "0.5"), ("LEKIWI_ENROLL_BURST", "2")],
    )?;
    op.wait_ready().await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enroll-token");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let url = gateway_url(&op);

    // A robot enrolls and is connected before the crowd arrives.
    let _veteran = AgentProcess::start(
        &url,
        &format!("{ns}/veteran"),
        &token_file,
        &dir.path().join("veteran"),
        &[],
    )?;
    let r = wait_phase(
        &client,
        &ns,
        "veteran",
        RobotPhase::Online,
        Duration::from_secs(20),
    )
    .await?;
    let since = r.status.and_then(|s| s.connected_since);

    // The crowd: more enrollments at once than the burst admits.
    let _fleet = start_fleet(&url, &token_file, &ns, ENROLLING, dir.path())?;
    wait_for("a refused enrollment", Duration::from_secs(30), || async {
        let refused = op.metric(THROTTLED).await.unwrap_or(0.0);
        (refused >= 1.0).then_some(())
    })
    .await?;
    // One more, by hand, right behind them: refused before the upgrade, told when to retry.
    let probe = Credentials {
        token: std::fs::read_to_string(&token_file)?,
        robot: format!("{ns}/probe"),
    };
    match connect(&url, &probe, &hello(), Duration::from_secs(5)).await {
        Err(ConnectError::Unavailable {
            message,
            retry_after: Some(after),
        }) => {
            assert!(message.contains("503"), "{message}");
            assert!(after >= Duration::from_secs(1), "Retry-After {after:?}");
        }
        other => panic!(
            "expected 503 with Retry-After, got {:?}",
            other.map(|(_, w)| w)
        ),
    }

    // Every robot of the crowd enrolls in the end; the veteran never left Online meanwhile.
    let veteran_steady = || async {
        let r = get_robot(&client, &ns, "veteran").await.ok()?;
        let s = r.status?;
        (s.phase == Some(RobotPhase::Online) && s.connected_since == since).then_some(())
    };
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    wait_for("the crowd Online", Duration::from_secs(90), || async {
        assert!(
            veteran_steady().await.is_some(),
            "the connected robot left Online while others enrolled"
        );
        (count_phase(&robots, RobotPhase::Online).await == ENROLLING + 1).then_some(())
    })
    .await?;
    let refused = op.metric(THROTTLED).await.unwrap_or(0.0);
    assert!(refused >= 2.0, "enrollments refused: {refused}");
    assert!(op.running());
    Ok(())
}

/// Robots in the late-writes test.
const LATE: usize = 60;

/// A gateway whose status writes run late (here a fixed 2 writes/s for 60 robots refreshing
/// every 3 s, a 30 s cycle against a 12 s heartbeat grace; the 9 s above the refresh period
/// leave room for a Lease renewal slowed by a busy machine) declares its lag on its Lease, and
/// the Robot controller keeps its connected robots Online though their recorded heartbeats age
/// past the grace; once they disconnect, they still turn Offline.
#[tokio::test]
async fn late_status_writes_turn_no_connected_robot_offline() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "late").await?;
    #[rustfmt::skip]
    let args = [
        "--heartbeat-grace-seconds", "12", "--status-refresh-seconds", "3",
        "--heartbeat-interval-seconds", "1", "--gateway-lease-seconds", "3",
        "--status-qps", "2", "--status-qps-min", "2", "--status-qps-max", "2",
        "--status-burst", "1",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "op-late", &args)?;
    op.wait_ready().await?;
    let dir = tempfile::tempdir()?;
    let token_file = dir.path().join("enroll-token");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let mut fleet = start_fleet(&gateway_url(&op), &token_file, &ns, LATE, dir.path())?;
    wait_online(&client, &ns, LATE, Duration::from_secs(120)).await?;

    // For 30 s: every robot stays Online, while recorded heartbeats age past the grace.
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    let leases: Api<k8s_openapi::api::coordination::v1::Lease> =
        Api::namespaced(client.clone(), &ns);
    let (mut oldest, mut declared, mut gateway) = (0i64, 0u64, String::new());
    let until = std::time::Instant::now() + Duration::from_secs(30);
    while std::time::Instant::now() < until {
        let now = jiff::Timestamp::now();
        for r in robots.list(&ListParams::default()).await?.items {
            let s = r.status.unwrap_or_default();
            assert_eq!(s.phase, Some(RobotPhase::Online), "{:?}", s.conditions);
            gateway = s.gateway.map(String::from).unwrap_or_default();
            let beat = s.last_heartbeat_time.map(|t| t.0).unwrap_or(now);
            oldest = oldest.max(now.duration_since(beat).as_secs());
        }
        let lease = leases.get(&gateway).await?;
        let lag = lease.metadata.annotations.unwrap_or_default();
        let lag = lag.get(lekiwi_crds::contract::STATUS_LAG_ANNOTATION);
        declared = declared.max(lag.and_then(|v| v.parse().ok()).unwrap_or(0));
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    eprintln!("oldest recorded heartbeat {oldest} s; largest declared lag {declared} s");
    assert!(
        oldest > 8,
        "no heartbeat aged past the grace: the test proves nothing"
    );
    assert!(declared >= 5, "declared status lag {declared} s");
    let exported = op.metric("lekiwi_gateway_status_lag_seconds").await;
    assert!(exported.is_some_and(|v| v > 0.0), "{exported:?}");

    // A lag hides no disconnect: the fleet stops, every robot turns Offline.
    fleet.kill();
    wait_for("every robot Offline", Duration::from_secs(90), || async {
        (count_phase(&robots, RobotPhase::Offline).await == LATE).then_some(())
    })
    .await?;
    Ok(())
}
