//! Post-switch analysis (issue 16 part 1): with `spec.analysis`, a robot counts as updated only
//! after a window in which its host process's memory stayed within the ratio over its baseline
//! before the switch. A real agent's restart hook starts a stand-in host process (a Python
//! script of the release matching `--host-process-pattern`): a release whose process only
//! wobbles completes, though the gateway restarts within its window (the new one goes on from
//! the summary in the Robot's status); a release whose process grows past the ratio fails its robots, with the
//! metric, value and baseline in the message, so the batch of three fails and the fleet rolls back. Real operator, a
//! control plane of the test's own (as `health.rs`, so its CRDs cannot race other worktrees').
//!
//! And what analysis costs the API server (issue 47), counted on a Robot watch of the shared
//! control plane with a fleet of real agents (`lekiwi-fleet`) and the default routine refresh:
//! a rollout without analysis leaves the fleet at the routine rate once it completes; one with
//! analysis costs each robot one status write more, which is what the rollout judges.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Child, Command};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::StreamExt;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{Patch, PatchParams, PostParams};
use kube::runtime::{WatchStreamExt, watcher};
use kube::{Api, ResourceExt};
use lekiwi_crds::analysis::{AnalysisSpec, WINDOW_ANNOTATION};
use lekiwi_crds::deployment::{RobotRolloutState, RolloutPhase};
use lekiwi_crds::{Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    ControlPlane, FleetProcess, FleetSpec, OperatorProcess, enrollment_token_file, gateway_url,
    namespace, push_release, rollout_finished, test_strategy, wait_for, wait_online,
};
use serde_json::json;

