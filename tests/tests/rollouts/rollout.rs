//! Rollouts end to end on the real control plane: a release pushed with the real CLI, a
//! `RobotDeployment`, the real operator (controller + gateway) and a fleet of real agents
//! (`lekiwi-fleet`: the agent's own run loop, one state directory per robot).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use anyhow::bail;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams, PostParams};
use lekiwi_core::RobotKey;
use lekiwi_crds::deployment::{RolloutPhase, RolloutStrategy};
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    AgentProcess, FleetProcess, FleetSpec, OperatorSite, bin, gateway_url, http_get_with,
    rollout_finished, test_strategy, wait_for, wait_online,
};
use serde_json::{Value, json};

const HEALTH: &str = r#"test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health""#;

/// The shared operator site (`OperatorSite`), and what these tests do with it.
struct Site {
    base: OperatorSite,
}

lekiwi_tests::deref_to_operator_site!(Site);

impl Site {
    async fn new(prefix: &str) -> anyhow::Result<Self> {
        Ok(Self {
            base: OperatorSite::start(prefix).await?,
        })
    }

    fn cli(&self, args: &[&str]) -> anyhow::Result<std::process::Output> {
        Ok(Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(self.cp.kubeconfig())
            .args(["-n", &self.ns])
            .args(args)
            .env_remove("LEKIWI_SERVER")
            .output()?)
    }

    /// `lekiwi-fleet` with `robots` robots of this site.
    fn fleet(&self, robots: usize, extra: &[&str]) -> anyhow::Result<FleetProcess> {
        FleetProcess::start(FleetSpec {
            gateway: &gateway_url(&self.op),
            token_file: &self.token_file,
            namespace: &self.ns,
            robots,
            state_root: &self.dir.path().join("robots"),
            health_command: HEALTH,
            report_every: "2",
            rust_log: "warn,lekiwi_agent::release=info",
            extra,
        })
    }

    async fn deploy(
        &self,
        name: &str,
        release: &ReleaseRef,
        strategy: RolloutStrategy,
        selector: LabelSelector,
    ) -> anyhow::Result<()> {
        let d = RobotDeployment::new(
            name,
            RobotDeploymentSpec {
                selector,
                release: Some(release.clone()),
                agent: None,
                strategy,
                paused: false,
                analysis: None,
                priority: 0,
            },
        );
        Api::<RobotDeployment>::namespaced(self.client.clone(), &self.ns)
            .create(&PostParams::default(), &d)
            .await?;
        Ok(())
    }

    async fn deployment(&self, name: &str) -> anyhow::Result<RobotDeployment> {
        Ok(
            Api::<RobotDeployment>::namespaced(self.client.clone(), &self.ns)
                .get(name)
                .await?,
        )
    }

    /// Waits for a terminal phase (from the current generation) and returns the deployment.
    async fn finished(&self, name: &str, timeout: Duration) -> anyhow::Result<RobotDeployment> {
        let api = Api::<RobotDeployment>::namespaced(self.client.clone(), &self.ns);
        rollout_finished(&api, name, timeout)
            .await
            .map_err(|e| anyhow::anyhow!("{e}\noperator log tail:\n{}", tail(&self.op.log_text())))
    }

    async fn robots(&self) -> anyhow::Result<Vec<Robot>> {
        Ok(Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .list(&ListParams::default())
            .await?
            .items)
    }

    async fn wait_online(&self, n: usize) -> anyhow::Result<()> {
        wait_online(&self.client, &self.ns, n, Duration::from_secs(120)).await
    }

    /// Robots by the release they report.
    async fn releases(&self) -> anyhow::Result<BTreeMap<String, usize>> {
        let mut by = BTreeMap::new();
        for r in self.robots().await? {
            let v = r
                .status
                .and_then(|s| s.current_release)
                .map_or("-".to_owned(), |r| r.version.to_string());
            *by.entry(v).or_default() += 1;
        }
        Ok(by)
    }

    /// Bytes the gateway served to one robot, counted by the gateway.
    async fn bytes_served(&self, robot: &str) -> anyhow::Result<u64> {
        // A Kubernetes user's token (the admin's: RBAC allows it `get robots`).
        let token = self.cp.admin_token()?;
        let (code, _, body) = http_get_with(
            self.op.gateway_port,
            &format!("/v1/blobs-served?robot={}/{robot}", self.ns),
            &[("authorization", &format!("Bearer {token}"))],
        )
        .await?;
        if code != 200 {
            bail!("blobs-served answered {code}: {body}");
        }
        let v: Value = serde_json::from_str(&body)?;
        Ok(v["bytes"].as_u64().unwrap_or_default())
    }
}

