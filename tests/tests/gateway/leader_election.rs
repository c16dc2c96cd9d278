//! Two operator processes: exactly one reconciles; when it dies the other takes over within
//! the lease duration (plus one retry period); a graceful stop hands over at once.

use std::time::{Duration, Instant};

use k8s_openapi::api::coordination::v1::Lease;
use kube::Api;
use lekiwi_crds::RobotPhase;
use lekiwi_tests::{ControlPlane, OperatorProcess, create_robot, get_robot, namespace, wait_for};

const LEASE_SECS: u64 = 4;
const RETRY_SECS: u64 = 1;

async fn is_leader(op: &OperatorProcess) -> bool {
    op.metric("lekiwi_leader_election_is_leader").await == Some(1.0)
}

async fn reconciles(op: &OperatorProcess) -> f64 {
    op.metric("lekiwi_controller_reconciliations_total{controller=\"robot\"}")
        .await
        .unwrap_or(0.0)
}

async fn wait_reconciled(client: &kube::Client, ns: &str, name: &str) -> anyhow::Result<()> {
    wait_for(
        &format!("{name} reconciled"),
        Duration::from_secs(20),
        || async {
            let r = get_robot(client, ns, name).await.ok()?;
            (r.status?.phase == Some(RobotPhase::Pending)).then_some(())
        },
    )
    .await
}

async fn holder(client: &kube::Client, ns: &str) -> Option<String> {
    let lease = Api::<Lease>::namespaced(client.clone(), ns)
        .get("lekiwi-operator")
        .await
        .ok()?;
    lease.spec?.holder_identity
}

#[tokio::test]
async fn one_leader_and_handover_when_it_dies() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "leader").await?;
    let mut a = OperatorProcess::start(cp, &ns, "replica-a", &[])?;
    a.wait_ready().await?;
    wait_for("replica-a to lead", Duration::from_secs(10), || async {
        is_leader(&a).await.then_some(())
    })
    .await?;
    let mut b = OperatorProcess::start(cp, &ns, "replica-b", &[])?;
    b.wait_ready().await?;

    // Both serve; only the leader reconciles.
    for i in 0..5 {
        create_robot(&client, &ns, &format!("before-{i}"), &[]).await?;
    }
    for i in 0..5 {
        wait_reconciled(&client, &ns, &format!("before-{i}")).await?;
    }
    tokio::time::sleep(Duration::from_secs(2 * RETRY_SECS)).await;
    assert!(
        is_leader(&a).await && !is_leader(&b).await,
        "exactly one leader"
    );
    assert!(reconciles(&a).await >= 5.0);
    assert_eq!(reconciles(&b).await, 0.0, "the standby reconciled");
    assert_eq!(holder(&client, &ns).await.as_deref(), Some("replica-a"));

    // The leader crashes: the standby takes over within the lease duration plus a retry.
    a.kill();
    let killed = Instant::now();
    wait_for(
        "replica-b to lead",
        Duration::from_secs(LEASE_SECS * 3),
        || async { is_leader(&b).await.then_some(()) },
    )
    .await?;
    let handover = killed.elapsed();
    println!("handover after SIGKILL: {handover:?} (lease {LEASE_SECS}s, retry {RETRY_SECS}s)");
    assert!(
        handover <= Duration::from_secs(LEASE_SECS + 2 * RETRY_SECS),
        "handover took {handover:?}, more than lease duration {LEASE_SECS}s + retry"
    );
    create_robot(&client, &ns, "after", &[]).await?;
    wait_reconciled(&client, &ns, "after").await?;
    assert_eq!(holder(&client, &ns).await.as_deref(), Some("replica-b"));

    // A graceful stop releases the Lease: a new replica leads at its first attempt.
    let mut c = OperatorProcess::start(cp, &ns, "replica-c", &[])?;
    c.wait_ready().await?;
    let status = b.terminate()?;
    assert!(status.success(), "SIGTERM exit status: {status}");
    assert!(
        b.log_text().contains("released the leader Lease"),
        "{}",
        b.log_text()
    );
    let stopped = Instant::now();
    wait_for(
        "replica-c to lead",
        Duration::from_secs(LEASE_SECS * 3),
        || async { is_leader(&c).await.then_some(()) },
    )
    .await?;
    let graceful = stopped.elapsed();
    println!("handover after SIGTERM: {graceful:?}");
    assert!(
        graceful <= Duration::from_secs(RETRY_SECS + 1),
        "graceful handover took {graceful:?}"
    );
    Ok(())
}
