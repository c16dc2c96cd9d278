//! Client steps of the RobotDeployment controller: write the planned robots (mark plus
//! `spec.release`, or `spec.agent` for agent rollouts, by server-side apply under the rollout
//! kind's own field manager; with `spec.analysis`, the window it asks for), apply the status,
//! and publish the planned Events.

use std::collections::BTreeMap;

use futures::StreamExt;
use jiff::Timestamp;
use kube::api::{Patch, PatchParams};
use kube::runtime::events::{Event, EventType, Recorder};
use kube::{Api, Resource, ResourceExt};
use lekiwi_crds::analysis::WINDOW_ANNOTATION;
use lekiwi_crds::contract::managers;
use lekiwi_crds::deployment::{ABORT_ANNOTATION, RESTART_ANNOTATION, RolloutKind, UNDO_ANNOTATION};
use lekiwi_crds::{AgentArch, AgentBuild, AgentRef, ReleaseRef, Robot, RobotDeployment};
use tracing::{debug, info, warn};

use super::plan::{Facts, Mark, Plan, PlannedEvent, RobotView};
use crate::apply_status;
use crate::{Error, Result};
use lekiwi_core::apply::{RobotApply, RobotSpecPart, StatusApply};

/// Robot writes in flight at once.
const WRITE_CONCURRENCY: usize = 16;

/// One robot as this reconcile wrote it: its name, the mark annotation's key and text, the
/// part of its spec written, and the resourceVersion the API server gave the write.
pub struct Written {
    pub robot: String,
    pub key: &'static str,
    pub mark: String,
    pub spec: Option<RobotSpecPart>,
    pub resource_version: Option<String>,
}

/// One robot's write: its name, mark, the owned part of its spec, and the analysis window.
type Job = (String, Mark, Option<RobotSpecPart>, Option<i64>);

/// How a plan's robot writes went: the writes that succeeded, the first error after trying
/// all, and whether the rest were left unwritten because the deployment changed meanwhile.
pub(super) struct Writes {
    pub written: Vec<Written>,
    pub failed: Result<()>,
    pub interrupted: bool,
}

/// Writes every planned robot, a few at a time, until `changed` says a user changed the
/// deployment since the plan read it (an abort, undo, restart or new spec: the robots not yet
/// written are left for the plan of the new state). A batch of a thousand robots takes seconds
/// to write, and minutes on a busy API server: an abort that came meanwhile let the writes go
/// on starting robots it had stopped.
pub(super) async fn write_robots(
    client: &kube::Client,
    deployment: &RobotDeployment,
    (facts, plan): (&Facts, &Plan),
    changed: impl Fn() -> bool,
) -> Writes {
    let namespace = deployment.metadata.namespace.clone().unwrap_or_default();
    let robots: Api<Robot> = Api::namespaced(client.clone(), &namespace);
    let kind = deployment.spec.kind();
    let jobs = robot_writes(deployment, facts, plan);
    let planned_at = facts.now;
    let planned = jobs.len();
    let results: Vec<Result<Written>> = futures::stream::iter(jobs)
        // Asked as each write is about to start.
        .take_while(|_| std::future::ready(!changed()))
        .map(|(robot, mark, spec, window)| {
            let robots = robots.clone();
            async move {
                let mark = entered_now(mark, planned_at);
                write_robot(&robots, kind, &robot, &mark, spec, window).await
            }
        })
        .buffer_unordered(WRITE_CONCURRENCY)
        .collect()
        .await;
    let interrupted = results.len() < planned;
    let (mut written, mut failed) = (Vec::with_capacity(results.len()), Ok(()));
    for result in results {
        match result {
            Ok(w) => written.push(w),
            Err(e) if failed.is_ok() => failed = Err(e),
            Err(_) => {}
        }
    }
    if !plan.writes.is_empty() {
        info!(
            robots = written.len(),
            of = plan.writes.len(),
            interrupted,
            "robots written"
        );
    }
    Writes {
        written,
        failed,
        interrupted,
    }
}

/// Whether `now` (the store's) is a change of `seen` a user made that a plan from `seen` does
/// not know: a new spec, or a new abort, undo or restart request.
pub(super) fn changed_by_user(seen: &RobotDeployment, now: &RobotDeployment) -> bool {
    let asked = |d: &RobotDeployment, key: &str| d.annotations().get(key).cloned();
    now.metadata.generation != seen.metadata.generation
        || [ABORT_ANNOTATION, UNDO_ANNOTATION, RESTART_ANNOTATION]
            .iter()
            .any(|key| asked(now, key) != asked(seen, key))
}

