//! Rollouts whose controller hears the API server late, against a gateway and `lekiwi-sim`
//! robots at full speed: the Robot controller and the rollout controller run behind
//! [`LagProxy`].
//!
//! A slow API server: every answer and watch event some seconds late. A robot's timeout counts
//! from the write that told it, not from the plan: a batch of 160 robots takes ten times the lag
//! to write (16 writes at once), longer than a robot's timeout, while each robot needs less than
//! the timeout from its own write to its outcome. Counted from the plan, the robots written last
//! are still busy when the controller first looks at the batch after its writes, past their
//! timeout: they time out and the rollout rolls back.
//!
//! A watch that runs behind: the controller's open connections (its watches) a minute late,
//! its new requests answered at once. Each robot is done a few seconds after its write, well
//! within its timeout, but the controller's store shows that only a minute later: it plans past
//! every robot's timeout on a store that shows none of them done. Judged on that store every
//! robot times out and the rollout rolls back (what the soak at 10,000 robots met, with an API
//! server whose watches ran a minute behind); the controller reads each such robot afresh and
//! sees it done.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use k8s_openapi::api::core::v1::Event;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use kube::Api;
use kube::api::{Patch, PatchParams, PostParams};
use lekiwi_controllers::deployment::plan::Mark;
use lekiwi_crds::deployment::{ABORT_ANNOTATION, RolloutKind, RolloutPhase, RolloutStrategy};
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::lag_proxy::LagProxy;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, SimProcess, SimSpec, enrollment_token_file, gateway_url,
    namespace, push_release, rollout_finished, test_strategy, wait_for, wait_online,
};

/// A gateway and simulated robots at full speed, a controller behind a [`LagProxy`], and a
/// release pushed.
struct LaggedBed {
    client: kube::Client,
    proxy: LagProxy,
    controller: OperatorProcess,
    sim: SimProcess,
    release: ReleaseRef,
    deployments: Api<RobotDeployment>,
    _gateway: OperatorProcess,
    _dir: tempfile::TempDir,
}

impl LaggedBed {
    async fn start(name: &str, robots: usize, health_seconds: &str) -> anyhow::Result<Self> {
        let cp = ControlPlane::shared();
        let client = cp.client().await?;
        let ns = namespace(&client, name).await?;
        let dir = tempfile::tempdir()?;
        let blobs: PathBuf = dir.path().join("blobs");
        std::fs::create_dir_all(&blobs)?;
        let blob_dir = blobs.to_str().expect("a UTF-8 temp path");
        let mut gateway = OperatorProcess::start(
            cp,
            &ns,
            "gw",
            &["--role", "gateway", "--blob-dir", blob_dir],
        )?;
        gateway.wait_ready().await?;
        let proxy = LagProxy::start(cp.api_server_addr()?).await?;
        let kubeconfig = dir.path().join("slow-kubeconfig");
        cp.kubeconfig_via(&format!("https://{}", proxy.addr), &kubeconfig)?;
        let mut controller = OperatorProcess::start_with_kubeconfig(
            &kubeconfig,
            &ns,
            "ctl",
            &["--role", "controller"],
        )?;
        controller.wait_ready().await?;
        let token_file = dir.path().join("enroll");
        enrollment_token_file(&client, &ns, &token_file).await?;
        let sim = SimProcess::start(
            SimSpec {
                gateway: &gateway_url(&gateway),
                token_file: &token_file,
                namespace: &ns,
                robots,
                prefix: "sim",
                extra: &["--health-check-seconds", health_seconds],
            },
            dir.path(),
        )?;
        wait_online(&client, &ns, robots, Duration::from_secs(120)).await?;
        let release_dir = dir.path().join("release");
        std::fs::create_dir_all(&release_dir)?;
        std::fs::write(release_dir.join("app.txt"), format!("{name}\n"))?;
        let server = format!("http://127.0.0.1:{}", gateway.gateway_port);
        let release = push_release(&cp.kubeconfig(), &ns, &server, None, &release_dir, "2.0.0")?;
        Ok(Self {
            deployments: Api::namespaced(client.clone(), &ns),
            client,
            proxy,
            controller,
            sim,
            release,
            _gateway: gateway,
            _dir: dir,
        })
    }

