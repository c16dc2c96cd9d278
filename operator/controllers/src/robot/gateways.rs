//! Gateway liveness for the Robot controller: a gateway's Lease says whether the robots it
//! holds can be trusted; a tick re-checks those robots when it changes, refreshes the fleet
//! gauges, publishes the robots marked `Unknown` (see [`super::marks`]) and deletes the Leases
//! of gateways gone for good.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::core::DeserializeGuard;
use kube::runtime::reflector::{ObjectRef, Store};
use kube::{Api, ResourceExt};
use lekiwi_crds::contract::STATUS_LAG_ANNOTATION;
use lekiwi_crds::{Robot, RobotPhase};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::Context;
use crate::trigger::Trigger;
use lekiwi_liveness::GatewayState;
use lekiwi_metrics::PhaseLabels;

/// The end of a Lease's validity: its last renewal plus its duration (`None` without either).
pub(super) fn valid_until(lease: &Lease) -> Option<Timestamp> {
    let spec = lease.spec.as_ref()?;
    let renew = spec.renew_time.as_ref()?.0;
    renew
        .checked_add(jiff::SignedDuration::from_secs(i64::from(
            spec.lease_duration_seconds?,
        )))
        .ok()
}

/// Whether a Lease has a holder and was renewed within its duration.
pub(crate) fn lease_alive(lease: &Lease, now: Timestamp) -> bool {
    lease
        .spec
        .as_ref()
        .and_then(|s| s.holder_identity.as_deref())
        .is_some_and(|h| !h.is_empty())
        && valid_until(lease).is_some_and(|end| now <= end)
}

pub(super) fn gateway_state(
    store: &Store<Lease>,
    namespace: &str,
    gateway: &str,
    now: Timestamp,
) -> GatewayState {
    match store.get(&ObjectRef::new(gateway).within(namespace)) {
        Some(lease) if lease_alive(&lease, now) => GatewayState::Alive,
        _ => GatewayState::Gone,
    }
}

/// The status lag (see [`lekiwi_crds::contract::STATUS_LAG_ANNOTATION`]) that the live Lease of
/// `gateway` declares, at most `max`; zero for a dead or missing Lease, or a value that is not a
/// whole number of seconds.
pub(crate) fn status_lag(
    store: &Store<Lease>,
    namespace: &str,
    gateway: &str,
    now: Timestamp,
    max: Duration,
) -> Duration {
    store
        .get(&ObjectRef::new(gateway).within(namespace))
        .filter(|lease| lease_alive(lease, now))
        .and_then(|lease| {
            let value = lease.annotations().get(STATUS_LAG_ANNOTATION)?;
            value.parse::<u64>().ok().map(Duration::from_secs)
        })
        .unwrap_or_default()
        .min(max)
}

/// A gateway Lease expired this long and held by no robot is deleted.
const STALE_GATEWAY_LEASE: jiff::SignedDuration = jiff::SignedDuration::from_hours(1);
/// Time between two looks for stale gateway Leases.
const LEASE_GC_EVERY: Duration = Duration::from_secs(60);

/// Gateway Leases (by their label) that expired more than `stale` ago (a Lease never renewed
/// counts from its creation) and that no robot's `status.gateway` names (`held`), as (name,
/// resourceVersion). Deleting one changes no robot's state: a missing Lease reads as a dead
/// gateway, like an expired one.
fn stale_gateway_leases(
    leases: &[Arc<Lease>],
    held: impl Fn(&str) -> bool,
    now: Timestamp,
    stale: jiff::SignedDuration,
) -> Vec<(String, Option<String>)> {
    leases
        .iter()
        .filter(|l| {
            l.labels()
                .contains_key(lekiwi_crds::contract::GATEWAY_LEASE_LABEL)
        })
        .filter(|l| !held(&l.name_any()))
        .filter(|l| {
            valid_until(l)
                .or_else(|| l.metadata.creation_timestamp.as_ref().map(|t| t.0))
                .is_some_and(|end| now.duration_since(end) > stale)
        })
        .map(|l| (l.name_any(), l.resource_version()))
        .collect()
}

/// Deletes stale gateway Leases (see [`stale_gateway_leases`]); the resourceVersion
/// precondition spares a Lease its gateway renewed meanwhile.
async fn remove_stale_gateway_leases(
    ctx: &Context,
    leases: &Store<Lease>,
    held: impl Fn(&str) -> bool,
    now: Timestamp,
) {
    let stale = stale_gateway_leases(&leases.state(), held, now, STALE_GATEWAY_LEASE);
    let api: Api<Lease> = Api::namespaced(ctx.client.clone(), &ctx.config.namespace);
    for (name, version) in stale {
        let params = kube::api::DeleteParams {
            preconditions: Some(kube::api::Preconditions {
                resource_version: version,
                uid: None,
            }),
            ..kube::api::DeleteParams::default()
        };
        match api.delete(&name, &params).await {
            Ok(_) => info!(lease = %name, "deleted the Lease of a gateway gone for over an hour"),
            Err(kube::Error::Api(e)) if e.code == 404 || e.code == 409 => {}
            Err(e) => warn!(lease = %name, error = %e, "cannot delete a stale gateway Lease"),
        }
    }
}

