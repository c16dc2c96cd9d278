//! The agent on the robots' own CPU: built for aarch64 and run on an emulated Raspberry Pi 5
//! (`scripts/pi.sh`: QEMU `virt`, Cortex-A76, Debian's arm64 kernel). Its unit tests pass there,
//! and an arm64 agent enrolls against the x86_64 operator over wss://, goes Online, reports
//! telemetry and teleoperation, applies a release from a RobotDeployment and rolls back when the
//! next one fails its health check.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::bail;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{Patch, PatchParams, PostParams};
use kube::{Api, Client};
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, RobotDeployment, RobotDeploymentSpec, RobotPhase};
use lekiwi_tests::pi::{self, GUEST_STATUS_PORT, HOST_FROM_GUEST, PiGuest, Run};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, bin, enrollment_token_file, get_robot, namespace,
    rollout_finished, test_strategy, wait_for,
};
use serde_json::json;

/// The Pi 5's core as `/proc/cpuinfo` names it.
const CORTEX_A76: &str = "0xd0b";

#[tokio::test]
async fn agent_unit_tests_pass_on_an_emulated_pi5() -> anyhow::Result<()> {
    let name = format!("unit-{}", std::process::id());
    let mut guest = PiGuest::boot(&name, Run::UnitTests, None, &[])?;
    let status = guest.wait_exit(Duration::from_secs(200)).await?;
    eprintln!(
        "unit tests ran in the guest for {:?}",
        guest.booted.elapsed()
    );
    let cpu = guest.marker("LEKIWI-CPU").unwrap_or_default();
    assert!(cpu.contains(CORTEX_A76), "not a Cortex-A76: {cpu:?}");
    assert_eq!(status, 0, "console tail:\n{}", guest.console_tail(80));
    let console = guest.console();
    assert!(
        console.contains("test result: ok"),
        "no test summary:\n{}",
        guest.console_tail(40)
    );
    Ok(())
}

/// Pushes `dir` as `version` with the real CLI over https:// (trusting `ca`).
fn push(
    cp: &ControlPlane,
    ns: &str,
    port: u16,
    ca: &Path,
    dir: &Path,
    version: &str,
) -> anyhow::Result<ReleaseRef> {
    let out = Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args(["-n", ns, "release", "push", dir.to_str().unwrap()])
        .args([
            "--version",
            version,
            "--server",
            &format!("https://127.0.0.1:{port}"),
        ])
        .args(["--certificate-authority", ca.to_str().unwrap()])
        .env_remove("LEKIWI_SERVER")
        .output()?;
    if !out.status.success() {
        bail!(
            "release push failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(ReleaseRef {
        version: version.into(),
        digest: String::from_utf8_lossy(&out.stdout).trim().to_owned(),
    })
}

/// A small release; `failing` adds the file the agent's health check refuses.
fn release(root: &Path, tag: &str, failing: bool) -> anyhow::Result<std::path::PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi"))?;
    std::fs::write(dir.join("lekiwi/config.yaml"), format!("release: {tag}\n"))?;
    std::fs::write(dir.join("policy.bin"), tag.repeat(200_000))?;
    if failing {
        // Empty, as a flag file would be: the agent stores it without a download.
        std::fs::write(dir.join("fail-health"), "")?;
    }
    Ok(dir)
}

async fn deploy(client: &Client, ns: &str, release: &ReleaseRef) -> anyhow::Result<()> {
    let spec = RobotDeploymentSpec {
        selector: LabelSelector::default(),
        release: release.clone(),
        strategy: test_strategy(1, 0),
        paused: false,
    };
    Api::<RobotDeployment>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &RobotDeployment::new("pi", spec))
        .await?;
    Ok(())
}

/// Waits for the rollout's end and returns its phase and message.
async fn finished(
    client: &Client,
    ns: &str,
    guest: &PiGuest,
) -> anyhow::Result<(RolloutPhase, String)> {
    let api = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    let d = rollout_finished(&api, "pi", Duration::from_secs(120))
        .await
        .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(40)))?;
    let st = d.status.unwrap_or_default();
    Ok((
        st.phase.unwrap_or(RolloutPhase::Failed),
        st.message.unwrap_or_default(),
    ))
}

async fn reported_release(client: &Client, ns: &str) -> Option<String> {
    let robot = get_robot(client, ns, "kiwi-pi").await.ok()?;
    Some(robot.status?.current_release?.version)
}

