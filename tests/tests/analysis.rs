//! Post-switch analysis (issue 16 part 1): with `spec.analysis`, a robot counts as updated only
//! after a window in which its host process's memory stayed within the ratio over its baseline
//! before the switch. A real agent's restart hook starts a stand-in host process (a Python
//! script of the release matching `--host-process-pattern`): a release whose process only
//! wobbles completes, though the gateway restarts within its window (the new one goes on from
//! the summary in the Robot's status); a release whose process grows past the ratio fails its robots, with the
//! metric, value and baseline in the message, so the batch of three fails and the fleet rolls back. Real operator, a
//! control plane of the test's own (as `health.rs`, so its CRDs cannot race other worktrees').

use std::path::Path;
use std::process::{Child, Command};
use std::time::Duration;

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::Api;
use kube::api::{Patch, PatchParams, PostParams};
use lekiwi_crds::analysis::AnalysisSpec;
use lekiwi_crds::deployment::{RobotRolloutState, RolloutPhase};
use lekiwi_crds::{Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, enrollment_token_file, gateway_url, namespace, push_release,
    rollout_finished, test_strategy, wait_for, wait_online,
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