fn tail(s: &str) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}

/// A release directory: `files` small files plus a 256 KiB "policy checkpoint"; `changed`
/// names files whose content differs (by `tag`).
fn release_dir(root: &Path, files: usize, tag: &str, changed: &[usize]) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi/config"))?;
    for i in 0..files {
        let content = if changed.contains(&i) {
            format!("file {i} of release {tag}\n").repeat(200)
        } else {
            format!("file {i}\n").repeat(200)
        };
        let sub = if i % 3 == 0 {
            "lekiwi/config"
        } else {
            "lekiwi"
        };
        std::fs::write(dir.join(sub).join(format!("f{i:03}.py")), content)?;
    }
    let policy: Vec<u8> = (0..256 * 1024u32).map(|i| (i * 7 % 251) as u8).collect();
    std::fs::write(dir.join("policy.safetensors"), policy)?;
    Ok(dir)
}

fn robot_name(i: usize) -> String {
    format!("kiwi-{i:03}")
}

/// 50 agents: a clean rollout (canary, then batches); then a second release whose second batch
/// has 3 of 10 robots failing their health check, so every updated robot goes back; transfers
/// are differential (bytes counted by the gateway).
#[tokio::test]
async fn fifty_agents_clean_rollout_then_automatic_rollback() -> anyhow::Result<()> {
    let site = Site::new("rollout").await?;
    let _fleet = site.fleet(50, &[])?;
    site.wait_online(50).await?;

    let v1_dir = release_dir(site.dir.path(), 40, "1", &[])?;
    let v1 = site.push(&v1_dir, "1.0.0")?;
    let started = std::time::Instant::now();
    site.deploy("fleet", &v1, test_strategy(13, 1), LabelSelector::default())
        .await?;
    let d = site.finished("fleet", Duration::from_secs(180)).await?;
    let st = d.status.clone().unwrap();
    eprintln!(
        "v1 to 50 robots: {:?} in {:?}: {:?}",
        st.phase,
        started.elapsed(),
        st.message
    );
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    assert_eq!((st.updated, st.failed, st.targeted), (50, 0, 50));
    assert_eq!(st.total_batches, Some(5), "canary + 4 batches of 13");
    wait_for(
        "all robots report 1.0.0",
        Duration::from_secs(30),
        || async {
            let by = site.releases().await.ok()?;
            (by.get("1.0.0") == Some(&50)).then_some(())
        },
    )
    .await?;
    let full = site.bytes_served("kiwi-000").await?;
    let release_bytes: u64 = walk(&v1_dir)
        .iter()
        .map(|p| p.metadata().unwrap().len())
        .sum();
    eprintln!("first deploy: {full} bytes to kiwi-000 for a {release_bytes}-byte release");
    assert!(full >= release_bytes, "the first deploy fetches everything");

    // v2 changes 2 of 41 files. Robots 2, 5 and 8 (batch 1 of 10, after a canary of 1) fail
    // their health check: 70% < 80%.
    for i in [2, 5, 8] {
        std::fs::write(_fleet.state(&robot_name(i)).join("fail-health"), "")?;
    }
    let v2_dir = release_dir(site.dir.path(), 40, "2", &[4, 17])?;
    let v2 = site.push(&v2_dir, "2.0.0")?;
    let before: BTreeMap<usize, u64> = {
        let mut m = BTreeMap::new();
        for i in 0..11 {
            m.insert(i, site.bytes_served(&robot_name(i)).await?);
        }
        m
    };
    let patch = json!({"spec": {"release": v2, "strategy": {"batchSize": 10, "canary": 1}}});
    Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns)
        .patch("fleet", &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    let failing_batch = std::time::Instant::now();
    let d = site.finished("fleet", Duration::from_secs(180)).await?;
    let st = d.status.clone().unwrap();
    eprintln!(
        "v2: {:?} after {:?}: {:?}",
        st.phase,
        failing_batch.elapsed(),
        st.message
    );
    assert_eq!(st.phase, Some(RolloutPhase::RolledBack), "{:?}", st.message);
    let msg = st.message.clone().unwrap_or_default();
    assert!(msg.contains("3 of 10"), "{msg}");
    wait_for(
        "every robot back on 1.0.0",
        Duration::from_secs(60),
        || async {
            let by = site.releases().await.ok()?;
            (by.get("1.0.0") == Some(&50)).then_some(())
        },
    )
    .await?;
    // Nobody beyond batch 1 was touched.
    let robots = site.robots().await?;
    let touched = robots
        .iter()
        .filter(|r| r.spec.release.as_ref() == Some(&v2))
        .count();
    assert_eq!(touched, 0, "every robot's spec is back on 1.0.0");
    // Differential transfer: each updated robot fetched the manifest and the 2 changed files.
    let changed: u64 = [4usize, 17]
        .iter()
        .map(|i| {
            let sub = if i % 3 == 0 {
                "lekiwi/config"
            } else {
                "lekiwi"
            };
            std::fs::metadata(v2_dir.join(sub).join(format!("f{i:03}.py")))
                .unwrap()
                .len()
        })
        .sum();
    for (i, b) in &before {
        let delta = site.bytes_served(&robot_name(*i)).await? - b;
        eprintln!("kiwi-{i:03}: {delta} bytes for v2 ({changed} bytes of changed files)");
        assert!(
            delta >= changed && delta < changed + 16 * 1024,
            "kiwi-{i:03} fetched {delta} bytes; changed files are {changed} bytes"
        );
    }
    Ok(())
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// Robots of the crash test.
const CRASH_ROBOTS: usize = 50;

/// The operator is SIGKILLed mid-rollout and restarted; the agents are SIGKILLed mid-download
/// and mid-switch (restart command of 2 s) and come back; robots go offline and return. The
/// rollout completes, no robot that had finished is deployed again, and every robot's
/// `current` points at a complete release.
#[tokio::test]
async fn rollout_survives_operator_and_agent_crashes() -> anyhow::Result<()> {
    let mut site = Site::new("rollcrash").await?;
    let mut fleet = site.fleet(CRASH_ROBOTS, &["--restart-command", "sleep 2"])?;
    site.wait_online(CRASH_ROBOTS).await?;
    let v1_dir = release_dir(site.dir.path(), 30, "1", &[])?;
    let v1 = site.push(&v1_dir, "1.0.0")?;
    site.deploy("crash", &v1, test_strategy(10, 0), LabelSelector::default())
        .await?;

    // Kill the whole fleet while some robots are in their restart command (switched, not yet
    // confirmed) and others download.
    let store = site.op.event_store().await?;
    let restarting = wait_for("a robot restarting", Duration::from_secs(60), || async {
        for i in 0..CRASH_ROBOTS {
            let key = RobotKey::new(site.ns.clone(), robot_name(i));
            let events = store.events(&key, None, 1000).await.ok()?;
            if events.iter().any(|e| e.data["phase"] == "restarting") {
                return Some(robot_name(i));
            }
        }
        None
    })
    .await?;
    fleet.kill();
    eprintln!("fleet killed while {restarting} was restarting");
    tokio::time::sleep(Duration::from_secs(3)).await;
    fleet.restart()?;

    // Kill the operator once the second batch is under way.
    wait_for("batch 1 started", Duration::from_secs(120), || async {
        let d = site.deployment("crash").await.ok()?;
        (d.status?.current_batch? >= 1).then_some(())
    })
    .await?;
    site.op.kill();
    tokio::time::sleep(Duration::from_secs(2)).await;
    site.op.restart()?;
    site.op.wait_ready().await?;

    let t = std::time::Instant::now();
    let d = site.finished("crash", Duration::from_secs(240)).await?;
    eprintln!("finished after {:?}", t.elapsed());
    let st = d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    assert_eq!(st.updated, CRASH_ROBOTS as i32);
    // The restarted gateway forgot the update reports its predecessor wrote; its status writes
    // must still be accepted (Kubernetes 1.20 nulls the fields a manager stops sending).
    assert!(
        !site.op.log_text().contains("status write failed"),
        "{}",
        tail(&site.op.log_text())
    );
    wait_for(
        "all robots report 1.0.0",
        Duration::from_secs(60),
        || async {
            let by = site.releases().await.ok()?;
            (by.get("1.0.0") == Some(&CRASH_ROBOTS)).then_some(())
        },
    )
    .await?;
    eprintln!("all report 1.0.0 after {:?}", t.elapsed());
    for i in 0..CRASH_ROBOTS {
        let name = robot_name(i);
        // `current` points at a complete release.
        let current = std::fs::read_link(fleet.state(&name).join("current"))?;
        let dir = fleet.state(&name).join(&current);
        let meta: Value =
            serde_json::from_slice(&std::fs::read(dir.join(".lekiwi/release.json"))?)?;
        assert_eq!(meta["version"], "1.0.0", "{name}");
        assert_eq!(
            walk(&dir).len(),
            31 + 2,
            "{name}: every file plus the metadata"
        );
        // Every robot completed exactly one deploy: the crashes neither lost one (a robot
        // killed before its switch is told again) nor repeated one (a finished robot is never
        // started again by the new leader).
        let key = RobotKey::new(site.ns.clone(), name.clone());
        let done = store
            .events(&key, None, 10_000)
            .await?
            .iter()
            .filter(|e| e.kind == "progress" && e.data["phase"] == "done")
            .count();
        assert_eq!(done, 1, "{name}: deployed exactly once");
    }

    // After the restart the gateway numbers its sessions from 1 again: its commands must still
    // be new to agents that finished commands of the previous gateway process.
    let v2_dir = release_dir(site.dir.path(), 30, "2", &[3])?;
    let v2 = site.push(&v2_dir, "2.0.0")?;
    let patch = json!({"spec": {"release": v2}});
    Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns)
        .patch("crash", &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    let d = site.finished("crash", Duration::from_secs(120)).await?;
    let st = d.status.unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    assert_eq!(st.updated, CRASH_ROBOTS as i32);
    Ok(())
}

/// A teleoperated robot is waited for, never interrupted, and updated once idle; an invalid
/// release digest is reported clearly.
#[tokio::test]
async fn teleoperated_robot_is_waited_for_and_invalid_release_is_clear() -> anyhow::Result<()> {
    let site = Site::new("rollteleop").await?;
    // A real agent whose teleoperation indicator is a real ESTABLISHED connection on a port
    // held by a real process.
    let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
    let port = listener.local_addr()?.port();
    let state = site.dir.path().join("teleop-robot");
    let agent = AgentProcess::start(
        &gateway_url(&site.op),
        &format!("{}/kiwi-t", site.ns),
        &site.token_file,
        &state,
        &[
            "--teleop-command-ports",
            &port.to_string(),
            "--teleop-process-weight",
            "0",
            "--teleop-serial-weight",
            "0",
            "--teleop-video-weight",
            "0",
            "--teleop-stream-weight",
            "0",
            "--teleop-threshold",
            "0.5",
        ],
    )?;
    site.wait_online(1).await?;
    let client_conn = std::net::TcpStream::connect(("127.0.0.1", port))?;
    let (_server_conn, _) = listener.accept()?;
    let robots: Api<Robot> = Api::namespaced(site.client.clone(), &site.ns);
    wait_for("teleoperation seen", Duration::from_secs(20), || async {
        let r = robots.get("kiwi-t").await.ok()?;
        r.status?.teleoperation?.active.then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", agent.log_text()))?;

    let v1_dir = release_dir(site.dir.path(), 5, "1", &[])?;
    let v1 = site.push(&v1_dir, "1.0.0")?;
    site.deploy("teleop", &v1, test_strategy(1, 0), LabelSelector::default())
        .await?;
    tokio::time::sleep(Duration::from_secs(5)).await;
    let d = site.deployment("teleop").await?;
    let st = d.status.clone().unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Progressing));
    assert!(
        st.robots
            .iter()
            .any(|r| r.robot == "kiwi-t" && r.message.as_deref() == Some("waiting: teleoperated")),
        "{:?}",
        st.robots
    );
    let r = robots.get("kiwi-t").await?;
    assert_eq!(
        r.spec.release, None,
        "not told to switch while teleoperated"
    );

    // The operator goes home: the robot is updated.
    drop(client_conn);
    let d = site.finished("teleop", Duration::from_secs(60)).await?;
    assert_eq!(d.status.unwrap().phase, Some(RolloutPhase::Completed));
    let r = robots.get("kiwi-t").await?;
    assert_eq!(
        r.status.and_then(|s| s.current_release).map(|r| r.version),
        Some("1.0.0".into())
    );

    // A digest nobody pushed.
    let bogus = ReleaseRef {
        version: "9.9.9".into(),
        digest: format!("sha256:{}", "0".repeat(64)).into(),
    };
    site.deploy(
        "bogus",
        &bogus,
        test_strategy(1, 0),
        LabelSelector::default(),
    )
    .await?;
    let d = site.finished("bogus", Duration::from_secs(30)).await?;
    let st = d.status.unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Failed));
    let msg = st.message.unwrap_or_default();
    assert!(msg.contains("not found in the blob store"), "{msg}");
    let valid = st
        .conditions
        .iter()
        .find(|c| c.r#type == "ReleaseValid")
        .unwrap();
    assert_eq!(valid.reason, "InvalidRelease");
    drop(agent);
    Ok(())
}

