//! The RobotDeployment controller: rolls a release out to the robots a deployment selects, in
//! batches, with automatic rollback. [`plan`] decides; this module gathers the facts, writes
//! robots (`spec.release` plus the rollout mark, by server-side apply under the rollout's own
//! field manager), applies status, records Events and exports metrics.

pub mod metrics;
pub mod plan;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use futures::StreamExt;
use jiff::Timestamp;
use kube::api::{Patch, PatchParams};
use kube::core::{DeserializeGuard, Selector, SelectorExt};
use kube::runtime::controller::{Action, Controller};
use kube::runtime::events::{Event, EventType};
use kube::runtime::reflector::{ObjectRef, Store};
use kube::runtime::{WatchStreamExt, reflector, watcher};
use kube::{Api, Resource, ResourceExt};
use lekiwi_crds::contract::managers;
use lekiwi_crds::deployment::RolloutPhase;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment};
use lekiwi_protocol::release::{ReleaseManifest, digest_hex};
use serde_json::json;
use tokio_util::sync::CancellationToken;
use tracing::{Instrument, debug, info, info_span, warn};

use self::plan::{Facts, MARK_ANNOTATION, Mark, Overlap, ReleaseCheck, RobotView};
use super::Context;
use crate::error::{Error, Result};
use crate::metrics::{
    ControllerName, DeploymentLabels, DeploymentPhaseLabels, ErrorLabels, OutcomeLabels,
};

/// Robot writes in flight at once.
const WRITE_CONCURRENCY: usize = 16;

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
    let (robot_store, robot_writer) = reflector::store();
    let controller = Controller::new(deploys, watcher::Config::default().any_semantic())
        .with_config(
            kube::runtime::controller::Config::default().concurrency(ctx.config.concurrency),
        );
    let deployment_store = controller.store();
    // Any robot change may move a rollout of its namespace on.
    let (trigger_tx, trigger_rx) =
        futures::channel::mpsc::channel::<ObjectRef<DeserializeGuard<RobotDeployment>>>(4096);
    let robot_watch = {
        let deployments = deployment_store.clone();
        let mut trigger = trigger_tx;
        reflector(
            robot_writer,
            watcher(robots, watcher::Config::default().any_semantic()).modify(|r: &mut Robot| {
                // Only labels, annotations, spec and status are read; drop the rest.
                r.managed_fields_mut().clear();
            }),
        )
        .default_backoff()
        .applied_objects()
        .for_each(move |robot| {
            if let Ok(robot) = robot {
                let ns = robot.namespace();
                for d in deployments.state() {
                    if d.namespace() == ns && is_active(&d) {
                        let _ = trigger.try_send(ObjectRef::from_obj(d.as_ref()));
                    }
                }
            }
            futures::future::ready(())
        })
    };
    let robot_task = tokio::spawn(robot_watch);
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
    let shutdown = cancel.clone();
    controller
        .reconcile_on(trigger_rx)
        .graceful_shutdown_on(async move { shutdown.cancelled().await })
        .run(reconcile, error_policy, state)
        .for_each(|res| {
            if let Err(e) = res {
                debug!(error = %e, "deployment controller stream item");
            }
            futures::future::ready(())
        })
        .await;
    robot_task.abort();
    info!("robot deployment controller stopped");
    Ok(())
}

fn is_active(d: &DeserializeGuard<RobotDeployment>) -> bool {
    match &d.0 {
        Ok(d) => {
            d.status.as_ref().and_then(|s| s.phase).is_none_or(|p| {
                matches!(
                    p,
                    RolloutPhase::Pending
                        | RolloutPhase::Progressing
                        | RolloutPhase::Paused
                        | RolloutPhase::RollingBack
                )
            }) || !plan::same_rollout(
                d.status.as_ref().and_then(|s| s.rollout_id.as_deref()),
                &plan::rollout_id(
                    &d.spec.release,
                    d.annotations()
                        .get(plan::RESTART_ANNOTATION)
                        .map(String::as_str),
                ),
            )
        }
        Err(_) => false,
    }
}

fn selector(d: &RobotDeployment) -> Option<Selector> {
    Selector::try_from(d.spec.selector.clone()).ok()
}

