//! Which robots each deployment's selector selects, and which deployments select each robot,
//! kept up to date by the robot watch. A plan reads its deployment's own robots and the
//! deployments that share them from here, so its cost follows the deployment's size: scanning
//! every robot of the store, and matching each of them against every other deployment's
//! selector, made each robot change cost more the more deployments there were.
//!
//! A deployment's set is built by one scan of the Robot store when a plan first asks for it,
//! and again when its selector changes; the watch then adds and removes robots as their labels
//! change. Scans and watch updates take one lock, and the watch updates a set only after the
//! store shows the change, so a set never misses a robot that changes during its scan.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::sync::{Arc, Mutex, MutexGuard};

use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::ResourceExt;
use kube::core::{DeserializeGuard, Selector, SelectorExt};
use kube::runtime::reflector::Store;
use lekiwi_crds::{Robot, RobotDeployment};

/// A deployment by namespace and name.
type Id = (String, String);

/// One deployment's selection.
struct Set {
    /// The selector as the deployment states it: a different one means scanning again.
    spec: LabelSelector,
    selector: Selector,
    robots: HashSet<String>,
}

#[derive(Default)]
struct Inner {
    sets: HashMap<Id, Set>,
    /// By namespace, for each robot some set holds: the deployments whose sets hold it.
    by_robot: HashMap<String, HashMap<String, BTreeSet<String>>>,
}

/// The selections of the deployments the controller plans (see the module's text).
#[derive(Default)]
pub(super) struct Members {
    inner: Mutex<Inner>,
}

/// What a plan of one deployment reads from [`Members`].
#[derive(Debug, Default, PartialEq, Eq)]
pub(super) struct Selection {
    /// The names of the robots it selects.
    pub robots: Vec<String>,
    /// For each of those robots that other deployments of the namespace select: their names.
    pub shared: BTreeMap<String, Vec<String>>,
}

impl Members {
    /// The selection of `deployment`, or None when its selector cannot be evaluated. First
    /// brings the set of every deployment of its namespace (among `all`, the deployment
    /// store's content) up to its current selector, scanning `robots` for the ones that lack
    /// one, and forgets the sets of deployments no longer among `all`.
    pub fn select(
        &self,
        robots: &Store<Robot>,
        all: &[Arc<DeserializeGuard<RobotDeployment>>],
        deployment: &RobotDeployment,
    ) -> Option<Selection> {
        let namespace = deployment.namespace().unwrap_or_default();
        let name = deployment.name_any();
        let mut inner = self.lock();
        inner.forget_gone(all);
        let mut scanned: Option<Vec<Arc<Robot>>> = None;
        for d in all.iter().filter_map(|g| g.0.as_ref().ok()) {
            if d.metadata.namespace.as_deref() != Some(namespace.as_str()) {
                continue;
            }
            let id = (namespace.clone(), d.name_any());
            if inner
                .sets
                .get(&id)
                .is_some_and(|s| s.spec == d.spec.selector)
            {
                continue;
            }
            let store = scanned.get_or_insert_with(|| {
                let mut of_namespace = robots.state();
                of_namespace.retain(|r| r.metadata.namespace.as_deref() == Some(&namespace));
                of_namespace
            });
            inner.rebuild(id, &d.spec.selector, store);
        }
        let set = inner.sets.get(&(namespace.clone(), name.clone()))?;
        let robots: Vec<String> = set.robots.iter().cloned().collect();
        let holders = inner.by_robot.get(&namespace);
        let shared = robots
            .iter()
            .filter_map(|robot| {
                let others: Vec<String> = holders?
                    .get(robot)?
                    .iter()
                    .filter(|d| **d != name)
                    .cloned()
                    .collect();
                (!others.is_empty()).then(|| (robot.clone(), others))
            })
            .collect();
        Some(Selection { robots, shared })
    }

    /// A robot was added or changed (its labels may have): it joins the sets whose selector
    /// matches it and leaves the others of its namespace.
    pub fn applied(&self, robot: &Robot) {
        self.place(robot, true);
    }

    /// A robot was deleted: it leaves every set.
    pub fn deleted(&self, robot: &Robot) {
        self.place(robot, false);
    }