    /// Creates a deployment of the release over every robot in one batch.
    async fn deploy(&self, name: &str, timeout_seconds: i64) -> anyhow::Result<()> {
        let strategy = RolloutStrategy {
            batch_size: IntOrString::String("100%".into()),
            success_threshold: 1.0,
            robot_timeout_seconds: timeout_seconds,
            ..test_strategy(0, 0)
        };
        let d = RobotDeployment::new(
            name,
            RobotDeploymentSpec {
                selector: LabelSelector::default(),
                release: Some(self.release.clone()),
                agent: None,
                strategy,
                paused: false,
                analysis: None,
                priority: 0,
            },
        );
        self.deployments.create(&PostParams::default(), &d).await?;
        Ok(())
    }

    /// Waits for the rollout `name` started at `t` to end, prints how (`what` says how the
    /// controller was slowed) and asserts it completed on all `robots`; the time it took.
    async fn completed(
        &self,
        name: &str,
        robots: usize,
        t: Instant,
        what: &str,
    ) -> anyhow::Result<Duration> {
        let d = rollout_finished(&self.deployments, name, Duration::from_secs(240))
            .await
            .map_err(|e| {
                anyhow::anyhow!(
                    "{e}\ncontroller log tail:\n{}\nsim log tail:\n{}",
                    tail(&self.controller.log_text()),
                    tail(&self.sim.log_text())
                )
            })?;
        let took = t.elapsed();
        let st = d.status.unwrap_or_default();
        println!(
            "{robots} robots, {what}: {:?} after {took:?} ({} updated, {} failed)",
            st.phase, st.updated, st.failed
        );
        assert_eq!(
            st.phase,
            Some(RolloutPhase::Completed),
            "{:?}\ncontroller log tail:\n{}",
            st.message,
            tail(&self.controller.log_text())
        );
        assert_eq!((st.updated, st.failed), (robots as i32, 0));
        Ok(took)
    }
}

#[tokio::test]
async fn a_robots_timeout_counts_from_the_write_that_told_it() -> anyhow::Result<()> {
    /// Robots of the one batch: ten rounds of 16 writes.
    const ROBOTS: usize = 160;
    /// How late the controller hears every answer: a round of writes takes at least this long.
    const LAG: Duration = Duration::from_secs(4);
    /// A robot's timeout: shorter than the batch's writes (10 × 4 s), longer than a robot needs
    /// from its write (its 14 s health check, then its status, which the controller hears 4 s
    /// late: about 19 s).
    const TIMEOUT_SECONDS: i64 = 25;
    let bed = LaggedBed::start("slowwrites", ROBOTS, "14").await?;
    bed.proxy.set_lag(LAG);
    let t = Instant::now();
    bed.deploy("slow", TIMEOUT_SECONDS).await?;
    let what = format!("a controller {LAG:?} behind, robot timeout {TIMEOUT_SECONDS} s");
    let took = bed.completed("slow", ROBOTS, t, &what).await?;
    assert!(
        took > LAG * (ROBOTS as u32 / 16),
        "the batch's writes should have outlasted a robot's timeout: {took:?}"
    );
    Ok(())
}

#[tokio::test]
async fn a_robots_timeout_is_judged_on_a_fresh_read_not_on_a_watch_behind() -> anyhow::Result<()> {
    const ROBOTS: usize = 4;
    /// How late the controller's watches run once the robots are written.
    const WATCH_LAG: Duration = Duration::from_secs(60);
    /// A robot's timeout: longer than a robot needs (its 5 s health check after a small
    /// download), far shorter than the watch lag.
    const TIMEOUT_SECONDS: i64 = 15;
    let bed = LaggedBed::start("freshreads", ROBOTS, "5").await?;
    let t = Instant::now();
    bed.deploy("fresh", TIMEOUT_SECONDS).await?;
    // Once the rollout has told every robot, said so in its status and published its Event (the
    // last answers of that reconcile), the connections the controller holds, its watches among
    // them, fall a minute behind.
    let ns = bed.deployments.namespace().unwrap_or_default().to_owned();
    let robots = Api::<Robot>::namespaced(bed.client.clone(), &ns);
    let events = Api::<Event>::namespaced(bed.client.clone(), &ns);
    let (deployments, release) = (&bed.deployments, &bed.release);
    let (robots, events) = (&robots, &events);
    wait_for(
        "the batch to start",
        Duration::from_secs(60),
        || async move {
            let st = deployments.get("fresh").await.ok()?.status?;
            let told = robots.list(&Default::default()).await.ok()?.items;
            let started = events.list(&Default::default()).await.ok()?.items;
            let started = started
                .iter()
                .any(|e| e.reason.as_deref() == Some("BatchStarted"));
            let all_told = told.len() == ROBOTS
                && told
                    .iter()
                    .all(|r| r.spec.release.as_ref() == Some(release));
            (st.phase == Some(RolloutPhase::Progressing) && all_told && started).then_some(())
        },
    )
    .await?;
    bed.proxy.lag_open(WATCH_LAG);
    let lagged_at = t.elapsed();
    let what = format!(
        "the controller's watches {WATCH_LAG:?} behind from {lagged_at:?}, robot timeout \
         {TIMEOUT_SECONDS} s"
    );
    let took = bed.completed("fresh", ROBOTS, t, &what).await?;
    assert!(
        took < lagged_at + WATCH_LAG,
        "the rollout should end before the store shows the robots done: {took:?}\n{}",
        tail(&bed.controller.log_text())
    );
    // The controller's own count of robots past their timeout on its store that a fresh read
    // found done (`in_time=N`): the rollout completed by that read, not by the store.
    let log = bed.controller.log_text();
    let found_done: usize = log
        .lines()
        .filter(|l| l.contains("robots past their timeout on the store read fresh"))
        .filter_map(|l| {
            l.split("in_time=")
                .nth(1)?
                .split_whitespace()
                .next()?
                .parse::<usize>()
                .ok()
        })
        .sum();
    assert!(
        found_done >= 1,
        "robots past their timeout on the store should have been read done:\n{}",
        tail(&log)
    );
    Ok(())
}

