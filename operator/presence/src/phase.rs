//! The phase and conditions the Robot controller would compute for the status the gateway is
//! about to write, added to that same write: a robot coming Online (or going Offline, or
//! changing health) costs the API server one status write, and the controller, finding the
//! status it would write already there, writes nothing.
//!
//! The controller stays the authority: it computes the same plan from what is stored, and writes
//! only where it differs (heartbeat expiry, a dead gateway's Lease, a spec the gateway's cache
//! had not seen yet).

use std::sync::Arc;
use std::time::Duration;

use jiff::Timestamp;
use kube::api::ObjectMeta;
use lekiwi_crds::{Robot, RobotStatus};
use serde_json::Value;

use super::patch::planned_status_patch;
use super::{Entry, Presence};
use crate::watched::WatchedRobots;
use lekiwi_core::RobotKey;
use lekiwi_core::apply::Metadata;
use lekiwi_liveness::{Facts, GatewayState, plan};

/// What the gateway needs to plan a robot's phase: its Robot cache (spec, generation, phase and
/// conditions) and the controller's heartbeat grace.
#[derive(Clone)]
pub struct PhasePlanner {
    robots: WatchedRobots,
    heartbeat_grace: Duration,
}

impl PhasePlanner {
    /// A planner over the gateway's Robot cache.
    pub fn new(robots: WatchedRobots, heartbeat_grace: Duration) -> Self {
        Self {
            robots,
            heartbeat_grace,
        }
    }

    /// Adds to `status` (what the gateway writes) the phase, conditions and
    /// `observedGeneration` the controller would derive from it for `known` (the Robot as the
    /// gateway knows it: just read, or in its cache).
    fn plan_into(&self, known: &Robot, status: &mut RobotStatus, now: Timestamp) {
        let stored = known.status.as_ref();
        let robot = robot_as_written(known, status, stored);
        let facts = Facts {
            now,
            heartbeat_grace: self.heartbeat_grace,
            // This gateway is writing, so it is alive; if its Lease says otherwise the
            // controller corrects the phase.
            gateway: Some(GatewayState::Alive),
        };
        let planned = plan(&robot, &facts);
        status.phase = Some(planned.phase);
        status.conditions = planned.conditions;
        status.observed_generation = planned.observed_generation;
    }
}

/// The Robot as it will be once `status` is written: the cached spec and generation, the
/// written gateway facts, and the stored phase and conditions (whose transition times a
/// condition of unchanged status keeps).
fn robot_as_written(cached: &Robot, status: &RobotStatus, stored: Option<&RobotStatus>) -> Robot {
    Robot {
        metadata: ObjectMeta {
            name: cached.metadata.name.clone(),
            namespace: cached.metadata.namespace.clone(),
            generation: cached.metadata.generation,
            ..ObjectMeta::default()
        },
        spec: cached.spec.clone(),
        status: Some(RobotStatus {
            phase: stored.and_then(|s| s.phase),
            conditions: stored.map(|s| s.conditions.clone()).unwrap_or_default(),
            observed_generation: stored.and_then(|s| s.observed_generation),
            ..status.clone()
        }),
    }
}

impl Presence {
    /// The Robot as the gateway's cache holds it, once the cache is there.
    pub(super) fn cached_robot(&self, key: &RobotKey) -> Option<Arc<Robot>> {
        self.planner.get()?.robots.robot(key)
    }

    /// Plans phases from now on (see the module docs).
    pub fn plan_phases(&self, planner: PhasePlanner) {
        let _ = self.planner.set(Arc::new(planner));
    }

