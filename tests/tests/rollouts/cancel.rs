//! Cancelling deployments in flight, end to end: real agent processes (`lekiwi-agent`, each
//! with its download rate capped by `--release-download-rate-limit`) download a 30 MB release
//! from the real operator; `kubectl lekiwi rollout undo` and `rollout pause` make the gateway
//! send `cancel`, the agents stop within moments on the release they ran, and a later rollout
//! of the same release resumes their partial downloads. The gateway alone (no controller)
//! cancels downloads the moment it sees an abort, before any robot's `spec.release` changes.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{ListParams, Patch, PatchParams, PostParams};
use kube::{Api, ResourceExt};
use lekiwi_controllers::deployment::plan;
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    AgentProcess, OperatorSite, bin, gateway_url, http_get_with, test_strategy, wait_for,
    wait_online,
};
use serde_json::{Value, json};

/// Robots, each a `lekiwi-agent` process.
const ROBOTS: usize = 3;
/// Size of the big release's one file.
const BIG: u64 = 30 * 1024 * 1024;
/// Each agent's download cap: the big release takes 15 s.
const RATE: &str = "2000000";

/// A namespace with an operator, agents and two releases: small `1.0.0` and big `2.0.0`.
struct Site {
    base: OperatorSite,
    agents: Vec<AgentProcess>,
}

lekiwi_tests::deref_to_operator_site!(Site);

impl Site {
    async fn new(prefix: &str) -> anyhow::Result<Self> {
        Self::new_with(prefix, &[]).await
    }

    /// As [`Self::new`], the operator started with `extra` flags.
    async fn new_with(prefix: &str, extra: &[&str]) -> anyhow::Result<Self> {
        let base = OperatorSite::start_with(prefix, extra).await?;
        let (dir, ns, op, token_file) = (&base.dir, &base.ns, &base.op, &base.token_file);
        let mut agents = Vec::new();
        for i in 0..ROBOTS {
            let state = dir.path().join(format!("robot-{i}"));
            std::fs::create_dir_all(&state)?;
            agents.push(AgentProcess::start(
                &gateway_url(op),
                &format!("{ns}/kiwi-{i}"),
                token_file,
                &state,
                &["--release-download-rate-limit", RATE],
            )?);
        }
        wait_online(&base.client, ns, ROBOTS, Duration::from_secs(120)).await?;
        Ok(Self { base, agents })
    }

    /// `kubectl lekiwi rollout <verb> <name>`, which must succeed.
    fn rollout(&self, verb: &str, name: &str) -> anyhow::Result<()> {
        let out = Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(self.cp.kubeconfig())
            .args(["-n", &self.ns, "rollout", verb, name])
            .env_remove("LEKIWI_SERVER")
            .output()?;
        if !out.status.success() {
            bail!("rollout {verb}: {}", String::from_utf8_lossy(&out.stderr));
        }
        Ok(())
    }

    fn deployments(&self) -> Api<RobotDeployment> {
        Api::namespaced(self.client.clone(), &self.ns)
    }

    async fn deploy(&self, name: &str, release: &ReleaseRef) -> anyhow::Result<()> {
        let d = RobotDeployment::new(
            name,
            RobotDeploymentSpec {
                selector: LabelSelector::default(),
                release: Some(release.clone()),
                agent: None,
                strategy: test_strategy(ROBOTS as i32, 0),
                paused: false,
                priority: 0,
                analysis: None,
            },
        );
        self.deployments()
            .create(&PostParams::default(), &d)
            .await?;
        Ok(())
    }

    async fn phase_is(&self, name: &str, want: RolloutPhase, within: u64) -> anyhow::Result<()> {
        wait_for(
            &format!("{name} {want:?}"),
            Duration::from_secs(within),
            || async {
                let d = self.deployments().get(name).await.ok()?;
                (d.status?.phase == Some(want)).then_some(())
            },
        )
        .await
    }

    async fn robots(&self) -> anyhow::Result<Vec<Robot>> {
        Ok(Api::<Robot>::namespaced(self.client.clone(), &self.ns)
            .list(&ListParams::default())
            .await?
            .items)
    }

    /// Gives every robot of `names` `release`, as a controller would, and waits until each
    /// runs it.
    async fn all_on(&self, names: &[String], release: &ReleaseRef) -> anyhow::Result<()> {
        let robots: Api<Robot> = Api::namespaced(self.client.clone(), &self.ns);
        for name in names {
            let patch = json!({"spec": {"release": release}});
            robots
                .patch(name, &PatchParams::default(), &Patch::Merge(&patch))
                .await?;
        }
        wait_for(
            "every robot on the release",
            Duration::from_secs(60),
            || async {
                let all = self.robots().await.ok()?;
                all.iter()
                    .all(|r| {
                        r.status.as_ref().and_then(|s| s.current_release.as_ref()) == Some(release)
                    })
                    .then_some(())
            },
        )
        .await
    }

