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
use lekiwi_crds::{Robot, RobotPhase};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::Context;
use crate::trigger::Trigger;
use lekiwi_liveness::GatewayState;
use lekiwi_liveness::gateways::{gateway_state, valid_until};
use lekiwi_metrics::PhaseLabels;

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

#[cfg(test)]
mod tests {
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;

    use super::*;

    fn lease(name: &str, gateway: bool, renewed_ago_s: i64) -> Arc<Lease> {
        let mut lease = lekiwi_liveness::gateways::test_lease(name, renewed_ago_s);
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
            .map(|l| lekiwi_liveness::gateways::lease_alive(l, Timestamp::now()))
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
}
