//! The Robots as the gateway's watch last saw them, read by what each part of the gateway
//! needs: the release and agent build a robot should run (what sessions send deploy commands for
//! and what the legacy poll answers), the digests a namespace may download, and who holds each
//! robot (what the status writer's fence reads first).

use std::collections::BTreeSet;
use std::sync::Arc;

use lekiwi_crds::{AgentRef, Robot};
use lekiwi_protocol::Release;

use lekiwi_core::RobotKey;
use lekiwi_core::cache::Cache;
use lekiwi_liveness::holder::Holder;

/// The gateway's Robot cache (the one its Robot watch fills and the Fleet API answers from),
/// read robot by robot.
#[derive(Clone)]
pub struct WatchedRobots(pub Arc<Cache<Robot>>);

impl WatchedRobots {
    /// The Robot `key` as the cache holds it.
    pub fn robot(&self, key: &RobotKey) -> Option<Arc<Robot>> {
        self.0.get(&key.namespace, &key.name)
    }

    /// The release `key` should run, if its Robot is in the cache and names one.
    pub fn get(&self, key: &RobotKey) -> Option<Release> {
        self.lookup(key).flatten()
    }

    /// `None` when the Robot is not in the cache (it may not exist, or the watch has not
    /// delivered it yet); otherwise its `spec.release`, which may be unset.
    pub fn lookup(&self, key: &RobotKey) -> Option<Option<Release>> {
        self.robot(key)
            .map(|r| r.spec.release.as_ref().map(Release::from))
    }

    /// The robot's `spec.agent`, if its Robot is in the cache and names one.
    pub fn agent(&self, key: &RobotKey) -> Option<AgentRef> {
        self.robot(key).and_then(|r| r.spec.agent.clone())
    }

    /// The agent build digests the Robots of `namespace` name in `spec.agent`: the agent
    /// binaries a robot of that namespace may download.
    pub fn agent_digests_in(&self, namespace: &str) -> BTreeSet<String> {
        self.in_namespace(namespace)
            .iter()
            .filter_map(|r| r.spec.agent.as_ref())
            .flat_map(|a| a.builds.iter().map(|b| b.digest.clone()))
            .collect()
    }

    /// Who holds `key` according to its status as the watch last saw it; `None` when the Robot
    /// is not in the cache.
    pub fn holder(&self, key: &RobotKey) -> Option<Holder> {
        self.robot(key).map(|r| Holder::of(&r))
    }

    /// The manifest digests the Robots of `namespace` name in `spec.release`: the releases a
    /// robot of that namespace may download.
    pub fn digests_in(&self, namespace: &str) -> BTreeSet<String> {
        self.in_namespace(namespace)
            .iter()
            .filter_map(|r| r.spec.release.as_ref().map(|rel| rel.digest.to_string()))
            .collect()
    }

    fn in_namespace(&self, namespace: &str) -> Vec<Arc<Robot>> {
        self.0.page(Some(namespace), None, usize::MAX, |_| true).0
    }
}
