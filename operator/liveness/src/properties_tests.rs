//! Properties of the liveness rules over random robots and facts (proptest; cases:
//! `PROPTEST_CASES`): Online only through a live gateway with a fresh heartbeat, Unknown exactly
//! when a connected robot's gateway is gone, one condition per concern that agrees with the
//! phase, a plan that is a fixed point once written, and an Online robot that turns Offline
//! when its heartbeat ages past the grace without a wake-up missed in between.

use std::time::Duration;

use jiff::{SignedDuration, Timestamp};
use lekiwi_crds::{ConditionStatus, Robot, RobotPhase};
use proptest::prelude::*;
use serde_json::json;

use super::{Facts, GatewayState, Plan, plan};

/// A robot as either writer may find it: any mix of connection facts, reports and spec.
#[derive(Clone, Debug)]
struct Case {
    connected: Option<bool>,
    /// Seconds between the last heartbeat and now (negative: a clock ahead of ours).
    heartbeat_age_s: Option<i64>,
    ever_connected: bool,
    maintenance: bool,
    healthy: Option<bool>,
    teleoperated: Option<bool>,
    release: (Option<u8>, Option<u8>),
    generation: i64,
    gateway: Option<GatewayState>,
    grace_s: u64,
}

fn case() -> impl Strategy<Value = Case> {
    let gateway = prop_oneof![
        Just(None),
        Just(Some(GatewayState::Alive)),
        Just(Some(GatewayState::Gone))
    ];
    (
        (
            proptest::option::of(any::<bool>()),
            proptest::option::of(-120i64..400),
            any::<bool>(),
            any::<bool>(),
        ),
        (
            proptest::option::of(any::<bool>()),
            proptest::option::of(any::<bool>()),
            (proptest::option::of(0u8..3), proptest::option::of(0u8..3)),
            1i64..5,
        ),
        (gateway, 5u64..200),
    )
        .prop_map(
            |(
                (connected, age, ever, maintenance),
                (healthy, teleop, release, generation),
                (gateway, grace_s),
            )| Case {
                connected,
                heartbeat_age_s: age,
                ever_connected: ever,
                maintenance,
                healthy,
                teleoperated: teleop,
                release,
                generation,
                gateway,
                grace_s,
            },
        )
}

const NOW: &str = "2026-12-01T12:00:00Z";

fn release(n: u8) -> serde_json::Value {
    json!({ "version": format!("1.0.{n}"), "digest": format!("sha256:{}", format!("{n}").repeat(64)) })
}

impl Case {
    fn now(&self) -> Timestamp {
        NOW.parse().unwrap()
    }

    fn facts(&self, now: Timestamp) -> Facts {
        Facts {
            now,
            heartbeat_grace: Duration::from_secs(self.grace_s),
            gateway: self.gateway,
        }
    }

    fn heartbeat(&self) -> Option<Timestamp> {
        let age = SignedDuration::from_secs(self.heartbeat_age_s?);
        Some(self.now() - age)
    }

    fn robot(&self) -> Robot {
        let mut status = json!({ "gateway": "gw-a" });
        if let Some(c) = self.connected {
            status["connected"] = json!(c);
        }
        if let Some(t) = self.heartbeat() {
            status["lastHeartbeatTime"] = json!(t.to_string());
        }
        if self.ever_connected {
            status["connectedSince"] = json!("2026-12-01T11:00:00Z");
        }
        if let Some(h) = self.healthy {
            status["health"] = json!({ "healthy": h });
        }
        if let Some(t) = self.teleoperated {
            status["teleoperation"] = json!({ "active": t });
        }
        if let Some(r) = self.release.1 {
            status["currentRelease"] = release(r);
        }
        let mut spec = json!({ "maintenance": self.maintenance });
        if let Some(r) = self.release.0 {
            spec["release"] = release(r);
        }
        serde_json::from_value(json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "metadata": { "name": "kiwi", "namespace": "lab", "generation": self.generation },
            "spec": spec,
            "status": status,
        }))
        .unwrap()
    }

    /// Whether the connection itself is live: connected, through a live gateway, with a
    /// heartbeat within the grace.
    fn live(&self) -> bool {
        self.connected == Some(true)
            && self.gateway == Some(GatewayState::Alive)
            && self
                .heartbeat_age_s
                .is_some_and(|age| age <= self.grace_s as i64)
    }
}

