//! Fleet objects a test starts from: Robots, the enrollment token Secret, the gateway's URL.

use std::path::Path;
use std::time::Duration;

use anyhow::Result;
use k8s_openapi::api::core::v1::Secret;
use k8s_openapi::apimachinery::pkg::util::intstr::IntOrString;
use kube::api::{Patch, PatchParams, PostParams};
use kube::{Api, Client};
use lekiwi_crds::deployment::{RolloutPhase, RolloutStrategy, UnavailablePolicy};
use lekiwi_crds::{Robot, RobotDeployment, RobotPhase};
use serde_json::{Value, json};

use crate::operator::OperatorProcess;
use crate::wait_for;

/// Reads a robot.
pub async fn get_robot(client: &Client, namespace: &str, name: &str) -> Result<Robot> {
    Ok(Api::<Robot>::namespaced(client.clone(), namespace)
        .get(name)
        .await?)
}

/// Waits until robot `name` is in `phase` and returns it; fails after `within`.
pub async fn wait_phase(
    client: &Client,
    namespace: &str,
    name: &str,
    phase: RobotPhase,
    within: Duration,
) -> Result<Robot> {
    wait_for(&format!("{name} to be {phase}"), within, || async {
        let r = get_robot(client, namespace, name).await.ok()?;
        (r.status.as_ref()?.phase == Some(phase)).then_some(r)
    })
    .await
}

/// Waits until at least `n` robots of `namespace` are `Online`; fails after `within`.
pub async fn wait_online(
    client: &Client,
    namespace: &str,
    n: usize,
    within: Duration,
) -> Result<()> {
    let api = Api::<Robot>::namespaced(client.clone(), namespace);
    wait_for(&format!("{n} robots Online"), within, || async {
        let robots = api.list(&Default::default()).await.ok()?.items;
        let online = robots
            .iter()
            .filter(|r| r.status.as_ref().and_then(|s| s.phase) == Some(RobotPhase::Online))
            .count();
        (online >= n).then_some(())
    })
    .await
}

/// Waits until rollout `name` has ended (`Completed`, `RolledBack` or `Failed`, in a status of
/// its current generation) and returns the RobotDeployment; fails after `within`.
pub async fn rollout_finished(
    api: &Api<RobotDeployment>,
    name: &str,
    within: Duration,
) -> Result<RobotDeployment> {
    wait_for(&format!("rollout {name} to end"), within, || async {
        let d = api.get(name).await.ok()?;
        let st = d.status.as_ref()?;
        (st.observed_generation == d.metadata.generation
            && matches!(
                st.phase,
                Some(
                    RolloutPhase::Completed
                        | RolloutPhase::RolledBack
                        | RolloutPhase::Failed
                        | RolloutPhase::Aborted
                )
            ))
        .then_some(d)
    })
    .await
}

/// A rollout strategy for tests: batches of `batch` robots after a canary of `canary`, success
/// threshold 0.8, robots given 60 s, no pause between batches, teleoperated and unavailable
/// robots waited for up to 120 s.
pub fn test_strategy(batch: i32, canary: i32) -> RolloutStrategy {
    RolloutStrategy {
        batch_size: IntOrString::Int(batch),
        canary,
        success_threshold: 0.8,
        robot_timeout_seconds: 60,
        pause_between_batches_seconds: 0,
        teleoperated: UnavailablePolicy::Wait,
        unavailable: UnavailablePolicy::Wait,
        wait_timeout_seconds: 120,
    }
}

/// Creates a robot with only a display name and `labels` in its spec.
pub async fn create_robot(
    client: &Client,
    namespace: &str,
    name: &str,
    labels: &[(&str, &str)],
) -> Result<Robot> {
    let labels: serde_json::Map<String, Value> = labels
        .iter()
        .map(|(k, v)| (k.to_string(), json!(v)))
        .collect();
    let robot: Robot = serde_json::from_value(json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "Robot",
        "metadata": { "name": name, "labels": labels },
        "spec": { "displayName": format!("Test robot {name}") }
    }))?;
    Ok(Api::<Robot>::namespaced(client.clone(), namespace)
        .create(&PostParams::default(), &robot)
        .await?)
}

/// Sets robot `name`'s `spec.release` to `release` (a `ReleaseRef` as JSON, or a hand-written
/// one), by merge patch.
pub async fn set_release(
    client: &Client,
    namespace: &str,
    name: &str,
    release: &Value,
) -> Result<Robot> {
    let patch = json!({"spec": {"release": release}});
    Ok(Api::<Robot>::namespaced(client.clone(), namespace)
        .patch(name, &PatchParams::default(), &Patch::Merge(&patch))
        .await?)
}

/// Sets robot `name`'s `spec.agent` to `version` with the one build `arch`/`digest`; fails when
/// the API server pruned the field (a CRD without it).
pub async fn set_agent(
    client: &Client,
    namespace: &str,
    name: &str,
    version: &str,
    arch: &str,
    digest: &str,
) -> Result<()> {
    let agent = json!({"version": version, "builds": [{"arch": arch, "digest": digest}]});
    let patch = json!({"spec": {"agent": agent}});
    let robot = Api::<Robot>::namespaced(client.clone(), namespace)
        .patch(name, &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    anyhow::ensure!(
        robot.spec.agent.is_some(),
        "the API server pruned spec.agent"
    );
    Ok(())
}

/// The gateway's WebSocket URL of an operator process.
pub fn gateway_url(op: &OperatorProcess) -> String {
    format!(
        "ws://127.0.0.1:{}{}",
        op.gateway_port,
        lekiwi_protocol::AGENT_PATH
    )
}

/// Creates a fleet enrollment token for `namespace` and writes it to `path`, for an agent's
/// `--enrollment-token-file`.
pub async fn enrollment_token_file(client: &Client, namespace: &str, path: &Path) -> Result<()> {
    std::fs::write(path, enrollment_token(client, namespace).await?)?;
    Ok(())
}

/// Creates a fleet enrollment token for `namespace` (stored as a hash) and returns it.
pub async fn enrollment_token(client: &Client, namespace: &str) -> Result<String> {
    let token = lekiwi_crds::contract::new_token("lke_");
    let secret = lekiwi_crds::contract::enrollment_token_secret(&token);
    Api::<Secret>::namespaced(client.clone(), namespace)
        .create(&PostParams::default(), &secret)
        .await?;
    Ok(token)
}

/// Gives existing robot `name` its own token (as `kubectl lekiwi robot add` does: the hash in
/// Secret `<name>-agent-token`, owned by the Robot) and returns it.
pub async fn robot_token(client: &Client, namespace: &str, name: &str) -> Result<String> {
    use kube::Resource;
    let robot = get_robot(client, namespace, name).await?;
    let token = lekiwi_crds::contract::new_token("lkr_");
    let secret =
        lekiwi_crds::contract::robot_token_secret(name, &token, robot.controller_owner_ref(&()));
    Api::<Secret>::namespaced(client.clone(), namespace)
        .create(&PostParams::default(), &secret)
        .await?;
    Ok(token)
}
