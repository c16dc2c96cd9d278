//! `lekiwi-sim` against the real operator (controller and gateway) on the real control plane:
//! its robots carry out rollouts frame for frame as a real `lekiwi-agent` does. One agent and
//! three simulated robots take the same five rollouts side by side, and the progress each sends
//! (as the gateway stored it) is compared command by command: a first release, one changing a
//! file (the same bytes fetched, only the changed file), one whose health check fails
//! (rolled back), one cancelled mid-download (`rollout undo`), and one the simulated robots
//! break off by going offline (a failed command, then the retry, resumed). A second test rolls
//! an agent build out to simulated robots and back; a third freezes the agent and the
//! simulated robots mid-deploy (as the soak's cut-off does) and checks they take the next
//! rollout once thawed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use anyhow::bail;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::Api;
use kube::api::{Patch, PatchParams, PostParams};
use lekiwi_core::RobotKey;
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{AgentArch, AgentBuild, AgentRef, ReleaseRef, Robot, RobotDeployment};
use lekiwi_crds::{RobotDeploymentSpec, RobotDeploymentStatus};
use lekiwi_tests::{
    AgentProcess, OperatorSite, SimProcess, SimSpec, bin, gateway_url, http_get_with, push_agent,
    rollout_finished, test_strategy, wait_for, wait_online,
};
use serde_json::{Value, json};

const HEALTH: &str = r#"test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health""#;
/// The real agent's robot.
const AGENT: &str = "kiwi-0";
/// Simulated robots.
const SIMS: usize = 3;
/// The real agent's download rate: the big release of the cancel takes 12 s.
const RATE: &str = "2000000";
const DEPLOYMENT: &str = "cmp";
/// Final phases of a command.
const FINAL: [&str; 4] = ["done", "failed", "rolled_back", "cancelled"];

/// The phases of each command a robot reported, in the order the commands began.
type Commands = Vec<Vec<String>>;

/// A namespace with an operator, one real agent and `SIMS` simulated robots.
struct Site {
    base: OperatorSite,
    agent: AgentProcess,
    sim: SimProcess,
}

lekiwi_tests::deref_to_operator_site!(Site);

impl Site {
    async fn new(prefix: &str, sim_flags: &[&str]) -> anyhow::Result<Self> {
        let base = OperatorSite::start(prefix).await?;
        let (dir, ns, op, token_file) = (&base.dir, &base.ns, &base.op, &base.token_file);
        let state = dir.path().join(AGENT);
        std::fs::create_dir_all(&state)?;
        let hooks = [
            "--release-pre-switch-command",
            "true",
            "--release-restart-command",
            "true",
            "--release-health-command",
            HEALTH,
            "--release-health-timeout-s",
            "2",
            "--release-download-rate-limit",
            RATE,
        ];
        let agent = AgentProcess::start(
            &gateway_url(op),
            &format!("{ns}/{AGENT}"),
            token_file,
            &state,
            &hooks,
        )?;
        let sim = SimProcess::start(
            SimSpec {
                gateway: &gateway_url(op),
                token_file,
                namespace: ns,
                robots: SIMS,
                prefix: "sim",
                extra: sim_flags,
            },
            dir.path(),
        )?;
        wait_online(&base.client, ns, SIMS + 1, Duration::from_secs(120)).await?;
        Ok(Self { base, agent, sim })
    }

    fn robots() -> Vec<String> {
        std::iter::once(AGENT.to_owned())
            .chain((1..=SIMS).map(|i| format!("sim-{i:05}")))
            .collect()
    }

    fn deployments(&self) -> Api<RobotDeployment> {
        Api::namespaced(self.client.clone(), &self.ns)
    }

    /// Starts rolling `release` out to every robot in one batch (creating the deployment the
    /// first time).
    async fn roll_out(&self, release: &ReleaseRef) -> anyhow::Result<()> {
        let api = self.deployments();
        if api.get_opt(DEPLOYMENT).await?.is_none() {
            let d = RobotDeployment::new(
                DEPLOYMENT,
                RobotDeploymentSpec {
                    selector: LabelSelector::default(),
                    release: Some(release.clone()),
                    agent: None,
                    strategy: test_strategy(SIMS as i32 + 1, 0),
                    paused: false,
                    analysis: None,
                    priority: 0,
                },
            );
            api.create(&PostParams::default(), &d).await?;
        } else {
            let patch = json!({"spec": {"release": release}});
            api.patch(DEPLOYMENT, &PatchParams::default(), &Patch::Merge(&patch))
                .await?;
        }
        Ok(())
    }