/// `mark` with the time of its write for the time its state was entered, when this plan
/// entered it (at `planned_at`): a robot's timeout counts from when it was told, not from when
/// the plan began. A batch of a thousand robots written to an API server busy after its restart
/// took four minutes; robots told last had timed out before they were told, and their batch
/// failed. A mark kept from an earlier plan keeps its time.
fn entered_now(mut mark: Mark, planned_at: Timestamp) -> Mark {
    if mark.since == planned_at {
        mark.since = Timestamp::now().max(planned_at);
    }
    mark
}

/// What each planned write sends. A write that sets no release (a mark-only write) still sends
/// the value this rollout's field manager owns, or server-side apply would drop it: the one
/// this rollout told the robot to run, by the mark being written ([`Mark::told`]); for a robot
/// it told nothing, the one the store shows (an earlier rollout's).
fn robot_writes(deployment: &RobotDeployment, facts: &Facts, plan: &Plan) -> Vec<Job> {
    let kind = deployment.spec.kind();
    let views: BTreeMap<&str, &RobotView> =
        facts.robots.iter().map(|r| (r.name.as_str(), r)).collect();
    plan.writes
        .iter()
        .map(|w| {
            let view = views.get(w.robot.as_str()).copied();
            let planned = w.release.clone().or_else(|| w.mark.told(&facts.target));
            let (spec, window) = match kind {
                RolloutKind::Release => {
                    let release = planned.as_ref().or_else(|| view?.desired.as_ref());
                    let window = analysis_window(deployment, facts, release);
                    (release_spec(release), window)
                }
                RolloutKind::Agent => (agent_spec(planned.as_ref(), view, facts, deployment), None),
            };
            (w.robot.clone(), w.mark.clone(), spec, window)
        })
        .collect()
}

/// The Robot `spec` of a release rollout's write: `release` (see [`robot_writes`]), so that
/// server-side apply keeps this manager owning `spec.release` instead of dropping it.
fn release_spec(release: Option<&ReleaseRef>) -> Option<RobotSpecPart> {
    Some(RobotSpecPart {
        release: Some(release?.clone()),
        agent: None,
    })
}

/// The analysis window (`windowSeconds`) a write that leaves the robot's `spec.release` at
/// `release` asks of its switch, written as [`WINDOW_ANNOTATION`]: the deployment's when it
/// has `spec.analysis` and `release` is its target (a rollback is not judged, so it asks for
/// nothing). A write without it removes the annotation (server-side apply drops a field its
/// manager stops sending), so a later switch no analysis asked for costs no write.
fn analysis_window(
    deployment: &RobotDeployment,
    facts: &Facts,
    release: Option<&ReleaseRef>,
) -> Option<i64> {
    let analysis = deployment.spec.analysis.as_ref()?;
    (release == Some(&facts.target)).then_some(analysis.window_seconds)
}

/// The Robot `spec` of an agent rollout's write: the deployment's `spec.agent` when the robot
/// is started; the version and digest it ran before, as a build of its own architecture, when
/// it is rolled back (it switches to that build from its own disk); else the `spec.agent` it
/// has, kept owned like [`release_spec`] keeps `spec.release`.
fn agent_spec(
    planned: Option<&ReleaseRef>,
    view: Option<&RobotView>,
    facts: &Facts,
    deployment: &RobotDeployment,
) -> Option<RobotSpecPart> {
    let agent = match planned {
        Some(target) if *target == facts.target => deployment.spec.agent.clone()?,
        Some(previous) => {
            // The digest names one file, so both architectures may name it when the robot's
            // own is unknown: the robot finds it on its disk whichever it is.
            let arches = match view.and_then(|v| v.arch) {
                Some(arch) => vec![arch],
                None => vec![AgentArch::Amd64, AgentArch::Arm64],
            };
            AgentRef {
                version: previous.version.to_string(),
                builds: arches
                    .into_iter()
                    .map(|arch| AgentBuild {
                        arch,
                        digest: previous.digest.to_string(),
                    })
                    .collect(),
            }
        }
        None => view.and_then(|v| v.desired_agent.clone())?,
    };
    Some(RobotSpecPart {
        release: None,
        agent: Some(agent),
    })
}