fn condition(p: &Plan, t: &str) -> ConditionStatus {
    let found: Vec<_> = p.conditions.iter().filter(|c| c.r#type == t).collect();
    assert_eq!(found.len(), 1, "one {t} condition: {:?}", p.conditions);
    found[0].status
}

/// The robot with `p` written as its controller or gateway would write it.
fn written(robot: &Robot, p: &Plan) -> Robot {
    let mut robot = robot.clone();
    let status = robot.status.get_or_insert_with(Default::default);
    status.phase = Some(p.phase);
    status.conditions = p.conditions.clone();
    status.observed_generation = p.observed_generation;
    robot
}

proptest! {
    #[test]
    fn the_phase_follows_from_the_connection_and_the_gateway(c in case()) {
        let p = plan(&c.robot(), &c.facts(c.now()));
        let expected = if c.maintenance {
            RobotPhase::Maintenance
        } else if c.connected == Some(true) && c.gateway != Some(GatewayState::Alive) {
            RobotPhase::Unknown
        } else if c.live() {
            RobotPhase::Online
        } else if c.connected == Some(true) || c.heartbeat_age_s.is_some() || c.ever_connected {
            RobotPhase::Offline
        } else {
            RobotPhase::Pending
        };
        prop_assert_eq!(p.phase, expected, "{:?}", c);
        // Never Online without a live session through a live gateway.
        prop_assert!(p.phase != RobotPhase::Online || c.live());
    }

    #[test]
    fn conditions_agree_with_the_connection(c in case()) {
        let p = plan(&c.robot(), &c.facts(c.now()));
        let connected = condition(&p, "Connected");
        prop_assert_eq!(connected == ConditionStatus::True, c.live(), "{:?}", c);
        prop_assert_eq!(
            connected == ConditionStatus::Unknown,
            c.connected == Some(true) && c.gateway != Some(GatewayState::Alive)
        );
        // Health and teleoperation are known only while the connection is live.
        for t in ["Healthy", "Teleoperating"] {
            let s = condition(&p, t);
            prop_assert!(c.live() || s == ConditionStatus::Unknown, "{} {:?} for {:?}", t, s, c);
        }
        let up_to_date = condition(&p, "UpToDate") == ConditionStatus::True;
        prop_assert_eq!(up_to_date, c.release.0.is_none() || c.release.0 == c.release.1);
        prop_assert!(p.conditions.iter().all(|x| x.observed_generation == Some(c.generation)));
    }

    #[test]
    fn a_written_plan_is_a_fixed_point(c in case(), later_s in 0i64..30) {
        let robot = c.robot();
        let p = plan(&robot, &c.facts(c.now()));
        let robot = written(&robot, &p);
        prop_assert!(!p.differs_from(&robot));
        // Planned again a little later from what was written, with the same facts: nothing
        // to write, unless the heartbeat crossed the grace meanwhile.
        let later = c.now() + SignedDuration::from_secs(later_s);
        let again = plan(&robot, &c.facts(later));
        let crossed = c.live() && c.heartbeat_age_s.is_some_and(|a| a + later_s > c.grace_s as i64);
        if !crossed {
            prop_assert!(!again.differs_from(&robot), "{:?}: {:?} then {:?}", c, p, again);
            // Transition times of unchanged conditions are kept.
            prop_assert_eq!(&again.conditions, &p.conditions);
        }
    }

    #[test]
    fn an_online_robot_goes_offline_when_its_heartbeat_expires_and_is_woken_then(c in case()) {
        let p = plan(&c.robot(), &c.facts(c.now()));
        prop_assert_eq!(p.requeue_after.is_some(), c.live(), "{:?}", c);
        if let Some(wake) = p.requeue_after {
            prop_assume!(!c.maintenance);
            // Woken no later than half a second past the grace, and at that moment Offline.
            let age = c.heartbeat_age_s.unwrap_or_default().max(0).unsigned_abs();
            prop_assert!(wake <= Duration::from_secs(c.grace_s.saturating_sub(age)) + Duration::from_millis(500));
            let then = c.now() + SignedDuration::try_from(wake).unwrap();
            let woken = plan(&written(&c.robot(), &p), &c.facts(then));
            if c.heartbeat_age_s.is_some_and(|a| a >= 0) {
                prop_assert_eq!(woken.phase, RobotPhase::Offline, "{:?} woken after {:?}", c, wake);
            }
        }
    }
}
