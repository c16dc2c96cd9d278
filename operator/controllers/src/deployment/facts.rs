//! First client step of the RobotDeployment controller: gathers the [`Facts`] the planner needs
//! from the shared stores (selected robots, overlapping deployments) and the blob store
//! (whether the release can be rolled out).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use jiff::{SignedDuration, Timestamp};
use kube::ResourceExt;
use kube::core::{DeserializeGuard, Selector, SelectorExt};
use kube::runtime::reflector::{ObjectRef, Store};
use lekiwi_crds::deployment::RolloutKind;
use lekiwi_crds::{AgentArch, AgentRef, ReleaseRef, Robot, RobotDeployment, RobotPhase};
use lekiwi_protocol::ProgressPhase;
use lekiwi_protocol::release::{ReleaseManifest, digest_hex};

use super::State;
use super::plan::{Facts, Mark, Overlap, ReleaseCheck, RobotView};
use crate::{Error, Result};

/// The facts for one plan of `deployment`, or None when its selector cannot be evaluated.
pub(super) async fn gather(
    state: &State,
    deployment: &RobotDeployment,
    now: Timestamp,
) -> Result<Option<Facts>> {
    let namespace = deployment.namespace().unwrap_or_default();
    let Some(selector) = selector(deployment) else {
        return Ok(None);
    };
    let deployments = state.deployments.state();
    let Some(selection) = state
        .members
        .select(&state.robots, &deployments, deployment)
    else {
        return Ok(None);
    };
    let ours = own_robots(&state.robots, &namespace, &selector, &selection.robots);
    let (overlaps, active_deployments) = overlaps(&deployments, deployment, &selection.shared);
    let config = &state.ctx.config;
    let blob_dir = config.blob_dir.clone();
    let spec = deployment.spec.clone();
    // Reading the manifest and probing every blob is file I/O: keep it off the async workers.
    let release = tokio::task::spawn_blocking(move || {
        check_spec(blob_dir.is_dir().then_some(blob_dir.as_path()), &spec)
    })
    .await
    .map_err(|_| Error::TaskStopped("release check"))?;
    let mut owners = super::ownership::superseded(&deployments, deployment, &selection.shared);
    let target = target(&deployment.spec);
    let agent = deployment.spec.agent.as_ref();
    let kind = deployment.spec.kind();
    let robot_view = |r: &Robot| {
        let gateway = r.status.as_ref().and_then(|s| s.gateway.as_deref());
        let grace = state.ctx.heartbeat_grace(gateway, now);
        let view = view(r, now, grace, kind);
        match (kind, agent) {
            (RolloutKind::Agent, Some(agent)) => agent_view(view, r, agent, &target),
            _ => view,
        }
    };
    let mut robots: Vec<RobotView> = ours
        .iter()
        .map(|r| {
            // With the marks and spec this controller wrote, if the store is older.
            let laid = state.own.robot(r, kind.mark_annotation());
            RobotView {
                superseded_by: owners.remove(&r.name_any()),
                ..robot_view(&laid)
            }
        })
        .collect();
    let timeouts = super::confirm::Timeouts {
        namespace: &namespace,
        deployment: &deployment.name_any(),
        target: &target,
        timeout: SignedDuration::from_secs(deployment.spec.strategy.robot_timeout_seconds),
        now,
    };
    let api = kube::Api::<Robot>::namespaced(state.ctx.client.clone(), &namespace);
    let reads = super::confirm::Reads {
        api: &api,
        confirmed: &state.confirmed,
    };
    super::confirm::confirm(&reads, &timeouts, &mut robots, robot_view).await;
    Ok(Some(Facts {
        now,
        robots,
        target,
        release,
        overlaps,
        active_deployments,
    }))
}

/// What a deployment moves robots to, as the reference the planner compares and keys its
/// rollout id on: the release, or for an agent rollout the agent's version with a digest over
/// its builds (an identity, not a blob: pushing other builds of a version makes a new rollout).
pub(super) fn target(spec: &lekiwi_crds::RobotDeploymentSpec) -> ReleaseRef {
    use sha2::Digest;
    match (&spec.release, &spec.agent) {
        (Some(release), _) => release.clone(),
        (None, Some(agent)) => {
            let mut h = sha2::Sha256::new();
            h.update(b"lekiwi-agent\0");
            h.update(agent.version.as_bytes());
            let mut builds: Vec<(&str, &str)> = agent
                .builds
                .iter()
                .map(|b| (b.arch.as_str(), b.digest.as_str()))
                .collect();
            builds.sort_unstable();
            for (arch, digest) in builds {
                h.update(format!("\0{arch}={digest}").as_bytes());
            }
            ReleaseRef {
                version: agent.version.clone().into(),
                digest: format!("sha256:{}", hex::encode(h.finalize())).into(),
            }
        }
        (None, None) => ReleaseRef::default(),
    }
}

