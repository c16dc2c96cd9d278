//! Which deployments a robot's change can move on: those of its namespace whose selector matches
//! its labels, the ones its marks name (the deployment that started it, of either rollout kind),
//! and the ones its previous change concerned (so a robot that leaves a selector, or whose mark
//! is taken over, still wakes the deployment it left). Only active deployments are woken
//! ([`super::facts::is_active`]). A robot change thus costs reconciles of the few deployments
//! it concerns, not of every deployment of its namespace.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};

use kube::ResourceExt;
use kube::core::{DeserializeGuard, Selector, SelectorExt};
use lekiwi_crds::deployment::RolloutKind;
use lekiwi_crds::{Robot, RobotDeployment};

use super::facts::is_active;
use super::plan::Mark;

/// A robot by namespace and name.
type RobotId = (String, String);

/// The deployments each robot's last change concerned.
#[derive(Debug, Default)]
pub(super) struct RobotIndex {
    concerned: Mutex<HashMap<RobotId, BTreeSet<String>>>,
}

impl RobotIndex {
    /// The names of the active deployments of `robot`'s namespace that its change (added or
    /// modified) concerns, among `deployments`; remembers the ones it concerns now for its next
    /// change.
    pub fn applied(
        &self,
        robot: &Robot,
        deployments: &[Arc<DeserializeGuard<RobotDeployment>>],
    ) -> BTreeSet<String> {
        let namespace = robot.namespace().unwrap_or_default();
        let mut now: BTreeSet<String> = marked_by(robot).collect();
        now.extend(
            of_namespace(deployments, &namespace)
                .filter(|d| {
                    Selector::try_from(d.spec.selector.clone())
                        .is_ok_and(|s| s.matches(robot.labels()))
                })
                .map(|d| d.name_any()),
        );
        let before = self
            .lock()
            .insert((namespace.clone(), robot.name_any()), now.clone())
            .unwrap_or_default();
        active(deployments, &namespace, &now.union(&before).collect())
    }