fn selected<'a>(robots: &'a [Arc<Robot>], ns: &str, sel: &Selector) -> Vec<&'a Arc<Robot>> {
    robots
        .iter()
        .filter(|r| r.namespace().as_deref() == Some(ns) && sel.matches(r.labels()))
        .collect()
}

fn view(r: &Robot, now: Timestamp, grace: std::time::Duration) -> RobotView {
    let status = r.status.clone().unwrap_or_default();
    // `phase` is the Robot controller's verdict, which may lag (e.g. right after an operator
    // restart); a rollout only counts a robot Online with a live connection and a fresh heartbeat.
    let fresh = status.connected == Some(true)
        && status.last_heartbeat_time.as_ref().is_some_and(|t| {
            now.duration_since(t.0) <= jiff::SignedDuration::try_from(grace).unwrap_or_default()
        });
    let phase = match status.phase {
        Some(lekiwi_crds::RobotPhase::Online) if !fresh => Some(lekiwi_crds::RobotPhase::Offline),
        p => p,
    };
    RobotView {
        name: r.name_any(),
        maintenance: r.spec.maintenance,
        phase,
        healthy: status.health.as_ref().is_none_or(|h| h.healthy),
        teleoperated: status.teleoperation.as_ref().is_some_and(|t| t.active),
        desired: r.spec.release.clone(),
        current: status.current_release.clone(),
        last_update: status
            .last_update
            .and_then(|u| Some((u.release?, u.phase?, u.message, u.time.map(|t| t.0)))),
        mark: r
            .annotations()
            .get(MARK_ANNOTATION)
            .and_then(|m| serde_json::from_str::<Mark>(m).ok()),
    }
}

/// Checks the release against the blob store: the manifest exists, parses, names the same
/// version, and every file is present.
pub fn check_release(blob_dir: Option<&Path>, release: &ReleaseRef) -> ReleaseCheck {
    let Some(dir) = blob_dir else {
        return ReleaseCheck::Unchecked;
    };
    let hex = match digest_hex(&release.digest) {
        Ok(h) => h,
        Err(e) => return ReleaseCheck::Invalid(e.to_string()),
    };
    let path = dir.join("sha256").join(hex);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return ReleaseCheck::Invalid(format!(
                "release {} not found in the blob store: push it with `kubectl lekiwi release push DIR --version {}`",
                release.digest, release.version
            ));
        }
        Err(e) => return ReleaseCheck::Invalid(format!("cannot read {}: {e}", path.display())),
    };
    let manifest = match ReleaseManifest::parse(&bytes) {
        Ok(m) => m,
        Err(e) => {
            return ReleaseCheck::Invalid(format!(
                "{} is not a release manifest: {e}",
                release.digest
            ));
        }
    };
    if manifest.version != release.version {
        return ReleaseCheck::Invalid(format!(
            "{} is version {:?}, but the deployment says {:?}",
            release.digest, manifest.version, release.version
        ));
    }
    let missing: Vec<&str> = manifest
        .files
        .iter()
        .filter(|f| digest_hex(&f.digest).map_or(true, |h| !dir.join("sha256").join(h).exists()))
        .map(|f| f.path.as_str())
        .collect();
    if let Some(first) = missing.first() {
        return ReleaseCheck::Invalid(format!(
            "{} file(s) of {} are missing from the blob store (e.g. {first}); push the release again",
            missing.len(),
            release.digest
        ));
    }
    ReleaseCheck::Valid
}