    /// What the controller writes when a rollout of `release` (deployment `cx`) starts, 2 s
    /// ago: the deployment and its status; returns the rollout's id.
    async fn rollout_of(&self, release: &ReleaseRef) -> anyhow::Result<String> {
        let started = jiff::Timestamp::now() - jiff::SignedDuration::from_secs(2);
        let key = plan::rollout_id(release, None);
        let rollout_id = plan::rollout_id_at(&key, started);
        self.deploy("cx", release).await?;
        let status = json!({"status": {"phase": "Progressing", "rolloutId": rollout_id}});
        self.deployments()
            .patch_status("cx", &PatchParams::default(), &Patch::Merge(&status))
            .await?;
        Ok(rollout_id)
    }

    /// What the controller writes to start the robots `names` of the rollout `rollout_id` of
    /// `cx`: each one's mark and `spec.release` `to`, from `from`.
    async fn told_to_switch(
        &self,
        names: &[String],
        rollout_id: &str,
        from: &ReleaseRef,
        to: &ReleaseRef,
    ) -> anyhow::Result<()> {
        let robots: Api<Robot> = Api::namespaced(self.client.clone(), &self.ns);
        let started = plan::rollout_start(rollout_id).context("rollout id")?;
        for name in names {
            let mark = plan::Mark {
                deployment: "cx".into(),
                rollout_id: rollout_id.to_owned(),
                batch: 0,
                state: plan::MarkState::Started,
                since: started,
                previous: Some(from.clone()),
                message: None,
                failed: false,
            };
            let patch = json!({
                "metadata": {"annotations": {plan::MARK_ANNOTATION: serde_json::to_string(&mark)?}},
                "spec": {"release": to},
            });
            robots
                .patch(name, &PatchParams::default(), &Patch::Merge(&patch))
                .await?;
        }
        Ok(())
    }

    /// Bytes of partial downloads in each agent's store.
    fn partial_bytes(&self) -> Vec<u64> {
        self.agents
            .iter()
            .map(|a| dir_bytes(&a.state_dir.join("blobs/tmp"), ".partial"))
            .collect()
    }

    /// Waits until every agent has more than `bytes` of its download.
    async fn downloading_past(&self, bytes: u64) -> anyhow::Result<()> {
        wait_for(
            "every agent downloading",
            Duration::from_secs(60),
            || async {
                self.partial_bytes()
                    .iter()
                    .all(|b| *b > bytes)
                    .then_some(())
            },
        )
        .await
    }

    /// Waits until every robot reports `release` `cancelled` (a report that reached the gateway
    /// after `since`), while it runs `running`; fails when that takes longer than `within` from
    /// `started`; returns how long it took.
    async fn all_cancelled(
        &self,
        release: &ReleaseRef,
        running: &ReleaseRef,
        (started, since): (Instant, jiff::Timestamp),
        within: Duration,
    ) -> anyhow::Result<Duration> {
        let left = within.saturating_sub(started.elapsed());
        // Status times have whole seconds.
        let floor = since - jiff::SignedDuration::from_secs(1);
        wait_for("every robot cancelled", left, || async {
            let robots = self.robots().await.ok()?;
            let all = robots.len() == ROBOTS
                && robots.iter().all(|r| {
                    let Some(st) = r.status.as_ref() else {
                        return false;
                    };
                    let last = st.last_update.as_ref();
                    st.current_release.as_ref() == Some(running)
                        && last.and_then(|u| u.release.as_ref()) == Some(release)
                        && last.and_then(|u| u.phase.as_deref()) == Some("cancelled")
                        && last
                            .and_then(|u| u.time.as_ref())
                            .is_some_and(|t| t.0 >= floor)
                });
            all.then_some(())
        })
        .await?;
        Ok(started.elapsed())
    }

    /// Sends `kubectl lekiwi rollout <verb> cx` while the robots download `release`, and waits
    /// until every robot reports it `cancelled` while it runs `running`, within 5 s.
    async fn cancel_with(
        &self,
        verb: &str,
        release: &ReleaseRef,
        running: &ReleaseRef,
    ) -> anyhow::Result<()> {
        let asked = (Instant::now(), jiff::Timestamp::now());
        self.rollout(verb, "cx")?;
        let took = self
            .all_cancelled(release, running, asked, Duration::from_secs(5))
            .await?;
        eprintln!("{verb}: every robot cancelled after {took:?}");
        Ok(())
    }

