//! The Robot controller: turns the presence facts gateways record into phase, conditions and
//! Events, marks robots Offline when heartbeats age out and Unknown when their gateway dies.
//! Gateways write the phase and conditions they imply along with their facts (the same [`plan`]),
//! so for a robot coming Online the controller usually finds nothing to write; it still
//! notices the change and publishes its Event, within the budget of [`events`].

pub mod claims;
pub mod deferred;
pub mod events;
pub mod gateways;
pub mod marks;
pub mod status;

use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;
use jiff::Timestamp;
use k8s_openapi::api::coordination::v1::Lease;
use kube::core::DeserializeGuard;
use kube::runtime::controller::Action;
use kube::runtime::events::{Event, EventType};
use kube::runtime::{WatchStreamExt, reflector, watcher};
use kube::{Api, Resource, ResourceExt};
use lekiwi_crds::{Robot, RobotPhase};
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, debug, info, info_span, warn};

use self::gateways::watch_gateways;
use super::Context;
use super::trigger::trigger;
use crate::{Error, Result};
use lekiwi_liveness::gateways::{gateway_state, late_write_wait, renewal_wait};
use lekiwi_liveness::{self as liveness, Facts, GatewayState};
use lekiwi_metrics::{ControllerName, PhaseLabels};

/// Watches the gateways' Leases in the operator's namespace until `cancel` fires: returns `ctx`
/// with their store, once it has listed them (both controllers read it: whether a robot's
/// gateway lives, and by how much its status writes lag), and the watch's task; `None` if
/// cancelled first.
pub async fn watch_gateway_leases(
    ctx: &Context,
    cancel: &CancellationToken,
) -> Result<Option<(Arc<Context>, tokio::task::JoinHandle<()>)>> {
    let leases: Api<Lease> = Api::namespaced(ctx.client.clone(), &ctx.config.namespace);
    let (lease_store, lease_writer) = reflector::store();
    // Every version's claims are noted as the watch brings it (see `ClaimIndex::observe`).
    let claims = ctx.gateway_claims.clone();
    let lease_watch = reflector(
        lease_writer,
        watcher(leases, lekiwi_core::api_client::watch_config()),
    )
    .default_backoff()
    .touched_objects()
    .for_each(move |lease| {
        if let Ok(lease) = lease {
            claims.observe(&lease, Timestamp::now());
        }
        futures::future::ready(())
    });
    let lease_task = tokio::spawn(lease_watch);
    // Without the gateways' Leases every connected robot would look Unknown for a moment.
    tokio::select! {
        () = cancel.cancelled() => { lease_task.abort(); return Ok(None); }
        r = lease_store.wait_until_ready() => if r.is_err() {
            lease_task.abort();
            return Err(Error::TaskStopped("lease reflector"));
        }
    }
    let ctx = Arc::new(Context {
        gateway_leases: Some(lease_store),
        ..ctx.clone()
    });
    Ok(Some((ctx, lease_task)))
}

