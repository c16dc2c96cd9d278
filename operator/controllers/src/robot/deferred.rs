//! A new spec of an Online robot is acknowledged by its gateway: the status write that reports
//! the deploy's outcome carries the new `observedGeneration` and `UpToDate` (see
//! `lekiwi_presence`'s `phase`), so the controller does not write `ReleasePending` in between,
//! one write per robot of a rollout fewer. It writes only if the gateway has not within
//! [`GATEWAY_WAIT`] (a deploy that never starts, a gateway that lost the robot).

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Duration;

use lekiwi_crds::robot::CONDITION_UP_TO_DATE;
use lekiwi_crds::{Condition, Robot, RobotPhase};
use tokio::time::Instant;

use lekiwi_liveness::{GatewayState, Plan};

/// How long the controller leaves an Online robot's new spec to its gateway's write.
pub const GATEWAY_WAIT: Duration = Duration::from_secs(60);

/// A robot by namespace and name.
type Key = (String, String);

/// Since when each robot's plan has differed only by a new spec (of which generation).
#[derive(Debug, Default)]
pub struct Deferred {
    since: Mutex<HashMap<Key, (Option<i64>, Instant)>>,
}

impl Deferred {
    /// How much longer the write of `plan` waits for the gateway's, or `None` to write now.
    pub fn wait(
        &self,
        key: (&str, &str),
        robot: &Robot,
        plan: &Plan,
        gateway: Option<GatewayState>,
        now: Instant,
    ) -> Option<Duration> {
        let mut since = self.since.lock().unwrap_or_else(|e| e.into_inner());
        let id = (key.0.to_owned(), key.1.to_owned());
        if !only_new_spec(robot, plan, gateway) {
            since.remove(&id);
            return None;
        }
        let first = since.entry(id).or_insert((plan.observed_generation, now));
        if first.0 != plan.observed_generation {
            *first = (plan.observed_generation, now);
        }
        GATEWAY_WAIT
            .checked_sub(now.duration_since(first.1))
            .filter(|left| !left.is_zero())
    }

    /// The robot's status is written (or gone): nothing waits.
    pub fn forget(&self, key: (&str, &str)) {
        let mut since = self.since.lock().unwrap_or_else(|e| e.into_inner());
        since.remove(&(key.0.to_owned(), key.1.to_owned()));
    }
}

/// Whether `plan` differs from the stored status only by a new generation and what it implies
/// for `UpToDate`, for a robot Online through a live gateway (which will write both).
fn only_new_spec(robot: &Robot, plan: &Plan, gateway: Option<GatewayState>) -> bool {
    let Some(status) = robot.status.as_ref() else {
        return false;
    };
    let same = |a: &[Condition], b: &[Condition]| {
        let key = |c: &Condition| {
            (
                c.r#type.clone(),
                c.status,
                c.reason.clone(),
                c.message.clone(),
            )
        };
        let other = |c: &&Condition| c.r#type.as_str() != CONDITION_UP_TO_DATE;
        let a: Vec<_> = a.iter().filter(other).map(key).collect();
        let b: Vec<_> = b.iter().filter(other).map(key).collect();
        a == b
    };
    gateway == Some(GatewayState::Alive)
        && plan.phase == RobotPhase::Online
        && status.phase == Some(RobotPhase::Online)
        && status.observed_generation != plan.observed_generation
        && same(&status.conditions, &plan.conditions)
}

#[cfg(test)]
mod tests {
    use super::*;
    use jiff::Timestamp;
    use lekiwi_liveness::{Facts, plan};
    use serde_json::json;

    /// An Online robot of generation 1, as its gateway wrote it, whose spec then asks for 2.0.0.
    fn robot() -> Robot {
        let now = Timestamp::now().to_string();
        let mut r: Robot = serde_json::from_value(json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot",
            "metadata": { "name": "kiwi-1", "namespace": "ns", "generation": 1 },
            "spec": {},
            "status": { "connected": true, "gateway": "gw", "lastHeartbeatTime": now,
                        "connectedSince": now,
                        "currentRelease": { "version": "1.0.0", "digest": "sha256:1" } }
        }))
        .unwrap();
        let p = plan(&r, &facts());
        let status = r.status.as_mut().unwrap();
        status.phase = Some(p.phase);
        status.conditions = p.conditions;
        status.observed_generation = p.observed_generation;
        r.metadata.generation = Some(2);
        r.spec.release = Some(
            serde_json::from_value(json!({ "version": "2.0.0", "digest": "sha256:2" })).unwrap(),
        );
        r
    }

    fn facts() -> Facts {
        Facts {
            now: Timestamp::now(),
            heartbeat_grace: Duration::from_secs(90),
            gateway: Some(GatewayState::Alive),
        }
    }

    #[test]
    fn a_new_release_of_an_online_robot_waits_for_its_gateway_then_is_written() {
        let (r, d) = (robot(), Deferred::default());
        let p = plan(&r, &facts());
        assert!(p.differs_from(&r));
        let t0 = Instant::now();
        let key = ("ns", "kiwi-1");
        let alive = Some(GatewayState::Alive);
        assert_eq!(d.wait(key, &r, &p, alive, t0), Some(GATEWAY_WAIT));
        let later = t0 + Duration::from_secs(20);
        assert_eq!(
            d.wait(key, &r, &p, alive, later),
            Some(Duration::from_secs(40))
        );
        assert_eq!(d.wait(key, &r, &p, alive, t0 + GATEWAY_WAIT), None);
        // A gateway gone, or another difference (the phase), is written at once.
        let gone = Some(GatewayState::Gone);
        assert_eq!(Deferred::default().wait(key, &r, &p, gone, t0), None);
        let mut offline = p.clone();
        offline.phase = RobotPhase::Offline;
        assert_eq!(Deferred::default().wait(key, &r, &offline, alive, t0), None);
    }
}