    /// Asserts that no agent's partial download grows for 3 s (`why` says what that shows);
    /// returns the partial sizes.
    async fn downloads_stay_stopped(&self, why: &str) -> Vec<u64> {
        let stopped = self.partial_bytes();
        tokio::time::sleep(Duration::from_secs(3)).await;
        assert_eq!(self.partial_bytes(), stopped, "{why}");
        stopped
    }

    /// Bytes the gateway served to each robot.
    async fn bytes_served(&self) -> anyhow::Result<Vec<u64>> {
        let token = self.cp.admin_token()?;
        let mut out = Vec::new();
        for i in 0..ROBOTS {
            let (code, _, body) = http_get_with(
                self.op.gateway_port,
                &format!("/v1/blobs-served?robot={}/kiwi-{i}", self.ns),
                &[("authorization", &format!("Bearer {token}"))],
            )
            .await?;
            if code != 200 {
                bail!("blobs-served answered {code}: {body}");
            }
            let v: Value = serde_json::from_str(&body)?;
            out.push(v["bytes"].as_u64().unwrap_or_default());
        }
        Ok(out)
    }

    /// Whether any agent holds a release directory of `version`.
    fn any_installed(&self, version: &str) -> bool {
        self.agents
            .iter()
            .any(|a| a.state_dir.join("releases").join(version).exists())
    }
}

/// Total size of the files in `dir` whose names end with `suffix`.
fn dir_bytes(dir: &Path, suffix: &str) -> u64 {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(suffix))
        .filter_map(|e| e.metadata().ok())
        .map(|m| m.len())
        .sum()
}

/// A release directory with one file: `size` random bytes (nothing to compress or share).
fn release_dir(root: &Path, tag: &str, size: u64) -> anyhow::Result<PathBuf> {
    let dir = root.join(format!("src-{tag}"));
    std::fs::create_dir_all(&dir)?;
    let mut random = std::fs::File::open("/dev/urandom")?.take(size);
    let mut out = std::fs::File::create(dir.join("policy.bin"))?;
    std::io::copy(&mut random, &mut out)?;
    Ok(dir)
}

/// Undo while every robot downloads a 30 MB release: every robot is back on (still on) the
/// old release and reports `cancelled` within 5 s, the downloads stop, and none installs the
/// new release. Then the same release rolled out again and paused mid-download cancels too,
/// and on resume the agents finish from where they stopped: the gateway serves each of them
/// less than the release's size for the last leg.
#[tokio::test]
async fn undo_and_pause_cancel_downloads_in_flight_and_resume_continues_them() -> anyhow::Result<()>
{
    let site = Site::new("cancel").await?;
    let v1 = site.push(&release_dir(site.dir.path(), "1", 1024)?, "1.0.0")?;
    let v2 = site.push(&release_dir(site.dir.path(), "2", BIG)?, "2.0.0")?;
    site.deploy("cx", &v1).await?;
    site.phase_is("cx", RolloutPhase::Completed, 120).await?;

    site.deployments()
        .patch(
            "cx",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"release": v2}})),
        )
        .await?;
    site.downloading_past(2 * 1024 * 1024).await?;
    site.cancel_with("undo", &v2, &v1).await?;
    let stopped = site.downloads_stay_stopped("the downloads stopped").await;
    assert!(
        stopped.iter().all(|b| *b > 0 && *b < BIG),
        "partial downloads are kept: {stopped:?}"
    );
    assert!(!site.any_installed("2.0.0"), "no robot finished 2.0.0");
    site.phase_is("cx", RolloutPhase::RolledBack, 30).await?;

    // The same release again: the agents resume their partial files (4 MB more take 2 s: the
    // pause's reports are told from the undo's by their time); a pause cancels again.
    site.rollout("restart", "cx")?;
    wait_for("downloads resumed", Duration::from_secs(60), || async {
        let now = site.partial_bytes();
        now.iter()
            .zip(&stopped)
            .all(|(n, s)| *n > s + 4 * 1024 * 1024)
            .then_some(())
    })
    .await?;
    site.cancel_with("pause", &v2, &v1).await?;
    site.phase_is("cx", RolloutPhase::Paused, 10).await?;
    site.downloads_stay_stopped("a paused rollout downloads nothing")
        .await;
    assert!(!site.any_installed("2.0.0"));

    let served_before = site.bytes_served().await?;
    site.rollout("resume", "cx")?;
    site.phase_is("cx", RolloutPhase::Completed, 120).await?;
    let served_after = site.bytes_served().await?;
    for (i, (before, after)) in served_before.iter().zip(&served_after).enumerate() {
        let last_leg = after - before;
        assert!(
            last_leg < BIG - 4 * 1024 * 1024,
            "kiwi-{i} fetched {last_leg} bytes after the resume: the download started over"
        );
    }
    for r in site.robots().await? {
        let current = r.status.and_then(|s| s.current_release);
        assert_eq!(
            current.as_ref(),
            Some(&v2),
            "{}",
            r.metadata.name.unwrap_or_default()
        );
    }
    Ok(())
}

