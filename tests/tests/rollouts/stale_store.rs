//! A rollout's write of a robot planned from a Robot store that is behind the API server,
//! against the real API server: the write carries no value for the part of the spec the
//! rollout owns (the store shows none), yet the robot keeps the one the rollout set earlier.
//!
//! Found by the hour-long soak at 10,000 robots: after an API server restart the rollout
//! controller's store lagged, a batch rolled back, and its writes of robots that ran nothing
//! before carried no `spec.release`. Server-side apply then removes the field the rollout's
//! manager owned, the API server refused the result (`spec.release: null`), and every later
//! reconcile failed the same way, holding the rollout for minutes.

use jiff::Timestamp;
use kube::Api;
use lekiwi_controllers::deployment::apply::write_robot;
use lekiwi_controllers::deployment::plan::{Mark, MarkState};
use lekiwi_core::apply::RobotSpecPart;
use lekiwi_crds::deployment::RolloutKind;
use lekiwi_crds::{AgentArch, AgentBuild, AgentRef, ReleaseRef, Robot};
use lekiwi_tests::{ControlPlane, create_robot, namespace};

fn mark(state: MarkState) -> Mark {
    Mark {
        deployment: "roll".into(),
        rollout_id: "r1".into(),
        batch: 4,
        state,
        since: Timestamp::now(),
        previous: None,
        message: None,
        failed: false,
    }
}

fn release() -> anyhow::Result<ReleaseRef> {
    Ok(serde_json::from_value(serde_json::json!({
        "version": "4.0.0",
        "digest": format!("sha256:{}", "b".repeat(64)),
    }))?)
}

fn agent() -> AgentRef {
    AgentRef {
        version: "0.3.0".into(),
        builds: vec![AgentBuild {
            arch: AgentArch::Arm64,
            digest: format!("sha256:{}", "c".repeat(64)),
        }],
    }
}

#[tokio::test]
async fn a_write_planned_from_a_lagging_store_keeps_the_spec_the_rollout_set() -> anyhow::Result<()>
{
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "stale").await?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    // Created as enrollment creates robots: a plain create, no release, no agent.
    create_robot(&client, &ns, "kiwi", &[]).await?;

    // A release rollout starts the robot (its manager now owns `spec.release`), rolls it back
    // with nothing to return to, and plans that write from a store that shows no release.
    let target = release()?;
    let started = Some(RobotSpecPart {
        release: Some(target.clone()),
        agent: None,
    });
    let kind = RolloutKind::Release;
    write_robot(
        &robots,
        kind,
        "kiwi",
        &mark(MarkState::Started),
        started,
        None,
    )
    .await?;
    let back = write_robot(
        &robots,
        kind,
        "kiwi",
        &mark(MarkState::RollingBack),
        None,
        None,
    )
    .await
    .map_err(|e| anyhow::anyhow!("the rollback write was refused: {e}"))?;
    assert!(back.mark.contains("rolling-back"), "{}", back.mark);
    let robot = robots.get("kiwi").await?;
    assert_eq!(robot.spec.release.as_ref(), Some(&target));
    let annotations = robot.metadata.annotations.unwrap_or_default();
    assert!(annotations[kind.mark_annotation()].contains("rolling-back"));

    // The same for an agent rollout and `spec.agent`.
    let build = agent();
    let kind = RolloutKind::Agent;
    let started = Some(RobotSpecPart {
        release: None,
        agent: Some(build.clone()),
    });
    write_robot(
        &robots,
        kind,
        "kiwi",
        &mark(MarkState::Started),
        started,
        None,
    )
    .await?;
    write_robot(&robots, kind, "kiwi", &mark(MarkState::Waiting), None, None)
        .await
        .map_err(|e| anyhow::anyhow!("the agent rollout's write was refused: {e}"))?;
    let robot = robots.get("kiwi").await?;
    assert_eq!(robot.spec.agent.as_ref(), Some(&build));
    assert_eq!(
        robot.spec.release.as_ref(),
        Some(&target),
        "release kept too"
    );

    // A robot that never had a release gets none from such a write.
    create_robot(&client, &ns, "kiwi-new", &[]).await?;
    let kind = RolloutKind::Release;
    write_robot(
        &robots,
        kind,
        "kiwi-new",
        &mark(MarkState::Skipped),
        None,
        None,
    )
    .await?;
    assert_eq!(robots.get("kiwi-new").await?.spec.release, None);
    Ok(())
}