/// A user aborts a rollout while the controller writes a batch of 160 robots behind a 2 s lag
/// (ten rounds of 16 writes, 20 s): the controller stops starting robots once its store shows
/// the abort, and the rollout ends `Aborted` with the robots it had written. Before, the writes
/// went on to the last robot of the batch after the abort (as the soak found with a busy API
/// server: a batch of 1,021 robots written on after the abort, robots it had stopped switching).
#[tokio::test]
async fn an_abort_stops_the_writes_of_a_batch_under_way() -> anyhow::Result<()> {
    /// The canary, then one batch of the rest.
    const ROBOTS: usize = 161;
    const LAG: Duration = Duration::from_secs(2);
    let bed = LaggedBed::start("abortwrites", ROBOTS, "1").await?;
    bed.proxy.set_lag(LAG);
    let strategy = RolloutStrategy {
        batch_size: IntOrString::String("100%".into()),
        success_threshold: 1.0,
        robot_timeout_seconds: 300,
        ..test_strategy(0, 1)
    };
    let d = RobotDeployment::new(
        "abort",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(bed.release.clone()),
            agent: None,
            strategy,
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    bed.deployments.create(&PostParams::default(), &d).await?;
    let ns = bed.deployments.namespace().unwrap_or_default().to_owned();
    let robots = Api::<Robot>::namespaced(bed.client.clone(), &ns);
    // Robots the rollout's batch after the canary has told to switch (read from the API
    // server itself, not through the lag).
    let batch_told = || async {
        let all = robots.list(&Default::default()).await.ok()?.items;
        Some(
            all.iter()
                .filter(|r| Mark::of(r, RolloutKind::Release).is_some_and(|m| m.batch == 1))
                .count(),
        )
    };
    wait_for(
        "the batch's writes under way",
        Duration::from_secs(120),
        || async { batch_told().await.filter(|n| *n > 0) },
    )
    .await?;
    let patch = serde_json::json!({"metadata": {"annotations": {
        ABORT_ANNOTATION: jiff::Timestamp::now().to_string(),
    }}});
    bed.deployments
        .patch("abort", &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    let d = rollout_finished(&bed.deployments, "abort", Duration::from_secs(120)).await?;
    let told = batch_told().await.unwrap_or_default();
    println!(
        "after the abort: {told} of {} robots of the batch told",
        ROBOTS - 1
    );
    assert_eq!(
        d.status.as_ref().and_then(|s| s.phase),
        Some(RolloutPhase::Aborted),
        "{:?}\n{}",
        d.status,
        tail(&bed.controller.log_text())
    );
    assert!(
        told <= (ROBOTS - 1) * 3 / 4,
        "{told} of {} robots told after the abort:\n{}",
        ROBOTS - 1,
        tail(&bed.controller.log_text())
    );
    let log = bed.controller.log_text();
    assert!(
        log.contains("the deployment changed while its robots were written"),
        "{}",
        tail(&log)
    );
    Ok(())
}

/// The last 40 lines of a log.
fn tail(text: &str) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(80)..].join("\n")
}