/// Robots of the plugin test.
const CLI_ROBOTS: usize = 6;

/// `kubectl lekiwi rollout ...` steers a real rollout: `pause` holds it (robots updating finish,
/// no new one starts), `resume` lets it finish and `status` follows it to the end (exit 0);
/// `undo` takes every robot back to the release it ran before (`status` exits non-zero and
/// says so); `restart` rolls the release out again from the first batch.
#[tokio::test]
async fn the_plugin_pauses_resumes_undoes_and_restarts_a_rollout() -> anyhow::Result<()> {
    let site = Site::new("rollcli").await?;
    // A restart command of 1 s, so that one robot at a time takes a moment.
    let _fleet = site.fleet(CLI_ROBOTS, &["--restart-command", "sleep 1"])?;
    site.wait_online(CLI_ROBOTS).await?;
    let v1 = site.push(&release_dir(site.dir.path(), 5, "1", &[])?, "1.0.0")?;
    let v2 = site.push(&release_dir(site.dir.path(), 5, "2", &[2])?, "2.0.0")?;
    site.deploy("cli", &v1, test_strategy(1, 0), LabelSelector::default())
        .await?;
    let d = site.finished("cli", Duration::from_secs(120)).await?;
    assert_eq!(d.status.unwrap().phase, Some(RolloutPhase::Completed));

    let api = Api::<RobotDeployment>::namespaced(site.client.clone(), &site.ns);
    api.patch(
        "cli",
        &PatchParams::default(),
        &Patch::Merge(&json!({"spec": {"release": v2}})),
    )
    .await?;
    wait_for("the first v2 robot", Duration::from_secs(30), || async {
        let by = site.releases().await.ok()?;
        by.contains_key("2.0.0").then_some(())
    })
    .await?;
    let out = site.cli(&["rollout", "pause", "cli"])?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("paused"));
    wait_for("Paused", Duration::from_secs(20), || async {
        let st = site.deployment("cli").await.ok()?.status?;
        (st.phase == Some(RolloutPhase::Paused)).then_some(())
    })
    .await?;
    // The robot updating when the pause came finishes; then nothing moves.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let held = site.releases().await?;
    tokio::time::sleep(Duration::from_secs(4)).await;
    assert_eq!(site.releases().await?, held, "a robot started while paused");
    let on_v2 = held.get("2.0.0").copied().unwrap_or_default();
    assert!((1..CLI_ROBOTS).contains(&on_v2), "paused mid-way: {held:?}");
    let out = site.cli(&["rollout", "status", "cli", "--watch=false"])?;
    assert!(String::from_utf8_lossy(&out.stdout).contains("Paused"));

    let out = site.cli(&["rollout", "resume", "cli"])?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = site.cli(&["rollout", "status", "cli", "--timeout", "120"])?;
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("Completed"), "{text}");
    assert_eq!(
        site.releases().await?.get("2.0.0"),
        Some(&CLI_ROBOTS),
        "all on v2"
    );

    let out = site.cli(&["rollout", "undo", "cli"])?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let d = wait_for("RolledBack", Duration::from_secs(60), || async {
        let d = site.deployment("cli").await.ok()?;
        (d.status.as_ref()?.phase == Some(RolloutPhase::RolledBack)).then_some(d)
    })
    .await?;
    let message = d.status.unwrap().message.unwrap_or_default();
    assert!(message.contains("rollout undo"), "{message}");
    wait_for("all robots back on v1", Duration::from_secs(60), || async {
        let by = site.releases().await.ok()?;
        (by.get("1.0.0") == Some(&CLI_ROBOTS)).then_some(())
    })
    .await?;
    let out = site.cli(&["rollout", "status", "cli", "--timeout", "30"])?;
    assert!(
        !out.status.success(),
        "status exits non-zero after a rollback"
    );
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("rolled back"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let out = site.cli(&["rollout", "restart", "cli"])?;
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    wait_for("v2 rolled out again", Duration::from_secs(120), || async {
        let st = site.deployment("cli").await.ok()?.status?;
        let by = site.releases().await.ok()?;
        (st.phase == Some(RolloutPhase::Completed) && by.get("2.0.0") == Some(&CLI_ROBOTS))
            .then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", tail(&site.op.log_text())))?;

    // A rollout that does not exist is a clear error.
    let out = site.cli(&["rollout", "pause", "nope"])?;
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("not found"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    Ok(())
}

impl Site {
    /// Starts a plugin command that runs until killed (`-w`) and the lines it prints.
    fn follow(
        &self,
        args: &[&str],
    ) -> anyhow::Result<(std::process::Child, std::sync::mpsc::Receiver<String>)> {
        let mut child = Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(self.cp.kubeconfig())
            .args(["-n", &self.ns])
            .args(args)
            .stdout(std::process::Stdio::piped())
            .spawn()?;
        let stdout = child.stdout.take().expect("piped");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            use std::io::BufRead as _;
            for line in std::io::BufReader::new(stdout)
                .lines()
                .map_while(Result::ok)
            {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Ok((child, rx))
    }
}

/// The text a command printed, with its error output when it failed.
fn stdout_of(out: &std::process::Output) -> anyhow::Result<String> {
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    if !out.status.success() {
        bail!("{text}{}", String::from_utf8_lossy(&out.stderr));
    }
    Ok(text)
}

/// What an Argo Rollouts user reaches for, against a real operator and agents: `rollout list`
/// (table, `-o json` as a `List`, `-o name`, `-l`), `set-release` (with `--digest`, and by
/// version looked up from the releases the namespace knows), `abort` (no robot starts after it,
/// switched robots keep the new release, the phase says `Aborted`, `status` exits non-zero),
/// `get` (batches and robots as a tree) and `get -w` following a restart to its end.
#[tokio::test]
async fn the_plugin_lists_gets_sets_the_release_of_and_aborts_a_rollout() -> anyhow::Result<()> {
    let site = Site::new("rollabort").await?;
    let _fleet = site.fleet(CLI_ROBOTS, &["--restart-command", "sleep 1"])?;
    site.wait_online(CLI_ROBOTS).await?;
    let v1 = site.push(&release_dir(site.dir.path(), 5, "1", &[])?, "1.0.0")?;
    let v2 = site.push(&release_dir(site.dir.path(), 5, "2", &[2])?, "2.0.0")?;
    site.deploy("cli", &v1, test_strategy(1, 0), LabelSelector::default())
        .await?;
    site.finished("cli", Duration::from_secs(120)).await?;

    let table = stdout_of(&site.cli(&["rollout", "list"])?)?;
    let row: Vec<&str> = table
        .lines()
        .nth(1)
        .unwrap_or_default()
        .split_whitespace()
        .collect();
    assert_eq!(
        row[..5],
        ["cli", "Completed", "1.0.0", "6/6", "0"],
        "{table}"
    );
    let json = stdout_of(&site.cli(&["rollout", "list", "-o", "json"])?)?;
    let items: Vec<RobotDeployment> = lekiwi_tests::list_items(&json)?;
    assert_eq!(items.len(), 1, "{json}");
    let names = stdout_of(&site.cli(&["rollout", "list", "-o", "name"])?)?;
    assert_eq!(names, "robotdeployment.fleet.lekiwi.io/cli\n");
    let none = stdout_of(&site.cli(&["rollout", "list", "-l", "tier=none", "-o", "json"])?)?;
    assert!(
        lekiwi_tests::list_items::<Value>(&none)?.is_empty(),
        "{none}"
    );

    // 2.0.0 is named by no robot or rollout yet and this gateway lists no releases: the
    // lookup says to pass --digest.
    let out = site.cli(&["rollout", "set-release", "cli", "--version", "2.0.0"])?;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--digest"), "{err}");
    let digest = v2.digest.to_string();
    let set = [
        "rollout",
        "set-release",
        "cli",
        "--version",
        "2.0.0",
        "--digest",
        &digest,
    ];
    assert!(stdout_of(&site.cli(&set)?)?.contains("release set to 2.0.0"));
    wait_for("the first v2 robot", Duration::from_secs(60), || async {
        let by = site.releases().await.ok()?;
        by.contains_key("2.0.0").then_some(())
    })
    .await?;

    // The phase Aborted is new: test runs from other checkouts re-apply their CRDs to the
    // shared control plane, so ours are applied again right before it is needed.
    site.cp.install_crds()?;
    let (mut listing, rows) = site.follow(&["rollout", "list", "-w", "--no-headers"])?;
    let out = stdout_of(&site.cli(&["rollout", "abort", "cli"])?)?;
    assert_eq!(out, "robotdeployment/cli aborted\n");
    // `list -w` prints the rollout again when it changes.
    let aborted = wait_for(
        "list -w to show Aborted",
        Duration::from_secs(20),
        || async {
            rows.try_iter()
                .find(|l| l.starts_with("cli") && l.contains("Aborted"))
        },
    )
    .await;
    listing.kill()?;
    listing.wait()?;
    aborted?;
    let d = wait_for("Aborted", Duration::from_secs(20), || async {
        let d = site.deployment("cli").await.ok()?;
        (d.status.as_ref()?.phase == Some(RolloutPhase::Aborted)).then_some(d)
    })
    .await?;
    let message = d.status.and_then(|s| s.message).unwrap_or_default();
    assert!(message.contains("rollout abort"), "{message}");
    // A robot switching when the abort came may still finish its switch; then nothing moves.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let held = site.releases().await?;
    tokio::time::sleep(Duration::from_secs(6)).await;
    assert_eq!(
        site.releases().await?,
        held,
        "a robot moved after the abort"
    );
    let on_v2 = held.get("2.0.0").copied().unwrap_or_default();
    assert!(
        (1..CLI_ROBOTS).contains(&on_v2),
        "aborted mid-way: {held:?}"
    );

    let tree = stdout_of(&site.cli(&["rollout", "get", "cli"])?)?;
    assert!(tree.contains("Phase:     Aborted"), "{tree}");
    assert!(
        tree.contains("├──# batch 0") && tree.contains("└──kiwi-000"),
        "{tree}"
    );
    let out = site.cli(&["rollout", "status", "cli", "--timeout", "10s"])?;
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("rollout aborted"),
        "{err}"
    );

    // `get -w` follows a restart live to its end.
    let (mut follow, rx) = site.follow(&["rollout", "get", "cli", "-w"])?;
    stdout_of(&site.cli(&["rollout", "restart", "cli"])?)?;
    let seen = wait_for(
        "get -w to show Completed",
        Duration::from_secs(120),
        || async {
            let lines: Vec<String> = rx.try_iter().collect();
            lines
                .iter()
                .any(|l| l.contains("Phase:     Completed"))
                .then_some(())
        },
    )
    .await;
    follow.kill()?;
    follow.wait()?;
    seen?;
    assert_eq!(site.releases().await?.get("2.0.0"), Some(&CLI_ROBOTS));

    // By version: 1.0.0's digest is known from the robots' previous rollout.
    let gateway = gateway_url(&site.op);
    let back = [
        "rollout",
        "set-release",
        "cli",
        "--version",
        "1.0.0",
        "--server",
        &gateway,
    ];
    assert!(stdout_of(&site.cli(&back)?)?.contains(&*v1.digest));
    let d = site.finished("cli", Duration::from_secs(120)).await?;
    assert_eq!(
        d.status.and_then(|s| s.phase),
        Some(RolloutPhase::Completed)
    );
    assert_eq!(site.releases().await?.get("1.0.0"), Some(&CLI_ROBOTS));
    Ok(())
}

/// Robots of the write-cost guard.
const COST_ROBOTS: usize = 40;

/// Writes of `resources` in `by`.
fn sum_of(by: &BTreeMap<String, f64>, resources: &[&str]) -> f64 {
    resources.iter().filter_map(|k| by.get(*k)).sum()
}

/// The difference `after - before`, by resource, without the zeros.
fn delta(before: &BTreeMap<String, f64>, after: &BTreeMap<String, f64>) -> BTreeMap<String, f64> {
    let mut d = BTreeMap::new();
    for (k, v) in after {
        let n = v - before.get(k).copied().unwrap_or(0.0);
        if n > 0.0 {
            d.insert(k.clone(), n);
        }
    }
    d
}

/// Issue 44: a rollout over a few dozen real agents (canary 1, batches of 25%) costs the API
/// server at most 2 Robot writes per robot updated (the rollout's write of its spec and mark,
/// the gateway's status write of the outcome), and the deployment's status is written at a
/// bounded rate however many robots move: counted by the API server itself on a control plane
/// of the test's own, less the steady rate of the same fleet measured just before, so that the
/// cost of a rollout cannot creep up again unnoticed.
#[tokio::test]
async fn a_rollout_costs_at_most_two_api_writes_per_robot() -> anyhow::Result<()> {
    const QUIET: Duration = Duration::from_secs(15);
    const ROBOT: [&str; 2] = ["robots", "robots/status"];
    let cp = lekiwi_tests::ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = lekiwi_tests::namespace(&client, "rollcost").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let blob_dir = blobs.to_str().expect("a UTF-8 temp path");
    // Routine refreshes rarer than the test is long: what is counted is the rollout's.
    let flags = ["--blob-dir", blob_dir, "--status-refresh-seconds", "600"];
    let op = lekiwi_tests::gateway_operator(&cp, &ns, "rollcost", &flags).await?;
    let token_file = dir.path().join("enroll");
    lekiwi_tests::enrollment_token_file(&client, &ns, &token_file).await?;
    let _fleet = FleetProcess::start(FleetSpec {
        gateway: &gateway_url(&op),
        token_file: &token_file,
        namespace: &ns,
        robots: COST_ROBOTS,
        state_root: &dir.path().join("robots"),
        health_command: "true",
        report_every: "2",
        rust_log: "warn",
        extra: &[],
    })?;
    wait_online(&client, &ns, COST_ROBOTS, Duration::from_secs(120)).await?;
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let v1_dir = release_dir(dir.path(), 10, "1", &[])?;
    let v1 = lekiwi_tests::push_release(&cp.kubeconfig(), &ns, &server, None, &v1_dir, "1.0.0")?;

    // The fleet's steady Robot writes, just before.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let start = cp.writes()?;
    tokio::time::sleep(QUIET).await;
    let quiet = delta(&start, &cp.writes()?);
    let rate = sum_of(&quiet, &ROBOT) / QUIET.as_secs_f64();

    let before = cp.writes()?;
    let t = std::time::Instant::now();
    let deployments = Api::<RobotDeployment>::namespaced(client.clone(), &ns);
    let strategy = RolloutStrategy {
        batch_size: k8s_openapi::apimachinery::pkg::util::intstr::IntOrString::String("25%".into()),
        ..test_strategy(0, 1)
    };
    let d = RobotDeployment::new(
        "fleet",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(v1.clone()),
            agent: None,
            strategy,
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    deployments.create(&PostParams::default(), &d).await?;
    let d = rollout_finished(&deployments, "fleet", Duration::from_secs(180))
        .await
        .map_err(|e| anyhow::anyhow!("{e}\noperator log tail:\n{}", tail(&op.log_text())))?;
    let st = d.status.unwrap();
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{:?}", st.message);
    assert_eq!(st.updated, COST_ROBOTS as i32);
    let batches = f64::from(st.total_batches.unwrap_or_default());
    // Writes that trail the completion belong to the rollout too.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let spent = t.elapsed().as_secs_f64();
    let during = delta(&before, &cp.writes()?);
    let background = rate * spent;
    let robot = (sum_of(&during, &ROBOT) - background) / COST_ROBOTS as f64;
    let status = sum_of(&during, &["robotdeployments/status"]);
    let total = robot + status / COST_ROBOTS as f64;
    eprintln!(
        "rollout of {COST_ROBOTS} robots in {batches} batches, {spent:.1} s: {during:?}; \
         background {rate:.2}/s ({quiet:?} in {QUIET:?}); {robot:.2} Robot writes per robot, \
         {status} deployment status writes; {total:.2} writes per robot in all"
    );
    // Two each; an agent's health report after its switch may land after the outcome's write
    // and cost one more (a change of health is written), for a few robots in 40.
    assert!(
        robot <= 2.05,
        "{robot:.2} Robot writes per robot updated (goal <= 2): {during:?} in {spent:.1} s, \
         less {background:.1} of background ({quiet:?} in {QUIET:?})"
    );
    // A write per batch start and end, and at most one per 3 s (the status period) between.
    let bound = 2.0 * batches + spent / 3.0 + 3.0;
    assert!(
        status <= bound,
        "{status} status writes of the deployment (goal <= {bound:.0}: {batches} batches, \
         {spent:.1} s)"
    );
    Ok(())
}
