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

/// A rollout of `kind` starts `kiwi` with `part` (its manager then owns that part of the spec),
/// then writes it again in `state` as planned from a store that shows no value: no spec part.
/// Returns the second write's mark and the robot as the API server then holds it.
async fn started_then_written_blind(
    robots: &Api<Robot>,
    kind: RolloutKind,
    part: RobotSpecPart,
    state: MarkState,
) -> anyhow::Result<(String, Robot)> {
    write_robot(
        robots,
        kind,
        "kiwi",
        &mark(MarkState::Started),
        Some(part),
        None,
    )
    .await?;
    let blind = write_robot(robots, kind, "kiwi", &mark(state), None, None)
        .await
        .map_err(|e| anyhow::anyhow!("the {kind:?} rollout's write was refused: {e}"))?;
    Ok((blind.mark, robots.get("kiwi").await?))
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

    // A release rollout starts the robot, then rolls it back with nothing to return to.
    let target = release()?;
    let kind = RolloutKind::Release;
    let part = RobotSpecPart {
        release: Some(target.clone()),
        agent: None,
    };
    let (mark_text, robot) =
        started_then_written_blind(&robots, kind, part, MarkState::RollingBack).await?;
    assert!(mark_text.contains("rolling-back"), "{mark_text}");
    assert_eq!(robot.spec.release.as_ref(), Some(&target));
    let annotations = robot.metadata.annotations.unwrap_or_default();
    assert!(annotations[kind.mark_annotation()].contains("rolling-back"));

    // The same for an agent rollout and `spec.agent`, the robot told nothing at first.
    let build = agent();
    let part = RobotSpecPart {
        release: None,
        agent: Some(build.clone()),
    };
    let (_, robot) =
        started_then_written_blind(&robots, RolloutKind::Agent, part, MarkState::Waiting).await?;
    assert_eq!(robot.spec.agent.as_ref(), Some(&build));
    assert_eq!(
        robot.spec.release.as_ref(),
        Some(&target),
        "release kept too"
    );

    // A robot that never had a release gets none from such a write.
    create_robot(&client, &ns, "kiwi-new", &[]).await?;
    write_robot(
        &robots,
        RolloutKind::Release,
        "kiwi-new",
        &mark(MarkState::Skipped),
        None,
        None,
    )
    .await?;
    assert_eq!(robots.get("kiwi-new").await?.spec.release, None);
    Ok(())
}