    /// The apply patch of `e`: the gateway's facts plus, when the Robot is known (`fresh`, just
    /// read, or in the cache), the phase and conditions they imply. A robot that enrolled a
    /// moment ago is often not in the cache yet; planned from the Robot its write read, its
    /// first status write is the only one (without, the controller wrote the phase after it).
    pub(super) fn patch(
        &self,
        key: &RobotKey,
        e: &Entry,
        precondition: Option<Metadata>,
        fresh: Option<&Robot>,
    ) -> Value {
        // What was just read is newer than the cache; without either, the controller plans.
        let cached = fresh.is_none().then(|| self.cached_robot(key)).flatten();
        planned_status_patch(&self.config.gateway, e, precondition, |status| {
            if let (Some(planner), Some(known)) = (self.planner.get(), fresh.or(cached.as_deref()))
            {
                planner.plan_into(known, status, Timestamp::now());
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use lekiwi_core::cache::Cache;

    use super::*;
    use crate::{ConnectInfo, PresenceConfig};
    use lekiwi_metrics::Metrics;

    const CACHED: &str = r#"
apiVersion: fleet.lekiwi.io/v1alpha1
kind: Robot
metadata: { name: kiwi-1, namespace: lab, generation: 2 }
spec: {}
status:
  phase: Offline
  observedGeneration: 2
  conditions:
  - { type: Connected, status: "False", reason: Disconnected, message: "the agent disconnected from gateway gw", lastTransitionTime: "2026-01-01T00:00:00Z", observedGeneration: 2 }
  - { type: UpToDate, status: "True", reason: NoReleaseRequested, message: "spec.release is not set", lastTransitionTime: "2026-01-01T00:00:00Z", observedGeneration: 2 }
"#;

    fn presence() -> Presence {
        Presence::new(
            PresenceConfig {
                gateway: "gw".into(),
                status_refresh: Duration::from_secs(300),
                poll_grace: Duration::from_secs(180),
                qps: 10.0,
                adaptive: None,
                burst: 10,
                concurrency: 2,
            },
            Metrics::default(),
        )
    }

    /// A connect of a cached robot is written with the phase and conditions the controller
    /// would write (transition times of unchanged conditions kept); without the cache, or for
    /// a robot not in it, the write holds the gateway's facts alone, as before.
    #[test]
    fn a_connect_write_carries_the_phase_the_controller_would_write() {
        let store = WatchedRobots(Arc::new(Cache::listed([
            serde_yaml::from_str(CACHED).unwrap()
        ])));
        let p = presence();
        let (cached, stranger) = (
            RobotKey::new("lab", "kiwi-1"),
            RobotKey::new("lab", "kiwi-2"),
        );
        let info = ConnectInfo {
            protocol: "websocket",
            ..ConnectInfo::default()
        };
        p.connect(&cached, 1, 1_000, info.clone());
        p.connect(&stranger, 1, 1_000, info);
        let entry = |k: &RobotKey| p.with_state(|s| s.robots[k].clone());
        let status = |k: &RobotKey| p.patch(k, &entry(k), None, None)["status"].clone();
        assert_eq!(status(&cached).get("phase"), None, "no cache yet");

        p.plan_phases(PhasePlanner::new(store, Duration::from_secs(60)));
        let s = status(&cached);
        assert_eq!(s["phase"], json!("Online"));
        assert_eq!(s["observedGeneration"], json!(2));
        assert_eq!(s["connected"], json!(true));
        let condition = |t: &str| {
            s["conditions"]
                .as_array()
                .unwrap()
                .iter()
                .find(|c| c["type"] == t)
                .cloned()
                .unwrap()
        };
        assert_eq!(condition("Connected")["status"], json!("True"));
        assert_ne!(
            condition("Connected")["lastTransitionTime"],
            json!("2026-01-01T00:00:00Z")
        );
        assert_eq!(
            condition("UpToDate")["lastTransitionTime"],
            json!("2026-01-01T00:00:00Z")
        );
        assert_eq!(status(&stranger).get("phase"), None, "not in the cache");

        // The write read the Robot from the API server (a robot enrolled a moment ago, not in
        // the cache yet): planned from what it read.
        let mut read: Robot = serde_yaml::from_str(CACHED).unwrap();
        read.metadata.name = Some("kiwi-2".into());
        read.metadata.generation = Some(1);
        read.status = None;
        let s = p.patch(&stranger, &entry(&stranger), None, Some(&read))["status"].clone();
        assert_eq!(s["phase"], json!("Online"));
        assert_eq!(s["observedGeneration"], json!(1));
        // What was read is newer than the cache: it wins.
        read.metadata.name = Some("kiwi-1".into());
        let s = p.patch(&cached, &entry(&cached), None, Some(&read))["status"].clone();
        assert_eq!(s["observedGeneration"], json!(1));
    }
}