    /// Waits for the rollout's end; its status.
    async fn finished(&self) -> anyhow::Result<RobotDeploymentStatus> {
        let d = rollout_finished(&self.deployments(), DEPLOYMENT, Duration::from_secs(120))
            .await
            .map_err(|e| anyhow::anyhow!("{e}\nsim log:\n{}", tail(&self.sim.log_text())))?;
        Ok(d.status.unwrap_or_default())
    }

    /// The highest seq the gateway stored of each robot.
    async fn marks(&self) -> anyhow::Result<BTreeMap<String, u64>> {
        let store = self.op.event_store().await?;
        let mut marks = BTreeMap::new();
        for robot in Self::robots() {
            let key = RobotKey::new(self.ns.clone(), robot.clone());
            let last = store
                .events(&key, None, 100_000)
                .await?
                .last()
                .map(|e| e.seq);
            marks.insert(robot, last.unwrap_or(0));
        }
        Ok(marks)
    }

    /// Each robot's commands reported after `marks`: the phases of each (consecutive repeats,
    /// download percentages, merged), and the messages.
    async fn commands(
        &self,
        marks: &BTreeMap<String, u64>,
    ) -> anyhow::Result<BTreeMap<String, (Commands, Vec<String>)>> {
        let store = self.op.event_store().await?;
        let mut out = BTreeMap::new();
        for (robot, after) in marks {
            let key = RobotKey::new(self.ns.clone(), robot.clone());
            let mut ids: Vec<String> = Vec::new();
            let mut phases: Commands = Vec::new();
            let mut messages = Vec::new();
            for e in store.events(&key, Some(*after), 100_000).await? {
                if e.kind != "progress" {
                    continue;
                }
                let id = e.data["command_id"].as_str().unwrap_or_default().to_owned();
                let phase = e.data["phase"].as_str().unwrap_or_default().to_owned();
                let i = ids.iter().position(|x| *x == id).unwrap_or_else(|| {
                    ids.push(id);
                    phases.push(Vec::new());
                    ids.len() - 1
                });
                if phases[i].last() != Some(&phase) {
                    phases[i].push(phase);
                }
                messages.push(e.message);
            }
            out.insert(robot.clone(), (phases, messages));
        }
        Ok(out)
    }

    /// Waits until every robot reported `at_least` commands since `marks`, each to its end,
    /// and asserts the simulated robots' phases equal the agent's (or `sims` when given); the
    /// agent's.
    async fn same_frames(
        &self,
        what: &str,
        marks: &BTreeMap<String, u64>,
        sims: Option<&[&[&str]]>,
    ) -> anyhow::Result<Commands> {
        let all = wait_for(
            &format!("{what}: every command ended"),
            Duration::from_secs(60),
            || async {
                let all = self.commands(marks).await.ok()?;
                let ended = all.values().all(|(cmds, _)| {
                    !cmds.is_empty()
                        && cmds
                            .iter()
                            .all(|c| c.last().is_some_and(|p| FINAL.contains(&p.as_str())))
                });
                ended.then_some(all)
            },
        )
        .await?;
        let (agent, agent_messages) = all[AGENT].clone();
        for (robot, (cmds, messages)) in &all {
            let want: Commands = match sims {
                Some(s) if robot != AGENT => s
                    .iter()
                    .map(|c| c.iter().map(|p| p.to_string()).collect())
                    .collect(),
                _ => agent.clone(),
            };
            if *cmds != want {
                bail!(
                    "{what}: {robot} reported {cmds:?}, want {want:?}\n{robot}: {messages:#?}\n{AGENT}: {agent_messages:#?}"
                );
            }
        }
        eprintln!("{what}: every robot reported {agent:?}");
        Ok(agent)
    }

