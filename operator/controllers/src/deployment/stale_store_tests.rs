//! Unit test of planning from a Robot store that lags behind this controller's writes (what the
//! soak at 10,000 robots met after an API server restart): the planner, the robot views of
//! [`super::facts`] and the writes [`super::own_writes`] lays over the store.

use std::time::Duration;

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use kube::ResourceExt;
use lekiwi_crds::deployment::RolloutKind;
use lekiwi_crds::{ReleaseRef, Robot, RobotDeployment, RobotPhase, RobotSpec, RobotStatus};

use super::apply::Written;
use super::facts::view;
use super::own_writes::OwnWrites;
use super::plan::{Facts, Plan, ReleaseCheck, plan};
use lekiwi_core::apply::RobotSpecPart;

fn release(v: &str) -> ReleaseRef {
    serde_json::from_value(serde_json::json!({
        "version": v,
        "digest": format!("sha256:{}", v.replace('.', "").repeat(64).chars().take(64).collect::<String>()),
    }))
    .unwrap()
}

/// Robot `kiwi-n` as the store holds it: Online, fresh, on release 1, at resourceVersion 10+n.
fn robot(n: usize, now: Timestamp) -> Robot {
    let mut r = Robot::new(&format!("kiwi-{n}"), RobotSpec::default());
    r.metadata.namespace = Some("lab".into());
    r.metadata.resource_version = Some((10 + n).to_string());
    r.status = Some(RobotStatus {
        phase: Some(RobotPhase::Online),
        connected: Some(true),
        last_heartbeat_time: Some(Time(now)),
        current_release: Some(release("1")),
        ..RobotStatus::default()
    });
    r
}

fn deployment() -> RobotDeployment {
    serde_json::from_value(serde_json::json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "RobotDeployment",
        "metadata": {"name": "roll", "namespace": "lab", "generation": 1, "resourceVersion": "5"},
        "spec": {"selector": {}, "release": release("2"), "strategy": {"canary": 1, "batchSize": 2}},
    }))
    .unwrap()
}

fn facts(robots: &[Robot], own: Option<&OwnWrites>, now: Timestamp) -> Facts {
    let kind = RolloutKind::Release;
    let grace = Duration::from_secs(60);
    Facts {
        now,
        robots: robots
            .iter()
            .map(|r| match own {
                Some(own) => view(&own.robot(r, kind.mark_annotation()), now, grace, kind),
                None => view(r, now, grace, kind),
            })
            .collect(),
        target: release("2"),
        release: ReleaseCheck::Valid,
        overlaps: vec![],
        active_deployments: vec!["roll".into()],
    }
}

/// What the API server answered the plan's robot writes with: resourceVersions from 100 on.
fn written(plan: &Plan) -> Vec<Written> {
    let key = RolloutKind::Release.mark_annotation();
    plan.writes
        .iter()
        .enumerate()
        .map(|(i, w)| Written {
            robot: w.robot.clone(),
            key,
            mark: serde_json::to_string(&w.mark).unwrap(),
            spec: w.release.clone().map(|release| RobotSpecPart {
                release: Some(release),
                agent: None,
            }),
            resource_version: Some((100 + i).to_string()),
        })
        .collect()
}

fn started(plan: &Plan) -> usize {
    plan.events
        .iter()
        .filter(|e| e.reason == "BatchStarted")
        .count()
}

#[test]
fn a_store_behind_the_writes_of_the_batch_just_started_does_not_start_it_again() {
    let now = Timestamp::now();
    let robots: Vec<Robot> = (0..4).map(|n| robot(n, now)).collect();
    let mut d = deployment();
    let own = OwnWrites::default();

    // The canary batch starts: kiwi-0 is told release 2.
    let first = plan(&d, &facts(&robots, None, now));
    assert_eq!(started(&first), 1);
    assert_eq!(first.writes.len(), 1);
    own.wrote_robots("lab", &written(&first));
    d.status = Some(first.status.clone());
    let later = now + jiff::SignedDuration::from_secs(10);

    // The store still holds every robot as before the writes. Planned from it alone, the
    // canary batch looks empty and starts again: kiwi-0 is written again, its clock reset.
    let blind = plan(&d, &facts(&robots, None, later));
    assert_eq!(started(&blind), 1, "the failure this guards against");
    assert_eq!(blind.writes[0].robot, "kiwi-0");

    // With the writes laid over the store, the batch is under way: nothing is written again.
    let seeing = plan(&d, &facts(&robots, Some(&own), later));
    assert_eq!(started(&seeing), 0, "{:?}", seeing.events);
    assert!(seeing.writes.is_empty(), "{:?}", seeing.writes);
    assert_eq!(seeing.status.current_batch, first.status.current_batch);

    // Once the store shows the write (or a later version), it speaks for itself again.
    let mut caught_up = robots.clone();
    caught_up[0].metadata.resource_version = Some("100".into());
    let view = own.robot(&caught_up[0], RolloutKind::Release.mark_annotation());
    assert!(
        view.annotations()
            .get(RolloutKind::Release.mark_annotation())
            .is_none()
    );
}
