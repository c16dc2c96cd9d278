//! A Robot's liveness rules, pure: its phase, conditions and next wake-up from the facts a
//! gateway recorded, the robot's spec and the state of the gateway's Lease; which gateway's
//! session holds it and which writes of its status may land ([`holder`]); what a gateway's
//! Lease says ([`gateways`]). Both writers of a Robot's phase apply them: the gateway that
//! holds its session and the Robot controller.

#[cfg(test)]
mod fence_tests;
pub mod gateways;
pub mod holder;

use std::borrow::Cow;
use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use kube::ResourceExt;
use lekiwi_crds::condition::merge_conditions;
use lekiwi_crds::contract::ENROLLED_LABEL;
use lekiwi_crds::robot::{
    CONDITION_CONNECTED, CONDITION_HEALTHY, CONDITION_TELEOPERATING, CONDITION_UP_TO_DATE,
    HealthReport, TeleoperationReport,
};
use lekiwi_crds::{Condition, ConditionStatus, ReleaseRef, Robot, RobotPhase, RobotStatus};

/// What the controller knows about the gateway named in a robot's status.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GatewayState {
    /// Its Lease was renewed within its duration.
    Alive,
    /// Its Lease expired or does not exist.
    Gone,
}

/// Inputs besides the robot itself.
#[derive(Clone, Copy, Debug)]
pub struct Facts {
    /// The current time.
    pub now: Timestamp,
    /// Heartbeats older than this make the robot Offline.
    pub heartbeat_grace: Duration,
    /// State of the robot's gateway, if its status names one.
    pub gateway: Option<GatewayState>,
}

/// Where the connection stands, before maintenance is taken into account.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Presence {
    NeverConnected,
    Online,
    Disconnected,
    HeartbeatExpired,
    GatewayGone,
}

/// The status the controller wants, and when to look again.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// The phase to write.
    pub phase: RobotPhase,
    /// The conditions to write, with transition times kept where status did not change.
    pub conditions: Vec<Condition>,
    /// The generation the plan was computed from.
    pub observed_generation: Option<i64>,
    /// Wake up after this long even if nothing changes (a heartbeat is about to expire).
    pub requeue_after: Option<Duration>,
}

impl Plan {
    /// Whether writing this plan would change the robot's status (ignoring timestamps of
    /// conditions whose status is unchanged, which `merge_conditions` already kept).
    pub fn differs_from(&self, robot: &Robot) -> bool {
        let Some(status) = robot.status.as_ref() else {
            return true;
        };
        status.phase != Some(self.phase)
            || status.observed_generation != self.observed_generation
            || status.conditions != self.conditions
    }
}

/// Computes the robot's phase and conditions: where its connection stands, the phase that
/// follows (maintenance wins), one condition per concern, and when to look again.
pub fn plan(robot: &Robot, facts: &Facts) -> Plan {
    let status = robot.status.clone().unwrap_or_default();
    let generation = robot.metadata.generation;
    let heartbeat = status.last_heartbeat_time.as_ref().map(|t| t.0);
    // A heartbeat stamped ahead of this clock (the gateway's clock runs ahead) is fresh, not
    // old: its age is zero until this clock passes it.
    let heartbeat_age = heartbeat.map(|t| {
        facts
            .now
            .duration_since(t)
            .max(jiff::SignedDuration::ZERO)
            .unsigned_abs()
    });
    let presence = presence(&status, facts, heartbeat_age);
    let phase = if robot.spec.maintenance {
        RobotPhase::Maintenance
    } else {
        presence.phase()
    };
    let online = presence == Presence::Online;
    let desired = [
        connected(presence, status.gateway.as_deref(), facts.heartbeat_grace),
        healthy(status.health.as_ref(), online),
        teleoperating(status.teleoperation.as_ref(), online),
        up_to_date(robot.spec.release.as_ref(), status.current_release.as_ref()),
    ]
    .into_iter()
    .map(|(t, s, r, m)| Condition {
        last_transition_time: Time(facts.now),
        ..Condition::new(t, s, &r, m, generation)
    })
    .collect();
    let conditions = merge_conditions(&status.conditions, desired);
    // An Online robot turns Offline when its heartbeat ages past the grace: wake up just then.
    let requeue_after = match (presence, heartbeat_age) {
        (Presence::Online, Some(age)) => {
            Some(facts.heartbeat_grace.saturating_sub(age) + Duration::from_millis(500))
        }
        _ => None,
    };
    Plan {
        phase,
        conditions,
        observed_generation: generation,
        requeue_after,
    }
}