/// The stand-in host process: writes its pid to argv[2], holds a 4 MiB ballast and, by
/// `MODE`, keeps it (`steady`), varies it by up to 1 MiB (`wobble`) or adds 4 MiB every
/// 200 ms up to 40 MiB more (`grow`).
const HOST_PY: &str = r#"
import os, sys, time
open(sys.argv[2], "w").write(str(os.getpid()))
MB = 1 << 20
ballast = [bytearray(b"\x01") * (4 * MB)]
i = 0
while True:
    i += 1
    if MODE == "wobble":
        ballast[1:] = [bytearray(b"\x01") * ((i % 4) * MB // 4 + 1)]
    elif MODE == "grow" and len(ballast) <= 10:
        ballast.append(bytearray(b"\x01") * (4 * MB))
    time.sleep(0.2)
"#;

/// The fleet: one batch of three robots.
const ROBOTS: [&str; 3] = ["kiwi-a", "kiwi-b", "kiwi-c"];

/// A release directory whose `host.py` runs in `mode`.
fn release_dir(root: &Path, mode: &str) -> anyhow::Result<std::path::PathBuf> {
    let dir = root.join(format!("release-{mode}"));
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("host.py"), format!("MODE = {mode:?}\n{HOST_PY}"))?;
    Ok(dir)
}

/// Ends the stand-in whose pid is in `pid_file` (started by this test or its hook).
fn stop_host(pid_file: &Path) {
    if let Ok(pid) = std::fs::read_to_string(pid_file) {
        let _ = Command::new("kill").arg(pid.trim()).status();
    }
}

fn analysis(window_seconds: i64) -> AnalysisSpec {
    AnalysisSpec {
        window_seconds,
        max_host_memory_ratio: Some(1.5),
        max_error_event_fraction: Some(0.5),
        ..AnalysisSpec::default()
    }
}

#[tokio::test]
async fn a_host_process_that_doubles_its_memory_rolls_the_fleet_back() -> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "analysis").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let mut op = OperatorProcess::start(
        &cp,
        &ns,
        "op-analysis",
        &[
            "--blob-dir",
            blobs.to_str().unwrap(),
            "--status-refresh-seconds",
            "1",
            "--heartbeat-interval-seconds",
            "1",
        ],
    )?;
    op.wait_ready().await?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;

    // Each robot's host process before any release: the test starts it, the hook replaces it.
    let steady = release_dir(dir.path(), "steady")?;
    let mut sites = Vec::new();
    for name in ROBOTS {
        let token = format!("kiwi-host-{}-{name}", std::process::id());
        let pid_file = dir.path().join(format!("{name}.pid"));
        let first: Child = Command::new("python3")
            .arg(steady.join("host.py"))
            .args([&token, pid_file.to_str().unwrap()])
            .spawn()?;
        let restart = format!(
            "kill \"$(cat {pid})\" 2>/dev/null; python3 host.py {token} {pid} >/dev/null 2>&1 &",
            pid = pid_file.display()
        );
        let agent = lekiwi_tests::AgentProcess::start(
            &gateway_url(&op),
            &format!("{ns}/{name}"),
            &token_file,
            &dir.path().join(name),
            &[
                "--host-process-pattern",
                &token,
                "--health-interval-s",
                "0.5",
                "--release-restart-command",
                &restart,
            ],
        )?;
        sites.push((first, pid_file, agent));
    }
    wait_online(&client, &ns, ROBOTS.len(), Duration::from_secs(60)).await?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    for name in ROBOTS {
        wait_for(
            "the host process's memory",
            Duration::from_secs(30),
            || async {
                let t = robots.get(name).await.ok()?.status?.telemetry?;
                t.host_memory_bytes.filter(|&b| b > 0)
            },
        )
        .await?;
    }
    tokio::time::sleep(Duration::from_secs(2)).await;

    // A release whose host process only wobbles: the window passes, the rollout completes.
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let wobble = release_dir(dir.path(), "wobble")?;
    let v1 = push_release(&cp.kubeconfig(), &ns, &server, None, &wobble, "1.0.0")?;
    let deployments: Api<RobotDeployment> = Api::namespaced(client.clone(), &ns);
    let d = RobotDeployment::new(
        "fleet",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(v1.clone()),
            agent: None,
            strategy: test_strategy(ROBOTS.len() as i32, 0),
            paused: false,
            analysis: Some(analysis(8)),
            priority: 0,
        },
    );
    deployments.create(&PostParams::default(), &d).await?;
    // The gateway restarts within the window: the next one goes on from the stored summary.
    let opened = wait_for("the window of 1.0.0", Duration::from_secs(60), || async {
        let a = robots.get("kiwi-a").await.ok()?.status?.analysis?;
        (a.release.as_ref() == Some(&v1)).then_some(a)
    })
    .await?;
    op.restart()?;
    op.wait_ready().await?;
    let finished = rollout_finished(&deployments, "fleet", Duration::from_secs(90)).await;
    let robot = robots.get("kiwi-a").await?;
    let d = finished.map_err(|e| anyhow::anyhow!("{e}\n{:?}", robot.status))?;
    let st = d.status.unwrap();
    if st.phase != Some(RolloutPhase::Completed) {
        let mut all = String::new();
        for name in ROBOTS {
            let r = robots.get(name).await?;
            all += &format!("{name}: {:?}\n", r.status);
        }
        for (_, _, agent) in &sites {
            all += &agent.log_text();
        }
        panic!("{st:?}\n{all}");
    }
    let report = robots
        .get("kiwi-a")
        .await?
        .status
        .unwrap()
        .analysis
        .unwrap();
    assert_eq!(report.release.as_ref(), Some(&v1));
    let (start, end) = (
        report.window_start.clone().unwrap().0,
        report.window_end.clone().unwrap().0,
    );
    assert!(
        end.duration_since(start) >= jiff::SignedDuration::from_secs(8),
        "{report:?}"
    );
    assert_eq!(report.window_start, opened.window_start, "{report:?}");
    assert_eq!(
        report.baseline, opened.baseline,
        "the baseline survived the restart"
    );
    // The agent's heartbeat round-trip times are summarised too.
    assert!(
        report.window.rtt_ms.as_ref().unwrap().samples >= 2,
        "{report:?}"
    );
    assert!(
        report.baseline.host_memory_bytes.as_ref().unwrap().samples >= 2,
        "{report:?}"
    );
    for (first, _, _) in &mut sites {
        let _ = first.kill();
        let _ = first.wait();
    }

    // A release whose host process grows to several times its size: failed, rolled back.
    let grow = release_dir(dir.path(), "grow")?;
    let v2 = push_release(&cp.kubeconfig(), &ns, &server, None, &grow, "2.0.0")?;
    deployments
        .patch(
            "fleet",
            &PatchParams::default(),
            &Patch::Merge(json!({ "spec": { "release": v2 } })),
        )
        .await?;
    let d = wait_for(
        "the rollout of 2.0.0 to roll back",
        Duration::from_secs(90),
        || async {
            let d = deployments.get("fleet").await.ok()?;
            (d.status.as_ref()?.phase == Some(RolloutPhase::RolledBack)).then_some(d)
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", sites[0].2.log_text()))?;
    let st = d.status.unwrap();
    // The batch rolls back as soon as its threshold cannot be met: robots whose window had not
    // ended by then are rolled back without a verdict of their own.
    assert!(st.failed >= 1, "{st:?}");
    assert_eq!(st.robots.len(), ROBOTS.len(), "{st:?}");
    let mut verdicts = 0;
    for r in &st.robots {
        assert_eq!(r.state, RobotRolloutState::RolledBack, "{r:?}");
        let why = r.message.as_deref().unwrap_or_default();
        if why.contains("hostMemoryBytes highest") {
            assert!(why.contains("baseline mean"), "{why}");
            assert!(why.contains("maxHostMemoryRatio 1.5"), "{why}");
            verdicts += 1;
        }
    }
    assert!(verdicts >= 1, "{st:?}");
    // `kubectl lekiwi rollout status` shows the verdict.
    let out = Command::new(lekiwi_tests::bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args(["-n", &ns, "rollout", "status", "fleet", "--watch=false"])
        .output()?;
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("RolledBack") && text.contains("maxHostMemoryRatio 1.5"),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for name in ROBOTS {
        wait_for(
            "every robot back on 1.0.0",
            Duration::from_secs(60),
            || async {
                let s = robots.get(name).await.ok()?.status?;
                (s.current_release.as_ref() == Some(&v1)).then_some(())
            },
        )
        .await?;
    }

    for (_, pid_file, agent) in sites {
        stop_host(&pid_file);
        drop(agent);
    }
    op.terminate()?;
    Ok(())
}

/// Robots of the write-counting tests: enough that a per-robot figure is not one robot's luck,
/// few enough for a loaded 2-core machine.
const FLEET: usize = 8;

/// How long the fleet is watched once a rollout completed.
const QUIET: Duration = Duration::from_secs(40);

/// The gateway's routine refresh period (its default, which these tests keep).
const ROUTINE_REFRESH: Duration = Duration::from_secs(300);

/// An operator of the shared control plane with its default routine refresh and a 1 s
/// heartbeat (a window fills fast, and every heartbeat could be written), and [`FLEET`] real
/// agents, `Online`.
struct CostSite {
    client: kube::Client,
    ns: String,
    kubeconfig: std::path::PathBuf,
    server: String,
    dir: tempfile::TempDir,
    op: OperatorProcess,
    _fleet: FleetProcess,
}

impl CostSite {
    async fn start(prefix: &str) -> anyhow::Result<Self> {
        let cp = ControlPlane::shared();
        let client = cp.client().await?;
        let ns = namespace(&client, prefix).await?;
        let dir = tempfile::tempdir()?;
        let blobs = dir.path().join("blobs");
        std::fs::create_dir_all(&blobs)?;
        let flags = [
            "--blob-dir",
            blobs.to_str().unwrap(),
            "--heartbeat-interval-seconds",
            "1",
        ];
        let mut op = OperatorProcess::start(cp, &ns, prefix, &flags)?;
        op.wait_ready().await?;
        let token_file = dir.path().join("enroll");
        enrollment_token_file(&client, &ns, &token_file).await?;
        let fleet = FleetProcess::start(FleetSpec {
            gateway: &gateway_url(&op),
            token_file: &token_file,
            namespace: &ns,
            robots: FLEET,
            state_root: &dir.path().join("robots"),
            health_command: "true",
            report_every: "5",
            rust_log: "warn",
            extra: &[],
        })?;
        wait_online(&client, &ns, FLEET, Duration::from_secs(120)).await?;
        Ok(Self {
            client,
            ns,
            kubeconfig: cp.kubeconfig(),
            server: format!("http://127.0.0.1:{}", op.gateway_port),
            dir,
            op,
            _fleet: fleet,
        })
    }

    /// Pushes a one-file release `version`.
    fn push(&self, version: &str) -> anyhow::Result<lekiwi_crds::ReleaseRef> {
        let dir = self.dir.path().join(format!("release-{version}"));
        std::fs::create_dir_all(&dir)?;
        std::fs::write(dir.join("VERSION"), version)?;
        push_release(
            &self.kubeconfig,
            &self.ns,
            &self.server,
            None,
            &dir,
            version,
        )
    }

    /// Rolls `release` out to the whole fleet in one batch, with `analysis` if given, and
    /// waits for the rollout to end.
    async fn roll_out(
        &self,
        release: &lekiwi_crds::ReleaseRef,
        analysis: Option<AnalysisSpec>,
    ) -> anyhow::Result<RobotDeployment> {
        let d = RobotDeployment::new(
            "fleet",
            RobotDeploymentSpec {
                selector: LabelSelector::default(),
                release: Some(release.clone()),
                agent: None,
                strategy: test_strategy(FLEET as i32, 0),
                paused: false,
                analysis,
                priority: 0,
            },
        );
        self.deployments()
            .create(&PostParams::default(), &d)
            .await?;
        rollout_finished(&self.deployments(), "fleet", Duration::from_secs(120))
            .await
            .map_err(|e| anyhow::anyhow!("{e}\noperator log:\n{}", self.op.log_text()))
    }

    fn deployments(&self) -> Api<RobotDeployment> {
        Api::namespaced(self.client.clone(), &self.ns)
    }

    async fn robots(&self) -> anyhow::Result<Vec<Robot>> {
        Ok(Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .list(&Default::default())
            .await?
            .items)
    }
}

/// Status changes per robot of a namespace as a Robot watch delivers them, from its start: each
/// one a write that changed the status (a write that changes nothing makes no event, and one of
/// the spec or annotations alone is not counted).
struct StatusWrites {
    counts: Arc<Mutex<BTreeMap<String, usize>>>,
    task: tokio::task::JoinHandle<()>,
}

impl StatusWrites {
    async fn start(client: &kube::Client, ns: &str) -> anyhow::Result<Self> {
        let api: Api<Robot> = Api::namespaced(client.clone(), ns);
        let counts: Arc<Mutex<BTreeMap<String, usize>>> = Arc::default();
        let (listed, ready) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(count_status_changes(api, Arc::clone(&counts), listed));
        tokio::time::timeout(Duration::from_secs(30), ready).await??;
        Ok(Self { counts, task })
    }

    /// The changes counted since the last call, per robot, and their sum.
    fn take(&self) -> (BTreeMap<String, usize>, usize) {
        let counts = std::mem::take(&mut *self.counts.lock().unwrap());
        let sum = counts.values().sum();
        (counts, sum)
    }
}

impl Drop for StatusWrites {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Counts into `counts` each event of `api`'s watch whose status differs from the robot's
/// last; `listed` is told once the first list is in.
async fn count_status_changes(
    api: Api<Robot>,
    counts: Arc<Mutex<BTreeMap<String, usize>>>,
    listed: tokio::sync::oneshot::Sender<()>,
) {
    let mut last: BTreeMap<String, serde_json::Value> = BTreeMap::new();
    let mut listed = Some(listed);
    let mut events = std::pin::pin!(watcher(api, watcher::Config::default()).default_backoff());
    while let Some(event) = events.next().await {
        match event {
            Ok(watcher::Event::InitApply(r)) => {
                last.insert(r.name_any(), json!(r.status));
            }
            Ok(watcher::Event::InitDone) => {
                if let Some(tx) = listed.take() {
                    let _ = tx.send(());
                }
            }
            Ok(watcher::Event::Apply(r)) => {
                let (name, status) = (r.name_any(), json!(r.status));
                if last.get(&name) != Some(&status) {
                    *counts.lock().unwrap().entry(name.clone()).or_default() += 1;
                }
                last.insert(name, status);
            }
            _ => {}
        }
    }
}

/// Issue 47: once a rollout without analysis completed, the fleet's status writes are back at
/// the routine rate at once (they were one every few seconds per robot for ten minutes, an
/// analysis window nobody asked for), and no robot carries an analysis window.
#[tokio::test]
async fn after_a_rollout_without_analysis_the_fleet_is_back_at_the_routine_rate()
-> anyhow::Result<()> {
    let site = CostSite::start("quiet").await?;
    let writes = StatusWrites::start(&site.client, &site.ns).await?;
    let v1 = site.push("1.0.0")?;
    let d = site.roll_out(&v1, None).await?;
    assert_eq!(
        d.status.as_ref().and_then(|s| s.phase),
        Some(RolloutPhase::Completed),
        "{:?}",
        d.status
    );
    let (during, rollout) = writes.take();
    for r in site.robots().await? {
        assert_eq!(r.annotations().get(WINDOW_ANNOTATION), None, "{r:?}");
    }
    tokio::time::sleep(QUIET).await;
    let (after, quiet) = writes.take();
    // About FLEET x 40 / 300 routine refreshes; a refresh at every 5 s would be FLEET x 8.
    let routine = FLEET as f64 * QUIET.as_secs_f64() / ROUTINE_REFRESH.as_secs_f64();
    eprintln!("status writes: rollout {rollout} {during:?}; {QUIET:?} after it {quiet} {after:?}");
    assert!(
        quiet <= FLEET,
        "{quiet} status writes in the {QUIET:?} after the rollout completed ({after:?}); the \
         routine refresh makes about {routine:.1}; the rollout itself made {rollout} ({during:?})"
    );
    Ok(())
}

/// Issue 47: with analysis, a robot's switch costs one status write more (the one that
/// completes its window, which the rollout judges), however long the window and however
/// often the robot sends heartbeats; the rollout completes without any routine refresh (the
/// window is far shorter than the refresh period). A window that fails is judged too, and the
/// rollback switch asks for no window.
#[tokio::test]
async fn with_analysis_a_switch_costs_one_status_write_more_and_is_judged() -> anyhow::Result<()> {
    const WINDOW: i64 = 20;
    let site = CostSite::start("judged").await?;
    let writes = StatusWrites::start(&site.client, &site.ns).await?;
    let v1 = site.push("1.0.0")?;
    let spec = AnalysisSpec {
        window_seconds: WINDOW,
        ..AnalysisSpec::default()
    };
    let d = site.roll_out(&v1, Some(spec)).await?;
    let st = d.status.unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{st:?}");
    let (during, rollout) = writes.take();
    eprintln!("status writes of the rollout with analysis: {rollout} {during:?}");
    // Three each: the controller's of the new spec's condition, the switch's, the window's end
    // (a robot's routine refresh may fall in the rollout too). A refresh every 5 s in the
    // window made about seven.
    assert!(
        rollout <= 4 * FLEET,
        "{rollout} status writes for {FLEET} switches with a {WINDOW} s window ({during:?})"
    );
    for r in site.robots().await? {
        let window = r.annotations().get(WINDOW_ANNOTATION).cloned();
        assert_eq!(window, Some(WINDOW.to_string()), "{r:?}");
        let report = r.status.and_then(|s| s.analysis).expect("a window");
        assert_eq!(report.release.as_ref(), Some(&v1));
        let span = report
            .window_end
            .unwrap()
            .0
            .duration_since(report.window_start.unwrap().0);
        assert!(span.as_secs() >= WINDOW, "{span:?}");
    }

    // A window whose round-trip times are more than 0 times the baseline's fails every robot.
    let v2 = site.push("2.0.0")?;
    let patch = json!({ "spec": { "release": v2, "analysis": { "windowSeconds": 5, "maxRttRatio": 0.0 } } });
    site.deployments()
        .patch("fleet", &PatchParams::default(), &Patch::Merge(patch))
        .await?;
    let d = wait_for(
        "the rollout of 2.0.0 to roll back",
        Duration::from_secs(120),
        || async {
            let d = site.deployments().get("fleet").await.ok()?;
            (d.status.as_ref()?.phase == Some(RolloutPhase::RolledBack)).then_some(d)
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\noperator log:\n{}", site.op.log_text()))?;
    let st = d.status.unwrap();
    let judged = st.robots.iter().filter_map(|r| r.message.as_deref());
    let judged: Vec<&str> = judged.filter(|m| m.contains("rttMs mean")).collect();
    assert!(!judged.is_empty(), "{st:?}");
    assert!(
        judged.iter().all(|m| m.contains("maxRttRatio 0")),
        "{judged:?}"
    );
    // Back on 1.0.0: a rollback is not judged, and its write removed the window.
    wait_for(
        "every robot back on 1.0.0",
        Duration::from_secs(60),
        || async {
            let robots = site.robots().await.ok()?;
            robots
                .iter()
                .all(|r| {
                    let back = r.status.as_ref().and_then(|s| s.current_release.as_ref());
                    back == Some(&v1) && r.annotations().get(WINDOW_ANNOTATION).is_none()
                })
                .then_some(())
        },
    )
    .await?;
    Ok(())
}