/// Writes one robot: its mark (and the analysis window) and the part of its spec the rollout
/// kind's field manager owns, by server-side apply. A `spec` without that part (a mark-only
/// write of a robot the rollout told nothing, when the Robot store shows no value) would drop
/// what this manager set earlier if the store is behind the API server: the API server refuses
/// such a write (a removed object field becomes `null`, which the schema rejects: every later
/// reconcile failed the same way and held the rollout), or removes the robot's desired release.
/// So the robot is read first, and the value it has is kept.
pub async fn write_robot(
    api: &Api<Robot>,
    kind: RolloutKind,
    name: &str,
    mark: &Mark,
    spec: Option<RobotSpecPart>,
    window: Option<i64>,
) -> Result<Written> {
    let spec = keep_live(api, kind, name, spec).await?;
    let text = serde_json::to_string(mark).unwrap_or_default();
    let key = kind.mark_annotation();
    let mut annotations = BTreeMap::from([(key.to_owned(), text.clone())]);
    if let Some(seconds) = window {
        annotations.insert(WINDOW_ANNOTATION.to_owned(), seconds.to_string());
    }
    let patch = RobotApply::new(annotations, spec.clone());
    let robot = api
        .patch(
            name,
            &PatchParams::apply(kind.manager()).force(),
            &Patch::Apply(&patch),
        )
        .await
        .map_err(|source| Error::PatchRobot {
            object: name.to_owned(),
            source,
        })?;
    debug!(robot = %name, state = ?mark.state, batch = mark.batch, ?spec, ?window, "robot written");
    Ok(Written {
        robot: name.to_owned(),
        key,
        mark: text,
        spec,
        resource_version: robot.metadata.resource_version,
    })
}

