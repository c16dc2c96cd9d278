//! The agent on the robots' own CPU: built for aarch64 and run on an emulated Raspberry Pi 5
//! (`scripts/testbed/pi.sh`: QEMU `virt`, Cortex-A76, Debian's arm64 kernel). Its unit tests pass there,
//! and an arm64 agent enrolls against the x86_64 operator over wss://, goes Online, reports
//! telemetry and teleoperation, applies a release from a RobotDeployment and rolls back when the
//! next one fails its health check. Installed from the `.deb` under systemd, it also survives a
//! reboot and updates itself to another agent build and back to the package's own binary; and a
//! robot of the legacy polling endpoint moves to the agent with the migration script and the
//! `.deb`.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{Patch, PatchParams, PostParams};
use kube::{Api, Client};
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, RobotDeployment, RobotDeploymentSpec, RobotPhase};
use lekiwi_tests::pi::{self, GUEST_STATUS_PORT, HOST_FROM_GUEST, PiGuest, Run};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, enrollment_token_file, get_robot, namespace, push_release,
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

/// An x86_64 operator serving wss:// with a test CA the guest trusts, and the payload directory
/// the guest sees as `/lekiwi` (the CA and an enrollment token file in it).
struct Site {
    op: OperatorProcess,
    dir: tempfile::TempDir,
    ca: PathBuf,
    payload: PathBuf,
}

impl Site {
    async fn start(
        cp: &ControlPlane,
        client: &Client,
        ns: &str,
        identity: &str,
    ) -> anyhow::Result<Self> {
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
            ns,
            identity,
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
        enrollment_token_file(client, ns, &payload.join("enroll")).await?;
        Ok(Self {
            op,
            dir,
            ca,
            payload,
        })
    }

    /// Pushes release `tag` (see [`release`]) as `<tag>.0.0` with the real CLI over https://.
    fn push(
        &self,
        cp: &ControlPlane,
        ns: &str,
        tag: &str,
        failing: bool,
    ) -> anyhow::Result<ReleaseRef> {
        let server = format!("https://127.0.0.1:{}", self.op.gateway_port);
        let dir = release(self.dir.path(), tag, failing)?;
        push_release(
            &cp.kubeconfig(),
            ns,
            &server,
            Some(&self.ca),
            &dir,
            &format!("{tag}.0.0"),
        )
    }

    /// A release applies to the guest's robot (real download over https:// from the gateway,
    /// real switch), and the next one, whose health check fails on the robot, rolls back to it.
    async fn roll_out_and_back(
        &self,
        cp: &ControlPlane,
        client: &Client,
        ns: &str,
        guest: &PiGuest,
    ) -> anyhow::Result<()> {
        let v1 = self.push(cp, ns, "1", false)?;
        deploy(client, ns, &v1).await?;
        let (phase, msg) = finished(client, ns, guest).await?;
        assert_eq!(phase, RolloutPhase::Completed, "{msg}");
        wait_for("kiwi-pi on 1.0.0", Duration::from_secs(30), || async {
            (reported_release(client, ns).await? == "1.0.0").then_some(())
        })
        .await?;
        let v2 = self.push(cp, ns, "2", true)?;
        let started = Instant::now();
        Api::<RobotDeployment>::namespaced(client.clone(), ns)
            .patch(
                "pi",
                &PatchParams::default(),
                &Patch::Merge(&json!({"spec": {"release": v2}})),
            )
            .await?;
        let (phase, msg) = finished(client, ns, guest).await?;
        eprintln!("2.0.0: {phase:?} after {:?}: {msg}", started.elapsed());
        assert_eq!(phase, RolloutPhase::RolledBack, "{msg}");
        assert!(msg.contains("health check of 2.0.0 failed"), "{msg}");
        wait_for("kiwi-pi back on 1.0.0", Duration::from_secs(60), || async {
            (reported_release(client, ns).await? == "1.0.0").then_some(())
        })
        .await
    }
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
        release: Some(release.clone()),
        agent: None,
        strategy: test_strategy(1, 0),
        paused: false,
        analysis: None,
        priority: 0,
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
    Some(robot.status?.current_release?.version.to_string())
}

