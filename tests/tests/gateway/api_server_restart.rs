//! On a private control plane: the operator refuses to start without CRDs (or installs them),
//! and survives an etcd + kube-apiserver restart, catching up without a restart of its own; and
//! requests a restarting API server took in and never answered are sent again.

use std::time::{Duration, Instant};

use lekiwi_core::api_client::READ_TIMEOUT;
use lekiwi_crds::RobotPhase;
use lekiwi_tests::lag_proxy::LagProxy;
use lekiwi_tests::{
    ControlPlane, GatewayStandIn, OperatorProcess, connect_agent, create_robot, get_robot,
    namespace, wait_for, wait_phase,
};

#[tokio::test]
async fn refuses_without_crds_installs_them_and_survives_api_restart() -> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "restart").await?;

    // No CRDs: a clear refusal, non-zero exit.
    let mut op = OperatorProcess::start(&cp, &ns, "op-nocrd", &[])?;
    let err = op
        .wait_ready()
        .await
        .expect_err("operator started without CRDs");
    let msg = err.to_string();
    assert!(
        msg.contains("CustomResourceDefinition robots.fleet.lekiwi.io is not installed"),
        "{msg}"
    );
    assert!(msg.contains("--install-crds"), "{msg}");
    drop(op);

    // --install-crds installs them and starts.
    let mut op = OperatorProcess::start(
        &cp,
        &ns,
        "op",
        &["--install-crds", "--heartbeat-grace-seconds", "30"],
    )?;
    op.wait_ready().await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    wait_for("kiwi-1 Pending", Duration::from_secs(20), || async {
        (get_robot(&client, &ns, "kiwi-1").await.ok()?.status?.phase == Some(RobotPhase::Pending))
            .then_some(())
    })
    .await?;

    // Kill etcd and the API server, keep them down for a while, bring them back.
    cp.kill()?;
    tokio::time::sleep(Duration::from_secs(5)).await;
    assert!(
        op.running(),
        "operator died while the API server was down:\n{}",
        op.log_text()
    );
    let restarted = Instant::now();
    cp.up()?;
    println!("control plane back after {:?}", restarted.elapsed());

    // Changes made after the restart are picked up by the same operator process.
    let client = cp.client().await?;
    create_robot(&client, &ns, "kiwi-2", &[]).await?;
    let mut gw = GatewayStandIn::start(&client, &ns, "gateway-r", 15).await?;
    gw.connect("kiwi-1").await?;
    let caught_up = Instant::now();
    wait_for(
        "kiwi-1 Online after the restart",
        Duration::from_secs(60),
        || async {
            (get_robot(&client, &ns, "kiwi-1").await.ok()?.status?.phase
                == Some(RobotPhase::Online))
            .then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\noperator log:\n{}", op.log_text()))?;
    wait_for(
        "kiwi-2 Pending after the restart",
        Duration::from_secs(30),
        || async {
            (get_robot(&client, &ns, "kiwi-2").await.ok()?.status?.phase
                == Some(RobotPhase::Pending))
            .then_some(())
        },
    )
    .await?;
    println!(
        "operator caught up {:?} after the API server was ready",
        caught_up.elapsed()
    );
    assert!(op.running());
    assert_eq!(
        op.metric("lekiwi_leader_election_is_leader").await,
        Some(1.0)
    );
    Ok(())
}

/// Status writes that fail while the API server is down are retried, not dropped: a robot that
/// disconnects during the outage shows Offline once the API server is back.
#[tokio::test]
async fn gateway_status_writes_survive_an_api_outage() -> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "outage").await?;
    let mut op = OperatorProcess::start(&cp, &ns, "op", &["--heartbeat-grace-seconds", "300"])?;
    op.wait_ready().await?;
    let token = lekiwi_tests::enrollment_token(&client, &ns).await?;
    let (stays, _) = connect_agent(&op, &token, &format!("{ns}/stays")).await?;
    let (leaves, _) = connect_agent(&op, &token, &format!("{ns}/leaves")).await?;
    for name in ["stays", "leaves"] {
        wait_for(
            &format!("{name} Online"),
            Duration::from_secs(10),
            || async {
                (get_robot(&client, &ns, name).await.ok()?.status?.phase
                    == Some(RobotPhase::Online))
                .then_some(())
            },
        )
        .await?;
    }

    cp.kill()?;
    drop(leaves); // the disconnect happens while nothing can be written
    tokio::time::sleep(Duration::from_secs(4)).await;
    cp.up()?;
    let client = cp.client().await?;
    let t = Instant::now();
    wait_for(
        "the disconnect written after the outage",
        Duration::from_secs(60),
        || async {
            (get_robot(&client, &ns, "leaves").await.ok()?.status?.phase
                == Some(RobotPhase::Offline))
            .then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    println!(
        "disconnect from the outage written {:?} after the API server came back",
        t.elapsed()
    );
    assert_eq!(
        get_robot(&client, &ns, "stays")
            .await?
            .status
            .and_then(|s| s.phase),
        Some(RobotPhase::Online)
    );
    let failed = op
        .metric("lekiwi_gateway_status_writes_total{priority=\"high\",result=\"error\"}")
        .await
        .unwrap_or(0.0);
    assert!(
        failed >= 1.0,
        "the write during the outage should have failed and been retried"
    );
    assert!(op.running());
    drop(stays);
    Ok(())
}

/// An API server that restarts can take requests in while it starts and never answer them. The
/// operator reaches the API server through a proxy that cuts every connection and then, for a
/// few seconds, takes the next ones in without answering: the watches, lists and Lease renewals
/// the operator sends in that time get no answer, ever. Once the proxy forwards again the
/// operator gets over them without a restart (its requests time out, its watches end and
/// resume, a leadership it lost is won back): a Robot created afterwards is seen and given its
/// status. (The read timeout that ends such a request is tested on its own in
/// `lekiwi_core::api_client`.)
#[tokio::test]
async fn requests_the_api_server_takes_in_and_never_answers_are_sent_again() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "held").await?;
    let dir = tempfile::tempdir()?;
    let proxy = LagProxy::start(cp.api_server_addr()?).await?;
    let kubeconfig = dir.path().join("kubeconfig");
    cp.kubeconfig_via(&format!("https://{}", proxy.addr), &kubeconfig)?;
    let mut op = OperatorProcess::start_with_kubeconfig(
        &kubeconfig,
        &ns,
        "held",
        &["--role", "controller"],
    )?;
    op.wait_ready().await?;
    create_robot(&client, &ns, "before", &[]).await?;
    wait_phase(
        &client,
        &ns,
        "before",
        RobotPhase::Pending,
        Duration::from_secs(20),
    )
    .await?;

    proxy.cut_and_hold();
    tokio::time::sleep(Duration::from_secs(5)).await;
    proxy.release();
    let released = Instant::now();
    create_robot(&client, &ns, "after", &[]).await?;
    // Once the unanswered requests timed out.
    let within = READ_TIMEOUT + Duration::from_secs(60);
    wait_phase(&client, &ns, "after", RobotPhase::Pending, within)
        .await
        .map_err(|e| anyhow::anyhow!("{e}\noperator log:\n{}", op.log_text()))?;
    println!("seen {:?} after the release", released.elapsed());
    assert!(op.running());
    Ok(())
}
