//! Health that comes from the robot (issue 16 part 0): a real agent whose host process (a dummy
//! process matching `--host-process-pattern`) dies turns unhealthy with the reason in its
//! `Healthy` condition, a rollout waits for it, and it turns healthy again (and is updated)
//! when the process returns. Real operator, real agent, a control plane of the test's own (so
//! that the Robot CRD it installs cannot race other worktrees' on the shared one). The host
//! process's memory, read by the agent, reaches the Robot's `status.telemetry`.

use std::process::{Child, Command};
use std::time::Duration;

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::Api;
use kube::api::PostParams;
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{Condition, ConditionStatus, Robot, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, enrollment_token_file, gateway_url, namespace,
    push_release, rollout_finished, test_strategy, wait_for, wait_online,
};

/// A process standing in for `lekiwi_host`: `sleep` with a fraction no other process uses, so
/// its command line is the pattern.
fn host_process(pattern: &str) -> anyhow::Result<Child> {
    let seconds = pattern.trim_start_matches("sleep ");
    Ok(Command::new("sleep").arg(seconds).spawn()?)
}

fn healthy_condition(r: &Robot) -> Option<Condition> {
    r.status
        .as_ref()?
        .conditions
        .iter()
        .find(|c| c.r#type == "Healthy")
        .cloned()
}

/// Waits until the robot's `Healthy` condition has `status` and returns it.
async fn wait_healthy(
    robots: &Api<Robot>,
    name: &str,
    status: ConditionStatus,
    agent: &AgentProcess,
) -> anyhow::Result<Condition> {
    wait_for(
        &format!("Healthy={status:?}"),
        Duration::from_secs(30),
        || async {
            let r = robots.get(name).await.ok()?;
            healthy_condition(&r).filter(|c| c.status == status)
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))
}

#[tokio::test]
async fn a_dead_host_process_makes_the_robot_unhealthy_and_a_rollout_waits() -> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "health").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let mut op = OperatorProcess::start(
        &cp,
        &ns,
        "op-health",
        &[
            "--blob-dir",
            blobs.to_str().unwrap(),
            "--status-refresh-seconds",
            "1",
        ],
    )?;
    op.wait_ready().await?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;

    let pattern = format!("sleep 600.{}", std::process::id());
    let mut host = host_process(&pattern)?;
    let agent = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/kiwi-h"),
        &token_file,
        &dir.path().join("robot"),
        &[
            "--host-process-pattern",
            &pattern,
            "--health-interval-s",
            "0.5",
        ],
    )?;
    wait_online(&client, &ns, 1, Duration::from_secs(60)).await?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    let c = wait_healthy(&robots, "kiwi-h", ConditionStatus::True, &agent).await?;
    assert_eq!(c.reason, "HealthChecksPassed");
    // Its resident memory reaches the Robot's status (the agent reads it from /proc).
    let rss = wait_for(
        "the host process's memory",
        Duration::from_secs(30),
        || async {
            let t = robots.get("kiwi-h").await.ok()?.status?.telemetry?;
            t.host_memory_bytes.filter(|&b| b > 0)
        },
    )
    .await?;
    assert!(rss < 1 << 30, "a sleeping process of {rss} bytes");

    // The host process dies: unhealthy, and the condition says why.
    host.kill()?;
    host.wait()?;
    let c = wait_healthy(&robots, "kiwi-h", ConditionStatus::False, &agent).await?;
    assert_eq!(c.reason, "HostProcessNotRunning", "{c:?}");
    assert!(c.message.contains(&pattern), "{c:?}");

    // A rollout waits for it (the strategy's `unavailable: Wait`) and does not touch it.
    let release_dir = dir.path().join("release-1");
    std::fs::create_dir_all(&release_dir)?;
    std::fs::write(release_dir.join("main.py"), "print('kiwi')\n")?;
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let v1 = push_release(&cp.kubeconfig(), &ns, &server, None, &release_dir, "1.0.0")?;
    let deployments: Api<RobotDeployment> = Api::namespaced(client.clone(), &ns);
    let d = RobotDeployment::new(
        "fleet",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(v1.clone()),
            agent: None,
            strategy: test_strategy(1, 0),
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    deployments.create(&PostParams::default(), &d).await?;
    wait_for(
        "the robot waited for as unhealthy",
        Duration::from_secs(30),
        || async {
            let st = deployments.get("fleet").await.ok()?.status?;
            st.robots
                .iter()
                .any(|r| r.robot == "kiwi-h" && r.message.as_deref() == Some("waiting: unhealthy"))
                .then_some(())
        },
    )
    .await?;
    let d = deployments.get("fleet").await?;
    assert_eq!(d.status.unwrap().phase, Some(RolloutPhase::Progressing));
    assert_eq!(robots.get("kiwi-h").await?.spec.release, None);

    // The process returns: healthy again, and the rollout updates the robot.
    let mut host = host_process(&pattern)?;
    let c = wait_healthy(&robots, "kiwi-h", ConditionStatus::True, &agent).await?;
    assert_eq!(c.reason, "HealthChecksPassed");
    let d = rollout_finished(&deployments, "fleet", Duration::from_secs(60)).await?;
    assert_eq!(d.status.unwrap().phase, Some(RolloutPhase::Completed));
    let r = robots.get("kiwi-h").await?;
    assert_eq!(
        r.status.and_then(|s| s.current_release),
        Some(v1),
        "the robot runs the release"
    );
    host.kill()?;
    host.wait()?;
    drop(agent);
    op.terminate()?;
    Ok(())
}