    /// Bytes the gateway served to each robot so far.
    async fn served(&self) -> anyhow::Result<BTreeMap<String, u64>> {
        let token = self.cp.admin_token()?;
        let mut out = BTreeMap::new();
        for robot in Self::robots() {
            let path = format!("/v1/blobs-served?robot={}/{robot}", self.ns);
            let auth = format!("Bearer {token}");
            let (code, _, body) =
                http_get_with(self.op.gateway_port, &path, &[("authorization", &auth)]).await?;
            anyhow::ensure!(code == 200, "blobs-served answered {code}: {body}");
            let v: Value = serde_json::from_str(&body)?;
            out.insert(robot, v["bytes"].as_u64().unwrap_or_default());
        }
        Ok(out)
    }

    /// The release each robot reports.
    async fn releases(&self) -> anyhow::Result<BTreeMap<String, String>> {
        let robots = Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .list(&Default::default())
            .await?;
        Ok(robots
            .items
            .into_iter()
            .map(|r| {
                let v = r
                    .status
                    .and_then(|s| s.current_release)
                    .map(|c| c.version.to_string());
                (r.metadata.name.unwrap_or_default(), v.unwrap_or_default())
            })
            .collect())
    }

    /// Waits until every robot reports `version`.
    async fn all_on(&self, version: &str) -> anyhow::Result<()> {
        wait_for(
            &format!("every robot on {version}"),
            Duration::from_secs(60),
            || async {
                let by = self.releases().await.ok()?;
                (by.len() == SIMS + 1 && by.values().all(|v| v == version)).then_some(())
            },
        )
        .await
    }

    /// `kubectl lekiwi rollout <verb>`, which must succeed.
    fn rollout(&self, verb: &str) -> anyhow::Result<()> {
        let out = Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(self.cp.kubeconfig())
            .args(["-n", &self.ns, "rollout", verb, DEPLOYMENT])
            .env_remove("LEKIWI_SERVER")
            .output()?;
        if !out.status.success() {
            bail!("rollout {verb}: {}", String::from_utf8_lossy(&out.stderr));
        }
        Ok(())
    }
}

fn tail(s: &str) -> String {
    let lines: Vec<&str> = s.lines().collect();
    lines[lines.len().saturating_sub(30)..].join("\n")
}

/// A release directory `tag`: 6 small files, those in `changed` different, plus `big` bytes
/// of checkpoint when not 0.
fn release_dir(root: &Path, tag: &str, changed: &[usize], big: usize) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi"))?;
    for i in 0..6 {
        let content = if changed.contains(&i) {
            format!("file {i} of release {tag}\n").repeat(400)
        } else {
            format!("file {i}\n").repeat(400)
        };
        std::fs::write(dir.join("lekiwi").join(format!("f{i}.py")), content)?;
    }
    if big > 0 {
        let bytes: Vec<u8> = (0..big)
            .map(|i| (i * 7 % 251) as u8 ^ tag.as_bytes()[0])
            .collect();
        std::fs::write(dir.join("checkpoint.safetensors"), bytes)?;
    }
    Ok(dir)
}

