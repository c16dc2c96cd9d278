//! A rollout whose controller writes to a slow API server: a robot's timeout counts from the
//! write that told it, not from the plan. The Robot controller and the rollout controller run
//! behind [`LagProxy`] (every answer and watch event some seconds late), the gateway and
//! `lekiwi-sim` robots at full speed; a batch of 160 robots takes ten times the lag to write
//! (16 writes at once), longer than a robot's timeout, while each robot needs less than the
//! timeout from its own write to its outcome. Counted from the plan, the robots written last
//! are still busy when the controller first looks at the batch after its writes, past their
//! timeout: they time out and the rollout rolls back.

use std::time::{Duration, Instant};

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use kube::Api;
use kube::api::PostParams;
use lekiwi_crds::deployment::{RolloutPhase, RolloutStrategy};
use lekiwi_crds::{RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::lag_proxy::LagProxy;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, SimProcess, SimSpec, enrollment_token_file, gateway_url,
    namespace, push_release, rollout_finished, test_strategy, wait_online,
};

/// Robots of the one batch: ten rounds of 16 writes.
const ROBOTS: usize = 160;
/// How late the controller hears every answer: a round of writes takes at least this long.
const LAG: Duration = Duration::from_secs(4);
/// How long each robot's health check takes after its switch.
const HEALTH_SECONDS: &str = "14";
/// A robot's timeout: shorter than the batch's writes (10 × 4 s), longer than a robot needs
/// from its write (its 14 s health check, then its status, which the controller hears 4 s
/// late: about 19 s).
const TIMEOUT_SECONDS: i64 = 25;

#[tokio::test]
async fn a_robots_timeout_counts_from_the_write_that_told_it() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "slowwrites").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
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
    let mut controller =
        OperatorProcess::start_with_kubeconfig(&kubeconfig, &ns, "ctl", &["--role", "controller"])?;
    controller.wait_ready().await?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let sim = SimProcess::start(
        SimSpec {
            gateway: &gateway_url(&gateway),
            token_file: &token_file,
            namespace: &ns,
            robots: ROBOTS,
            prefix: "sim",
            extra: &["--health-check-seconds", HEALTH_SECONDS],
        },
        dir.path(),
    )?;
    wait_online(&client, &ns, ROBOTS, Duration::from_secs(120)).await?;
    let release_dir = dir.path().join("release");
    std::fs::create_dir_all(&release_dir)?;
    std::fs::write(release_dir.join("app.txt"), b"slow writes\n")?;
    let server = format!("http://127.0.0.1:{}", gateway.gateway_port);
    let release = push_release(&cp.kubeconfig(), &ns, &server, None, &release_dir, "2.0.0")?;

    proxy.set_lag(LAG);
    let deployments = Api::<RobotDeployment>::namespaced(client.clone(), &ns);
    let strategy = RolloutStrategy {
        batch_size: IntOrString::String("100%".into()),
        success_threshold: 1.0,
        robot_timeout_seconds: TIMEOUT_SECONDS,
        ..test_strategy(0, 0)
    };
    let d = RobotDeployment::new(
        "slow",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(release),
            agent: None,
            strategy,
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    let t = Instant::now();
    deployments.create(&PostParams::default(), &d).await?;
    let d = rollout_finished(&deployments, "slow", Duration::from_secs(240))
        .await
        .map_err(|e| {
            anyhow::anyhow!(
                "{e}\ncontroller log tail:\n{}\nsim log tail:\n{}",
                tail(&controller.log_text()),
                tail(&sim.log_text())
            )
        })?;
    let st = d.status.unwrap_or_default();
    println!(
        "{ROBOTS} robots in one batch through a controller {LAG:?} behind: {:?} after {:?} \
         ({} updated, {} failed; robot timeout {TIMEOUT_SECONDS} s)",
        st.phase,
        t.elapsed(),
        st.updated,
        st.failed
    );
    assert_eq!(
        st.phase,
        Some(RolloutPhase::Completed),
        "{:?}\ncontroller log tail:\n{}",
        st.message,
        tail(&controller.log_text())
    );
    assert_eq!((st.updated, st.failed), (ROBOTS as i32, 0));
    assert!(
        t.elapsed() > LAG * (ROBOTS as u32 / 16),
        "the batch's writes should have outlasted a robot's timeout: {:?}",
        t.elapsed()
    );
    Ok(())
}

/// The last 40 lines of a log.
fn tail(text: &str) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}
