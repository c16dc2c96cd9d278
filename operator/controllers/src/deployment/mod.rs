//! The RobotDeployment controller: rolls a release out to the robots a deployment selects, in
//! batches, with automatic rollback. A reconcile is a pipeline: gather the facts
//! ([`facts`]), plan ([`plan`], pure), write robots, apply status and publish Events
//! ([`apply`]), record metrics.

pub mod apply;
mod catch_up;
mod confirm;
mod facts;
#[cfg(test)]
mod facts_tests;
mod index;
mod members;
mod own_writes;
mod ownership;
mod pace;
pub mod plan;
#[cfg(test)]
mod stale_store_tests;

use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;
use jiff::Timestamp;
use kube::core::DeserializeGuard;
use kube::runtime::controller::Action;
use kube::runtime::reflector::{ObjectRef, Store};
use kube::runtime::{WatchStreamExt, reflector, watcher};
use kube::{Api, ResourceExt};
use lekiwi_core::watch::watch_first;
use lekiwi_crds::{Robot, RobotDeployment};
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, debug, info, info_span, warn};

pub use self::facts::check_release;
use super::Context;
use super::trigger::{Trigger, spaced_trigger};
use crate::{Error, Result};
use lekiwi_metrics::ControllerName;

/// What every reconcile of this controller reads: the context and the two shared stores.
struct State {
    ctx: Arc<Context>,
    robots: Store<Robot>,
    deployments: Store<DeserializeGuard<RobotDeployment>>,
    /// Asks for reconciles of other deployments (see [`ownership::wake_rivals`]).
    wake: Trigger<DeserializeGuard<RobotDeployment>>,
    /// When each deployment's status was last written (see [`pace`]).
    pace: pace::Pace,
    /// Each deployment's last writes, until the stores show them (see [`catch_up`]).
    catch_up: catch_up::CatchUp<ObjectRef<DeserializeGuard<RobotDeployment>>, LastWrites>,
    /// The writes laid over the stores while they do not show them (see [`own_writes`]).
    own: own_writes::OwnWrites,
    /// Robots a fresh read found past their timeout (see [`confirm`]).
    confirmed: confirm::Confirmed,
    /// Which robots each deployment selects, kept by the robot watch (see [`members`]).
    members: Arc<members::Members>,
}

/// The least time between two plans of one deployment woken by its robots' changes (or by
/// another deployment's): during a rollout its robots report all the time, and each plan reads
/// every robot it selects, so planning on every change made the controller's CPU per status
/// write grow with the number of deployments rolling at once. A deployment's own changes (an
/// edit, `rollout undo`/`abort`) and its timers are not spaced: they reach it through its own
/// watch and requeues. A batch's last robot is seen at most this much later.
const ROBOT_WAKE_SPACING: std::time::Duration = std::time::Duration::from_secs(1);

/// Runs the RobotDeployment controller until `cancel` fires.
pub async fn run(ctx: Arc<Context>, cancel: CancellationToken) -> Result<()> {
    let (deploys, robots): (Api<DeserializeGuard<RobotDeployment>>, Api<Robot>) =
        match &ctx.config.watch_namespace {
            Some(ns) => (
                Api::namespaced(ctx.client.clone(), ns),
                Api::namespaced(ctx.client.clone(), ns),
            ),
            None => (Api::all(ctx.client.clone()), Api::all(ctx.client.clone())),
        };
    let controller = super::controller_for(deploys, &ctx);
    let deployment_store = controller.store();
    let (wake, wake_requests) = spaced_trigger(ROBOT_WAKE_SPACING);
    let members = Arc::new(members::Members::default());
    let (robot_store, robot_watch) = watch_robots(
        robots,
        (deployment_store.clone(), members.clone()),
        wake.clone(),
    );
    let robot_task = tokio::spawn(robot_watch);
    // Planning before every robot is listed would see too few robots (even none).
    tokio::select! {
        () = cancel.cancelled() => { robot_task.abort(); return Ok(()); }
        r = robot_store.wait_until_ready() => if r.is_err() { return Err(Error::TaskStopped("robot reflector")); }
    }
    let state = Arc::new(State {
        ctx,
        robots: robot_store,
        deployments: deployment_store,
        wake,
        pace: pace::Pace::default(),
        catch_up: catch_up::CatchUp::default(),
        own: own_writes::OwnWrites::default(),
        confirmed: confirm::Confirmed::default(),
        members,
    });
    info!("robot deployment controller started");
    let handlers = (reconcile, error_policy);
    super::drive(
        controller,
        wake_requests,
        handlers,
        state,
        cancel.clone(),
        "deployment controller stream item",
    )
    .await;
    robot_task.abort();
    info!("robot deployment controller stopped");
    Ok(())
}