/// A connected robot is Online only through a live gateway and with a fresh heartbeat.
fn presence(status: &RobotStatus, facts: &Facts, heartbeat_age: Option<Duration>) -> Presence {
    if status.connected == Some(true) {
        if facts.gateway != Some(GatewayState::Alive) {
            Presence::GatewayGone
        } else if heartbeat_age.is_none_or(|age| age > facts.heartbeat_grace) {
            Presence::HeartbeatExpired
        } else {
            Presence::Online
        }
    } else if status.last_heartbeat_time.is_none() && status.connected_since.is_none() {
        Presence::NeverConnected
    } else {
        Presence::Disconnected
    }
}

impl Presence {
    /// The phase of a robot not in maintenance.
    fn phase(self) -> RobotPhase {
        match self {
            Presence::NeverConnected => RobotPhase::Pending,
            Presence::Online => RobotPhase::Online,
            Presence::Disconnected | Presence::HeartbeatExpired => RobotPhase::Offline,
            Presence::GatewayGone => RobotPhase::Unknown,
        }
    }
}

/// A condition before its generation and transition time are filled in.
type Desired = (&'static str, ConditionStatus, Cow<'static, str>, String);

fn connected(presence: Presence, gateway: Option<&str>, grace: Duration) -> Desired {
    let gateway = gateway.unwrap_or("none");
    let grace = grace.as_secs();
    match presence {
        Presence::Online => cond(
            CONDITION_CONNECTED,
            ConditionStatus::True,
            "Connected",
            format!("connected through gateway {gateway}"),
        ),
        Presence::NeverConnected => cond(
            CONDITION_CONNECTED,
            ConditionStatus::False,
            "NeverConnected",
            "the robot's agent has never connected",
        ),
        Presence::Disconnected => cond(
            CONDITION_CONNECTED,
            ConditionStatus::False,
            "Disconnected",
            format!("the agent disconnected from gateway {gateway}"),
        ),
        Presence::HeartbeatExpired => cond(
            CONDITION_CONNECTED,
            ConditionStatus::False,
            "HeartbeatExpired",
            format!("no heartbeat recorded for more than {grace}s"),
        ),
        Presence::GatewayGone => cond(
            CONDITION_CONNECTED,
            ConditionStatus::Unknown,
            "GatewayLost",
            format!("gateway {gateway} stopped renewing its Lease; the robot's state is unknown"),
        ),
    }
}

fn healthy(health: Option<&HealthReport>, online: bool) -> Desired {
    match (health, online) {
        (_, false) => cond(
            CONDITION_HEALTHY,
            ConditionStatus::Unknown,
            "NotConnected",
            "health is reported only while connected",
        ),
        (None, true) => cond(
            CONDITION_HEALTHY,
            ConditionStatus::Unknown,
            "NotReported",
            "the agent has not reported a health check",
        ),
        (Some(h), true) if h.healthy => cond(
            CONDITION_HEALTHY,
            ConditionStatus::True,
            "HealthChecksPassed",
            "every health check passes",
        ),
        (Some(h), true) => cond(
            CONDITION_HEALTHY,
            ConditionStatus::False,
            // The agent's own reason (the gateway let only a CamelCase word through).
            h.reason
                .clone()
                .map_or(Cow::Borrowed("HealthCheckFailed"), Cow::Owned),
            h.message
                .clone()
                .unwrap_or_else(|| "a health check failed".into()),
        ),
    }
}

