//! What a user's `rollout abort`, `undo` or `pause` stops at once, read from the RobotDeployment
//! change alone: the gateway cancels the downloads of those robots the moment its watch sees
//! the request, before the controller's plan rewrites each robot's `spec.release` (which, at
//! the API server's write rate, takes seconds for a large batch). The rules are the planner's
//! own (see [`super::abort`], [`super::rollback`] and [`super::pause`]): a robot told to switch
//! whose mark holds a release to return to stops switching; one that ran nothing before goes on.

use jiff::Timestamp;
use kube::ResourceExt;
use lekiwi_crds::condition::{ConditionStatus, find};
use lekiwi_crds::deployment::{RolloutKind, RolloutPhase};
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment};

use super::{
    ABORT_ANNOTATION, CONDITION_CONFLICT, Mark, MarkState, UNDO_ANNOTATION, abort, rollback,
};

/// The rollout a change of `old` into `new` stops downloads of: its id and release. Some when
/// the change brings a new abort or undo request, made after the rollout started, or a pause,
/// that the planner will act on in the rollout's phase. Agent rollouts have nothing to cancel.
pub fn stopped_by(old: &RobotDeployment, new: &RobotDeployment) -> Option<(String, ReleaseRef)> {
    let target = new.spec.release.clone()?;
    let status = new.status.as_ref()?;
    let rollout_id = status.rollout_id.clone()?;
    let started = super::rollout_start(&rollout_id)?;
    // Only a request for this rollout: the planner ignores one made before it started, and one
    // for another release (the spec changed in the same update) is a new rollout.
    if old.spec.release.as_ref() != Some(&target) {
        return None;
    }
    let asked = |key: &str| {
        old.annotations().get(key) != new.annotations().get(key) && asked_after(new, key, started)
    };
    let phase = status.phase?;
    let undo = asked(UNDO_ANNOTATION) && rollback::undo_applies(phase);
    let abort = asked(ABORT_ANNOTATION) && abort::applies(phase);
    // A pause holds robots only where the rollout moves forward (not while it waits for an
    // older overlapping deployment: robots started then keep going).
    let conflict = find(&status.conditions, CONDITION_CONFLICT)
        .is_some_and(|c| c.status == ConditionStatus::True);
    let pause =
        new.spec.paused && !old.spec.paused && phase == RolloutPhase::Progressing && !conflict;
    (undo || abort || pause).then_some((rollout_id, target))
}

/// Whether `robot` is one the stopped rollout `rollout_id` of `deployment` told to switch and
/// that has a release to stay on (its mark's `previous`): its download of the rollout's
/// release stops. (Its gateway's session knows whether one is in flight.)
pub fn halts(robot: &Robot, deployment: &str, rollout_id: &str) -> bool {
    Mark::of(robot, RolloutKind::Release).is_some_and(|m| {
        m.deployment == deployment
            && m.rollout_id == rollout_id
            && m.state == MarkState::Started
            && m.previous.is_some()
    })
}

/// Whether `robot`, told by `deployment`'s current rollout to switch to its release, belongs to
/// a rollout a user aborted or undid (a request made after the rollout started): a robot the
/// controller wrote only after the request (a batch whose writes were under way when it came)
/// must not start its download either; the controller's next plan sends it back. A pause is not
/// held here: a resumed rollout goes on with the robots it started.
pub fn held(robot: &Robot, deployment: &RobotDeployment) -> bool {
    let Some(rollout_id) = deployment
        .status
        .as_ref()
        .and_then(|s| s.rollout_id.as_deref())
    else {
        return false;
    };
    let Some(started) = super::rollout_start(rollout_id) else {
        return false;
    };
    if robot.spec.release.is_none() || robot.spec.release != deployment.spec.release {
        return false;
    }
    (asked_after(deployment, ABORT_ANNOTATION, started)
        || asked_after(deployment, UNDO_ANNOTATION, started))
        && halts(robot, &deployment.name_any(), rollout_id)
}

