//! Client steps of the RobotDeployment controller: write the planned robots (mark plus
//! `spec.release`, by server-side apply under the rollout's own field manager), apply the
//! status, and publish the planned Events.

use std::collections::BTreeMap;

use futures::StreamExt;
use kube::api::{Patch, PatchParams};
use kube::runtime::events::{Event, EventType, Recorder};
use kube::{Api, Resource};
use lekiwi_crds::contract::managers;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment};
use serde_json::json;
use tracing::{debug, info, warn};

use super::plan::{Facts, MARK_ANNOTATION, Mark, Plan, PlannedEvent};
use crate::controller::apply_status;
use crate::error::{Error, Result};

/// Robot writes in flight at once.
const WRITE_CONCURRENCY: usize = 16;

/// One robot as this reconcile wrote it: its name, the mark annotation's text and the
/// resourceVersion the API server gave the write.
pub(super) struct Written {
    pub robot: String,
    pub mark: String,
    pub resource_version: Option<String>,
}

/// Writes every planned robot, a few at a time; fails with the first error after trying all.
pub(super) async fn write_robots(
    client: &kube::Client,
    namespace: &str,
    facts: &Facts,
    plan: &Plan,
) -> Result<Vec<Written>> {
    let robots: Api<Robot> = Api::namespaced(client.clone(), namespace);
    let desired: BTreeMap<&str, Option<&ReleaseRef>> = facts
        .robots
        .iter()
        .map(|r| (r.name.as_str(), r.desired.as_ref()))
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
                .or_else(|| desired.get(w.robot.as_str()).copied().flatten().cloned());
            (w.robot.clone(), w.mark.clone(), release)
        })
        .collect();
    let results: Vec<Result<Written>> = futures::stream::iter(jobs)
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
    results.into_iter().collect()
}

async fn write_robot(
    api: &Api<Robot>,
    name: &str,
    mark: &Mark,
    release: Option<&ReleaseRef>,
) -> Result<Written> {
    let text = serde_json::to_string(mark).unwrap_or_default();
    let mut patch = json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "Robot",
        "metadata": { "annotations": { MARK_ANNOTATION: &text } },
    });
    if let Some(release) = release {
        patch["spec"] = json!({ "release": release });
    }
    let robot = api
        .patch(
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
    Ok(Written {
        robot: name.to_owned(),
        mark: text,
        resource_version: robot.metadata.resource_version,
    })
}

/// Applies the planned status when it differs from the one read; returns the written
/// object's resourceVersion (none when nothing was written).
pub(super) async fn update_status(
    client: &kube::Client,
    deployment: &RobotDeployment,
    plan: &Plan,
) -> Result<Option<String>> {
    if deployment.status.as_ref() == Some(&plan.status) {
        return Ok(None);
    }
    let (name, namespace) = (
        deployment.metadata.name.clone().unwrap_or_default(),
        deployment.metadata.namespace.clone().unwrap_or_default(),
    );
    let api: Api<RobotDeployment> = Api::namespaced(client.clone(), &namespace);
    apply_status(
        &api,
        &name,
        &format!("{namespace}/{name}"),
        json!(plan.status),
        managers::DEPLOYMENT_STATUS,
    )
    .await
    .map(|d| d.metadata.resource_version)
}

/// Logs and publishes the planned Events on the deployment.
pub(super) async fn publish_events(
    recorder: &Recorder,
    deployment: &RobotDeployment,
    events: &[PlannedEvent],
) {
    for e in events {
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
        if let Err(err) = recorder.publish(&event, &deployment.object_ref(&())).await {
            warn!(error = %err, "cannot publish Event");
        }
    }
}