fn teleoperating(teleoperation: Option<&TeleoperationReport>, online: bool) -> Desired {
    match (teleoperation, online) {
        (_, false) => cond(
            CONDITION_TELEOPERATING,
            ConditionStatus::Unknown,
            "NotConnected",
            "teleoperation is reported only while connected",
        ),
        (None, true) => cond(
            CONDITION_TELEOPERATING,
            ConditionStatus::Unknown,
            "NotReported",
            "the agent has not reported teleoperation",
        ),
        (Some(t), true) if t.active => cond(
            CONDITION_TELEOPERATING,
            ConditionStatus::True,
            "TeleoperationDetected",
            "somebody is operating the robot",
        ),
        (Some(_), true) => cond(
            CONDITION_TELEOPERATING,
            ConditionStatus::False,
            "Idle",
            "no teleoperation detected",
        ),
    }
}

fn up_to_date(want: Option<&ReleaseRef>, have: Option<&ReleaseRef>) -> Desired {
    match (want, have) {
        (None, _) => cond(
            CONDITION_UP_TO_DATE,
            ConditionStatus::True,
            "NoReleaseRequested",
            "spec.release is not set",
        ),
        (Some(want), Some(have)) if want == have => cond(
            CONDITION_UP_TO_DATE,
            ConditionStatus::True,
            "RunningDesiredRelease",
            format!("runs {want}"),
        ),
        (Some(want), Some(have)) => cond(
            CONDITION_UP_TO_DATE,
            ConditionStatus::False,
            "ReleasePending",
            format!("runs {have}, should run {want}"),
        ),
        (Some(want), None) => cond(
            CONDITION_UP_TO_DATE,
            ConditionStatus::False,
            "ReleaseUnknown",
            format!("should run {want}; the robot has not reported its release"),
        ),
    }
}

fn cond(
    r#type: &'static str,
    status: ConditionStatus,
    reason: impl Into<Cow<'static, str>>,
    message: impl Into<String>,
) -> Desired {
    (r#type, status, reason.into(), message.into())
}

/// How long a Robot that a gateway created for an enrolling robot ([`ENROLLED_LABEL`]) may go
/// without a status before the controller writes it `Pending`. The robot's session opens in the
/// same connection as its enrollment and its gateway writes it `Online` then, a few seconds later
/// or, while a whole fleet enrolls at once, up to a minute (the gateway's status writes run
/// late). A `Pending` written meanwhile was one more status write per robot and collided with the
/// gateway's (409), costing a read and a write more: at a fleet's first boot (10,000 robots) a
/// third of the status writes were those.
pub const ENROLLED_GRACE: Duration = Duration::from_secs(120);

/// How long to leave `robot` alone before planning it: the rest of [`ENROLLED_GRACE`] for a
/// Robot created by enrollment whose status nobody has written yet; `None` for every other.
pub fn enrolled_wait(robot: &Robot, now: Timestamp) -> Option<Duration> {
    let unwritten = robot
        .status
        .as_ref()
        .is_none_or(|s| s.phase.is_none() && s.gateway.is_none());
    let enrolled = robot
        .labels()
        .get(ENROLLED_LABEL)
        .is_some_and(|v| v == "true");
    if !unwritten || !enrolled {
        return None;
    }
    let created = robot.metadata.creation_timestamp.as_ref()?.0;
    let until = created.checked_add(ENROLLED_GRACE).ok()?;
    let left = until.duration_since(now);
    (left.is_positive()).then(|| left.unsigned_abs())
}

/// The Event reason for entering a phase, or None for the initial `Pending`.
pub fn transition_reason(from: Option<RobotPhase>, to: RobotPhase) -> Option<&'static str> {
    if from == Some(to) || (from.is_none() && to == RobotPhase::Pending) {
        return None;
    }
    Some(match to {
        RobotPhase::Pending => "RobotPending",
        RobotPhase::Online => "RobotOnline",
        RobotPhase::Offline => "RobotOffline",
        RobotPhase::Unknown => "RobotUnknown",
        RobotPhase::Maintenance => "RobotMaintenance",
    })
}

#[cfg(test)]
mod model_tests;
#[cfg(test)]
mod properties_tests;

#[cfg(test)]
mod tests {
    use super::*;

    const GRACE: Duration = Duration::from_secs(60);

    fn robot(yaml: &str) -> Robot {
        serde_yaml::from_str(yaml).unwrap()
    }