/// The five rollouts, agent and simulated robots side by side; see the module docs.
#[tokio::test]
async fn simulated_robots_report_the_frames_a_real_agent_reports() -> anyhow::Result<()> {
    let sim_flags = [
        "--release-version",
        "",
        "--health-timeout-seconds",
        "2",
        "--fail-health-share",
        "1",
        "--fail-health-versions",
        "3.0.0",
        "--timeout-share",
        "1",
        "--timeout-versions",
        "4.0.0",
        "--offline-mid-download-share",
        "1",
        "--offline-mid-download-versions",
        "5.0.0",
        "--offline-seconds",
        "2",
    ];
    let mut site = Site::new("simcmd", &sim_flags).await?;
    let root = site.dir.path().to_owned();
    let full = [
        "downloading",
        "verifying",
        "assembling",
        "pre_switch",
        "switching",
        "restarting",
        "health_check",
        "done",
    ];

    // 1.0.0 everywhere, then 2.0.0, which changes one file: the same frames and the same
    // bytes for the agent and the simulated robots.
    let mut served = site.served().await?;
    for (tag, version, changed) in [("1", "1.0.0", &[][..]), ("2", "2.0.0", &[2][..])] {
        let release = site.push(&release_dir(&root, tag, changed, 0)?, version)?;
        let marks = site.marks().await?;
        site.roll_out(&release).await?;
        let st = site.finished().await?;
        assert_eq!(
            st.phase,
            Some(RolloutPhase::Completed),
            "{version}: {st:#?}"
        );
        let agent = site.same_frames(version, &marks, None).await?;
        assert_eq!(agent, [full.map(String::from).to_vec()]);
        let now = site.served().await?;
        let fetched: BTreeMap<&String, u64> = now.iter().map(|(r, b)| (r, b - served[r])).collect();
        eprintln!("{version}: bytes served {fetched:?}");
        assert!(
            fetched.values().all(|b| *b == fetched[&AGENT.to_owned()]),
            "{version}: every robot fetched what the agent fetched: {fetched:?}"
        );
        served = now;
        site.all_on(version).await?;
    }

    // 3.0.0 fails every robot's health check: each switches back by itself, the rollout is
    // rolled back, everyone is on 2.0.0.
    std::fs::write(site.agent.state_dir.join("fail-health"), "")?;
    let v3 = site.push(&release_dir(&root, "3", &[3], 0)?, "3.0.0")?;
    let marks = site.marks().await?;
    site.roll_out(&v3).await?;
    let st = site.finished().await?;
    assert_eq!(st.phase, Some(RolloutPhase::RolledBack), "{st:#?}");
    let agent = site.same_frames("3.0.0", &marks, None).await?;
    let mut rolled_back = full[..7].to_vec();
    rolled_back.extend(["switching", "restarting", "rolled_back"]);
    assert_eq!(
        agent,
        [rolled_back
            .iter()
            .map(|p| p.to_string())
            .collect::<Vec<_>>()]
    );
    site.all_on("2.0.0").await?;
    std::fs::remove_file(site.agent.state_dir.join("fail-health"))?;

    // 4.0.0 is big: `rollout undo` while every robot downloads it (the agent slowly, the
    // simulated robots stalled) cancels each download, and the cancel is done.
    let v4 = site.push(&release_dir(&root, "4", &[4], 24 * 1024 * 1024)?, "4.0.0")?;
    let marks = site.marks().await?;
    site.roll_out(&v4).await?;
    wait_for(
        "every robot downloading 4.0.0",
        Duration::from_secs(60),
        || async {
            let all = site.commands(&marks).await.ok()?;
            let downloading = all
                .values()
                .all(|(_, messages)| messages.iter().any(|m| m.starts_with("downloading ")));
            (all.len() == SIMS + 1 && downloading).then_some(())
        },
    )
    .await?;
    site.rollout("undo")?;
    let agent = site.same_frames("4.0.0 undone", &marks, None).await?;
    assert_eq!(agent, [vec!["downloading", "cancelled"], vec!["done"]]);
    site.all_on("2.0.0").await?;

    // 5.0.0: the simulated robots go offline halfway through the download; back, they are
    // told again and finish what they had begun.
    let v5 = site.push(&release_dir(&root, "5", &[5], 2 * 1024 * 1024)?, "5.0.0")?;
    let marks = site.marks().await?;
    site.roll_out(&v5).await?;
    let st = site.finished().await?;
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "{st:#?}");
    let offline: [&[&str]; 2] = [&["downloading", "failed"], &full];
    let agent = site.same_frames("5.0.0", &marks, Some(&offline)).await?;
    assert_eq!(agent, [full.map(String::from).to_vec()]);
    site.all_on("5.0.0").await?;

    let summary = site.sim.stop()?;
    eprintln!("lekiwi-sim summary: {summary:#}");
    let n = SIMS as u64;
    for (field, want) in [
        ("deploys_done", 3 * n),
        ("deploys_rolled_back", n),
        ("deploys_cancelled", n),
        ("deploys_failed", n),
    ] {
        assert_eq!(summary[field], want, "{field}: {summary:#}");
    }
    assert!(
        summary["bytes_downloaded"].as_u64() > Some(2 * 1024 * 1024),
        "{summary:#}"
    );
    Ok(())
}