/// A robot as an agent rollout sees it: it runs the target when it reports the target's agent
/// version (the gateway's own rule for `spec.agent`), else the version and digest it reports
/// (its rollback target; unknown without a digest); `status.agentUpdate` is its update report;
/// a robot whose architecture has no build is left out, with that reason.
pub(super) fn agent_view(
    view: RobotView,
    robot: &Robot,
    agent: &AgentRef,
    target: &ReleaseRef,
) -> RobotView {
    let status = robot.status.as_ref();
    let version = status.and_then(|s| s.agent_version.clone());
    let current = match (version, status.and_then(|s| s.agent_digest.clone())) {
        (Some(v), _) if v == agent.version => Some(target.clone()),
        (Some(version), Some(digest)) => Some(ReleaseRef { version, digest }),
        _ => None,
    };
    let machine = status.and_then(|s| s.system.as_ref()?.arch.clone());
    let arch = machine.as_deref().and_then(AgentArch::of_machine);
    let no_build = match (&machine, arch) {
        // The robot's own words, quoted and cut: they end up in the deployment's status.
        (Some(m), None) => Some(format!(
            "skipped: no agent builds exist for architecture {:?}",
            m.chars().take(32).collect::<String>()
        )),
        (_, Some(a)) if agent.build_for(a).is_none() => Some(format!(
            "skipped: agent {} has no {} build",
            agent.version,
            a.as_str()
        )),
        _ => None,
    };
    let last_update = status
        .and_then(|s| s.agent_update.clone())
        .filter(|u| u.version.as_deref() == Some(agent.version.as_str()))
        .and_then(|u| {
            let phase = agent_update_phase(u.phase.as_deref()?);
            Some((
                target.clone(),
                phase.as_str().to_owned(),
                u.message,
                u.time.map(|t| t.0),
            ))
        });
    RobotView {
        desired: None,
        desired_agent: robot.spec.agent.clone(),
        arch,
        no_build,
        current,
        last_update,
        analysis: None,
        ..view
    }
}

/// The release-update phase an agent update's phase (`status.agentUpdate.phase`) counts as:
/// `Succeeded` is done; `Failed`, `FallenBack`, `Unavailable` and `Unsupported` are failures;
/// `Sent` and `Started` are in progress.
fn agent_update_phase(phase: &str) -> ProgressPhase {
    match phase {
        "Succeeded" => ProgressPhase::Done,
        "Failed" | "FallenBack" | "Unavailable" | "Unsupported" => ProgressPhase::Failed,
        _ => ProgressPhase::Switching,
    }
}

fn selector(deployment: &RobotDeployment) -> Option<Selector> {
    Selector::try_from(deployment.spec.selector.clone()).ok()
}

/// The robots named (a deployment's [`Selection`](super::members::Selection)) as the store
/// shows them, that `selector` selects there.
fn own_robots(
    store: &Store<Robot>,
    namespace: &str,
    selector: &Selector,
    names: &[String],
) -> Vec<Arc<Robot>> {
    names
        .iter()
        .filter_map(|name| store.get(&ObjectRef::new(name).within(namespace)))
        .filter(|r| selector.matches(r.labels()))
        .collect()
}

