//! The Robot controller: turns the presence facts gateways record into phase, conditions and
//! Events, marks robots Offline when heartbeats age out and Unknown when their gateway dies.

pub mod plan;
pub mod status;

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;
use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::core::DeserializeGuard;
use kube::runtime::controller::{Action, Controller};
use kube::runtime::events::{Event, EventType};
use kube::runtime::reflector::{ObjectRef, Store};
use kube::runtime::{WatchStreamExt, reflector, watcher};
use kube::{Api, Resource, ResourceExt};
use lekiwi_crds::{Robot, RobotPhase};
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, debug, info, info_span, warn};

use self::plan::{Facts, GatewayState};
use super::Context;
use crate::error::{Error, Result};
use crate::metrics::{ControllerName, ErrorLabels, PhaseLabels};

/// Runs the Robot controller until `cancel` fires.
pub async fn run(ctx: Arc<Context>, cancel: CancellationToken) -> Result<()> {
    let robots: Api<DeserializeGuard<Robot>> = match &ctx.config.watch_namespace {
        Some(ns) => Api::namespaced(ctx.client.clone(), ns),
        None => Api::all(ctx.client.clone()),
    };
    let leases: Api<Lease> = Api::namespaced(ctx.client.clone(), &ctx.config.namespace);
    let (lease_store, lease_writer) = reflector::store();
    let lease_watch = reflector(lease_writer, watcher(leases, watcher::Config::default()))
        .default_backoff()
        .touched_objects()
        .for_each(|_| futures::future::ready(()));
    let lease_task = tokio::spawn(lease_watch);
    // Without the gateways' Leases every connected robot would look Unknown for a moment.
    tokio::select! {
        () = cancel.cancelled() => { lease_task.abort(); return Ok(()); }
        r = lease_store.wait_until_ready() => if r.is_err() { return Err(Error::TaskStopped("lease reflector")); }
    }
    let ctx = Arc::new(Context {
        gateway_leases: Some(lease_store.clone()),
        ..(*ctx).clone()
    });

    let controller = Controller::new(robots, watcher::Config::default().any_semantic())
        .with_config(
            kube::runtime::controller::Config::default().concurrency(ctx.config.concurrency),
        );
    let robot_store = controller.store();
    let (trigger_tx, trigger_rx) =
        futures::channel::mpsc::channel::<ObjectRef<DeserializeGuard<Robot>>>(1024);
    let liveness = tokio::spawn(watch_gateways(
        ctx.clone(),
        robot_store,
        lease_store,
        trigger_tx,
        cancel.clone(),
    ));

    info!("robot controller started");
    let shutdown = cancel.clone();
    controller
        .reconcile_on(trigger_rx)
        .graceful_shutdown_on(async move { shutdown.cancelled().await })
        .run(reconcile, error_policy, ctx)
        .for_each(|res| {
            if let Err(e) = res {
                debug!(error = %e, "robot controller stream item");
            }
            futures::future::ready(())
        })
        .await;
    liveness.abort();
    lease_task.abort();
    info!("robot controller stopped");
    Ok(())
}

/// The end of a Lease's validity: its last renewal plus its duration (`None` without either).
fn valid_until(lease: &Lease) -> Option<Timestamp> {
    let spec = lease.spec.as_ref()?;
    let renew = spec.renew_time.as_ref()?.0;
    renew
        .checked_add(jiff::SignedDuration::from_secs(i64::from(
            spec.lease_duration_seconds?,
        )))
        .ok()
}

/// Whether a Lease has a holder and was renewed within its duration.
fn lease_alive(lease: &Lease, now: Timestamp) -> bool {
    lease
        .spec
        .as_ref()
        .and_then(|s| s.holder_identity.as_deref())
        .is_some_and(|h| !h.is_empty())
        && valid_until(lease).is_some_and(|end| now <= end)
}

fn gateway_state(
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
/// held; also refreshes the robots-by-phase gauge. Every minute, deletes the Leases of gateways
/// gone for good.
async fn watch_gateways(
    ctx: Arc<Context>,
    robots: Store<DeserializeGuard<Robot>>,
    leases: Store<Lease>,
    mut trigger: futures::channel::mpsc::Sender<ObjectRef<DeserializeGuard<Robot>>>,
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
        let all = robots.state();
        let mut by_gateway: HashMap<String, Vec<ObjectRef<DeserializeGuard<Robot>>>> =
            HashMap::new();
        let mut phases: HashMap<&'static str, i64> =
            RobotPhase::ALL.iter().map(|p| (p.as_str(), 0)).collect();
        let mut teleoperating = 0;
        for guard in &all {
            let Ok(robot) = &guard.0 else { continue };
            if let Some(phase) = robot.status.as_ref().and_then(|s| s.phase) {
                *phases.entry(phase.as_str()).or_default() += 1;
            }
            if robot
                .status
                .as_ref()
                .and_then(|s| s.teleoperation.as_ref())
                .is_some_and(|t| t.active)
            {
                teleoperating += 1;
            }
            if let Some(gw) = robot.status.as_ref().and_then(|s| s.gateway.clone()) {
                by_gateway
                    .entry(gw)
                    .or_default()
                    .push(ObjectRef::from_obj(guard.as_ref()));
            }
        }
        ctx.metrics
            .controllers
            .robots_teleoperating
            .set(teleoperating);
        for (phase, n) in phases {
            ctx.metrics
                .controllers
                .robots
                .get_or_create(&PhaseLabels { phase })
                .set(n);
        }
        // Only with every robot known: an unlisted robot may still name a gateway.
        let robots_known =
            futures::FutureExt::now_or_never(robots.wait_until_ready()).is_some_and(|r| r.is_ok());
        if robots_known && last_gc.is_none_or(|t| t.elapsed() >= LEASE_GC_EVERY) {
            let held = |name: &str| by_gateway.contains_key(name);
            remove_stale_gateway_leases(&ctx, &leases, held, now).await;
            last_gc = Some(std::time::Instant::now());
        }
        let mut current = HashMap::new();
        for (gateway, refs) in by_gateway {
            let state = gateway_state(&leases, &ctx.config.namespace, &gateway, now);
            if last.get(&gateway).is_some_and(|old| *old != state) {
                info!(%gateway, ?state, robots = refs.len(), "gateway Lease changed state; re-checking its robots");
                for r in refs {
                    // A full channel means reconciles are already queued; the requeue covers it.
                    let _ = trigger.try_send(r);
                }
            }
            current.insert(gateway, state);
        }
        last = current;
    }
}