#[tokio::test]
async fn arm64_agent_on_an_emulated_pi5_rolls_out_and_back() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "arm64").await?;
    let mut site = Site::start(cp, &client, &ns, "arm64").await?;

    let gateway = format!("wss://{HOST_FROM_GUEST}:{}/v1/agent", site.op.gateway_port);
    let robot = format!("{ns}/kiwi-pi");
    let status_listen = format!("0.0.0.0:{GUEST_STATUS_PORT}");
    let health = r#"test ! -e "$LEKIWI_RELEASE_DIR/fail-health""#;
    let guest = PiGuest::boot(
        &format!("e2e-{}", std::process::id()),
        Run::Agent,
        Some(&site.payload),
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
    let robot_obj = online(&client, &ns, &guest, None, Duration::from_secs(90)).await?;
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

    site.roll_out_and_back(cp, &client, &ns, &guest).await?;
    let status = guest.status().await?;
    eprintln!("agent status in the guest: {status}");
    eprintln!(
        "agent VmRSS in the guest (kB, every 10 s): {:?}",
        guest.rss_kb()
    );
    let _ = site.op.terminate();
    Ok(())
}

/// Runs `dpkg-deb ARGS deb` and returns its stdout.
fn dpkg_deb(args: &[&str], deb: &Path) -> anyhow::Result<String> {
    let out = Command::new("dpkg-deb").args(args).arg(deb).output()?;
    if !out.status.success() {
        bail!(
            "dpkg-deb {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

#[test]
fn the_arm64_deb_holds_the_agent_the_hardened_unit_and_its_config() -> anyhow::Result<()> {
    let deb = pi::deb()?;
    assert!(
        deb.ends_with(format!(
            "lekiwi-agent_{}_arm64.deb",
            env!("CARGO_PKG_VERSION")
        )),
        "{deb:?}"
    );
    let info = dpkg_deb(&["--info"], &deb)?;
    for field in [
        "Package: lekiwi-agent",
        "Architecture: arm64",
        "Depends: libc6",
    ] {
        assert!(info.contains(field), "no {field:?} in\n{info}");
    }
    for script in ["conffiles", "postinst", "prerm", "postrm"] {
        assert!(info.contains(script), "no {script} in\n{info}");
    }
    let contents = dpkg_deb(&["--contents"], &deb)?;
    let entry = |path: &str| {
        contents
            .lines()
            .find(|l| l.ends_with(path))
            .unwrap_or_default()
            .to_owned()
    };
    assert!(
        entry("./").starts_with("drwxr-xr-x root/root"),
        "{contents}"
    );
    assert!(
        entry("./usr/bin/lekiwi-agent").starts_with("-rwxr-xr-x root/root"),
        "{contents}"
    );
    for path in [
        "./lib/systemd/system/lekiwi-agent.service",
        "./etc/lekiwi/agent.yaml",
        "./usr/share/doc/lekiwi-agent/copyright",
    ] {
        assert!(
            entry(path).starts_with("-rw-r--r-- root/root"),
            "{path}: {contents}"
        );
    }
    // The files themselves: an aarch64 ELF, the repository's unit, the conffile.
    let root = tempfile::tempdir()?;
    let out = Command::new("dpkg-deb")
        .arg("-x")
        .arg(&deb)
        .arg(root.path())
        .output()?;
    assert!(out.status.success(), "{out:?}");
    let elf = std::fs::read(root.path().join("usr/bin/lekiwi-agent"))?;
    assert_eq!(&elf[..4], b"\x7fELF");
    assert_eq!(
        u16::from_le_bytes([elf[18], elf[19]]),
        183,
        "e_machine is not EM_AARCH64"
    );
    let unit =
        std::fs::read_to_string(root.path().join("lib/systemd/system/lekiwi-agent.service"))?;
    let repo_unit = std::fs::read_to_string(
        lekiwi_tests::repo_root().join("manifests/systemd/lekiwi-agent.service"),
    )?;
    assert_eq!(unit, repo_unit);
    assert!(unit.contains("--config /etc/lekiwi/agent.yaml"), "{unit}");
    let control = tempfile::tempdir()?;
    let out = Command::new("dpkg-deb")
        .arg("-e")
        .arg(&deb)
        .arg(control.path())
        .output()?;
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        std::fs::read_to_string(control.path().join("conffiles"))?,
        "/etc/lekiwi/agent.yaml\n"
    );
    Ok(())
}

/// The payload disk's `run.sh` (bash, run by the guest's `lekiwi-payload.service` at each boot):
/// on the first boot `dpkg -i` the .deb, put the configuration, CA and enrollment token where the
/// unit reads them and `systemctl enable --now lekiwi-agent`; at every boot print `LEKIWI-FIG`
/// lines (uptime, CPU ticks and VmRSS kB of the agent and of prometheus-node-exporter) every 5 s,
/// and reboot when the host accepts a connection on port `reboot-port` (the test's command).
const RUN_SH: &str = r#"[ -n "${BASH_VERSION:-}" ] || exec /bin/bash "$0" "$@"
P=/payload
if [ ! -e /var/lib/lekiwi-test/installed ]; then
  echo "LEKIWI-ARCH $(dpkg --print-architecture)"
  dpkg -i "$P/lekiwi-agent.deb" && echo "LEKIWI-DPKG ok"
  install -m 0644 "$P/agent.yaml" /etc/lekiwi/agent.yaml
  install -m 0644 "$P/ca.crt" /etc/lekiwi/ca.crt
  install -m 0600 "$P/enroll" /etc/lekiwi/enroll
  systemctl enable --now lekiwi-agent && echo "LEKIWI-ENABLED $(systemctl is-enabled lekiwi-agent)"
  mkdir -p /var/lib/lekiwi-test && touch /var/lib/lekiwi-test/installed
else
  echo "LEKIWI-REBOOTED agent $(systemctl is-enabled lekiwi-agent)"
fi
fig() {
  local pid t
  pid="$(systemctl show -p MainPID --value "$1")"
  [ "${pid:-0}" != 0 ] || { echo "- - -"; return; }
  t="$(cut -d' ' -f14,15 "/proc/$pid/stat" | tr ' ' +)"
  echo "$((t)) $(awk '/^VmRSS/ {print $2}' "/proc/$pid/status") $(cut -d' ' -f22 "/proc/$pid/stat")"
}
port="$(cat "$P/reboot-port")"
while sleep 5; do
  echo "LEKIWI-FIG $(cut -d' ' -f1 /proc/uptime) $(fig lekiwi-agent) $(fig prometheus-node-exporter)"
  if (exec 3<>"/dev/tcp/10.0.2.2/$port") 2>/dev/null; then
    echo "LEKIWI-REBOOT"
    systemctl reboot
    exit 0
  fi
done
"#;

/// One service's figures on a `LEKIWI-FIG` line: CPU seconds per hour over its life so far
/// (utime + stime over the time since it started) and VmRSS in kB.
#[derive(Debug, Clone, Copy)]
struct Usage {
    cpu_s_per_hour: f64,
    rss_kb: u64,
}

/// The last `LEKIWI-FIG` line where both the agent and prometheus-node-exporter run (the line:
/// uptime, then ticks, kB and start tick of each; 100 ticks a second).
fn figures(console: &str) -> Option<(Usage, Usage)> {
    console.lines().rev().find_map(|l| {
        let v: Vec<&str> = l.strip_prefix("LEKIWI-FIG ")?.split(' ').collect();
        let up: f64 = v.first()?.parse().ok()?;
        let n = |i: usize| v.get(i)?.parse::<u64>().ok();
        let usage = |i: usize| {
            let life = up - n(i + 2)? as f64 / 100.0;
            Some(Usage {
                cpu_s_per_hour: n(i)? as f64 / 100.0 / life * 3600.0,
                rss_kb: n(i + 1)?,
            })
        };
        Some((usage(1)?, usage(4)?))
    })
}

/// The guest's configuration of the agent (JSON is YAML).
fn agent_yaml(ns: &str, gateway_port: u16) -> String {
    json!({
        "gateway": format!("wss://{HOST_FROM_GUEST}:{gateway_port}/v1/agent"),
        "caFile": "/etc/lekiwi/ca.crt",
        "enrollmentTokenFile": "/etc/lekiwi/enroll",
        "robotName": format!("{ns}/kiwi-pi"),
        "statusListen": format!("0.0.0.0:{GUEST_STATUS_PORT}"),
        "mdns": false,
        "backoffInitialMs": 200,
        "backoffMaxMs": 2000,
        "teleopIntervalS": 0.5,
        "telemetryBatchIntervalS": 1,
        "releaseHealthCommand": r#"test ! -e "$LEKIWI_RELEASE_DIR/fail-health""#,
        "releaseHealthTimeoutS": 5,
        "logFormat": "text",
    })
    .to_string()
}

/// Waits for kiwi-pi Online with a `connectedSince` other than `before`, returns the Robot.
async fn online(
    client: &Client,
    ns: &str,
    guest: &PiGuest,
    before: Option<String>,
    within: Duration,
) -> anyhow::Result<lekiwi_crds::Robot> {
    wait_for("kiwi-pi Online", within, || async {
        let r = get_robot(client, ns, "kiwi-pi").await.ok()?;
        let s = r.status.as_ref()?;
        let since = s.connected_since.as_ref().map(|t| format!("{t:?}"));
        (s.phase == Some(RobotPhase::Online) && since != before).then_some(r)
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(60)))
}

#[tokio::test]
async fn the_arm64_deb_installs_on_a_systemd_pi5_rolls_out_and_survives_a_reboot()
-> anyhow::Result<()> {
    let deb = pi::deb()?;
    pi::rootfs()?;
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "arm64-deb").await?;
    let mut site = Site::start(cp, &client, &ns, "arm64-deb").await?;
    let payload = &site.payload;
    std::fs::copy(&deb, payload.join("lekiwi-agent.deb"))?;
    std::fs::write(
        payload.join("agent.yaml"),
        agent_yaml(&ns, site.op.gateway_port),
    )?;
    std::fs::write(payload.join("run.sh"), RUN_SH)?;
    let reboot = std::net::TcpListener::bind("127.0.0.1:0")?;
    let reboot_port = reboot.local_addr()?.port();
    drop(reboot); // bound again when the test asks for the reboot
    std::fs::write(payload.join("reboot-port"), reboot_port.to_string())?;

    // Installed with dpkg, started by systemd: enrolled and Online.
    let guest = PiGuest::boot_rootfs(&format!("deb-{}", std::process::id()), payload)?;
    let first = online(&client, &ns, &guest, None, Duration::from_secs(300)).await?;
    let to_online = guest.booted.elapsed();
    let console = guest.console();
    eprintln!("boot (systemd) + dpkg -i + enable to Online: {to_online:?}");
    assert!(console.contains("LEKIWI-ARCH arm64"), "{console}");
    assert!(console.contains("LEKIWI-DPKG ok"), "{console}");
    assert!(console.contains("LEKIWI-ENABLED enabled"), "{console}");
    let system = first.status.as_ref().and_then(|s| s.system.clone());
    assert_eq!(system.and_then(|s| s.arch).as_deref(), Some("aarch64"));

    // A release applies, and a failing one rolls back.
    site.roll_out_and_back(cp, &client, &ns, &guest).await?;

    // Figures: the agent next to prometheus-node-exporter in the same guest.
    tokio::time::sleep(Duration::from_secs(10)).await;
    let (agent, exporter) = figures(&guest.console()).context("no LEKIWI-FIG line")?;
    eprintln!(
        "agent {:.0} CPU-s/h, VmRSS {} kB; prometheus-node-exporter {:.0} CPU-s/h, VmRSS {} kB \
         (ratio CPU {:.2}, RSS {:.2})",
        agent.cpu_s_per_hour,
        agent.rss_kb,
        exporter.cpu_s_per_hour,
        exporter.rss_kb,
        agent.cpu_s_per_hour / exporter.cpu_s_per_hour.max(f64::MIN_POSITIVE),
        agent.rss_kb as f64 / exporter.rss_kb.max(1) as f64
    );
    assert!(
        agent.rss_kb > 0 && agent.rss_kb < 32 * 1024,
        "{agent:?} (MemoryMax=32M)"
    );

    // Reboot: the enrollment token is gone (so the robot must use its own token), systemd starts
    // the agent again and the same Robot is Online again.
    let uid = first.metadata.uid.clone();
    let since = first
        .status
        .as_ref()
        .and_then(|s| s.connected_since.as_ref())
        .map(|t| format!("{t:?}"));
    Api::<k8s_openapi::api::core::v1::Secret>::namespaced(client.clone(), &ns)
        .delete(
            lekiwi_crds::contract::ENROLLMENT_SECRET,
            &Default::default(),
        )
        .await?;
    let listener = tokio::net::TcpListener::bind(("127.0.0.1", reboot_port)).await?;
    let rebooted_at = Instant::now();
    tokio::time::timeout(Duration::from_secs(30), listener.accept()).await??;
    drop(listener);
    let again = online(&client, &ns, &guest, since, Duration::from_secs(300)).await?;
    eprintln!("reboot to Online again: {:?}", rebooted_at.elapsed());
    assert_eq!(again.metadata.uid, uid, "not the same Robot");
    let console = guest.console();
    assert!(
        console.contains("LEKIWI-REBOOTED agent enabled"),
        "{console}"
    );
    assert_eq!(
        reported_release(&client, &ns).await.as_deref(),
        Some("1.0.0")
    );

    site.update_agent_and_back(cp, &client, &ns, &guest, &deb)
        .await?;
    let _ = site.op.terminate();
    Ok(())
}

/// `sha256:<hex>` of `/usr/bin/lekiwi-agent` in the .deb `deb`.
fn packaged_agent_digest(deb: &Path) -> anyhow::Result<String> {
    use sha2::Digest as _;
    let dir = tempfile::tempdir()?;
    let out = Command::new("dpkg-deb")
        .arg("-x")
        .arg(deb)
        .arg(dir.path())
        .output()?;
    anyhow::ensure!(out.status.success(), "dpkg-deb -x: {out:?}");
    let bytes = std::fs::read(dir.path().join("usr/bin/lekiwi-agent"))?;
    Ok(format!(
        "sha256:{}",
        hex::encode(sha2::Sha256::digest(bytes))
    ))
}

/// Waits until kiwi-pi's agent reports `version` and its update `Succeeded`; its status.
async fn agent_on(
    client: &Client,
    ns: &str,
    guest: &PiGuest,
    version: &str,
) -> anyhow::Result<lekiwi_crds::RobotStatus> {
    wait_for(
        &format!("kiwi-pi on agent {version}"),
        Duration::from_secs(180),
        || async {
            let s = get_robot(client, ns, "kiwi-pi").await.ok()?.status?;
            let done = s.agent_update.as_ref().is_some_and(|u| {
                u.phase.as_deref() == Some("Succeeded") && u.version.as_deref() == Some(version)
            });
            (s.agent_version.as_deref() == Some(version) && done).then_some(s)
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(60)))
}

impl Site {
    /// The arm64 agent updates itself under systemd (issue 19): build B, pushed with the real
    /// CLI, is downloaded over https://, installed into a slot and started by systemd after the
    /// agent exits 75; then `spec.agent` names the package's own binary again (A, never pushed)
    /// and the robot switches back from its disk, downloading nothing.
    async fn update_agent_and_back(
        &self,
        cp: &ControlPlane,
        client: &Client,
        ns: &str,
        guest: &PiGuest,
        deb: &Path,
    ) -> anyhow::Result<()> {
        let guest_status = get_robot(client, ns, "kiwi-pi")
            .await?
            .status
            .unwrap_or_default();
        let a_version = guest_status.agent_version.context("no agentVersion")?;
        let a_digest = guest_status.agent_digest.context("no agentDigest")?;
        assert_eq!(
            a_digest,
            packaged_agent_digest(deb)?,
            "the digest of the .deb's binary"
        );
        // B: the package binary under another version name (a wrapper, as in agent_update.rs).
        let b_file = self.dir.path().join("agent-b");
        std::fs::write(
            &b_file,
            "#!/bin/sh\nLEKIWI_AGENT_VERSION_OVERRIDE=9.0.0-pi exec /usr/bin/lekiwi-agent \"$@\"\n",
        )?;
        let server = format!("https://127.0.0.1:{}", self.op.gateway_port);
        let b_digest = lekiwi_tests::push_agent(
            &cp.kubeconfig(),
            ns,
            &server,
            Some(&self.ca),
            &b_file,
            "9.0.0-pi",
            "arm64",
        )?;
        let t0 = Instant::now();
        lekiwi_tests::set_agent(client, ns, "kiwi-pi", "9.0.0-pi", "arm64", &b_digest).await?;
        let on_b = agent_on(client, ns, guest, "9.0.0-pi").await?;
        let to_b = t0.elapsed();
        assert_eq!(on_b.agent_digest.as_deref(), Some(b_digest.as_str()));

        let t1 = Instant::now();
        lekiwi_tests::set_agent(client, ns, "kiwi-pi", &a_version, "arm64", &a_digest).await?;
        let on_a = agent_on(client, ns, guest, &a_version).await?;
        let to_a = t1.elapsed();
        assert_eq!(on_a.agent_digest.as_deref(), Some(a_digest.as_str()));
        let store = self.op.event_store().await?;
        let key = lekiwi_core::RobotKey::new(ns.to_owned(), "kiwi-pi".to_owned());
        let started: Vec<serde_json::Value> = store
            .events(&key, None, 10_000)
            .await?
            .into_iter()
            .filter(|e| e.kind == "agent_update_started")
            .map(|e| e.data)
            .collect();
        assert_eq!(started.len(), 2, "{started:?}");
        assert!(
            started[0]["bytes"].as_u64().unwrap_or_default() > 0,
            "{started:?}"
        );
        assert_eq!(
            started[1]["bytes"], 0,
            "the rollback downloaded nothing: {started:?}"
        );
        eprintln!(
            "arm64 agent self-update under systemd: A -> B in {to_b:?} ({} bytes), \
             rollback B -> A (never pushed) in {to_a:?} (0 bytes)",
            started[0]["bytes"]
        );
        Ok(())
    }
}

/// The guest's `run.sh` for the migration test: a stand-in for the legacy poller's unit (which
/// the migration disables), then the poller's install step: the downloaded release's
/// `migrate-to-agent.sh`, run as root with what the poller knows (`/payload/env`).
const MIGRATE_SH: &str = r#"[ -n "${BASH_VERSION:-}" ] || exec /bin/bash "$0" "$@"
P=/payload
[ ! -e /var/lib/lekiwi-test/migrated ] || exit 0
printf '[Service]\nExecStart=/bin/sleep infinity\n[Install]\nWantedBy=multi-user.target\n' \
  >/etc/systemd/system/legacy-poller.service
systemctl daemon-reload && systemctl enable --now legacy-poller
echo "LEKIWI-POLLER $(systemctl is-active legacy-poller)"
install -m 0600 "$P/token" /etc/legacy-token
install -m 0644 "$P/ca.crt" /etc/legacy-ca.crt
mkdir -p /opt/legacy && cp -r "$P/release" /opt/legacy/2.0.0
set -a; . "$P/env"; set +a
if sh /opt/legacy/2.0.0/lekiwi-migrate/migrate-to-agent.sh; then echo "LEKIWI-MIGRATED ok"; fi
echo "LEKIWI-POLLER-AFTER $(systemctl is-enabled legacy-poller)"
echo "LEKIWI-AGENT $(systemctl is-active lekiwi-agent) $(systemctl is-enabled lekiwi-agent-guard.timer)"
mkdir -p /var/lib/lekiwi-test && touch /var/lib/lekiwi-test/migrated
"#;

/// Issue 19's migration path with the package: a robot known to the fleet only through the
/// legacy polling endpoint (its Robot and token exist, nothing of the agent is on it) runs
/// `migrate-to-agent.sh` from a release holding the arm64 `.deb`. dpkg installs the package
/// (unit, guard timer), `adopt` hands the robot's own token over, systemd starts the agent and
/// the poller's unit is disabled: the robot is Online over the agent under its old name, with
/// the same token Secret.
#[tokio::test]
async fn the_arm64_deb_moves_a_polling_robot_to_the_agent_on_a_systemd_pi5() -> anyhow::Result<()> {
    let deb = pi::deb()?;
    pi::rootfs()?;
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "arm64-migrate").await?;
    let site = Site::start(cp, &client, &ns, "arm64-migrate").await?;
    lekiwi_tests::create_robot(&client, &ns, "kiwi-old", &[]).await?;
    let token = lekiwi_tests::robot_token(&client, &ns, "kiwi-old").await?;
    let secrets = Api::<k8s_openapi::api::core::v1::Secret>::namespaced(client.clone(), &ns);
    let secret_version = secrets
        .get("kiwi-old-agent-token")
        .await?
        .metadata
        .resource_version;

    let payload = &site.payload;
    let migrate = payload.join("release/lekiwi-migrate");
    std::fs::create_dir_all(&migrate)?;
    std::fs::copy(
        lekiwi_tests::repo_root().join("manifests/legacy/migrate-to-agent.sh"),
        migrate.join("migrate-to-agent.sh"),
    )?;
    let deb_name = deb.file_name().context("deb name")?;
    std::fs::copy(&deb, migrate.join(deb_name))?;
    std::fs::write(payload.join("token"), format!("{token}\n"))?;
    std::fs::write(
        payload.join("env"),
        format!(
            "LEKIWI_ROBOT={ns}/kiwi-old\nLEKIWI_TOKEN_FILE=/etc/legacy-token\n\
             LEKIWI_GATEWAY_URL=wss://{HOST_FROM_GUEST}:{}/v1/agent\n\
             LEKIWI_CA_FILE=/etc/legacy-ca.crt\nLEKIWI_LEGACY_SERVICE=legacy-poller.service\n",
            site.op.gateway_port
        ),
    )?;
    std::fs::write(payload.join("run.sh"), MIGRATE_SH)?;

    let guest = PiGuest::boot_rootfs(&format!("migrate-{}", std::process::id()), payload)?;
    let robot = wait_for(
        "kiwi-old Online over the agent",
        Duration::from_secs(300),
        || async {
            let r = get_robot(&client, &ns, "kiwi-old").await.ok()?;
            let s = r.status.as_ref()?;
            (s.phase == Some(RobotPhase::Online) && s.protocol.as_deref() == Some("websocket"))
                .then_some(r)
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(60)))?;
    let took = guest.booted.elapsed();
    let console = wait_for(
        "the migration's last lines",
        Duration::from_secs(30),
        || async {
            let c = guest.console();
            c.contains("LEKIWI-AGENT ").then_some(c)
        },
    )
    .await?;
    assert!(console.contains("LEKIWI-POLLER active"), "{console}");
    assert!(console.contains("LEKIWI-MIGRATED ok"), "{console}");
    assert!(
        console.contains(&format!("installing {}", deb_name.to_string_lossy())),
        "{console}"
    );
    assert!(
        console.contains("LEKIWI-POLLER-AFTER disabled"),
        "{console}"
    );
    assert!(console.contains("LEKIWI-AGENT active enabled"), "{console}");
    let status = robot.status.clone().unwrap_or_default();
    assert_eq!(
        status.agent_digest.as_deref(),
        Some(packaged_agent_digest(&deb)?.as_str()),
        "the package's binary runs"
    );
    assert_eq!(
        status.system.and_then(|s| s.arch).as_deref(),
        Some("aarch64")
    );
    let after = secrets
        .get("kiwi-old-agent-token")
        .await?
        .metadata
        .resource_version;
    assert_eq!(
        after, secret_version,
        "the same token: adopted, not re-enrolled"
    );
    eprintln!("arm64 .deb migration of a polling robot: boot to Online over the agent in {took:?}");
    Ok(())
}