    /// The active deployments a deleted `robot` concerned; forgets the robot.
    pub fn deleted(
        &self,
        robot: &Robot,
        deployments: &[Arc<DeserializeGuard<RobotDeployment>>],
    ) -> BTreeSet<String> {
        let namespace = robot.namespace().unwrap_or_default();
        let mut names: BTreeSet<String> = marked_by(robot).collect();
        names.extend(
            self.lock()
                .remove(&(namespace.clone(), robot.name_any()))
                .unwrap_or_default(),
        );
        active(deployments, &namespace, &names.iter().collect())
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<RobotId, BTreeSet<String>>> {
        self.concerned.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The deployments named in `robot`'s marks (one per rollout kind).
fn marked_by(robot: &Robot) -> impl Iterator<Item = String> + '_ {
    [RolloutKind::Release, RolloutKind::Agent]
        .into_iter()
        .filter_map(|kind| Mark::of(robot, kind))
        .map(|m| m.deployment)
}

/// The deployments of `namespace` among `all` that match the schema.
fn of_namespace<'a>(
    all: &'a [Arc<DeserializeGuard<RobotDeployment>>],
    namespace: &'a str,
) -> impl Iterator<Item = &'a RobotDeployment> + 'a {
    all.iter()
        .filter_map(|g| g.0.as_ref().ok())
        .filter(move |d| d.namespace().as_deref() == Some(namespace))
}

/// Those of `names` that are active deployments of `namespace` among `all`.
fn active(
    all: &[Arc<DeserializeGuard<RobotDeployment>>],
    namespace: &str,
    names: &BTreeSet<&String>,
) -> BTreeSet<String> {
    all.iter()
        .filter(|g| {
            g.0.as_ref().is_ok_and(|d| {
                d.namespace().as_deref() == Some(namespace) && names.contains(&d.name_any())
            }) && is_active(g)
        })
        .map(|g| g.name_any())
        .collect()
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
    use lekiwi_crds::deployment::{MARK_ANNOTATION, RolloutPhase};
    use lekiwi_crds::{RobotDeploymentSpec, RobotDeploymentStatus, RobotSpec};

    use super::super::{facts, plan};
    use super::*;

    fn deployment(
        name: &str,
        group: &str,
        phase: RolloutPhase,
    ) -> Arc<DeserializeGuard<RobotDeployment>> {
        let mut d = RobotDeployment::new(
            name,
            RobotDeploymentSpec {
                selector: LabelSelector {
                    match_labels: Some(BTreeMap::from([("g".to_owned(), group.to_owned())])),
                    ..LabelSelector::default()
                },
                release: Some(Default::default()),
                agent: None,
                strategy: Default::default(),
                paused: false,
                analysis: None,
                priority: 0,
            },
        );
        d.metadata.namespace = Some("lab".into());
        let id = plan::rollout_id(&facts::target(&d.spec), None);
        d.status = Some(RobotDeploymentStatus {
            phase: Some(phase),
            rollout_id: Some(format!("{id}-20261205t100000z")),
            ..RobotDeploymentStatus::default()
        });
        Arc::new(DeserializeGuard(Ok(d)))
    }

    fn robot(group: &str, marked_by: Option<&str>) -> Robot {
        let mut r = Robot::new("kiwi-1", RobotSpec::default());
        r.metadata.namespace = Some("lab".into());
        r.metadata.labels = Some(BTreeMap::from([("g".to_owned(), group.to_owned())]));
        if let Some(d) = marked_by {
            let mark = serde_json::to_string(&Mark {
                deployment: d.to_owned(),
                rollout_id: "x".to_owned(),
                batch: 0,
                state: plan::MarkState::Started,
                since: "2026-12-05T10:00:00Z".parse().unwrap(),
                previous: None,
                message: None,
                failed: false,
            })
            .unwrap();
            r.metadata.annotations = Some(BTreeMap::from([(MARK_ANNOTATION.to_owned(), mark)]));
        }
        r
    }

    fn names(of: &[&str]) -> BTreeSet<String> {
        of.iter().map(|s| (*s).to_owned()).collect()
    }

    /// 100 active deployments over disjoint groups: a robot's change wakes the one that selects
    /// it, not the 99 others; leaving the selector still wakes the one it left, once.
    #[test]
    fn a_robot_change_wakes_only_the_deployments_it_concerns() {
        let index = RobotIndex::default();
        let mut all: Vec<_> = (0..100)
            .map(|g| {
                deployment(
                    &format!("d{g}"),
                    &format!("g{g}"),
                    RolloutPhase::Progressing,
                )
            })
            .collect();
        assert_eq!(index.applied(&robot("g7", None), &all), names(&["d7"]));
        assert_eq!(index.applied(&robot("g7", None), &all), names(&["d7"]));
        // Relabelled into another group: the old deployment hears of it, once.
        assert_eq!(
            index.applied(&robot("g8", None), &all),
            names(&["d7", "d8"])
        );
        assert_eq!(index.applied(&robot("g8", None), &all), names(&["d8"]));
        // Out of every selector but still marked by d8's rollout: d8 is woken by the mark.
        assert_eq!(
            index.applied(&robot("none", Some("d8")), &all),
            names(&["d8"])
        );
        // A finished deployment is not woken; an unknown mark wakes nothing.
        all[9] = deployment("d9", "g9", RolloutPhase::Completed);
        assert_eq!(
            index.applied(&robot("g9", Some("gone")), &all),
            names(&["d8"])
        );
        assert_eq!(index.applied(&robot("g9", None), &all), names(&[]));
        // Deleted: whatever it concerned last, then nothing more is remembered.
        index.applied(&robot("g3", None), &all);
        assert_eq!(index.deleted(&robot("g3", None), &all), names(&["d3"]));
        assert!(index.lock().is_empty());
    }
}