/// Whether `deployment`'s request annotation `key` (a time) was made after `started`: one made
/// before its rollout started, or that does not parse, counts for nothing (as for the planner).
fn asked_after(deployment: &RobotDeployment, key: &str, started: Timestamp) -> bool {
    deployment
        .annotations()
        .get(key)
        .and_then(|at| at.parse::<Timestamp>().ok())
        .is_some_and(|at| at > started)
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use lekiwi_crds::{RobotDeploymentSpec, RobotDeploymentStatus};

    use super::super::MARK_ANNOTATION;
    use super::*;

    fn release(version: &str) -> ReleaseRef {
        serde_json::from_value(serde_json::json!({
            "version": version,
            "digest": format!("sha256:{}", "b".repeat(64)),
        }))
        .unwrap()
    }

    const STARTED_MS: i64 = 1_800_000_000_000;

    fn rollout_id() -> String {
        super::super::rollout_id_at("abc", Timestamp::from_millisecond(STARTED_MS).unwrap())
    }

    fn deployment(phase: RolloutPhase, annotations: &[(&str, &str)]) -> RobotDeployment {
        let spec: RobotDeploymentSpec = serde_json::from_value(serde_json::json!({
            "selector": {},
            "release": release("2"),
        }))
        .unwrap();
        let mut d = RobotDeployment::new("d", spec);
        d.metadata.annotations = Some(
            annotations
                .iter()
                .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
                .collect::<BTreeMap<_, _>>(),
        );
        d.status = Some(RobotDeploymentStatus {
            phase: Some(phase),
            rollout_id: Some(rollout_id()),
            ..Default::default()
        });
        d
    }

    fn at(offset_s: i64) -> String {
        Timestamp::from_millisecond(STARTED_MS + offset_s * 1000)
            .unwrap()
            .to_string()
    }

    #[test]
    fn a_new_abort_or_undo_of_a_moving_rollout_stops_its_downloads() {
        let old = deployment(RolloutPhase::Progressing, &[]);
        for key in [ABORT_ANNOTATION, UNDO_ANNOTATION] {
            let new = deployment(RolloutPhase::Progressing, &[(key, &at(5))]);
            let (id, target) = stopped_by(&old, &new).expect(key);
            assert_eq!((id, target), (rollout_id(), release("2")));
            assert_eq!(stopped_by(&new, &new), None, "{key}: seen before");
        }
    }

    #[test]
    fn a_pause_of_a_moving_rollout_stops_its_downloads() {
        let old = deployment(RolloutPhase::Progressing, &[]);
        let mut new = old.clone();
        new.spec.paused = true;
        assert!(stopped_by(&old, &new).is_some());
        assert_eq!(stopped_by(&new, &new), None, "paused before");
        let mut waiting = new.clone();
        let st = waiting.status.as_mut().unwrap();
        st.conditions.push(lekiwi_crds::condition::Condition::new(
            CONDITION_CONFLICT,
            ConditionStatus::True,
            "OlderDeployment",
            "waiting",
            None,
        ));
        assert_eq!(stopped_by(&old, &waiting), None, "waits for an older one");
    }

    #[test]
    fn requests_the_planner_ignores_stop_nothing() {
        let old = deployment(RolloutPhase::Progressing, &[]);
        let before_start = deployment(RolloutPhase::Progressing, &[(ABORT_ANNOTATION, &at(-5))]);
        assert_eq!(
            stopped_by(&old, &before_start),
            None,
            "of an earlier rollout"
        );
        let unparsable = deployment(RolloutPhase::Progressing, &[(UNDO_ANNOTATION, "soon")]);
        assert_eq!(stopped_by(&old, &unparsable), None);
        let done = deployment(RolloutPhase::Completed, &[(ABORT_ANNOTATION, &at(5))]);
        assert_eq!(stopped_by(&old, &done), None, "nothing to abort");
        let back = deployment(RolloutPhase::RollingBack, &[(UNDO_ANNOTATION, &at(5))]);
        assert_eq!(stopped_by(&old, &back), None, "already rolling back");
        let mut other = deployment(RolloutPhase::Progressing, &[(UNDO_ANNOTATION, &at(5))]);
        other.spec.release = Some(release("3"));
        assert_eq!(stopped_by(&old, &other), None, "a new rollout");
    }

    fn robot(mark: Option<Mark>) -> Robot {
        let mut r = Robot::new("r", serde_json::from_value(serde_json::json!({})).unwrap());
        if let Some(mark) = mark {
            r.metadata.annotations = Some(BTreeMap::from([(
                MARK_ANNOTATION.to_owned(),
                serde_json::to_string(&mark).unwrap(),
            )]));
        }
        r
    }

    fn mark(state: MarkState, previous: Option<ReleaseRef>) -> Mark {
        Mark {
            deployment: "d".into(),
            rollout_id: rollout_id(),
            batch: 1,
            state,
            since: Timestamp::from_millisecond(STARTED_MS).unwrap(),
            previous,
            message: None,
            failed: false,
        }
    }

    #[test]
    fn only_robots_told_to_switch_with_a_release_to_stay_on_halt() {
        let id = rollout_id();
        let started = mark(MarkState::Started, Some(release("1")));
        assert!(halts(&robot(Some(started.clone())), "d", &id));
        assert!(!halts(&robot(Some(started.clone())), "other", &id));
        assert!(!halts(&robot(Some(started)), "d", "abc-1"));
        let fresh = mark(MarkState::Started, None);
        assert!(!halts(&robot(Some(fresh)), "d", &id), "nothing to stay on");
        let waiting = mark(MarkState::Waiting, Some(release("1")));
        assert!(!halts(&robot(Some(waiting)), "d", &id));
        assert!(!halts(&robot(None), "d", &id));
    }

    #[test]
    fn a_robot_written_after_an_abort_or_undo_of_its_rollout_is_held() {
        let told = |d: &RobotDeployment| {
            let mut r = robot(Some(mark(MarkState::Started, Some(release("1")))));
            r.spec.release = d.spec.release.clone();
            r
        };
        for key in [ABORT_ANNOTATION, UNDO_ANNOTATION] {
            // The request comes whatever the phase the cache shows yet (the controller may
            // have written the rollout Aborted before the late robot's change arrives).
            for phase in [RolloutPhase::Progressing, RolloutPhase::Aborted] {
                let d = deployment(phase, &[(key, &at(5))]);
                assert!(held(&told(&d), &d), "{key} in {phase:?}");
            }
            let earlier = deployment(RolloutPhase::Progressing, &[(key, &at(-5))]);
            assert!(
                !held(&told(&earlier), &earlier),
                "{key} of an earlier rollout"
            );
        }
        let d = deployment(RolloutPhase::Progressing, &[(ABORT_ANNOTATION, &at(5))]);
        let mut back = told(&d);
        back.spec.release = Some(release("1"));
        assert!(!held(&back, &d), "sent back: its own release goes out");
        let fresh = robot(Some(mark(MarkState::Started, None)));
        assert!(
            !held(&fresh, &d),
            "nothing to stay on: it goes on switching"
        );
        let mut paused = deployment(RolloutPhase::Progressing, &[]);
        paused.spec.paused = true;
        assert!(
            !held(&told(&paused), &paused),
            "a pause goes on with its robots"
        );
    }
}