/// The Robot store and the watch that fills it; a robot change wakes the active deployments
/// it concerns (see [`index`]), not every deployment of its namespace, and moves it in or out
/// of the deployments' selections (see [`members`]).
fn watch_robots(
    robots: Api<Robot>,
    (deployments, members): (
        Store<DeserializeGuard<RobotDeployment>>,
        Arc<members::Members>,
    ),
    wake: Trigger<DeserializeGuard<RobotDeployment>>,
) -> (Store<Robot>, impl Future<Output = ()> + Send + 'static) {
    let (store, writer) = reflector::store();
    let index = index::RobotIndex::default();
    // Started before its list, so a list longer than the API server's watch history (10,000
    // Robots after an API server restart) does not expire it (see `lekiwi_core::watch`).
    let watch = reflector(
        writer,
        watch_first(
            robots,
            lekiwi_core::api_client::watch_config(),
            |r: &mut Robot| {
                // Only labels, annotations, spec and status are read; drop the rest.
                r.managed_fields_mut().clear();
            },
        ),
    )
    .default_backoff()
    .for_each(move |event| {
        let all = deployments.state();
        // The reflector stored the event before passing it on: the selections follow the store.
        let concerned = match &event {
            Ok(watcher::Event::Apply(robot) | watcher::Event::InitApply(robot)) => {
                members.applied(robot);
                Some((robot, index.applied(robot, &all)))
            }
            Ok(watcher::Event::Delete(robot)) => {
                members.deleted(robot);
                Some((robot, index.deleted(robot, &all)))
            }
            Ok(watcher::Event::Init | watcher::Event::InitDone) => {
                members.clear();
                None
            }
            Err(_) => None,
        };
        if let Some((robot, names)) = concerned {
            let namespace = robot.namespace().unwrap_or_default();
            for name in names {
                wake.request(ObjectRef::new(&name).within(&namespace));
            }
        }
        futures::future::ready(())
    });
    (store, watch)
}

async fn reconcile(
    guard: Arc<DeserializeGuard<RobotDeployment>>,
    state: Arc<State>,
) -> Result<Action> {
    let deployment = match &guard.0 {
        Ok(d) => d,
        Err(invalid) => {
            warn!(deployment = ?invalid.metadata.name, error = %invalid.error,
                "ignoring a RobotDeployment that does not match the schema");
            return Ok(Action::await_change());
        }
    };
    let name = deployment.name_any();
    let namespace = deployment.namespace().unwrap_or_default();
    let key = ObjectRef::from_obj(guard.as_ref());
    let span = info_span!("reconcile", controller = "deployment", deployment = %name, %namespace);
    async move {
        let ctx = &state.ctx;
        let _timer = ctx
            .metrics
            .controllers
            .reconcile_started(ControllerName::deployment);
        // Planning from stores that do not show the last plan's writes yet would misjudge;
        // the watch that brings them wakes this deployment again (the wait holds no worker).
        if let Some(wait) = state
            .catch_up
            .behind(&key, |own| own.in_stores(&state, &key))
        {
            return Ok(Action::requeue(wait));
        }
        let now = Timestamp::now();
        let Some(facts) = facts::gather(&state, deployment, now).await? else {
            warn!("selector cannot be evaluated");
            return Ok(Action::await_change());
        };
        ownership::wake_rivals(&state.deployments, &state.wake, deployment);
        // A status held by the pace is where the rollout stands: plan on from it; else the one
        // this controller wrote last, while the store shows an older one.
        let held = state
            .pace
            .held((namespace.as_str(), name.as_str()), deployment)
            .or_else(|| state.own.status(deployment))
            .map(|status| RobotDeployment {
                status: Some(status),
                ..deployment.clone()
            });
        let planned_from = held.as_ref().unwrap_or(deployment);
        let plan = plan::plan(planned_from, &facts);
        // Robots first: if we die between the two, the marks let the next leader resume.
        let written = write_robots(&state, (&key, planned_from), (&facts, &plan)).await?;
        let Some(written) = written else {
            return Ok(Action::requeue(Duration::ZERO));
        };
        let (status_version, held) = write_status(&state, deployment, &plan).await?;
        state
            .own
            .wrote_status(deployment, status_version.as_deref(), &plan.status);
        apply::publish_events(&ctx.recorder, deployment, &plan.events).await;
        state.catch_up.wrote(
            key,
            LastWrites {
                status: plan.status.clone(),
                status_version,
                robots: written,
            },
        );
        let judged = plan.batch_result.map(|(_, ratio)| ratio);
        ctx.metrics
            .rollouts
            .record(deployment, &plan.status, (judged, plan.finished), now);
        ctx.reset_backoff(&name, &namespace);
        Ok(next_look(plan.requeue_after, held))
    }
    .instrument(span)
    .await
}

