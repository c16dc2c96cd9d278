//! Who owns a robot that several RobotDeployments of its namespace select: the one with the
//! highest `spec.priority`, and among equal priorities the newest (latest creation time, then
//! the greater name). Every other deployment that selects it leaves it alone and shows it
//! `Superseded`. Release and agent deployments (`spec.agent`) never compete: each kind owns a
//! robot apart from the other. Ownership follows from the deployments alone (their selectors, priorities and
//! ages), not from what any rollout did, so it never flips back and forth.

use std::collections::BTreeMap;
use std::sync::Arc;

use jiff::Timestamp;
use kube::core::{DeserializeGuard, Selector, SelectorExt};
use kube::runtime::reflector::{ObjectRef, Store};
use kube::{Resource, ResourceExt};
use lekiwi_crds::{Robot, RobotDeployment};

use crate::trigger::Trigger;

/// How a deployment ranks for ownership: greater wins.
type Rank = (i32, Option<Timestamp>, String);

fn rank(d: &RobotDeployment) -> Rank {
    (
        d.spec.priority,
        d.metadata.creation_timestamp.as_ref().map(|t| t.0),
        d.name_any(),
    )
}

/// For each of `ours` (robots `deployment` selects) that another deployment of the namespace
/// outranks it for: the robot's name and the owner's name. Deployments being deleted do not
/// own anything.
pub(super) fn superseded(
    deployments: &Store<DeserializeGuard<RobotDeployment>>,
    deployment: &RobotDeployment,
    ours: &[&Arc<Robot>],
) -> BTreeMap<String, String> {
    let namespace = deployment.namespace();
    let mine = rank(deployment);
    let rivals: Vec<(Rank, Selector)> = deployments
        .state()
        .iter()
        .filter_map(|g| g.0.as_ref().ok())
        .filter(|d| d.namespace() == namespace && d.name_any() != deployment.name_any())
        .filter(|d| d.spec.kind() == deployment.spec.kind())
        .filter(|d| d.metadata.deletion_timestamp.is_none())
        .filter(|d| rank(d) > mine)
        .filter_map(|d| Some((rank(d), Selector::try_from(d.spec.selector.clone()).ok()?)))
        .collect();
    let mut owners = BTreeMap::new();
    for robot in ours {
        let owner = rivals
            .iter()
            .filter(|(_, selector)| selector.matches(robot.labels()))
            .max_by(|a, b| a.0.cmp(&b.0));
        if let Some(((_, _, name), _)) = owner {
            owners.insert(robot.name_any(), name.clone());
        }
    }
    owners
}

/// Wakes the other deployments of `deployment`'s namespace when its spec is new to the
/// controller (created or changed: its selector, priority or release may move ownership), so
/// that a deployment that lost (or regained) robots says so, also when it finished long ago.
pub(super) fn wake_rivals(
    deployments: &Store<DeserializeGuard<RobotDeployment>>,
    wake: &Trigger<DeserializeGuard<RobotDeployment>>,
    deployment: &RobotDeployment,
) {
    let observed = deployment
        .status
        .as_ref()
        .and_then(|s| s.observed_generation);
    if observed.is_some() && observed == deployment.meta().generation {
        return;
    }
    for other in deployments.state() {
        if other.namespace() == deployment.namespace() && other.name_any() != deployment.name_any()
        {
            wake.request(ObjectRef::from_obj(other.as_ref()));
        }
    }
}