async fn reconcile(
    guard: Arc<DeserializeGuard<RobotDeployment>>,
    state: Arc<State>,
) -> Result<Action> {
    let d = match &guard.0 {
        Ok(d) => d,
        Err(invalid) => {
            warn!(deployment = ?invalid.metadata.name, error = %invalid.error,
                "ignoring a RobotDeployment that does not match the schema");
            return Ok(Action::await_change());
        }
    };
    let name = d.name_any();
    let namespace = d.namespace().unwrap_or_default();
    let span = info_span!("reconcile", controller = "deployment", deployment = %name, %namespace);
    async move {
        let ctx = &state.ctx;
        let _timer = ctx
            .metrics
            .controllers
            .reconcile_started(ControllerName::deployment);
        let now = Timestamp::now();
        let all_robots = state.robots.state();
        let Some(sel) = selector(d) else {
            warn!("selector cannot be evaluated");
            return Ok(Action::await_change());
        };
        let ours = selected(&all_robots, &namespace, &sel);
        let our_names: std::collections::BTreeSet<String> =
            ours.iter().map(|r| r.name_any()).collect();
        // Other active deployments of the namespace, and which of our robots they select.
        let mut overlaps = Vec::new();
        let mut active = vec![name.clone()];
        for other in state.deployments.state() {
            let Ok(o) = &other.0 else { continue };
            if o.namespace().as_deref() != Some(namespace.as_str()) || o.name_any() == name {
                continue;
            }
            if !is_active(&other) {
                continue;
            }
            active.push(o.name_any());
            let Some(osel) = selector(o) else { continue };
            let shared: Vec<String> = selected(&all_robots, &namespace, &osel)
                .iter()
                .map(|r| r.name_any())
                .filter(|n| our_names.contains(n))
                .collect();
            if !shared.is_empty() {
                let key = |x: &RobotDeployment| {
                    (
                        x.metadata.creation_timestamp.as_ref().map(|t| t.0),
                        x.name_any(),
                    )
                };
                overlaps.push(Overlap {
                    deployment: o.name_any(),
                    earlier: key(o) < key(d),
                    robots: shared,
                });
            }
        }
        let release = check_release(
            ctx.config
                .blob_dir
                .is_dir()
                .then_some(ctx.config.blob_dir.as_path()),
            &d.spec.release,
        );
        let facts = Facts {
            now,
            robots: ours
                .iter()
                .map(|r| {
                    view(
                        r,
                        now,
                        std::time::Duration::from_secs(ctx.config.heartbeat_grace_seconds),
                    )
                })
                .collect(),
            release,
            overlaps,
            active_deployments: active,
        };
        let plan = plan::plan(d, &facts);

        // Robots first: if we die between the two, the marks let the next leader resume.
        let robots: Api<Robot> = Api::namespaced(ctx.client.clone(), &namespace);
        let desired: BTreeMap<String, Option<ReleaseRef>> = facts
            .robots
            .iter()
            .map(|r| (r.name.clone(), r.desired.clone()))
            .collect();
        let jobs: Vec<(String, Mark, Option<ReleaseRef>)> = plan
            .writes
            .iter()
            .map(|w| {
                // Keep owning `spec.release` even for a mark-only write: server-side apply
                // would otherwise drop the field this manager set earlier.
                let release = w
                    .release
                    .clone()
                    .or_else(|| desired.get(&w.robot).cloned().flatten());
                (w.robot.clone(), w.mark.clone(), release)
            })
            .collect();
        let results: Vec<Result<()>> = futures::stream::iter(jobs)
            .map(|(robot, mark, release)| {
                let robots = robots.clone();
                async move { write_robot(&robots, &robot, &mark, release.as_ref()).await }
            })
            .buffer_unordered(WRITE_CONCURRENCY)
            .collect()
            .await;
        let written = results.iter().filter(|r| r.is_ok()).count();
        if !plan.writes.is_empty() {
            info!(robots = written, of = plan.writes.len(), "robots written");
        }
        if let Some(Err(e)) = results.into_iter().find(|r| r.is_err()) {
            return Err(e);
        }

        if d.status.as_ref() != Some(&plan.status) {
            let api: Api<RobotDeployment> = Api::namespaced(ctx.client.clone(), &namespace);
            let patch = json!({
                "apiVersion": "fleet.lekiwi.io/v1alpha1",
                "kind": "RobotDeployment",
                "status": plan.status,
            });
            api.patch_status(
                &name,
                &PatchParams::apply(managers::DEPLOYMENT_STATUS).force(),
                &Patch::Apply(&patch),
            )
            .await
            .map_err(|source| Error::PatchStatus {
                object: format!("{namespace}/{name}"),
                source,
            })?;
        }
        for e in &plan.events {
            if e.warning {
                warn!(reason = e.reason, "{}", e.note);
            } else {
                info!(reason = e.reason, "{}", e.note);
            }
            let event = Event {
                type_: if e.warning {
                    EventType::Warning
                } else {
                    EventType::Normal
                },
                reason: e.reason.to_owned(),
                note: Some(e.note.chars().take(1000).collect()),
                action: "Rollout".to_owned(),
                secondary: None,
            };
            if let Err(err) = ctx.recorder.publish(&event, &d.object_ref(&())).await {
                warn!(error = %err, "cannot publish Event");
            }
        }
        record_metrics(ctx, d, &namespace, &name, &plan, now);
        ctx.reset_backoff(&name, &namespace);
        Ok(match plan.requeue_after {
            Some(after) => Action::requeue(after),
            None => Action::await_change(),
        })
    }
    .instrument(span)
    .await
}

