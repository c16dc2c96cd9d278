//! Phase Events without a storm: the controller notices every phase change (its own writes and
//! the gateways', which plan the phase themselves), publishes a per-robot Event while a shared
//! budget allows, and counts the rest into one summary Event per gateway and phase, published
//! every [`SUMMARY_EVERY`] on that gateway's Lease.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use k8s_openapi::api::coordination::v1::Lease;
use k8s_openapi::api::core::v1::ObjectReference;
use kube::Resource;
use kube::core::DeserializeGuard;
use kube::runtime::events::{Event, EventType};
use kube::runtime::reflector::{ObjectRef, Store};
use lekiwi_crds::{Robot, RobotPhase};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::Context;
use lekiwi_core::rate::TokenBucket;

/// Per-robot phase Events published at once before the budget applies.
pub const ROBOT_EVENT_BURST: u32 = 10;
/// Per-robot phase Events per second, sustained, across all robots.
pub const ROBOT_EVENTS_PER_SECOND: f64 = 1.0;
/// How often the transitions beyond the budget are summarised.
pub const SUMMARY_EVERY: Duration = Duration::from_secs(5);

/// A robot, as (namespace, name).
type Key = (String, String);

/// Transitions beyond the budget, by (gateway, phase entered): how many, in which namespaces.
type Suppressed = HashMap<(Option<String>, RobotPhase), (u64, BTreeSet<String>)>;

/// The phase each robot was last seen in, the Event budget, and what it held back.
pub struct PhaseEvents {
    state: Mutex<State>,
}

struct State {
    seen: HashMap<Key, RobotPhase>,
    budget: TokenBucket,
    suppressed: Suppressed,
}

/// What a reconcile does about a robot's phase change.
#[derive(Debug, PartialEq, Eq)]
pub enum Publish {
    /// Publish its own Event.
    Robot,
    /// Counted into the next summary.
    Summarised,
}

impl Default for PhaseEvents {
    fn default() -> Self {
        Self {
            state: Mutex::new(State {
                seen: HashMap::new(),
                budget: TokenBucket::new(ROBOT_EVENTS_PER_SECOND, ROBOT_EVENT_BURST),
                suppressed: HashMap::new(),
            }),
        }
    }
}

impl PhaseEvents {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records that robot `key` is now in `phase` and returns the phase it was last seen in
    /// (`None` the first time: then `stored`, the phase found in its status, counts).
    pub fn observe(
        &self,
        key: (&str, &str),
        stored: Option<RobotPhase>,
        phase: RobotPhase,
    ) -> Option<RobotPhase> {
        let key = (key.0.to_owned(), key.1.to_owned());
        self.lock().seen.insert(key, phase).or(stored)
    }

    /// Whether the Event of a robot of `namespace` entering `phase` through `gateway` may be
    /// published now; if not, it is counted into the next summary.
    pub fn admit(&self, namespace: &str, gateway: Option<&str>, phase: RobotPhase) -> Publish {
        let mut state = self.lock();
        if state.budget.try_take() {
            return Publish::Robot;
        }
        let entry = state
            .suppressed
            .entry((gateway.map(str::to_owned), phase))
            .or_default();
        entry.0 += 1;
        entry.1.insert(namespace.to_owned());
        Publish::Summarised
    }

    /// Forgets robots `keep` says are gone.
    pub fn retain(&self, keep: impl Fn(&str, &str) -> bool) {
        self.lock().seen.retain(|(ns, name), _| keep(ns, name));
    }

    fn take_suppressed(&self) -> Suppressed {
        std::mem::take(&mut self.lock().suppressed)
    }
}

/// The Event reason of a summary of robots entering `phase`.
fn summary_reason(phase: RobotPhase) -> &'static str {
    match phase {
        RobotPhase::Pending => "RobotsPending",
        RobotPhase::Online => "RobotsOnline",
        RobotPhase::Offline => "RobotsOffline",
        RobotPhase::Unknown => "RobotsUnknown",
        RobotPhase::Maintenance => "RobotsMaintenance",
    }
}