/// Each simulated robot's agent version and update phase, from its status.
async fn agent_states(
    robots: &Api<Robot>,
) -> anyhow::Result<BTreeMap<String, (String, Option<String>)>> {
    Ok(robots
        .list(&Default::default())
        .await?
        .items
        .into_iter()
        .map(|r| {
            let name = r.metadata.name.clone().unwrap_or_default();
            let st = r.status.unwrap_or_default();
            let version = st.agent_version.map(|v| v.to_string()).unwrap_or_default();
            (name, (version, st.agent_update.and_then(|u| u.phase)))
        })
        .collect())
}

/// An agent rollout over simulated robots: each downloads the build, restarts as it, and its
/// update ends `Succeeded`; the rollout back to the build they ran before (which no blob store
/// holds) switches each without a download.
#[tokio::test]
async fn simulated_robots_update_their_agent_and_go_back() -> anyhow::Result<()> {
    let site = OperatorSite::start("simagent").await?;
    let spec = SimSpec {
        gateway: &gateway_url(&site.op),
        token_file: &site.token_file,
        namespace: &site.ns,
        robots: SIMS,
        prefix: "sim",
        extra: &[],
    };
    let mut sim = SimProcess::start(spec, site.dir.path())?;
    wait_online(&site.client, &site.ns, SIMS, Duration::from_secs(120)).await?;
    let robots: Api<Robot> = Api::namespaced(site.client.clone(), &site.ns);
    let first = robots.get("sim-00001").await?.status.unwrap_or_default();
    let (a_version, a_digest) = (
        first
            .agent_version
            .map(|v| v.to_string())
            .unwrap_or_default(),
        first
            .agent_digest
            .map(|d| d.to_string())
            .unwrap_or_default(),
    );
    assert!(
        a_version.starts_with("sim-") && a_digest.starts_with("sha256:"),
        "{a_version} {a_digest}"
    );
    let build = site.dir.path().join("agent-b");
    std::fs::write(&build, b"#!/bin/sh\necho agent B\n".repeat(2000))?;
    let server = format!("http://127.0.0.1:{}", site.op.gateway_port);
    let b_digest = push_agent(
        &site.cp.kubeconfig(),
        &site.ns,
        &server,
        None,
        &build,
        "9.0.0",
        "arm64",
    )?;
    let agent = |version: &str, digest: &str| AgentRef {
        version: version.to_owned(),
        builds: vec![AgentBuild {
            arch: AgentArch::Arm64,
            digest: digest.to_owned(),
        }],
    };
    let api: Api<RobotDeployment> = Api::namespaced(site.client.clone(), &site.ns);
    let d = RobotDeployment::new(
        "agents",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: None,
            agent: Some(agent("9.0.0", &b_digest)),
            strategy: test_strategy(SIMS as i32, 0),
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    api.create(&PostParams::default(), &d).await?;
    let store = site.op.event_store().await?;
    // To B, then back to the build before by `rollout undo` (from the robots' own "disk").
    for (version, digest, bytes, want) in [
        (
            "9.0.0",
            b_digest.as_str(),
            std::fs::metadata(&build)?.len(),
            RolloutPhase::Completed,
        ),
        (
            a_version.as_str(),
            a_digest.as_str(),
            0,
            RolloutPhase::RolledBack,
        ),
    ] {
        if want == RolloutPhase::RolledBack {
            let out = Command::new(bin("kubectl-lekiwi"))
                .arg("--kubeconfig")
                .arg(site.cp.kubeconfig())
                .args(["-n", &site.ns, "rollout", "undo", "agents"])
                .env_remove("LEKIWI_SERVER")
                .output()?;
            anyhow::ensure!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        wait_for(
            &format!("agents {want:?}"),
            Duration::from_secs(120),
            || async {
                let st = api.get("agents").await.ok()?.status?;
                (st.phase == Some(want)).then_some(())
            },
        )
        .await?;
        wait_for(
            &format!("every robot's update to {version} Succeeded"),
            Duration::from_secs(60),
            || async {
                let states = agent_states(&robots).await.ok()?;
                states
                    .values()
                    .all(|(v, p)| v == version && p.as_deref() == Some("Succeeded"))
                    .then_some(())
            },
        )
        .await?;
        for r in robots.list(&Default::default()).await?.items {
            let reported = r.status.and_then(|s| s.agent_digest).map(|d| d.to_string());
            assert_eq!(reported.as_deref(), Some(digest), "{:?}", r.metadata.name);
        }
        let states = agent_states(&robots).await?;
        for (name, (running, phase)) in &states {
            assert_eq!(running, version, "{name}: {states:?}");
            assert_eq!(phase.as_deref(), Some("Succeeded"), "{name}: {states:?}");
            let key = RobotKey::new(site.ns.clone(), name.clone());
            let events = store.events(&key, None, 10_000).await?;
            let started = events
                .iter()
                .rev()
                .find(|e| e.kind == "agent_update_started")
                .map(|e| e.data.clone())
                .unwrap_or_default();
            assert_eq!(started["version"], version, "{name}: {started}");
            assert_eq!(started["bytes"], bytes, "{name}: {started}");
        }
        eprintln!("agent {version}: every simulated robot updated ({bytes} bytes each)");
    }
    let summary = sim.stop()?;
    assert_eq!(summary["agent_updates"], 2 * SIMS as u64, "{summary:#}");
    Ok(())
}

/// Sends `signal` (`STOP`, `CONT`) to each process.
fn signal(signal: &str, pids: &[u32]) -> anyhow::Result<()> {
    for pid in pids {
        let ok = Command::new("kill")
            .args([format!("-{signal}"), pid.to_string()])
            .status()?
            .success();
        anyhow::ensure!(ok, "kill -{signal} {pid} failed");
    }
    Ok(())
}

/// Robots frozen in the middle of a deploy (SIGSTOP, as the soak's cut-off does) for longer
/// than the heartbeat grace and the rollout's robot timeout: the gateway drops their
/// sessions and the rollout rolls back without them. Thawed, each finishes or abandons what
/// it was doing, follows the rollback, and takes the next rollout like any robot.
#[tokio::test]
async fn robots_frozen_mid_deploy_take_the_next_rollout() -> anyhow::Result<()> {
    let sim_flags = ["--release-version", "", "--health-check-seconds", "30"];
    let site = Site::new("simfrz", &sim_flags).await?;
    let root = site.dir.path().to_owned();
    let v1 = site.push(&release_dir(&root, "1", &[], 0)?, "1.0.0")?;
    site.roll_out(&v1).await?;
    let st = site.finished().await?;
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "1.0.0: {st:#?}");
    site.all_on("1.0.0").await?;

    // 2.0.0: the agent is downloading it (slowly), the simulated robots check its health.
    let v2 = site.push(&release_dir(&root, "2", &[2], 24 * 1024 * 1024)?, "2.0.0")?;
    let marks = site.marks().await?;
    site.roll_out(&v2).await?;
    wait_for(
        "the agent downloading 2.0.0 and the simulated robots checking its health",
        Duration::from_secs(60),
        || async {
            let all = site.commands(&marks).await.ok()?;
            let at = |robot: &str, phase: &str| {
                all.get(robot)
                    .is_some_and(|(cmds, _)| cmds.iter().any(|c| c.iter().any(|p| p == phase)))
            };
            let sims = (1..=SIMS).all(|i| at(&format!("sim-{i:05}"), "health_check"));
            (sims && at(AGENT, "downloading")).then_some(())
        },
    )
    .await?;
    let pids = [site.agent.pid(), site.sim.pid()];
    signal("STOP", &pids)?;
    let frozen = rollout_finished(&site.deployments(), DEPLOYMENT, Duration::from_secs(180)).await;
    signal("CONT", &pids)?;
    let st = frozen?.status.unwrap_or_default();
    assert_eq!(st.phase, Some(RolloutPhase::RolledBack), "2.0.0: {st:#?}");
    eprintln!("2.0.0 rolled back while every robot was frozen; thawed");
    site.all_on("1.0.0").await?;

    // 3.0.0 reaches every robot.
    let v3 = site.push(&release_dir(&root, "3", &[3], 0)?, "3.0.0")?;
    site.roll_out(&v3).await?;
    let st = site.finished().await?;
    assert_eq!(st.phase, Some(RolloutPhase::Completed), "3.0.0: {st:#?}");
    site.all_on("3.0.0").await?;
    Ok(())
}
