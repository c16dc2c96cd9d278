//! Where a new session's analysis tracker starts ([`Tracker::at_connect`]): a switch no gateway
//! saw opens its window at the reconnect; a robot that did not switch keeps its tracker. And
//! when a window's outcome is written: once per switch a rollout asked to watch ([`Asked`]),
//! never for another.

use jiff::{SignedDuration, Timestamp};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use lekiwi_crds::{ReleaseRef, Robot, RobotPhase, RobotStatus};
use lekiwi_protocol::{Release, Vitals};

use super::analysis::{Asked, Tracker};

fn rel(v: &str) -> Release {
    Release {
        version: v.into(),
        digest: format!("sha256:{v}"),
    }
}

fn stored(current: Option<&str>) -> RobotStatus {
    RobotStatus {
        phase: Some(RobotPhase::Online),
        last_heartbeat_time: Some(Time(Timestamp::from_second(1_000).unwrap())),
        current_release: current.map(|v| ReleaseRef {
            version: v.into(),
            digest: format!("sha256:{v}").into(),
        }),
        ..RobotStatus::default()
    }
}

fn window_release(t: &Tracker) -> Option<String> {
    Some(t.report()?.release?.version.to_string())
}

/// A gateway that restarted (nothing of its own) meets a robot whose status says 1 (or no
/// release) but which runs 2: it switched unseen, and the window of 2 opens at the reconnect.
#[test]
fn a_switch_no_gateway_saw_opens_its_window_at_the_reconnect() {
    let now = Timestamp::from_second(2_000).unwrap();
    for before in [Some("1"), None] {
        // As the gateway's Robot cache holds it: this is what a reconnect reads.
        let status = stored(before);
        let t = Tracker::at_connect(None, Some(&status), Some(&rel("2")), None, now);
        let report = t.report().expect("a window");
        assert_eq!(report.release.unwrap().version, "2");
        assert_eq!(report.window_start.unwrap().0, now);
    }
}

/// No window opens for a robot that runs what its status or this gateway last saw, nor for
/// one no gateway ever wrote a status for (its first connect is no switch).
#[test]
fn a_robot_that_did_not_switch_keeps_its_tracker() {
    let now = Timestamp::from_second(2_000).unwrap();
    let same = stored(Some("2"));
    let t = Tracker::at_connect(None, Some(&same), Some(&rel("2")), None, now);
    assert_eq!(window_release(&t), None);
    let never_written = RobotStatus::default();
    let t = Tracker::at_connect(None, Some(&never_written), Some(&rel("2")), None, now);
    assert_eq!(window_release(&t), None);
    // A new robot the controller marked Pending (a phase, but no gateway ever saw it).
    let pending = RobotStatus {
        phase: Some(RobotPhase::Pending),
        ..RobotStatus::default()
    };
    let t = Tracker::at_connect(None, Some(&pending), Some(&rel("2")), None, now);
    assert_eq!(
        window_release(&t),
        None,
        "a first connection opens no window"
    );
    let t = Tracker::at_connect(None, None, Some(&rel("2")), None, now);
    assert_eq!(window_release(&t), None);
    // This gateway saw 2 already (its status write may still be on its way): no new window.
    let ours = Tracker::default();
    let stale = stored(Some("1"));
    let t = Tracker::at_connect(
        Some((&ours, Some(&rel("2")))),
        Some(&stale),
        Some(&rel("2")),
        None,
        now,
    );
    assert_eq!(window_release(&t), None);
}

/// A Robot whose `spec.release` is `version`, with the rollout's window annotation if given.
fn robot(version: &str, window: Option<&str>) -> Robot {
    let annotations = window.map_or(String::new(), |w| {
        format!("annotations: {{ fleet.lekiwi.io/analysis-window-seconds: {w:?} }}")
    });
    serde_yaml::from_str(&format!(
        "apiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\n\
         metadata: {{ name: kiwi, namespace: lab, {annotations} }}\n\
         spec: {{ release: {{ version: {version:?}, digest: \"sha256:{version}\" }} }}\n"
    ))
    .unwrap()
}

