//! Where a new session's analysis tracker starts ([`Tracker::at_connect`]): a switch no gateway
//! saw opens its window at the reconnect; a robot that did not switch keeps its tracker.

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use lekiwi_crds::{ReleaseRef, RobotPhase, RobotStatus};
use lekiwi_protocol::Release;

use super::analysis::Tracker;

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
        let t = Tracker::at_connect(None, Some(&status), Some(&rel("2")), now);
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
    let t = Tracker::at_connect(None, Some(&same), Some(&rel("2")), now);
    assert_eq!(window_release(&t), None);
    let never_written = RobotStatus::default();
    let t = Tracker::at_connect(None, Some(&never_written), Some(&rel("2")), now);
    assert_eq!(window_release(&t), None);
    // A new robot the controller marked Pending (a phase, but no gateway ever saw it).
    let pending = RobotStatus {
        phase: Some(RobotPhase::Pending),
        ..RobotStatus::default()
    };
    let t = Tracker::at_connect(None, Some(&pending), Some(&rel("2")), now);
    assert_eq!(
        window_release(&t),
        None,
        "a first connection opens no window"
    );
    let t = Tracker::at_connect(None, None, Some(&rel("2")), now);
    assert_eq!(window_release(&t), None);
    // This gateway saw 2 already (its status write may still be on its way): no new window.
    let ours = Tracker::default();
    let stale = stored(Some("1"));
    let t = Tracker::at_connect(
        Some((&ours, Some(&rel("2")))),
        Some(&stale),
        Some(&rel("2")),
        now,
    );
    assert_eq!(window_release(&t), None);
}