    fn facts(now: &str, gateway: Option<GatewayState>) -> Facts {
        Facts {
            now: now.parse().unwrap(),
            heartbeat_grace: GRACE,
            gateway,
        }
    }

    fn status_of(plan: &Plan, t: &str) -> (ConditionStatus, String) {
        let c = plan.conditions.iter().find(|c| c.r#type == t).unwrap();
        (c.status, c.reason.to_string())
    }

    const CONNECTED: &str = r#"
apiVersion: fleet.lekiwi.io/v1alpha1
kind: Robot
metadata: { name: kiwi-1, namespace: lab, generation: 3 }
spec:
  release: { version: "1.1.0", digest: "sha256:1111111111111111111111111111111111111111111111111111111111111111" }
status:
  connected: true
  gateway: gw-a
  lastHeartbeatTime: "2026-11-22T10:00:00Z"
  connectedSince: "2026-11-22T09:00:00Z"
  currentRelease: { version: "1.0.0", digest: "sha256:0000000000000000000000000000000000000000000000000000000000000000" }
  health: { healthy: true }
  teleoperation: { active: true }
"#;

    #[test]
    fn new_robot_is_pending_without_an_event() {
        let r = robot(
            "apiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\nmetadata: {name: a, generation: 1}\nspec: {}\n",
        );
        let p = plan(&r, &facts("2026-11-22T10:00:00Z", None));
        assert_eq!(p.phase, RobotPhase::Pending);
        assert_eq!(
            status_of(&p, "Connected"),
            (ConditionStatus::False, "NeverConnected".into())
        );
        assert_eq!(status_of(&p, "UpToDate").0, ConditionStatus::True);
        assert_eq!(p.observed_generation, Some(1));
        assert_eq!(p.requeue_after, None);
        assert_eq!(transition_reason(None, p.phase), None);
    }

    #[test]
    fn an_enrolled_robot_is_left_to_its_gateway_for_a_while() {
        let enrolled = |created: &str, status: &str| {
            robot(&format!(
                "apiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\nmetadata: {{name: a, \
                 creationTimestamp: \"{created}\", labels: {{fleet.lekiwi.io/enrolled: \"true\"}}}}\n\
                 spec: {{}}\n{status}"
            ))
        };
        let now: Timestamp = "2026-11-22T10:01:00Z".parse().unwrap();
        // Created a minute ago, nothing written: the rest of the grace.
        let fresh = enrolled("2026-11-22T10:00:00Z", "");
        assert_eq!(enrolled_wait(&fresh, now), Some(Duration::from_secs(60)));
        let empty = enrolled("2026-11-22T10:00:00Z", "status: {}\n");
        assert_eq!(enrolled_wait(&empty, now), Some(Duration::from_secs(60)));
        // The grace is over: planned (and written `Pending`) as any other robot.
        assert_eq!(
            enrolled_wait(&enrolled("2026-11-22T09:59:00Z", ""), now),
            None
        );
        assert_eq!(
            enrolled_wait(&enrolled("2026-11-22T09:58:00Z", ""), now),
            None
        );
        // Its gateway wrote it (or the controller did): planned at once.
        let written = enrolled("2026-11-22T10:00:00Z", "status: {gateway: gw-a}\n");
        assert_eq!(enrolled_wait(&written, now), None);
        let pending = enrolled("2026-11-22T10:00:00Z", "status: {phase: Pending}\n");
        assert_eq!(enrolled_wait(&pending, now), None);
        // A Robot a person created is planned at once.
        let created = robot(
            "apiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\nmetadata: {name: a, \
             creationTimestamp: \"2026-11-22T10:00:00Z\"}\nspec: {}\n",
        );
        assert_eq!(enrolled_wait(&created, now), None);
    }

    #[test]
    fn fresh_heartbeat_through_live_gateway_is_online_and_requeues_at_expiry() {
        let p = plan(
            &robot(CONNECTED),
            &facts("2026-11-22T10:00:20Z", Some(GatewayState::Alive)),
        );
        assert_eq!(p.phase, RobotPhase::Online);
        assert_eq!(status_of(&p, "Connected").0, ConditionStatus::True);
        assert_eq!(status_of(&p, "Healthy").0, ConditionStatus::True);
        assert_eq!(
            status_of(&p, "Teleoperating"),
            (ConditionStatus::True, "TeleoperationDetected".into())
        );
        assert_eq!(
            status_of(&p, "UpToDate"),
            (ConditionStatus::False, "ReleasePending".into())
        );
        assert_eq!(p.requeue_after, Some(Duration::from_millis(40_500)));
        assert_eq!(
            transition_reason(Some(RobotPhase::Pending), p.phase),
            Some("RobotOnline")
        );
    }

    /// An unhealthy report's reason becomes the condition's; without one it is generic.
    #[test]
    fn the_agents_health_reason_is_the_conditions() {
        let mut r = robot(CONNECTED);
        let now = facts("2026-11-22T10:00:20Z", Some(GatewayState::Alive));
        r.status.as_mut().unwrap().health = Some(HealthReport {
            healthy: false,
            message: Some("no process matching \"lekiwi_host\" runs".into()),
            reason: Some("HostProcessNotRunning".into()),
        });
        let p = plan(&r, &now);
        assert_eq!(
            status_of(&p, "Healthy"),
            (ConditionStatus::False, "HostProcessNotRunning".into())
        );
        r.status.as_mut().unwrap().health.as_mut().unwrap().reason = None;
        let p = plan(&r, &now);
        assert_eq!(status_of(&p, "Healthy").1, "HealthCheckFailed");
    }

    #[test]
    fn stale_heartbeat_is_offline() {
        let p = plan(
            &robot(CONNECTED),
            &facts("2026-11-22T10:01:01Z", Some(GatewayState::Alive)),
        );
        assert_eq!(p.phase, RobotPhase::Offline);
        assert_eq!(
            status_of(&p, "Connected"),
            (ConditionStatus::False, "HeartbeatExpired".into())
        );
        assert_eq!(status_of(&p, "Healthy").0, ConditionStatus::Unknown);
        assert_eq!(p.requeue_after, None);
    }

    #[test]
    fn expired_gateway_lease_is_unknown() {
        let p = plan(
            &robot(CONNECTED),
            &facts("2026-11-22T10:00:05Z", Some(GatewayState::Gone)),
        );
        assert_eq!(p.phase, RobotPhase::Unknown);
        assert_eq!(
            status_of(&p, "Connected"),
            (ConditionStatus::Unknown, "GatewayLost".into())
        );
    }

    #[test]
    fn disconnect_is_offline_and_maintenance_wins() {
        let mut r = robot(CONNECTED);
        r.status.as_mut().unwrap().connected = Some(false);
        let p = plan(
            &r,
            &facts("2026-11-22T10:00:05Z", Some(GatewayState::Alive)),
        );
        assert_eq!(p.phase, RobotPhase::Offline);
        assert_eq!(status_of(&p, "Connected").1, "Disconnected");

        r.spec.maintenance = true;
        let p = plan(
            &r,
            &facts("2026-11-22T10:00:05Z", Some(GatewayState::Alive)),
        );
        assert_eq!(p.phase, RobotPhase::Maintenance);
        assert_eq!(
            transition_reason(Some(RobotPhase::Offline), p.phase),
            Some("RobotMaintenance")
        );
    }

    #[test]
    fn replanning_an_applied_plan_changes_nothing() {
        let mut r = robot(CONNECTED);
        let f = facts("2026-11-22T10:00:20Z", Some(GatewayState::Alive));
        let first = plan(&r, &f);
        assert!(first.differs_from(&r));
        let status = r.status.as_mut().unwrap();
        status.phase = Some(first.phase);
        status.conditions = first.conditions.clone();
        status.observed_generation = first.observed_generation;
        let later = facts("2026-11-22T10:00:30Z", Some(GatewayState::Alive));
        let second = plan(&r, &later);
        assert!(
            !second.differs_from(&r),
            "an unchanged robot must not be written again"
        );
        assert_eq!(
            second.conditions[0].last_transition_time,
            first.conditions[0].last_transition_time
        );
    }
}