/// Once a second: when a gateway's Lease expires (or comes back), re-reconciles the robots it
/// held; also refreshes the robots-by-phase gauges and publishes the robots marked `Unknown`.
/// Every minute, deletes the Leases of gateways gone for good.
pub(super) async fn watch_gateways(
    ctx: Arc<Context>,
    robots: Store<DeserializeGuard<Robot>>,
    leases: Store<Lease>,
    wake: Trigger<DeserializeGuard<Robot>>,
    cancel: CancellationToken,
) {
    let mut last: HashMap<String, GatewayState> = HashMap::new();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    let mut last_gc: Option<std::time::Instant> = None;
    loop {
        tokio::select! {
            () = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let now = Timestamp::now();
        let census = Census::of(&robots.state());
        census.export(&ctx);
        // Only with every robot known: an unlisted robot may still name a gateway.
        let robots_known =
            futures::FutureExt::now_or_never(robots.wait_until_ready()).is_some_and(|r| r.is_ok());
        if robots_known && last_gc.is_none_or(|t| t.elapsed() >= LEASE_GC_EVERY) {
            let held = |name: &str| census.by_gateway.contains_key(name);
            remove_stale_gateway_leases(&ctx, &leases, held, now).await;
            last_gc = Some(std::time::Instant::now());
        }
        ctx.gateway_marks
            .publish(&ctx, &leases, &census.by_gateway, now)
            .await;
        last = recheck_changed_gateways(&ctx, &leases, census.by_gateway, &last, &wake, now);
    }
}

/// The robots whose status names each gateway.
pub(super) type ByGateway = HashMap<String, Vec<ObjectRef<DeserializeGuard<Robot>>>>;

/// One pass over the robots: who each gateway holds, and the counts the gauges show.
struct Census {
    /// The robots whose status names each gateway.
    by_gateway: ByGateway,
    /// Robots per phase, every phase present (0 when none).
    phases: HashMap<&'static str, i64>,
    /// Robots reporting active teleoperation.
    teleoperating: i64,
}

impl Census {
    fn of(all: &[Arc<DeserializeGuard<Robot>>]) -> Self {
        let mut census = Census {
            by_gateway: HashMap::new(),
            phases: RobotPhase::ALL.iter().map(|p| (p.as_str(), 0)).collect(),
            teleoperating: 0,
        };
        for guard in all {
            let Ok(robot) = &guard.0 else { continue };
            let Some(status) = robot.status.as_ref() else {
                continue;
            };
            if let Some(phase) = status.phase {
                *census.phases.entry(phase.as_str()).or_default() += 1;
            }
            if status.teleoperation.as_ref().is_some_and(|t| t.active) {
                census.teleoperating += 1;
            }
            if let Some(gw) = status.gateway.clone() {
                census
                    .by_gateway
                    .entry(gw.to_string())
                    .or_default()
                    .push(ObjectRef::from_obj(guard.as_ref()));
            }
        }
        census
    }

    fn export(&self, ctx: &Context) {
        let metrics = &ctx.metrics.controllers;
        metrics.robots_teleoperating.set(self.teleoperating);
        for (phase, n) in &self.phases {
            metrics.robots.get_or_create(&PhaseLabels { phase }).set(*n);
        }
    }
}

/// Wakes the robots of every gateway whose Lease changed state since the last tick; returns
/// the states of this tick.
fn recheck_changed_gateways(
    ctx: &Context,
    leases: &Store<Lease>,
    by_gateway: ByGateway,
    last: &HashMap<String, GatewayState>,
    wake: &Trigger<DeserializeGuard<Robot>>,
    now: Timestamp,
) -> HashMap<String, GatewayState> {
    let mut current = HashMap::new();
    for (gateway, refs) in by_gateway {
        let state = gateway_state(leases, &ctx.config.namespace, &gateway, now);
        if last.get(&gateway).is_some_and(|old| *old != state) {
            info!(%gateway, ?state, robots = refs.len(), "gateway Lease changed state; re-checking its robots");
            for r in refs {
                wake.request(r);
            }
        }
        current.insert(gateway, state);
    }
    current
}

/// A gateway's Lease in namespace `ops` for tests: held by `name`, 15 s long, renewed
/// `renewed_ago_s` seconds ago, resourceVersion `1`.
#[cfg(any(test, feature = "test-util"))]
pub fn test_lease(name: &str, renewed_ago_s: i64) -> Lease {
    use k8s_openapi::api::coordination::v1::LeaseSpec;
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::MicroTime;
    Lease {
        metadata: kube::api::ObjectMeta {
            name: Some(name.into()),
            namespace: Some("ops".into()),
            resource_version: Some("1".into()),
            labels: Some(
                [(
                    lekiwi_crds::contract::GATEWAY_LEASE_LABEL.to_owned(),
                    "true".to_owned(),
                )]
                .into(),
            ),
            ..kube::api::ObjectMeta::default()
        },
        spec: Some(LeaseSpec {
            holder_identity: Some(name.into()),
            lease_duration_seconds: Some(15),
            renew_time: Some(MicroTime(
                Timestamp::now() - jiff::SignedDuration::from_secs(renewed_ago_s),
            )),
            ..LeaseSpec::default()
        }),
    }
}

#[cfg(test)]
mod tests {
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;

    use super::*;

    fn lease(name: &str, gateway: bool, renewed_ago_s: i64) -> Arc<Lease> {
        let mut lease = test_lease(name, renewed_ago_s);
        if !gateway {
            lease.metadata.labels = None;
        }
        Arc::new(lease)
    }

    /// Only gateway Leases expired for longer than the limit and named by no robot go.
    #[test]
    fn stale_gateway_leases_are_old_unreferenced_gateway_leases() {
        let mut unrenewed = (*lease("gw-never-renewed", true, 0)).clone();
        unrenewed.spec = None;
        let mut young = unrenewed.clone();
        young.metadata.name = Some("gw-just-created".into());
        unrenewed.metadata.creation_timestamp =
            Some(Time(Timestamp::now() - jiff::SignedDuration::from_hours(3)));
        young.metadata.creation_timestamp = Some(Time(Timestamp::now()));
        let leases = [
            Arc::new(unrenewed),
            Arc::new(young),
            lease("gw-alive", true, 5),
            lease("gw-recently-dead", true, 600),
            lease("gw-old", true, 7200),
            lease("gw-old-but-held", true, 7200),
            lease("lekiwi-operator", false, 7200),
        ];
        let alive: Vec<bool> = leases
            .iter()
            .map(|l| lease_alive(l, Timestamp::now()))
            .collect();
        // Only the Lease renewed 5 s ago is alive (one without a renewal never is).
        assert_eq!(alive, [false, false, true, false, false, false, false]);
        let stale = stale_gateway_leases(
            &leases,
            |name| name == "gw-old-but-held",
            Timestamp::now(),
            STALE_GATEWAY_LEASE,
        );
        assert_eq!(
            stale,
            vec![
                ("gw-never-renewed".to_owned(), Some("1".to_owned())),
                ("gw-old".to_owned(), Some("1".to_owned()))
            ]
        );
    }

    /// A live Lease's status lag counts, capped; a dead Lease's, a missing one's or a value
    /// that is not whole seconds does not.
    #[test]
    fn a_live_gateways_status_lag_extends_within_the_cap() {
        use kube::runtime::{reflector, watcher};
        let (store, mut writer) = reflector::store::<Lease>();
        let annotated = |name: &str, renewed_ago_s: i64, lag: &str| {
            let mut l = (*lease(name, true, renewed_ago_s)).clone();
            l.metadata.namespace = Some("ops".into());
            l.metadata.annotations =
                Some([(STATUS_LAG_ANNOTATION.to_owned(), lag.to_owned())].into());
            l
        };
        for l in [
            annotated("gw-late", 2, "120"),
            annotated("gw-very-late", 2, "5000"),
            annotated("gw-dead", 60, "120"),
            annotated("gw-garbled", 2, "2m"),
            annotated("gw-negative", 2, "-30"),
        ] {
            writer.apply_watcher_event(&watcher::Event::Apply(l));
        }
        let max = Duration::from_secs(900);
        let lag = |gw: &str| status_lag(&store, "ops", gw, Timestamp::now(), max).as_secs();
        assert_eq!(lag("gw-late"), 120);
        assert_eq!(lag("gw-very-late"), 900, "capped");
        assert_eq!(lag("gw-dead"), 0, "a dead gateway vouches for nothing");
        assert_eq!(lag("gw-garbled"), 0);
        assert_eq!(lag("gw-negative"), 0);
        assert_eq!(lag("gw-missing"), 0);
        assert_eq!(
            status_lag(&store, "lab", "gw-late", Timestamp::now(), max).as_secs(),
            0
        );
    }
}
