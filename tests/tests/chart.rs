//! The Helm chart: lints, renders to objects the API server accepts, installs, and its RBAC is
//! exactly enough: the operator runs the Robot controller with the chart's ServiceAccount token
//! and never meets a Forbidden.

use std::time::Duration;

use lekiwi_crds::RobotPhase;
use lekiwi_tests::{
    ControlPlane, GatewayStandIn, OperatorProcess, create_robot, get_robot, namespace, wait_for,
};

fn ok(out: std::process::Output, what: &str) -> String {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{what} failed:\n{text}");
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[tokio::test]
async fn chart_installs_and_its_rbac_suffices() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "chart").await?;
    let watch = format!("operator.watchNamespace={ns}");

    ok(
        cp.tool("helm", &["lint", "--strict", "charts/lekiwi-operator"]),
        "helm lint",
    );
    let rendered = ok(
        cp.tool(
            "helm",
            &[
                "template",
                &ns,
                "charts/lekiwi-operator",
                "-n",
                &ns,
                "--include-crds",
                "--set",
                &watch,
            ],
        ),
        "helm template",
    );
    let dir = tempfile::tempdir()?;
    let file = dir.path().join("rendered.yaml");
    std::fs::write(&file, &rendered)?;
    ok(
        cp.kubectl(&[
            "apply",
            "--dry-run=server",
            "-n",
            &ns,
            "-f",
            file.to_str().unwrap(),
        ]),
        "server dry-run of the rendered chart",
    );

    // Release named after the namespace so cluster-scoped RBAC objects never collide.
    ok(
        cp.tool(
            "helm",
            &[
                "install",
                &ns,
                "charts/lekiwi-operator",
                "-n",
                &ns,
                "--set",
                &watch,
                "--wait=false",
            ],
        ),
        "helm install",
    );
    let sa = format!("{ns}-lekiwi-operator");
    let token = ok(
        cp.kubectl(&["create", "token", &sa, "-n", &ns, "--duration=1h"]),
        "kubectl create token",
    );
    let kubeconfig = dir.path().join("kubeconfig-sa");
    cp.kubeconfig_with_token(token.trim(), &kubeconfig)?;

    let mut op = OperatorProcess::start_with_kubeconfig(
        &kubeconfig,
        &ns,
        "chart-sa",
        &["--heartbeat-grace-seconds", "30"],
    )?;
    op.wait_ready().await?;
    wait_for("leadership", Duration::from_secs(10), || async {
        (op.metric("lekiwi_leader_election_is_leader").await == Some(1.0)).then_some(())
    })
    .await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let mut gw = GatewayStandIn::start(&client, &ns, "gateway-c", 10).await?;
    gw.connect("kiwi-1").await?;
    wait_for(
        "Online under the chart's RBAC",
        Duration::from_secs(20),
        || async {
            (get_robot(&client, &ns, "kiwi-1").await.ok()?.status?.phase
                == Some(RobotPhase::Online))
            .then_some(())
        },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    gw.disconnect("kiwi-1").await?;
    wait_for("Offline", Duration::from_secs(10), || async {
        (get_robot(&client, &ns, "kiwi-1").await.ok()?.status?.phase == Some(RobotPhase::Offline))
            .then_some(())
    })
    .await?;
    // The gateway under the same credentials: enrollment (creates a Robot and its token Secret),
    // presence, durable events, a legacy poll.
    let enroll = lekiwi_tests::enrollment_token(&client, &ns).await?;
    let creds = lekiwi_agent::connection::Credentials {
        token: enroll.clone(),
        robot: format!("{ns}/kiwi-2"),
    };
    let (ws, welcome) = lekiwi_agent::connection::connect(
        &lekiwi_tests::gateway_url(&op),
        &creds,
        &lekiwi_tests::hello(),
        Duration::from_secs(10),
    )
    .await?;
    assert!(welcome.robot_token.is_some());
    wait_for("enrolled robot Online", Duration::from_secs(20), || async {
        (get_robot(&client, &ns, "kiwi-2").await.ok()?.status?.phase == Some(RobotPhase::Online))
            .then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", op.log_text()))?;
    drop(ws);
    wait_for(
        "enrolled robot Offline",
        Duration::from_secs(20),
        || async {
            (get_robot(&client, &ns, "kiwi-2").await.ok()?.status?.phase
                == Some(RobotPhase::Offline))
            .then_some(())
        },
    )
    .await?;
    let (code, _, body) = lekiwi_tests::http_get_with(
        op.gateway_port,
        &format!("/v1/poll?robot={ns}/kiwi-1&version=0.1.0"),
        &[("authorization", &format!("Bearer {enroll}"))],
    )
    .await?;
    assert_eq!(code, 200, "{body}");

    // Events went through too (they are written with the same credentials).
    let events = ok(
        cp.kubectl(&[
            "get",
            "events",
            "-n",
            &ns,
            "-o",
            "jsonpath={.items[*].reason}",
        ]),
        "get events",
    );
    assert!(
        events.contains("RobotOnline") && events.contains("RobotOffline"),
        "events: {events}"
    );
    op.terminate()?;
    let log = op.log_text();
    assert!(
        !log.contains("Forbidden") && !log.contains("forbidden"),
        "RBAC gap:\n{log}"
    );
    assert!(log.contains("released the leader Lease"), "{log}");
    Ok(())
}