/// `spec` when it carries the part `kind` owns (`release` or `agent`); otherwise that part as
/// the API server has it now (read, not taken from the store), or `spec` when the robot has
/// none (or is gone).
async fn keep_live(
    api: &Api<Robot>,
    kind: RolloutKind,
    name: &str,
    spec: Option<RobotSpecPart>,
) -> Result<Option<RobotSpecPart>> {
    if spec.as_ref().is_some_and(|s| s.owns(kind)) {
        return Ok(spec);
    }
    let live = api.get_opt(name).await.map_err(|source| Error::ReadRobot {
        object: name.to_owned(),
        source,
    })?;
    let Some(live) = live else {
        return Ok(spec);
    };
    let kept = RobotSpecPart::owned(kind, &live.spec);
    if kept.is_some() {
        debug!(robot = %name, ?kept, "the Robot store showed no value this rollout may own; keeping the robot's");
    }
    Ok(kept.or(spec))
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
        &StatusApply::new::<RobotDeployment>(&plan.status),
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

#[cfg(test)]
mod tests {
    use jiff::Timestamp;
    use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
    use lekiwi_crds::RobotDeploymentSpec;
    use lekiwi_crds::deployment::RolloutStrategy;

    use super::super::plan::{MarkState, ReleaseCheck, RobotWrite};
    use super::*;

    fn rel(version: &str, hex: char) -> ReleaseRef {
        serde_json::from_value(serde_json::json!({
            "version": version,
            "digest": format!("sha256:{}", hex.to_string().repeat(64)),
        }))
        .unwrap()
    }

    fn deployment(release: Option<ReleaseRef>, agent: Option<AgentRef>) -> RobotDeployment {
        let spec = RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release,
            agent,
            strategy: RolloutStrategy::default(),
            paused: false,
            analysis: None,
            priority: 0,
        };
        let mut d = RobotDeployment::new("roll", spec);
        d.metadata.namespace = Some("lab".into());
        d
    }

    /// A plan with one mark-only write of `kiwi` in `state`, and facts whose store shows the
    /// robot without the value the rollout wrote on it a moment ago (the store lags).
    fn mark_only(state: MarkState, target: &ReleaseRef) -> (Facts, Plan) {
        let mark = Mark {
            deployment: "roll".into(),
            rollout_id: "r1".into(),
            batch: 3,
            state,
            since: Timestamp::UNIX_EPOCH,
            previous: Some(rel("1.0.0", 'a')),
            message: None,
            failed: state == MarkState::Failed,
        };
        let facts = Facts {
            now: Timestamp::UNIX_EPOCH,
            robots: vec![RobotView {
                name: "kiwi".into(),
                ..RobotView::default()
            }],
            target: target.clone(),
            release: ReleaseCheck::Valid,
            overlaps: vec![],
            active_deployments: vec![],
        };
        let plan = Plan {
            writes: vec![RobotWrite {
                robot: "kiwi".into(),
                mark,
                release: None,
            }],
            status: Default::default(),
            events: vec![],
            requeue_after: None,
            batch_result: None,
            finished: false,
        };
        (facts, plan)
    }

    #[test]
    fn a_mark_only_write_keeps_what_the_rollout_told_the_robot_when_the_store_lags() {
        let target = rel("2.0.0", 'b');
        let release = deployment(Some(target.clone()), None);
        for state in [MarkState::Started, MarkState::Failed] {
            let (facts, plan) = mark_only(state, &target);
            let (_, _, spec, _) = robot_writes(&release, &facts, &plan).remove(0);
            assert_eq!(
                spec.and_then(|s| s.release),
                Some(target.clone()),
                "{state:?}"
            );
        }
        let (facts, plan) = mark_only(MarkState::RollingBack, &target);
        let (_, _, spec, _) = robot_writes(&release, &facts, &plan).remove(0);
        assert_eq!(spec.and_then(|s| s.release), Some(rel("1.0.0", 'a')));

        let build = AgentRef {
            version: "0.2.0".into(),
            builds: vec![AgentBuild {
                arch: AgentArch::Arm64,
                digest: format!("sha256:{}", "c".repeat(64)),
            }],
        };
        let agent = deployment(None, Some(build.clone()));
        let agent_target = rel("0.2.0", 'c');
        let (facts, plan) = mark_only(MarkState::Failed, &agent_target);
        let (_, _, spec, _) = robot_writes(&agent, &facts, &plan).remove(0);
        // Without the agent in the write, server-side apply would remove `spec.agent` (the
        // API server 1.20 refused the write as `null`, stopping the rollout for good).
        assert_eq!(spec.and_then(|s| s.agent), Some(build));
    }

    #[test]
    fn a_robot_told_nothing_keeps_what_the_store_shows() {
        let target = rel("2.0.0", 'b');
        let release = deployment(Some(target.clone()), None);
        let (mut facts, plan) = mark_only(MarkState::Waiting, &target);
        facts.robots[0].desired = Some(rel("1.5.0", 'd'));
        let (_, _, spec, _) = robot_writes(&release, &facts, &plan).remove(0);
        assert_eq!(spec.and_then(|s| s.release), Some(rel("1.5.0", 'd')));
    }

    /// A state this plan entered takes the time of its write (the robot's timeout counts from
    /// when it was told); a mark kept from an earlier plan keeps its time.
    #[test]
    fn a_mark_entered_now_takes_the_time_of_its_write() {
        let target = rel("2.0.0", 'b');
        let (_, plan) = mark_only(MarkState::Started, &target);
        let mark = plan.writes[0].mark.clone();
        let planned_at = Timestamp::now() - jiff::SignedDuration::from_secs(240);
        let entered = Mark {
            since: planned_at,
            ..mark.clone()
        };
        let written = entered_now(entered, planned_at);
        assert!(written.since > planned_at + jiff::SignedDuration::from_secs(200));
        let kept = Mark {
            since: planned_at - jiff::SignedDuration::from_secs(60),
            ..mark
        };
        assert_eq!(entered_now(kept.clone(), planned_at), kept);
    }

    /// A user's new spec or new abort, undo or restart request stops a plan's writes; the
    /// status (this controller's own writes) and other annotations do not.
    #[test]
    fn only_a_users_change_stops_the_writes() {
        let seen = deployment(Some(rel("2.0.0", 'b')), None);
        assert!(!changed_by_user(&seen, &seen));
        let mut status = seen.clone();
        status.status = Some(Default::default());
        status.metadata.resource_version = Some("2".into());
        assert!(!changed_by_user(&seen, &status), "its own status write");
        let mut other = seen.clone();
        other
            .annotations_mut()
            .insert("example.org/note".into(), "x".into());
        assert!(!changed_by_user(&seen, &other));
        for key in [ABORT_ANNOTATION, UNDO_ANNOTATION, RESTART_ANNOTATION] {
            let mut asked = seen.clone();
            asked
                .annotations_mut()
                .insert(key.into(), "2026-12-07T20:00:00Z".into());
            assert!(changed_by_user(&seen, &asked), "{key}");
        }
        let mut spec = seen.clone();
        spec.metadata.generation = Some(seen.metadata.generation.unwrap_or(1) + 1);
        assert!(changed_by_user(&seen, &spec), "a new generation");
    }
}