/// Runs the Robot controller until `cancel` fires; `ctx` comes from [`watch_gateway_leases`].
pub async fn run(ctx: Arc<Context>, cancel: CancellationToken) -> Result<()> {
    let robots: Api<DeserializeGuard<Robot>> = match &ctx.config.watch_namespace {
        Some(ns) => Api::namespaced(ctx.client.clone(), ns),
        None => Api::all(ctx.client.clone()),
    };
    let Some(lease_store) = ctx.gateway_leases.clone() else {
        return Err(Error::TaskStopped("gateway Lease watch"));
    };

    let controller = super::controller_for(robots, &ctx);
    let robot_store = controller.store();
    let (wake, wake_requests) = trigger();
    let summaries = tokio::spawn(events::publish_summaries(
        ctx.clone(),
        robot_store.clone(),
        cancel.clone(),
    ));
    let liveness = tokio::spawn(watch_gateways(
        ctx.clone(),
        robot_store,
        lease_store,
        wake,
        cancel.clone(),
    ));

    info!("robot controller started");
    let handlers = (reconcile, error_policy);
    super::drive(
        controller,
        wake_requests,
        handlers,
        ctx,
        cancel.clone(),
        "robot controller stream item",
    )
    .await;
    liveness.abort();
    summaries.abort();
    info!("robot controller stopped");
    Ok(())
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
        if let Some(wait) = hold(&ctx, robot, gateway, now) {
            return Ok(Action::requeue(wait));
        }
        let facts = Facts {
            now,
            heartbeat_grace: ctx.heartbeat_grace(
                robot.status.as_ref().and_then(|s| s.gateway.as_deref()),
                now,
            ),
            gateway,
        };
        let plan = liveness::plan(robot, &facts);
        if let Some(action) = write_status(&ctx, robot, &plan, gateway).await? {
            return Ok(action);
        }
        // A gateway may have written the new phase itself: compare with the last look too.
        let stored = robot.status.as_ref().and_then(|s| s.phase);
        let old_phase = ctx
            .robot_events
            .observe((&namespace, &name), stored, plan.phase);
        if let Some(reason) = liveness::transition_reason(old_phase, plan.phase) {
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
        ctx.reset_backoff(&name, &namespace);
        Ok(match plan.requeue_after {
            Some(after) => Action::requeue(after),
            None => Action::await_change(),
        })
    }
    .instrument(span)
    .await
}

/// Writes `plan` where it differs from the stored status, unless the robot's gateway is to
/// write it (see [`deferred`]); `Some` action when the reconcile ends here (the write waits,
/// or met a newer version of the Robot).
async fn write_status(
    ctx: &Context,
    robot: &Robot,
    plan: &liveness::Plan,
    gateway: Option<GatewayState>,
) -> Result<Option<Action>> {
    let (name, namespace) = (robot.name_any(), robot.namespace().unwrap_or_default());
    let key = (namespace.as_str(), name.as_str());
    if plan.differs_from(robot) {
        let now = tokio::time::Instant::now();
        if let Some(wait) = ctx.robot_deferred.wait(key, robot, plan, gateway, now) {
            debug!(
                ?wait,
                "a new spec of an Online robot: its gateway writes it"
            );
            let wait = plan.requeue_after.map_or(wait, |after| after.min(wait));
            return Ok(Some(Action::requeue(wait)));
        }
        let api: Api<Robot> = Api::namespaced(ctx.client.clone(), &namespace);
        let seen = robot.metadata.resource_version.as_deref();
        if let Err(e) = status::apply(&api, &name, plan, seen).await {
            if !e.is_conflict() {
                return Err(e);
            }
            // The Robot changed since this plan was made: the newer version's reconcile,
            // which its watch event starts, decides (see CONFLICT_RECHECK); nothing written.
            debug!("the robot changed under the plan; waiting for the newer version");
            return Ok(Some(Action::requeue(CONFLICT_RECHECK)));
        }
        // Rare (a robot whose gateway is gone, or whose heartbeats stopped): each one named, so
        // a robot shown gone can be traced to the write that said so.
        info!(
            from = ?robot.status.as_ref().and_then(|s| s.phase),
            to = %plan.phase,
            gateway = ?gateway,
            "wrote the robot's status"
        );
        note_marked(ctx, robot, plan, gateway);
    }
    ctx.robot_deferred.forget(key);
    Ok(None)
}

/// Notes `robot` in the list of robots marked `Unknown` (see [`marks`]) when this reconcile
/// just wrote `plan`, `Unknown` because its gateway is gone.
fn note_marked(ctx: &Context, robot: &Robot, plan: &liveness::Plan, gateway: Option<GatewayState>) {
    if plan.phase != RobotPhase::Unknown || gateway != Some(GatewayState::Gone) {
        return;
    }
    let namespace = robot.namespace().unwrap_or_default();
    if let Some(gw) = robot.status.as_ref().and_then(|s| s.gateway.as_deref()) {
        ctx.gateway_marks.record(gw, &namespace, &robot.name_any());
    }
}

