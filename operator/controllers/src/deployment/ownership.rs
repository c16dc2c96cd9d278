//! Who owns a robot that several RobotDeployments of its namespace select: the one with the
//! highest `spec.priority`, and among equal priorities the newest (latest creation time, then
//! the greater name). Every other deployment that selects it leaves it alone and shows it
//! `Superseded`. Release and agent deployments (`spec.agent`) never compete: each kind owns a
//! robot apart from the other. Ownership follows from the deployments alone (their selectors, priorities and
//! ages), not from what any rollout did, so it never flips back and forth.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use jiff::Timestamp;
use kube::core::DeserializeGuard;
use kube::runtime::reflector::{ObjectRef, Store};
use kube::{Resource, ResourceExt};
use lekiwi_crds::RobotDeployment;

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

/// For each robot `deployment` selects that another deployment of the namespace outranks it
/// for: the robot's name and the owner's name. `shared` gives, for each of its robots that
/// others select, their names ([`super::members::Selection`]). Deployments being deleted do not
/// own anything.
pub(super) fn superseded(
    all: &[Arc<DeserializeGuard<RobotDeployment>>],
    deployment: &RobotDeployment,
    shared: &BTreeMap<String, Vec<String>>,
) -> BTreeMap<String, String> {
    let namespace = deployment.namespace();
    let mine = rank(deployment);
    let rivals: HashMap<String, Rank> = all
        .iter()
        .filter_map(|g| g.0.as_ref().ok())
        .filter(|d| d.namespace() == namespace && d.name_any() != deployment.name_any())
        .filter(|d| d.spec.kind() == deployment.spec.kind())
        .filter(|d| d.metadata.deletion_timestamp.is_none())
        .map(|d| (d.name_any(), rank(d)))
        .filter(|(_, rank)| *rank > mine)
        .collect();
    shared
        .iter()
        .filter_map(|(robot, others)| {
            let (owner, _) = others
                .iter()
                .filter_map(|o| rivals.get_key_value(o))
                .max_by(|a, b| a.1.cmp(b.1))?;
            Some((robot.clone(), owner.clone()))
        })
        .collect()
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

#[cfg(test)]
mod tests {
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
    use lekiwi_crds::RobotDeploymentSpec;

    use super::*;

    fn deployment(
        name: &str,
        priority: i32,
        created: &str,
    ) -> Arc<DeserializeGuard<RobotDeployment>> {
        let spec: RobotDeploymentSpec = serde_json::from_value(serde_json::json!({
            "selector": {},
            "release": {"version": "1", "digest": format!("sha256:{}", "a".repeat(64))},
            "priority": priority,
        }))
        .unwrap();
        let mut d = RobotDeployment::new(name, spec);
        d.metadata.namespace = Some("lab".into());
        d.metadata.creation_timestamp = Some(Time(created.parse().unwrap()));
        Arc::new(DeserializeGuard(Ok(d)))
    }

    fn shared(of: &[(&str, &[&str])]) -> BTreeMap<String, Vec<String>> {
        of.iter()
            .map(|(robot, others)| {
                (
                    (*robot).to_owned(),
                    others.iter().map(|o| (*o).to_owned()).collect(),
                )
            })
            .collect()
    }

    /// The highest priority owns a shared robot, then the newest; a deployment being deleted,
    /// an outranked one or one of the other kind does not.
    #[test]
    fn the_highest_ranked_deployment_that_selects_a_robot_owns_it() {
        let mut all = vec![
            deployment("mine", 0, "2026-12-05T10:00:00Z"),
            deployment("older", 0, "2026-12-05T09:00:00Z"),
            deployment("newer", 0, "2026-12-05T11:00:00Z"),
            deployment("urgent", 5, "2026-12-05T08:00:00Z"),
            deployment("leaving", 9, "2026-12-05T12:00:00Z"),
        ];
        let mut leaving = all[4].0.as_ref().unwrap().clone();
        leaving.metadata.deletion_timestamp = Some(Time("2026-12-05T12:30:00Z".parse().unwrap()));
        all[4] = Arc::new(DeserializeGuard(Ok(leaving)));
        let mine = all[0].0.as_ref().unwrap().clone();
        let owners = superseded(
            &all,
            &mine,
            &shared(&[
                ("a", &["older"]),
                ("b", &["newer", "older"]),
                ("c", &["newer", "urgent"]),
                ("d", &["leaving"]),
                ("e", &["unknown"]),
            ]),
        );
        let expected: BTreeMap<String, String> = [("b", "newer"), ("c", "urgent")]
            .into_iter()
            .map(|(r, o)| (r.to_owned(), o.to_owned()))
            .collect();
        assert_eq!(owners, expected);
    }
}