/// The gateway stops downloads from the RobotDeployment change alone: with no controller running
/// (`--role gateway`), the test writes what the controller would (each robot's `spec.release`
/// and mark, the deployment's status) and aborts the rollout with the plugin. Every agent
/// reports `cancelled` within 5 s although its `spec.release` still names the new release, and
/// no download starts again while it does.
#[tokio::test]
async fn the_gateway_cancels_downloads_on_abort_before_any_robot_is_written() -> anyhow::Result<()>
{
    let site = Site::new_with("halt", &["--role", "gateway"]).await?;
    let v1 = site.push(&release_dir(site.dir.path(), "1", 1024)?, "1.0.0")?;
    let v2 = site.push(&release_dir(site.dir.path(), "2", BIG)?, "2.0.0")?;
    let names: Vec<String> = (0..ROBOTS).map(|i| format!("kiwi-{i}")).collect();
    site.all_on(&names, &v1).await?;
    let rollout_id = site.rollout_of(&v2).await?;
    site.told_to_switch(&names, &rollout_id, &v1, &v2).await?;
    site.downloading_past(2 * 1024 * 1024).await?;

    site.cancel_with("abort", &v2, &v1).await?;
    for r in site.robots().await? {
        assert_eq!(
            r.spec.release.as_ref(),
            Some(&v2),
            "no controller wrote the robot back"
        );
    }
    site.downloads_stay_stopped("no download started again while spec.release still names 2.0.0")
        .await;
    assert!(!site.any_installed("2.0.0"));
    Ok(())
}

/// A robot the controller starts only after a user aborted its rollout (the writes of a batch
/// were under way when the abort came, as the soak found, with a busy API server): its gateway
/// does not deploy the release its `spec.release` and mark name, neither to its live session
/// nor to the session it opens after a restart. With the operator as the gateway alone, the
/// test writes what the controller would.
#[tokio::test]
async fn a_robot_started_after_the_abort_is_not_deployed() -> anyhow::Result<()> {
    let mut site = Site::new_with("held", &["--role", "gateway"]).await?;
    let v1 = site.push(&release_dir(site.dir.path(), "1", 1024)?, "1.0.0")?;
    let v2 = site.push(&release_dir(site.dir.path(), "2", BIG)?, "2.0.0")?;
    let names: Vec<String> = (0..ROBOTS).map(|i| format!("kiwi-{i}")).collect();
    site.all_on(&names, &v1).await?;
    let rollout_id = site.rollout_of(&v2).await?;
    let (batch, late) = names.split_at(ROBOTS - 1);
    site.told_to_switch(batch, &rollout_id, &v1, &v2).await?;
    wait_for("the batch downloading", Duration::from_secs(60), || async {
        site.partial_bytes()[..ROBOTS - 1]
            .iter()
            .all(|b| *b > 1024 * 1024)
            .then_some(())
    })
    .await?;
    site.rollout("abort", "cx")?;
    // The batch's downloads stop: the gateway has seen the abort.
    wait_for("the batch cancelled", Duration::from_secs(10), || async {
        let robots = site.robots().await.ok()?;
        let cancelled = robots.iter().filter(|r| {
            r.status
                .as_ref()
                .and_then(|s| s.last_update.as_ref())
                .is_some_and(|u| {
                    u.release.as_ref() == Some(&v2) && u.phase.as_deref() == Some("cancelled")
                })
        });
        (cancelled.count() == ROBOTS - 1).then_some(())
    })
    .await?;

    site.told_to_switch(late, &rollout_id, &v1, &v2).await?;
    let late_bytes = |site: &Site| site.partial_bytes()[ROBOTS - 1];
    tokio::time::sleep(Duration::from_secs(3)).await;
    assert_eq!(late_bytes(&site), 0, "the late robot started its download");
    site.agents[ROBOTS - 1].restart()?;
    tokio::time::sleep(Duration::from_secs(5)).await;
    assert_eq!(
        late_bytes(&site),
        0,
        "the late robot's new session deployed it"
    );
    let robot = site
        .robots()
        .await?
        .into_iter()
        .find(|r| r.name_any() == late[0])
        .unwrap();
    let status = robot.status.unwrap_or_default();
    assert_eq!(status.current_release.as_ref(), Some(&v1));
    assert!(
        status.last_update.as_ref().and_then(|u| u.release.as_ref()) != Some(&v2),
        "no update to 2.0.0 reported: {:?}",
        status.last_update
    );
    assert_eq!(
        robot.spec.release.as_ref(),
        Some(&v2),
        "no controller wrote it back"
    );
    assert!(!site.any_installed("2.0.0"));
    Ok(())
}