async fn reconcile(guard: Arc<DeserializeGuard<Robot>>, ctx: Arc<Context>) -> Result<Action> {
    let robot = match &guard.0 {
        Ok(robot) => robot,
        Err(invalid) => {
            warn!(robot = ?invalid.metadata.name, namespace = ?invalid.metadata.namespace, error = %invalid.error,
                "ignoring a Robot that does not match the schema");
            return Ok(Action::await_change());
        }
    };
    let name = robot.name_any();
    let namespace = robot.namespace().unwrap_or_default();
    let span = info_span!("reconcile", controller = "robot", robot = %name, %namespace);
    async move {
        let _timer = ctx
            .metrics
            .controllers
            .reconcile_started(ControllerName::robot);
        let now = Timestamp::now();
        let gateway = robot
            .status
            .as_ref()
            .and_then(|s| s.gateway.as_deref())
            .map(|gw| match &ctx.gateway_leases {
                Some(store) => gateway_state(store, &ctx.config.namespace, gw, now),
                None => GatewayState::Gone,
            });
        let facts = Facts {
            now,
            heartbeat_grace: Duration::from_secs(ctx.config.heartbeat_grace_seconds),
            gateway,
        };
        let plan = plan::plan(robot, &facts);
        if plan.differs_from(robot) {
            let api: Api<Robot> = Api::namespaced(ctx.client.clone(), &namespace);
            status::apply(&api, &name, &plan).await?;
            let old_phase = robot.status.as_ref().and_then(|s| s.phase);
            if let Some(reason) = plan::transition_reason(old_phase, plan.phase) {
                info!(from = ?old_phase, to = %plan.phase, "robot phase changed");
                ctx.metrics
                    .controllers
                    .robot_transitions
                    .get_or_create(&PhaseLabels {
                        phase: plan.phase.as_str(),
                    })
                    .inc();
                publish_transition(&ctx, robot, reason, &plan).await;
            }
        }
        ctx.reset_backoff(&name, &namespace);
        Ok(match plan.requeue_after {
            Some(after) => Action::requeue(after),
            None => Action::await_change(),
        })
    }
    .instrument(span)
    .await
}

async fn publish_transition(ctx: &Context, robot: &Robot, reason: &str, plan: &plan::Plan) {
    let note = plan
        .conditions
        .iter()
        .find(|c| c.r#type == lekiwi_crds::robot::CONDITION_CONNECTED)
        .map(|c| c.message.clone());
    let event = Event {
        type_: if matches!(plan.phase, RobotPhase::Offline | RobotPhase::Unknown) {
            EventType::Warning
        } else {
            EventType::Normal
        },
        reason: reason.to_owned(),
        note,
        action: "UpdatePhase".to_owned(),
        secondary: None,
    };
    if let Err(e) = ctx.recorder.publish(&event, &robot.object_ref(&())).await {
        warn!(error = %e, "cannot publish Event");
    }
}

fn error_policy(guard: Arc<DeserializeGuard<Robot>>, error: &Error, ctx: Arc<Context>) -> Action {
    let (name, namespace) = (guard.name_any(), guard.namespace().unwrap_or_default());
    ctx.metrics
        .controllers
        .reconcile_errors
        .get_or_create(&ErrorLabels {
            controller: ControllerName::robot,
            reason: error.metric_reason(),
        })
        .inc();
    let delay = ctx.next_backoff(&name, &namespace);
    warn!(robot = %name, %namespace, error = %error, retry_in = ?delay, "reconcile failed");
    Action::requeue(delay)
}

#[cfg(test)]
mod tests {
    use k8s_openapi::api::coordination::v1::LeaseSpec;
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::{MicroTime, Time};
    use kube::api::ObjectMeta;

    use super::*;

    fn lease(name: &str, gateway: bool, renewed_ago_s: i64) -> Arc<Lease> {
        let now = Timestamp::now();
        Arc::new(Lease {
            metadata: ObjectMeta {
                name: Some(name.into()),
                resource_version: Some("7".into()),
                labels: gateway.then(|| {
                    [(
                        lekiwi_crds::contract::GATEWAY_LEASE_LABEL.to_owned(),
                        "true".to_owned(),
                    )]
                    .into()
                }),
                ..ObjectMeta::default()
            },
            spec: Some(LeaseSpec {
                holder_identity: Some(name.into()),
                lease_duration_seconds: Some(15),
                renew_time: Some(MicroTime(
                    now - jiff::SignedDuration::from_secs(renewed_ago_s),
                )),
                ..LeaseSpec::default()
            }),
        })
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
                ("gw-never-renewed".to_owned(), Some("7".to_owned())),
                ("gw-old".to_owned(), Some("7".to_owned()))
            ]
        );
    }
}