    /// Puts `robot` in the sets of its namespace whose selector matches it, if it `exists`, and
    /// takes it out of the others; records which sets hold it.
    fn place(&self, robot: &Robot, exists: bool) {
        let (Some(namespace), Some(name)) = (&robot.metadata.namespace, &robot.metadata.name)
        else {
            return;
        };
        let mut inner = self.lock();
        let Inner { sets, by_robot } = &mut *inner;
        let mut holding = BTreeSet::new();
        for ((set_namespace, deployment), set) in sets.iter_mut() {
            if set_namespace != namespace {
                continue;
            }
            if exists && set.selector.matches(robot.labels()) {
                if !set.robots.contains(name) {
                    set.robots.insert(name.clone());
                }
                holding.insert(deployment.clone());
            } else {
                set.robots.remove(name);
            }
        }
        if holding.is_empty() {
            if let Some(of_namespace) = by_robot.get_mut(namespace) {
                of_namespace.remove(name);
            }
        } else {
            by_robot
                .entry(namespace.clone())
                .or_default()
                .insert(name.clone(), holding);
        }
    }

    /// Forgets every set: the watch lists the robots again (a robot deleted meanwhile brings no
    /// delete event), so the next plans scan the store the list fills.
    pub fn clear(&self) {
        let mut inner = self.lock();
        inner.sets.clear();
        inner.by_robot.clear();
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl Inner {
    /// Builds deployment `id`'s set for `spec` from `robots` (its namespace's), or drops it
    /// when the selector cannot be evaluated.
    fn rebuild(&mut self, id: Id, spec: &LabelSelector, robots: &[Arc<Robot>]) {
        self.drop_set(&id);
        let Ok(selector) = Selector::try_from(spec.clone()) else {
            return;
        };
        let members: HashSet<String> = robots
            .iter()
            .filter(|r| selector.matches(r.labels()))
            .map(|r| r.name_any())
            .collect();
        let holders = self.by_robot.entry(id.0.clone()).or_default();
        for robot in &members {
            holders
                .entry(robot.clone())
                .or_default()
                .insert(id.1.clone());
        }
        let set = Set {
            spec: spec.clone(),
            selector,
            robots: members,
        };
        self.sets.insert(id, set);
    }

    /// Removes deployment `id`'s set, and it from the robots it held.
    fn drop_set(&mut self, id: &Id) {
        let Some(set) = self.sets.remove(id) else {
            return;
        };
        let Some(of_namespace) = self.by_robot.get_mut(&id.0) else {
            return;
        };
        for robot in set.robots {
            if let Some(holders) = of_namespace.get_mut(&robot) {
                holders.remove(&id.1);
                if holders.is_empty() {
                    of_namespace.remove(&robot);
                }
            }
        }
    }

    /// Drops the sets of deployments no longer among `all`.
    fn forget_gone(&mut self, all: &[Arc<DeserializeGuard<RobotDeployment>>]) {
        let live: HashSet<(Option<&str>, &str)> = all
            .iter()
            .filter_map(|g| {
                let meta = &g.0.as_ref().ok()?.metadata;
                Some((meta.namespace.as_deref(), meta.name.as_deref()?))
            })
            .collect();
        let gone: Vec<Id> = self
            .sets
            .keys()
            .filter(|(ns, name)| !live.contains(&(Some(ns.as_str()), name.as_str())))
            .cloned()
            .collect();
        for id in gone {
            self.drop_set(&id);
        }
    }
}

#[cfg(test)]
mod tests {
    use kube::runtime::reflector;
    use kube::runtime::watcher::Event;
    use lekiwi_crds::{RobotDeploymentSpec, RobotSpec};

    use super::*;

    fn deployment(name: &str, labels: &[(&str, &str)]) -> Arc<DeserializeGuard<RobotDeployment>> {
        let mut d = RobotDeployment::new(
            name,
            RobotDeploymentSpec {
                selector: LabelSelector {
                    match_labels: Some(
                        labels
                            .iter()
                            .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
                            .collect(),
                    ),
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
        Arc::new(DeserializeGuard(Ok(d)))
    }

    fn robot(name: &str, labels: &[(&str, &str)]) -> Robot {
        let mut r = Robot::new(name, RobotSpec::default());
        r.metadata.namespace = Some("lab".into());
        r.metadata.labels = Some(
            labels
                .iter()
                .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
                .collect(),
        );
        r
    }

    fn of(d: &Arc<DeserializeGuard<RobotDeployment>>) -> &RobotDeployment {
        d.0.as_ref().unwrap()
    }

    fn sorted(mut names: Vec<String>) -> Vec<String> {
        names.sort();
        names
    }

    /// The store and the sets see the same changes in the same order: the store first.
    struct Fleet {
        store: Store<Robot>,
        writer: reflector::store::Writer<Robot>,
        members: Members,
    }

    impl Fleet {
        fn new(robots: &[Robot]) -> Self {
            let (store, mut writer) = reflector::store();
            for r in robots {
                writer.apply_watcher_event(&Event::Apply(r.clone()));
            }
            Self {
                store,
                writer,
                members: Members::default(),
            }
        }

        fn apply(&mut self, robot: Robot) {
            self.writer
                .apply_watcher_event(&Event::Apply(robot.clone()));
            self.members.applied(&robot);
        }

        fn delete(&mut self, robot: Robot) {
            self.writer
                .apply_watcher_event(&Event::Delete(robot.clone()));
            self.members.deleted(&robot);
        }

        fn select(
            &self,
            all: &[Arc<DeserializeGuard<RobotDeployment>>],
            which: usize,
        ) -> Selection {
            let mut s = self
                .members
                .select(&self.store, all, of(&all[which]))
                .unwrap();
            s.robots.sort();
            s
        }
    }

    /// A set follows the robots' labels and deletions after its first scan, is built again
    /// when its selector changes, and tells which robots another deployment shares.
    #[test]
    fn a_selection_follows_labels_selectors_and_deletions() {
        let mut fleet = Fleet::new(&[
            robot("a", &[("g", "1")]),
            robot("b", &[("g", "1"), ("lab", "x")]),
            robot("c", &[("g", "2")]),
        ]);
        let mut all = vec![
            deployment("one", &[("g", "1")]),
            deployment("x", &[("lab", "x")]),
        ];
        let first = fleet.select(&all, 0);
        assert_eq!(first.robots, ["a", "b"]);
        assert_eq!(
            first.shared,
            BTreeMap::from([("b".to_owned(), vec!["x".to_owned()])])
        );
        // Relabelled, added, deleted: no scan needed to see it.
        fleet.apply(robot("c", &[("g", "1")]));
        fleet.apply(robot("d", &[("g", "1"), ("lab", "x")]));
        fleet.apply(robot("a", &[("g", "3")]));
        fleet.delete(robot("b", &[("g", "1"), ("lab", "x")]));
        let later = fleet.select(&all, 0);
        assert_eq!(later.robots, ["c", "d"]);
        assert_eq!(
            later.shared,
            BTreeMap::from([("d".to_owned(), vec!["x".to_owned()])])
        );
        assert_eq!(sorted(fleet.select(&all, 1).robots), ["d"]);
        // A new selector is scanned again; a deployment gone is forgotten.
        all[0] = deployment("one", &[("g", "3")]);
        all.remove(1);
        assert_eq!(
            fleet.select(&all, 0),
            Selection {
                robots: vec!["a".to_owned()],
                shared: BTreeMap::new(),
            }
        );
        assert_eq!(fleet.members.lock().sets.len(), 1);
        fleet.members.clear();
        assert_eq!(fleet.select(&all, 0).robots, ["a"]);
    }

    /// A selector that cannot be evaluated selects nothing and holds no set.
    #[test]
    fn an_invalid_selector_has_no_selection() {
        let fleet = Fleet::new(&[robot("a", &[("g", "1")])]);
        let mut bad = of(&deployment("bad", &[])).clone();
        bad.spec.selector.match_expressions = Some(vec![
            k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelectorRequirement {
                key: "g".into(),
                operator: "Sideways".into(),
                values: None,
            },
        ]);
        let all = vec![Arc::new(DeserializeGuard(Ok(bad.clone())))];
        assert_eq!(fleet.members.select(&fleet.store, &all, &bad), None);
        assert!(fleet.members.lock().sets.is_empty());
    }
}