/// When to reconcile again: when the plan asks (`requeue_after`) or the pace releases the
/// status it held, whichever comes first; else on the next change.
fn next_look(requeue_after: Option<Duration>, held: Option<Duration>) -> Action {
    let again = match (requeue_after, held) {
        (Some(after), Some(held)) => Some(after.min(held)),
        (Some(after), None) | (None, Some(after)) => Some(after),
        (None, None) => None,
    };
    debug!(?again, "reconciled");
    again.map_or_else(Action::await_change, Action::requeue)
}

/// Writes the plan's robots ([`apply::write_robots`]) and records them as this controller's
/// own writes: the robots written, or `None` when a user changed the deployment meanwhile and
/// the rest were left unwritten (the status of this plan would claim robots it did not start:
/// the caller plans again from the change, with the marks of the robots written so far). Only a
/// rollout whose status (`planned_from`'s) records it stops so: the next plan goes on with it,
/// where the first plan of a rollout would start another, told nothing of the writes.
async fn write_robots(
    state: &State,
    (key, planned_from): (
        &ObjectRef<DeserializeGuard<RobotDeployment>>,
        &RobotDeployment,
    ),
    (facts, plan): (&plan::Facts, &plan::Plan),
) -> Result<Option<Vec<apply::Written>>> {
    let recorded = planned_from
        .status
        .as_ref()
        .and_then(|s| s.rollout_id.as_ref())
        .is_some_and(|id| plan.status.rollout_id.as_ref() == Some(id));
    let changed = || {
        recorded
            && state.deployments.get(key).is_some_and(|now| {
                now.0
                    .as_ref()
                    .is_ok_and(|now| apply::changed_by_user(planned_from, now))
            })
    };
    let apply::Writes {
        written,
        failed,
        interrupted,
    } = apply::write_robots(&state.ctx.client, planned_from, (facts, plan), changed).await;
    let namespace = planned_from.namespace().unwrap_or_default();
    state.own.wrote_robots(&namespace, &written);
    failed?;
    if interrupted {
        info!(
            written = written.len(),
            "the deployment changed while its robots were written; planning again"
        );
        return Ok(None);
    }
    Ok(Some(written))
}

/// Writes the planned status unless [`pace`] holds it: its resourceVersion if written, and how
/// long it is held otherwise (the reconcile looks again then).
async fn write_status(
    state: &State,
    deployment: &RobotDeployment,
    plan: &plan::Plan,
) -> Result<(Option<String>, Option<Duration>)> {
    let (name, namespace) = (
        deployment.name_any(),
        deployment.namespace().unwrap_or_default(),
    );
    let key = (namespace.as_str(), name.as_str());
    let now = tokio::time::Instant::now();
    if let Some(held) = state.pace.wait(key, deployment.status.as_ref(), plan, now) {
        return Ok((None, Some(held)));
    }
    let version = apply::update_status(&state.ctx.client, deployment, plan).await?;
    state.pace.stored(key, version.is_some().then_some(now));
    Ok((version, None))
}

/// What one reconcile wrote: the next reconcile plans from the shared stores, which the
/// watches fill a little after each write; planning from a store older than the last plan's
/// own writes would judge a batch from robots' new marks under the old status (a rollback
/// taken for a success) or start robots again.
struct LastWrites {
    status: lekiwi_crds::RobotDeploymentStatus,
    status_version: Option<String>,
    robots: Vec<apply::Written>,
}

impl LastWrites {
    /// Whether the stores show every write: the object at the written resourceVersion, or with
    /// the same content (another writer may have changed it since). A deleted object counts.
    fn in_stores(
        &self,
        state: &State,
        deployment: &ObjectRef<DeserializeGuard<RobotDeployment>>,
    ) -> bool {
        let namespace = deployment.namespace.clone().unwrap_or_default();
        let status_seen = self.status_version.is_none()
            || state.deployments.get(deployment).is_none_or(|g| {
                g.resource_version() == self.status_version
                    || g.0
                        .as_ref()
                        .is_ok_and(|d| d.status.as_ref() == Some(&self.status))
            });
        status_seen
            && self.robots.iter().all(|w| {
                let key = ObjectRef::new(&w.robot).within(&namespace);
                state.robots.get(&key).is_none_or(|r| {
                    r.resource_version() == w.resource_version
                        || r.annotations().get(w.key) == Some(&w.mark)
                })
            })
    }
}

fn error_policy(
    guard: Arc<DeserializeGuard<RobotDeployment>>,
    error: &Error,
    state: Arc<State>,
) -> Action {
    let (name, namespace) = (guard.name_any(), guard.namespace().unwrap_or_default());
    let delay = state
        .ctx
        .reconcile_failed(ControllerName::deployment, &name, &namespace, error);
    Action::requeue(delay)
}
