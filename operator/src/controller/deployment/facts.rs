//! First client step of the RobotDeployment controller: gathers the [`Facts`] the planner needs
//! from the shared stores (selected robots, overlapping deployments) and the blob store
//! (whether the release can be rolled out).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use jiff::{SignedDuration, Timestamp};
use kube::ResourceExt;
use kube::core::{DeserializeGuard, Selector, SelectorExt};
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotPhase};
use lekiwi_protocol::release::{ReleaseManifest, digest_hex};

use super::State;
use super::plan::{Facts, MARK_ANNOTATION, Mark, Overlap, ReleaseCheck, RobotView};
use crate::error::{Error, Result};

/// The facts for one plan of `deployment`, or None when its selector cannot be evaluated.
pub(super) async fn gather(
    state: &State,
    deployment: &RobotDeployment,
    now: Timestamp,
) -> Result<Option<Facts>> {
    let namespace = deployment.namespace().unwrap_or_default();
    let all_robots = state.robots.state();
    let Some(selector) = selector(deployment) else {
        return Ok(None);
    };
    let ours = selected(&all_robots, &namespace, &selector);
    let (overlaps, active_deployments) = overlaps(state, deployment, &all_robots, &ours);
    let config = &state.ctx.config;
    let blob_dir = config.blob_dir.clone();
    let release = deployment.spec.release.clone();
    // Reading the manifest and probing every blob is file I/O: keep it off the async workers.
    let release = tokio::task::spawn_blocking(move || {
        check_release(blob_dir.is_dir().then_some(blob_dir.as_path()), &release)
    })
    .await
    .map_err(|_| Error::TaskStopped("release check"))?;
    let grace = Duration::from_secs(config.heartbeat_grace_seconds);
    let mut owners = super::ownership::superseded(&state.deployments, deployment, &ours);
    Ok(Some(Facts {
        now,
        robots: ours
            .iter()
            .map(|r| RobotView {
                superseded_by: owners.remove(&r.name_any()),
                ..view(r, now, grace)
            })
            .collect(),
        release,
        overlaps,
        active_deployments,
    }))
}

fn selector(deployment: &RobotDeployment) -> Option<Selector> {
    Selector::try_from(deployment.spec.selector.clone()).ok()
}

fn selected<'a>(
    robots: &'a [Arc<Robot>],
    namespace: &str,
    selector: &Selector,
) -> Vec<&'a Arc<Robot>> {
    robots
        .iter()
        .filter(|r| r.namespace().as_deref() == Some(namespace) && selector.matches(r.labels()))
        .collect()
}

/// Other active deployments of the namespace and which of our robots they select; also the
/// names of all active deployments, ours first (their marks hold robots).
fn overlaps(
    state: &State,
    deployment: &RobotDeployment,
    all_robots: &[Arc<Robot>],
    ours: &[&Arc<Robot>],
) -> (Vec<Overlap>, Vec<String>) {
    let name = deployment.name_any();
    let namespace = deployment.namespace().unwrap_or_default();
    let our_names: BTreeSet<String> = ours.iter().map(|r| r.name_any()).collect();
    // Creation time, then name: the older deployment wins an overlap.
    let age = |x: &RobotDeployment| {
        (
            x.metadata.creation_timestamp.as_ref().map(|t| t.0),
            x.name_any(),
        )
    };
    let mut overlaps = Vec::new();
    let mut active = vec![name.clone()];
    for guard in state.deployments.state() {
        let Ok(other) = &guard.0 else { continue };
        if other.namespace().as_deref() != Some(namespace.as_str()) || other.name_any() == name {
            continue;
        }
        if !is_active(&guard) {
            continue;
        }
        active.push(other.name_any());
        let Some(other_selector) = selector(other) else {
            continue;
        };
        let shared: Vec<String> = selected(all_robots, &namespace, &other_selector)
            .iter()
            .map(|r| r.name_any())
            .filter(|n| our_names.contains(n))
            .collect();
        if !shared.is_empty() {
            overlaps.push(Overlap {
                deployment: other.name_any(),
                earlier: age(other) < age(deployment),
                robots: shared,
            });
        }
    }
    (overlaps, active)
}

/// Whether a deployment is one whose marks count: unfinished, or finished but of an older
/// spec (a new rollout is about to start).
pub(super) fn is_active(guard: &DeserializeGuard<RobotDeployment>) -> bool {
    use lekiwi_crds::deployment::RolloutPhase;
    let Ok(d) = &guard.0 else {
        return false;
    };
    let status = d.status.as_ref();
    let unfinished = status.and_then(|s| s.phase).is_none_or(|p| {
        matches!(
            p,
            RolloutPhase::Pending
                | RolloutPhase::Progressing
                | RolloutPhase::Paused
                | RolloutPhase::RollingBack
        )
    });
    let key = super::plan::rollout_id(
        &d.spec.release,
        d.annotations()
            .get(super::plan::RESTART_ANNOTATION)
            .map(String::as_str),
    );
    unfinished || !super::plan::same_rollout(status.and_then(|s| s.rollout_id.as_deref()), &key)
}

/// What a rollout needs to know about one robot.
fn view(robot: &Robot, now: Timestamp, grace: Duration) -> RobotView {
    let status = robot.status.clone().unwrap_or_default();
    // `phase` is the Robot controller's verdict, which may lag (e.g. right after an operator
    // restart); a rollout only counts a robot Online with a live connection and a fresh heartbeat.
    let fresh = status.connected == Some(true)
        && status.last_heartbeat_time.as_ref().is_some_and(|t| {
            now.duration_since(t.0) <= SignedDuration::try_from(grace).unwrap_or_default()
        });
    let phase = match status.phase {
        Some(RobotPhase::Online) if !fresh => Some(RobotPhase::Offline),
        p => p,
    };
    RobotView {
        name: robot.name_any(),
        maintenance: robot.spec.maintenance,
        phase,
        healthy: status.health.as_ref().is_none_or(|h| h.healthy),
        teleoperated: status.teleoperation.as_ref().is_some_and(|t| t.active),
        desired: robot.spec.release.clone(),
        current: status.current_release.clone(),
        last_update: status
            .last_update
            .and_then(|u| Some((u.release?, u.phase?, u.message, u.time.map(|t| t.0)))),
        mark: robot
            .annotations()
            .get(MARK_ANNOTATION)
            .and_then(|m| serde_json::from_str::<Mark>(m).ok()),
        analysis: status.analysis,
        superseded_by: None,
    }
}

/// Checks the release against the blob store: the manifest exists, parses, names the same
/// version, and every file is present. Blocking file I/O: call it from `spawn_blocking`.
pub fn check_release(blob_dir: Option<&Path>, release: &ReleaseRef) -> ReleaseCheck {
    let Some(dir) = blob_dir else {
        return ReleaseCheck::Unchecked;
    };
    let blob = |hex: &str| -> PathBuf { dir.join("sha256").join(hex) };
    let hex = match digest_hex(&release.digest) {
        Ok(h) => h,
        Err(e) => return ReleaseCheck::Invalid(e.to_string()),
    };
    let path = blob(hex);
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
        .filter(|f| digest_hex(&f.digest).map_or(true, |h| !blob(h).exists()))
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