async fn write_robot(
    api: &Api<Robot>,
    name: &str,
    mark: &Mark,
    release: Option<&ReleaseRef>,
) -> Result<()> {
    let mut patch = json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "Robot",
        "metadata": {
            "annotations": { MARK_ANNOTATION: serde_json::to_string(mark).unwrap_or_default() }
        },
    });
    if let Some(release) = release {
        patch["spec"] = json!({ "release": release });
    }
    api.patch(
        name,
        &PatchParams::apply(managers::ROLLOUT).force(),
        &Patch::Apply(&patch),
    )
    .await
    .map_err(|source| Error::PatchRobot {
        object: name.to_owned(),
        source,
    })?;
    debug!(robot = %name, state = ?mark.state, batch = mark.batch, release = ?release.map(|r| r.version.as_str()), "robot written");
    Ok(())
}

fn record_metrics(
    ctx: &Context,
    d: &RobotDeployment,
    namespace: &str,
    name: &str,
    plan: &plan::Plan,
    now: Timestamp,
) {
    let m = &ctx.metrics.rollouts;
    let labels = DeploymentLabels {
        namespace: namespace.to_owned(),
        deployment: name.to_owned(),
    };
    let st = &plan.status;
    m.targeted
        .get_or_create(&labels)
        .set(i64::from(st.targeted));
    m.updated.get_or_create(&labels).set(i64::from(st.updated));
    m.failed.get_or_create(&labels).set(i64::from(st.failed));
    m.current_batch
        .get_or_create(&labels)
        .set(i64::from(st.current_batch.unwrap_or(0)));
    for phase in [
        RolloutPhase::Pending,
        RolloutPhase::Progressing,
        RolloutPhase::Paused,
        RolloutPhase::Completed,
        RolloutPhase::RollingBack,
        RolloutPhase::RolledBack,
        RolloutPhase::Failed,
    ] {
        m.phase
            .get_or_create(&DeploymentPhaseLabels {
                namespace: namespace.to_owned(),
                deployment: name.to_owned(),
                phase: phase_str(phase),
            })
            .set(i64::from(st.phase == Some(phase)));
    }
    if let Some((_, ratio)) = plan.batch_result {
        m.batch_success.observe(ratio);
        m.batches
            .get_or_create(&OutcomeLabels {
                outcome: if ratio >= d.spec.strategy.success_threshold {
                    "succeeded"
                } else {
                    "failed"
                },
            })
            .inc();
    }
    if plan.finished {
        let outcome = match st.phase {
            Some(RolloutPhase::Completed) => "completed",
            Some(RolloutPhase::RolledBack) => "rolled_back",
            _ => "failed",
        };
        let labels = OutcomeLabels { outcome };
        m.finished.get_or_create(&labels).inc();
        if let Some(start) = &st.start_time {
            let secs = now.duration_since(start.0).as_secs_f64().max(0.0);
            m.duration.get_or_create(&labels).observe(secs);
        }
    }
}

fn phase_str(p: RolloutPhase) -> &'static str {
    match p {
        RolloutPhase::Pending => "Pending",
        RolloutPhase::Progressing => "Progressing",
        RolloutPhase::Paused => "Paused",
        RolloutPhase::Completed => "Completed",
        RolloutPhase::RollingBack => "RollingBack",
        RolloutPhase::RolledBack => "RolledBack",
        RolloutPhase::Failed => "Failed",
    }
}

fn error_policy(
    guard: Arc<DeserializeGuard<RobotDeployment>>,
    error: &Error,
    state: Arc<State>,
) -> Action {
    let (name, namespace) = (guard.name_any(), guard.namespace().unwrap_or_default());
    state
        .ctx
        .metrics
        .controllers
        .reconcile_errors
        .get_or_create(&ErrorLabels {
            controller: ControllerName::deployment,
            reason: error.metric_reason(),
        })
        .inc();
    let delay = state.ctx.next_backoff(&name, &namespace);
    warn!(deployment = %name, %namespace, error = %error, retry_in = ?delay, "reconcile failed");
    Action::requeue(delay)
}