/// Other active deployments of the namespace and which of our robots they select (`shared`:
/// robot -> the other deployments selecting it), by name; also the names of all active
/// deployments, ours first (their marks hold robots).
fn overlaps(
    all: &[Arc<DeserializeGuard<RobotDeployment>>],
    deployment: &RobotDeployment,
    shared: &BTreeMap<String, Vec<String>>,
) -> (Vec<Overlap>, Vec<String>) {
    let name = deployment.name_any();
    let namespace = deployment.namespace().unwrap_or_default();
    // Creation time, then name: the older deployment wins an overlap.
    let age = |x: &RobotDeployment| {
        (
            x.metadata.creation_timestamp.as_ref().map(|t| t.0),
            x.name_any(),
        )
    };
    let mut active = vec![name.clone()];
    // The other active deployments of our kind: whether each is older than ours.
    let mut earlier: HashMap<String, bool> = HashMap::new();
    for guard in all {
        let Ok(other) = &guard.0 else { continue };
        if other.metadata.namespace.as_deref() != Some(namespace.as_str())
            || other.name_any() == name
            || other.spec.kind() != deployment.spec.kind()
            || !is_active(guard)
        {
            continue;
        }
        active.push(other.name_any());
        earlier.insert(other.name_any(), age(other) < age(deployment));
    }
    let mut by_other: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for (robot, others) in shared {
        for other in others.iter().filter(|o| earlier.contains_key(*o)) {
            by_other.entry(other).or_default().push(robot.clone());
        }
    }
    let overlaps = by_other
        .into_iter()
        .map(|(other, robots)| Overlap {
            deployment: other.to_owned(),
            earlier: earlier[other],
            robots,
        })
        .collect();
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
        &target(&d.spec),
        d.annotations()
            .get(super::plan::RESTART_ANNOTATION)
            .map(String::as_str),
    );
    unfinished || !super::plan::same_rollout(status.and_then(|s| s.rollout_id.as_deref()), &key)
}

/// What a rollout needs to know about one robot.
pub(super) fn view(robot: &Robot, now: Timestamp, grace: Duration, kind: RolloutKind) -> RobotView {
    // Borrowed, not cloned: a plan views every robot of its deployment.
    let status = robot.status.as_ref();
    // `phase` is the Robot controller's verdict, which may lag (e.g. right after an operator
    // restart); a rollout only counts a robot Online with a live connection and a heartbeat
    // within the grace (the Robot controller's, extended by its gateway's status lag).
    let fresh = status.is_some_and(|s| {
        s.connected == Some(true)
            && s.last_heartbeat_time.as_ref().is_some_and(|t| {
                now.duration_since(t.0) <= SignedDuration::try_from(grace).unwrap_or_default()
            })
    });
    let phase = match status.and_then(|s| s.phase) {
        Some(RobotPhase::Online) if !fresh => Some(RobotPhase::Offline),
        p => p,
    };
    RobotView {
        name: robot.name_any(),
        maintenance: robot.spec.maintenance,
        phase,
        healthy: status
            .and_then(|s| s.health.as_ref())
            .is_none_or(|h| h.healthy),
        teleoperated: status
            .and_then(|s| s.teleoperation.as_ref())
            .is_some_and(|t| t.active),
        desired: robot.spec.release.clone(),
        current: status.and_then(|s| s.current_release.clone()),
        last_update: status.and_then(|s| s.last_update.as_ref()).and_then(|u| {
            Some((
                u.release.clone()?,
                u.phase.clone()?,
                u.message.clone(),
                u.time.as_ref().map(|t| t.0),
            ))
        }),
        mark: Mark::of(robot, kind),
        analysis: status.and_then(|s| s.analysis.as_deref().cloned()),
        superseded_by: None,
        ..RobotView::default()
    }
}

/// Checks what a deployment rolls out: exactly one of `release` and `agent`; a release against
/// the blob store ([`check_release`]); an agent's builds present in it, and no `analysis`.
/// Blocking file I/O: call it from `spawn_blocking`.
pub fn check_spec(
    blob_dir: Option<&Path>,
    spec: &lekiwi_crds::RobotDeploymentSpec,
) -> ReleaseCheck {
    match (&spec.release, &spec.agent) {
        (Some(release), None) => check_release(blob_dir, release),
        (None, Some(_)) if spec.analysis.is_some() => ReleaseCheck::Invalid(
            "spec.analysis watches a release's host process and does not apply to agent rollouts: remove it".to_owned(),
        ),
        (None, Some(agent)) => check_agent(blob_dir, agent),
        _ => ReleaseCheck::Invalid("set exactly one of spec.release and spec.agent".to_owned()),
    }
}

/// Every build of the agent is in the blob store.
fn check_agent(blob_dir: Option<&Path>, agent: &AgentRef) -> ReleaseCheck {
    let Some(dir) = blob_dir else {
        return ReleaseCheck::Unchecked;
    };
    for build in &agent.builds {
        let present =
            digest_hex(&build.digest).is_ok_and(|hex| dir.join("sha256").join(hex).is_file());
        if !present {
            return ReleaseCheck::Invalid(format!(
                "the {} build of agent {} ({}) is not in the blob store: push it with `kubectl lekiwi agent push`",
                build.arch.as_str(),
                agent.version,
                build.digest
            ));
        }
    }
    ReleaseCheck::Valid
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
