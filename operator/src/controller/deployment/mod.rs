//! The RobotDeployment controller: rolls a release out to the robots a deployment selects, in
//! batches, with automatic rollback. A reconcile is a pipeline: gather the facts
//! ([`facts`]), plan ([`plan`], pure), write robots, apply status and publish Events
//! ([`apply`]), record metrics.

mod apply;
mod facts;
pub mod metrics;
pub mod plan;

use std::sync::Arc;

use futures::StreamExt;
use jiff::Timestamp;
use kube::core::DeserializeGuard;
use kube::runtime::controller::Action;
use kube::runtime::reflector::{ObjectRef, Store};
use kube::runtime::{WatchStreamExt, reflector, watcher};
use kube::{Api, ResourceExt};
use lekiwi_crds::{Robot, RobotDeployment};
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, info, info_span, warn};

pub use self::facts::check_release;
use self::facts::is_active;
use super::Context;
use super::trigger::{Trigger, trigger};
use crate::error::{Error, Result};
use crate::metrics::ControllerName;

/// What every reconcile of this controller reads: the context and the two shared stores.
struct State {
    ctx: Arc<Context>,
    robots: Store<Robot>,
    deployments: Store<DeserializeGuard<RobotDeployment>>,
}

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
    let (wake, wake_requests) = trigger();
    let (robot_store, robot_watch) = watch_robots(robots, deployment_store.clone(), wake);
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

/// The Robot store and the watch that fills it; any robot change may move a rollout of its
/// namespace on, so it wakes every active deployment there.
fn watch_robots(
    robots: Api<Robot>,
    deployments: Store<DeserializeGuard<RobotDeployment>>,
    wake: Trigger<DeserializeGuard<RobotDeployment>>,
) -> (Store<Robot>, impl Future<Output = ()> + Send + 'static) {
    let (store, writer) = reflector::store();
    let watch = reflector(
        writer,
        watcher(robots, watcher::Config::default().any_semantic()).modify(|r: &mut Robot| {
            // Only labels, annotations, spec and status are read; drop the rest.
            r.managed_fields_mut().clear();
        }),
    )
    .default_backoff()
    .applied_objects()
    .for_each(move |robot| {
        if let Ok(robot) = robot {
            let namespace = robot.namespace();
            for d in deployments.state() {
                if d.namespace() == namespace && is_active(&d) {
                    wake.request(ObjectRef::from_obj(d.as_ref()));
                }
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
    let span = info_span!("reconcile", controller = "deployment", deployment = %name, %namespace);
    async move {
        let ctx = &state.ctx;
        let _timer = ctx
            .metrics
            .controllers
            .reconcile_started(ControllerName::deployment);
        let now = Timestamp::now();
        let Some(facts) = facts::gather(&state, deployment, now).await? else {
            warn!("selector cannot be evaluated");
            return Ok(Action::await_change());
        };
        let plan = plan::plan(deployment, &facts);
        // Robots first: if we die between the two, the marks let the next leader resume.
        apply::write_robots(&ctx.client, &namespace, &facts, &plan).await?;
        apply::update_status(&ctx.client, deployment, &plan).await?;
        apply::publish_events(&ctx.recorder, deployment, &plan.events).await;
        ctx.metrics.rollouts.record(deployment, &plan, now);
        ctx.reset_backoff(&name, &namespace);
        Ok(match plan.requeue_after {
            Some(after) => Action::requeue(after),
            None => Action::await_change(),
        })
    }
    .instrument(span)
    .await
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
    warn!(deployment = %name, %namespace, error = %error, retry_in = ?delay, "reconcile failed");
    Action::requeue(delay)
}