#[tokio::test]
async fn arm64_agent_on_an_emulated_pi5_rolls_out_and_back() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "arm64").await?;
    let dir = tempfile::tempdir()?;
    pi::gateway_ca(dir.path())?;
    let (ca, cert, key) = (
        dir.path().join("ca.crt"),
        dir.path().join("tls.crt"),
        dir.path().join("tls.key"),
    );
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let mut op = OperatorProcess::start(
        cp,
        &ns,
        "arm64",
        &[
            "--blob-dir",
            blobs.to_str().unwrap(),
            "--heartbeat-interval-seconds",
            "2",
            "--status-refresh-seconds",
            "2",
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ],
    )?;
    op.wait_ready().await?;
    let payload = dir.path().join("payload");
    std::fs::create_dir_all(&payload)?;
    std::fs::copy(&ca, payload.join("ca.crt"))?;
    enrollment_token_file(&client, &ns, &payload.join("enroll")).await?;

    let gateway = format!("wss://{HOST_FROM_GUEST}:{}/v1/agent", op.gateway_port);
    let robot = format!("{ns}/kiwi-pi");
    let status_listen = format!("0.0.0.0:{GUEST_STATUS_PORT}");
    let health = r#"test ! -e "$LEKIWI_RELEASE_DIR/fail-health""#;
    let guest = PiGuest::boot(
        &format!("e2e-{}", std::process::id()),
        Run::Agent,
        Some(&payload),
        &[
            "--config",
            "/nonexistent.yaml",
            "--gateway",
            &gateway,
            "--ca-file",
            "/lekiwi/ca.crt",
            "--robot-name",
            &robot,
            "--enrollment-token-file",
            "/lekiwi/enroll",
            "--state-dir",
            "/var/lib/lekiwi",
            "--status-listen",
            &status_listen,
            "--mdns",
            "false",
            "--backoff-initial-ms",
            "200",
            "--backoff-max-ms",
            "2000",
            "--teleop-interval-s",
            "0.5",
            "--telemetry-batch-interval-s",
            "1",
            "--release-health-command",
            health,
            "--release-health-timeout-s",
            "5",
            "--log-format",
            "text",
        ],
    )?;

    // Enrolled and Online, from the Pi 5's core.
    let robot_obj = wait_for("kiwi-pi Online", Duration::from_secs(90), || async {
        let r = get_robot(&client, &ns, "kiwi-pi").await.ok()?;
        (r.status.as_ref()?.phase == Some(RobotPhase::Online)).then_some(r)
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(40)))?;
    let to_online = guest.booted.elapsed();
    let cpu = guest.marker("LEKIWI-CPU").unwrap_or_default();
    eprintln!("boot to Online: {to_online:?}; {cpu}");
    assert!(cpu.contains(CORTEX_A76), "not a Cortex-A76: {cpu:?}");
    let system = robot_obj
        .status
        .as_ref()
        .and_then(|s| s.system.clone())
        .unwrap_or_default();
    assert_eq!(system.arch.as_deref(), Some("aarch64"), "{system:?}");
    let status = guest.status().await?;
    assert_eq!(status["connected"], true, "{status}");

    // Telemetry (written with the status refresh) and the teleoperation verdict reach the
    // Robot's status.
    let reported = wait_for(
        "telemetry and teleoperation",
        Duration::from_secs(60),
        || async {
            let s = get_robot(&client, &ns, "kiwi-pi").await.ok()?.status?;
            let t = s.telemetry.clone()?;
            (t.cpu_percent.is_some() && t.memory_percent.is_some() && s.teleoperation.is_some())
                .then_some(s)
        },
    )
    .await?;
    eprintln!(
        "telemetry {:?}; teleoperation {:?}",
        reported.telemetry, reported.teleoperation
    );
    assert_eq!(reported.teleoperation.map(|t| t.active), Some(false));

    // A release applies (real download over https:// from the gateway, real switch) ...
    let v1 = push(
        cp,
        &ns,
        op.gateway_port,
        &ca,
        &release(dir.path(), "1", false)?,
        "1.0.0",
    )?;
    deploy(&client, &ns, &v1).await?;
    let (phase, msg) = finished(&client, &ns, &guest).await?;
    assert_eq!(phase, RolloutPhase::Completed, "{msg}");
    wait_for("kiwi-pi on 1.0.0", Duration::from_secs(30), || async {
        (reported_release(&client, &ns).await? == "1.0.0").then_some(())
    })
    .await?;

    // ... and the next one, whose health check fails on the robot, rolls back.
    let v2 = push(
        cp,
        &ns,
        op.gateway_port,
        &ca,
        &release(dir.path(), "2", true)?,
        "2.0.0",
    )?;
    let started = Instant::now();
    Api::<RobotDeployment>::namespaced(client.clone(), &ns)
        .patch(
            "pi",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"release": v2}})),
        )
        .await?;
    let (phase, msg) = finished(&client, &ns, &guest).await?;
    eprintln!("2.0.0: {phase:?} after {:?}: {msg}", started.elapsed());
    assert_eq!(phase, RolloutPhase::RolledBack, "{msg}");
    assert!(msg.contains("health check of 2.0.0 failed"), "{msg}");
    wait_for("kiwi-pi back on 1.0.0", Duration::from_secs(60), || async {
        (reported_release(&client, &ns).await? == "1.0.0").then_some(())
    })
    .await?;
    let status = guest.status().await?;
    eprintln!("agent status in the guest: {status}");
    eprintln!(
        "agent VmRSS in the guest (kB, every 10 s): {:?}",
        guest.rss_kb()
    );
    let _ = op.terminate();
    Ok(())
}