/// The note of a summary: how many robots, which phase, through which gateway, where.
fn summary_note(
    count: u64,
    phase: RobotPhase,
    gateway: Option<&str>,
    namespaces: &BTreeSet<String>,
) -> String {
    let through = gateway.map_or_else(String::new, |g| format!(" through gateway {g}"));
    let mut listed: Vec<&str> = namespaces.iter().map(String::as_str).take(5).collect();
    if namespaces.len() > listed.len() {
        listed.push("...");
    }
    format!(
        "{count} robots became {phase}{through} in the last {}s (namespaces: {}); their own Events are rate-limited, see each Robot's Connected condition",
        SUMMARY_EVERY.as_secs(),
        listed.join(", ")
    )
}

/// The Lease a summary is about: the gateway's, or the controller's own leader Lease for robots
/// that name no gateway.
fn summary_object(ctx: &Context, gateway: Option<&str>) -> ObjectReference {
    ObjectReference {
        api_version: Some(Lease::api_version(&()).into_owned()),
        kind: Some(Lease::kind(&()).into_owned()),
        name: Some(gateway.unwrap_or(&ctx.config.leader_lease).to_owned()),
        namespace: Some(ctx.config.namespace.clone()),
        ..ObjectReference::default()
    }
}

/// Publishes the summaries every [`SUMMARY_EVERY`] until `cancel`, and forgets robots that
/// left the controller's cache.
pub async fn publish_summaries(
    ctx: Arc<Context>,
    robots: Store<DeserializeGuard<Robot>>,
    cancel: CancellationToken,
) {
    let events = ctx.robot_events.clone();
    let mut tick = tokio::time::interval(SUMMARY_EVERY);
    loop {
        tokio::select! {
            () = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let listed =
            futures::FutureExt::now_or_never(robots.wait_until_ready()).is_some_and(|r| r.is_ok());
        if listed {
            events.retain(|ns, name| robots.get(&ObjectRef::new(name).within(ns)).is_some());
        }
        for ((gateway, phase), (count, namespaces)) in events.take_suppressed() {
            let event = Event {
                type_: if matches!(phase, RobotPhase::Offline | RobotPhase::Unknown) {
                    EventType::Warning
                } else {
                    EventType::Normal
                },
                reason: summary_reason(phase).to_owned(),
                note: Some(summary_note(count, phase, gateway.as_deref(), &namespaces)),
                action: "UpdatePhase".to_owned(),
                secondary: None,
            };
            let regarding = summary_object(&ctx, gateway.as_deref());
            info!(%count, %phase, gateway = ?gateway, "summarised robot phase changes in one Event");
            if let Err(e) = ctx.recorder.publish(&event, &regarding).await {
                warn!(error = %e, "cannot publish a summary Event");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn a_burst_of_transitions_becomes_a_few_events_and_one_summary() {
        let events = PhaseEvents::default();
        let admitted = (0..100)
            .filter(|_| events.admit("lab", Some("gw-a"), RobotPhase::Online) == Publish::Robot)
            .count();
        assert_eq!(admitted, ROBOT_EVENT_BURST as usize);
        let suppressed = events.take_suppressed();
        let (count, namespaces) = &suppressed[&(Some("gw-a".to_owned()), RobotPhase::Online)];
        assert_eq!(*count, 100 - u64::from(ROBOT_EVENT_BURST));
        assert_eq!(
            summary_note(*count, RobotPhase::Online, Some("gw-a"), namespaces),
            "90 robots became Online through gateway gw-a in the last 5s (namespaces: lab); their own Events are rate-limited, see each Robot's Connected condition"
        );
        assert!(events.take_suppressed().is_empty());
        // The budget refills: a lone transition later gets its own Event.
        tokio::time::advance(Duration::from_secs(2)).await;
        assert_eq!(
            events.admit("lab", None, RobotPhase::Offline),
            Publish::Robot
        );
    }

    #[test]
    fn a_phase_change_is_seen_against_the_last_look_or_else_the_stored_phase() {
        let events = PhaseEvents::default();
        let key = ("lab", "kiwi-1");
        // First look: the stored phase is all we know.
        assert_eq!(
            events.observe(key, Some(RobotPhase::Offline), RobotPhase::Offline),
            Some(RobotPhase::Offline)
        );
        // The gateway wrote Online: the stored phase equals the new one, the last look does not.
        assert_eq!(
            events.observe(key, Some(RobotPhase::Online), RobotPhase::Online),
            Some(RobotPhase::Offline)
        );
        events.retain(|_, name| name != "kiwi-1");
        assert_eq!(events.observe(key, None, RobotPhase::Pending), None);
    }
}