/// A Robot asks for a window only with the rollout's annotation, in whole seconds, cut to the
/// longest window; without `spec.release` it asks for nothing.
#[test]
fn a_robot_asks_for_the_window_its_rollout_wrote() {
    let asked = |r: &Robot| Asked::of(r);
    assert_eq!(asked(&robot("2", None)), None);
    assert_eq!(asked(&robot("2", Some("soon"))), None);
    let mut bare = robot("2", Some("30"));
    bare.spec.release = None;
    assert_eq!(asked(&bare), None);
    let window = |r: &Robot| {
        let mut t = Tracker::default();
        let t0 = Timestamp::from_second(1_000).unwrap();
        t.switched(rel("2"), t0, Asked::of(r).as_ref());
        // The first heartbeat 600 s after the switch completes any window; one at 599 s only
        // a shorter one.
        let mut early = t.clone();
        early.record(
            &Vitals::default(),
            None,
            t0 + SignedDuration::from_secs(599),
        );
        t.record(
            &Vitals::default(),
            None,
            t0 + SignedDuration::from_secs(600),
        );
        (early.outcome_due(), t.outcome_due())
    };
    assert_eq!(window(&robot("2", Some("30"))), (true, true));
    assert_eq!(
        window(&robot("2", Some("99999"))),
        (false, true),
        "cut to 600 s"
    );
    assert_eq!(window(&robot("2", None)), (false, false));
}

/// A switch a rollout asked to watch for 30 s: its outcome is due once a heartbeat 30 s after
/// the switch arrived, and only until a write holding that landed (a write made before does
/// not count). A switch to another release than the one asked for is never due.
#[test]
fn the_outcome_of_an_asked_window_is_written_once() {
    let t0 = Timestamp::from_second(1_000).unwrap();
    let at = |s: i64| t0 + SignedDuration::from_secs(s);
    let asked = Asked::of(&robot("2", Some("30")));
    let mut t = Tracker::default();
    t.record(&Vitals::default(), Some(1.0), at(-5));
    t.switched(rel("2"), t0, asked.as_ref());
    t.record(&Vitals::default(), Some(1.0), at(10));
    assert!(!t.outcome_due());
    let before = t.clone();
    t.record(&Vitals::default(), Some(1.0), at(30));
    assert!(t.outcome_due());
    t.written(&before);
    assert!(t.outcome_due(), "the write held 10 s of the 30");
    let sent = t.clone();
    t.record(&Vitals::default(), Some(1.0), at(31));
    t.written(&sent);
    assert!(!t.outcome_due());
    t.record(&Vitals::default(), Some(1.0), at(60));
    assert!(!t.outcome_due(), "once per switch");

    // Rolled back to 1: the annotation asks for a switch to 2, not to 1.
    t.switched(rel("1"), at(70), asked.as_ref());
    t.record(&Vitals::default(), Some(1.0), at(200));
    assert!(!t.outcome_due());
}

/// A gateway that takes a robot over goes on from the stored summary: its outcome is due if
/// the summary does not span the window yet, and not again if it does.
#[test]
fn a_resumed_window_is_written_once_it_spans_what_was_asked() {
    let t0 = Timestamp::from_second(1_000).unwrap();
    let at = |s: i64| t0 + SignedDuration::from_secs(s);
    let asked = Asked::of(&robot("2", Some("30")));
    let mut t = Tracker::default();
    t.switched(rel("2"), t0, asked.as_ref());
    t.record(&Vitals::default(), Some(1.0), at(20));
    let mut short = Tracker::resume(&t.report().unwrap(), asked.as_ref()).unwrap();
    assert!(!short.outcome_due());
    short.record(&Vitals::default(), Some(1.0), at(30));
    assert!(short.outcome_due());
    t.record(&Vitals::default(), Some(1.0), at(40));
    let spanned = Tracker::resume(&t.report().unwrap(), asked.as_ref()).unwrap();
    assert!(!spanned.outcome_due(), "the old gateway wrote it");
}