/// How long to look again instead of planning `robot` now: a robot just enrolled is left to its
/// gateway (see [`plan::ENROLLED_GRACE`]), and one whose `gateway` is gone is held back from
/// `Unknown` for the reasons of [`hold_unknown`].
fn hold(
    ctx: &Context,
    robot: &Robot,
    gateway: Option<GatewayState>,
    now: Timestamp,
) -> Option<Duration> {
    if let Some(wait) = liveness::enrolled_wait(robot, now) {
        debug!(
            ?wait,
            "a robot just enrolled; leaving its first status to its gateway"
        );
        return Some(wait);
    }
    (gateway == Some(GatewayState::Gone))
        .then(|| hold_unknown(ctx, robot, now))
        .flatten()
}

/// How long to look again instead of calling `robot`, whose gateway is gone, `Unknown`: while a
/// live gateway claims it, while a live gateway has not renewed its Lease (and claims) since
/// that gateway's expired (see [`renewal_wait`]), or while its status may be a write
/// that outlived its gateway (see [`late_write_wait`]); `None` when nothing holds it
/// back.
fn hold_unknown(ctx: &Context, robot: &Robot, now: Timestamp) -> Option<Duration> {
    if let Some(claimant) = claimed_elsewhere(ctx, robot, now) {
        // Its session is on a live gateway whose write is on its way: no Unknown meanwhile.
        debug!(%claimant, "the robot's gateway is gone but another one claims it");
        return Some(CLAIM_RECHECK);
    }
    let leases = ctx.gateway_leases.as_ref()?;
    if let Some(wait) = renewal_wait(leases, &ctx.config.namespace, robot, now) {
        debug!("waiting for the live gateways to renew their Leases (and claims) once more");
        return Some(wait);
    }
    let wait = late_write_wait(leases, &ctx.config.namespace, robot, now)?;
    // The gateway that holds the robot now claims it once it sees that write.
    debug!(
        ?wait,
        "the robot's status was written after its gateway's Lease expired; waiting for a claim"
    );
    Some(wait.min(CLAIM_RECHECK))
}

/// How soon a robot whose status write was refused as stale (409) is planned again if its
/// newer version has not come through the watch by then (it normally has, and was planned on
/// arrival). Planning sooner reuses the stale version and is refused again: a kill benchmark's
/// audit log counted 3,230 refusals in 278 s (about 9 per robot) with a 1 s retry, its watch
/// running 100 s late.
const CONFLICT_RECHECK: Duration = Duration::from_secs(60);

/// How soon a robot claimed by a live gateway (see [`claims`]) is looked at again: if the claim
/// went without a status write (the session there ended too), the robot turns `Unknown` once
/// [`claims::RELEASED_GRACE`] has passed.
const CLAIM_RECHECK: Duration = Duration::from_secs(3);

/// The live gateway that claims `robot`, connected through a gateway whose Lease is gone.
fn claimed_elsewhere(ctx: &Context, robot: &Robot, now: Timestamp) -> Option<String> {
    let status = robot.status.as_ref()?;
    if status.connected != Some(true) {
        return None;
    }
    ctx.gateway_claims.claimant(
        ctx.gateway_leases.as_ref()?,
        status.gateway.as_deref()?,
        &robot.namespace().unwrap_or_default(),
        &robot.name_any(),
        now,
    )
}

/// Publishes the Event of a phase change, or counts it into a summary when the budget of
/// per-robot Events is spent.
async fn publish_transition(ctx: &Context, robot: &Robot, reason: &str, plan: &liveness::Plan) {
    let namespace = robot.namespace().unwrap_or_default();
    let gateway = robot.status.as_ref().and_then(|s| s.gateway.as_deref());
    if ctx.robot_events.admit(&namespace, gateway, plan.phase) == events::Publish::Summarised {
        return;
    }
    let note = plan
        .conditions
        .iter()
        .find(|c| c.r#type == lekiwi_crds::robot::CONDITION_CONNECTED)
        .map(|c| c.message.to_string());
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
    let delay = ctx.reconcile_failed(ControllerName::robot, &name, &namespace, error);
    Action::requeue(delay)
}
