//! The presence queue and its coalescing, and the typed status patch against the JSON the
//! gateway has always written.

use super::*;

use jiff::Timestamp;
use lekiwi_protocol::{Health, Release, SystemFacts, Teleoperation, Vitals};
use serde_json::{Value, json};

fn at(s: &str) -> Timestamp {
    s.parse().unwrap()
}

fn release(v: &str) -> Release {
    Release {
        version: v.into(),
        digest: format!("sha256:{}", "ab".repeat(32)),
    }
}

/// The JSON of [`release`]`(version)`.
fn release_json(version: &str) -> Value {
    json!({ "digest": format!("sha256:{}", "ab".repeat(32)), "version": version })
}

pub(super) fn entry(connected: bool, info: ConnectInfo) -> Entry {
    Entry {
        session: 7,
        epoch: 1_000,
        connected,
        info,
        connected_since: at("2026-11-20T08:00:00Z"),
        last_heartbeat: at("2026-11-20T08:05:30.250Z"),
        written_heartbeat: None,
        written_at: None,
        written_version: 0,
        refresh_hash: 0,
        teleoperation_since: None,
        vitals: Vitals::default(),
        retries: 0,
        last_update: None,
        analysis: Default::default(),
        agent_update: None,
        presence_only: false,
        settling: false,
        moved: false,
        restart_grace: 0,
    }
}

/// A few representative robots: what the typed patch writes is what the gateway always wrote.
fn representative_robots() -> Vec<(&'static str, Entry)> {
    let mut with_vitals = entry(
        true,
        ConnectInfo {
            protocol: "websocket",
            agent_version: "0.9.1".into(),
            agent_digest: Some(format!("sha256:{}", "9".repeat(64))),
            release: Some(release("1.4.2")),
            health: Some(Health {
                healthy: false,
                message: Some("camera missing".into()),
                reason: None,
            }),
            teleoperation: Some(Teleoperation {
                active: true,
                score: Some(1.7),
            }),
            system: SystemFacts {
                hostname: Some("kiwi-7".into()),
                os: Some("Debian GNU/Linux 12 (bookworm)".into()),
                kernel: None,
                arch: Some("aarch64".into()),
                cpus: Some(4),
                memory_bytes: Some(8 << 30),
            },
            address: Some("10.0.0.7:40112".into()),
        },
    );
    with_vitals.teleoperation_since = Some(at("2026-11-20T08:04:00Z"));
    with_vitals.vitals = Vitals {
        cpu_percent: Some(12.5),
        memory_percent: Some(f64::NAN),
        temperature_c: Some(51.0),
        battery_percent: None,
        ..Vitals::default()
    };
    let mut healthy = entry(
        true,
        ConnectInfo {
            protocol: "websocket",
            agent_version: "1.0.0-rc.1".into(),
            agent_digest: None,
            release: Some(release("2.0.0")),
            health: Some(Health {
                healthy: true,
                message: None,
                reason: None,
            }),
            teleoperation: Some(Teleoperation {
                active: false,
                score: None,
            }),
            system: SystemFacts {
                kernel: Some("6.6.31+rpt-rpi-2712".into()),
                memory_bytes: Some(4 << 30),
                ..SystemFacts::default()
            },
            address: None,
        },
    );
    healthy.vitals = Vitals {
        battery_percent: Some(f64::INFINITY),
        ..Vitals::default()
    };
    let disconnected = entry(
        false,
        ConnectInfo {
            protocol: "websocket",
            agent_version: "0.9.1".into(),
            ..ConnectInfo::default()
        },
    );
    let legacy_poll = entry(
        true,
        ConnectInfo {
            protocol: "poll",
            release: Some(release("1.0.0")),
            address: Some("192.168.1.20".into()),
            ..ConnectInfo::default()
        },
    );
    let mut updated = entry(
        true,
        ConnectInfo {
            protocol: "websocket",
            release: Some(release("1.4.2")),
            ..ConnectInfo::default()
        },
    );
    updated.last_update = Some(Box::new(UpdateOutcome {
        release: release("1.5.0"),
        phase: "rolled_back".into(),
        message: Some("é".repeat(1500)),
        time: at("2026-11-20T08:06:00Z"),
    }));
    let mut done = updated.clone();
    done.connected = false;
    // A `done` outcome also makes its release the current one.
    done.info.release = Some(release("1.5.0"));
    done.last_update = Some(Box::new(UpdateOutcome {
        release: release("1.5.0"),
        phase: "done".into(),
        message: None,
        time: at("2026-11-20T08:07:00Z"),
    }));
    vec![
        ("connected with vitals", with_vitals),
        ("healthy, not teleoperated", healthy),
        ("disconnected", disconnected),
        ("legacy poll", legacy_poll),
        ("update outcome", updated),
        ("disconnected after an update", done),
    ]
}

/// What the hand-written patch of the gateway before the typed one sent for each of
/// [`representative_robots`], in its order (checked against that code when it was replaced).
fn hand_written_patches() -> Vec<Value> {
    vec![
        // connected with vitals
        json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "status": {
                "address": "10.0.0.7:40112",
                "agentDigest": format!("sha256:{}", "9".repeat(64)),
                "agentVersion": "0.9.1",
                "connected": true,
                "connectedSince": "2026-11-20T08:00:00Z",
                "sessionEpoch": 1_000,
                "currentRelease": release_json("1.4.2"),
                "gateway": "gw-0",
                "health": {
                    "healthy": false,
                    "message": "camera missing"
                },
                "lastHeartbeatTime": "2026-11-20T08:05:30Z",
                "protocol": "websocket",
                "system": {
                    "arch": "aarch64",
                    "cpus": 4,
                    "hostname": "kiwi-7",
                    "memoryBytes": 8_589_934_592_u64,
                    "os": "Debian GNU/Linux 12 (bookworm)"
                },
                "telemetry": {
                    "cpuPercent": 12.5,
                    "temperatureCelsius": 51.0
                },
                "teleoperation": {
                    "active": true,
                    "score": 1.0,
                    "since": "2026-11-20T08:04:00Z"
                }
            }
        }),
        // healthy, not teleoperated
        json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "status": {
                "agentVersion": "1.0.0-rc.1",
                "connected": true,
                "connectedSince": "2026-11-20T08:00:00Z",
                "sessionEpoch": 1_000,
                "currentRelease": release_json("2.0.0"),
                "gateway": "gw-0",
                "health": {
                    "healthy": true
                },
                "lastHeartbeatTime": "2026-11-20T08:05:30Z",
                "protocol": "websocket",
                "system": {
                    "kernel": "6.6.31+rpt-rpi-2712",
                    "memoryBytes": 4_294_967_296_u64
                },
                "teleoperation": {
                    "active": false
                }
            }
        }),
        // disconnected
        json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "status": {
                "agentVersion": "0.9.1",
                "connected": false,
                "connectedSince": "2026-11-20T08:00:00Z",
                "sessionEpoch": 1_000,
                "gateway": "gw-0",
                "lastHeartbeatTime": "2026-11-20T08:05:30Z",
                "protocol": "websocket"
            }
        }),
        // legacy poll
        json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "status": {
                "address": "192.168.1.20",
                "connected": true,
                "connectedSince": "2026-11-20T08:00:00Z",
                "sessionEpoch": 1_000,
                "currentRelease": release_json("1.0.0"),
                "gateway": "gw-0",
                "lastHeartbeatTime": "2026-11-20T08:05:30Z",
                "protocol": "poll"
            }
        }),
        // update outcome
        json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "status": {
                "connected": true,
                "connectedSince": "2026-11-20T08:00:00Z",
                "sessionEpoch": 1_000,
                "currentRelease": release_json("1.4.2"),
                "gateway": "gw-0",
                "lastHeartbeatTime": "2026-11-20T08:05:30Z",
                "lastUpdate": {
                    "message": "é".repeat(1024),
                    "phase": "rolled_back",
                    "release": release_json("1.5.0"),
                    "time": "2026-11-20T08:06:00.000000Z"
                },
                "protocol": "websocket"
            }
        }),
        // disconnected after an update
        json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "status": {
                "connected": false,
                "connectedSince": "2026-11-20T08:00:00Z",
                "sessionEpoch": 1_000,
                "currentRelease": release_json("1.5.0"),
                "gateway": "gw-0",
                "lastHeartbeatTime": "2026-11-20T08:05:30Z",
                "lastUpdate": {
                    "phase": "done",
                    "release": release_json("1.5.0"),
                    "time": "2026-11-20T08:07:00.000000Z"
                },
                "protocol": "websocket"
            }
        }),
    ]
}

#[test]
fn typed_status_patch_matches_the_hand_written_one() {
    let robots = representative_robots();
    assert_eq!(robots.len(), hand_written_patches().len());
    for ((what, e), expected) in robots.into_iter().zip(hand_written_patches()) {
        let typed = patch::status_patch("gw-0", &e, None);
        assert_eq!(typed, expected, "{what}");
        assert_eq!(
            serde_json::to_string(&typed).unwrap(),
            serde_json::to_string(&expected).unwrap(),
            "{what}: the same bytes on the wire"
        );
        let guarded = patch::status_patch(
            "gw-0",
            &e,
            Some(lekiwi_core::apply::Metadata::fence(Some("4711".into()))),
        );
        let mut expected = expected;
        expected["metadata"] = json!({ "resourceVersion": "4711" });
        assert_eq!(guarded, expected, "{what}, guarded");
    }
}
fn key(n: &str) -> RobotKey {
    RobotKey {
        namespace: "lab".into(),
        name: n.into(),
    }
}

pub(super) fn presence() -> Presence {
    Presence::new(
        PresenceConfig {
            gateway: "gw".into(),
            status_refresh: Duration::from_secs(300),
            poll_grace: Duration::from_secs(180),
            qps: 10.0,
            adaptive: None,
            burst: 10,
            concurrency: 2,
        },
        Metrics::default(),
    )
}

/// A robot this gateway last wrote as disconnected: a session that fails within [`SETTLE`]
/// writes nothing at all; one that lasts is written by the next tick after it; a robot not
/// known to be shown disconnected is written at once.
#[test]
fn sessions_that_fail_at_once_write_nothing_for_a_robot_shown_offline() {
    let p = presence();
    p.with_state(|s| {
        s.known_offline.insert(key("flap"));
    });
    p.connect(&key("flap"), 1, 1_000, ConnectInfo::default());
    assert_eq!(p.queued(), 0, "not written while settling");
    p.disconnect(&key("flap"), 1);
    assert_eq!(
        p.queued(),
        0,
        "nothing to write: the status says disconnected"
    );
    p.with_state(|s| {
        assert!(!s.robots.contains_key(&key("flap")));
        assert!(s.known_offline.contains(&key("flap")));
    });

    p.connect(&key("flap"), 2, 1_000, ConnectInfo::default());
    p.with_state(|s| {
        let e = s.robots.get_mut(&key("flap")).unwrap();
        e.connected_since = Timestamp::now() - jiff::SignedDuration::from_secs(2);
    });
    p.tick();
    p.with_state(|s| {
        assert_eq!(s.pop(), Some((key("flap"), Priority::High)));
        // Taken for writing, as the writer does: its disconnect is written too.
        assert!(s.take_for_write(&key("flap")).unwrap().connected);
    });
    p.disconnect(&key("flap"), 2);
    assert_eq!(p.queued(), 1);

    p.connect(&key("new"), 3, 1_000, ConnectInfo::default());
    p.with_state(|s| assert!(s.queued.contains_key(&key("new")), "written at once"));
}

#[test]
fn transitions_jump_the_queue_and_bursts_coalesce() {
    let p = presence();
    p.with_state(|s| {
        s.robots.insert(
            key("a"),
            Box::new(Entry {
                session: 1,
                epoch: 1_000,
                connected: true,
                info: ConnectInfo::default(),
                connected_since: Timestamp::now(),
                last_heartbeat: Timestamp::now(),
                written_heartbeat: None,
                written_at: None,
                written_version: 0,
                refresh_hash: 0,
                teleoperation_since: None,
                vitals: Vitals::default(),
                retries: 0,
                last_update: None,
                analysis: Default::default(),
                agent_update: None,
                presence_only: false,
                settling: false,
                moved: false,
                restart_grace: 0,
            }),
        );
        s.enqueue(&key("a"), Priority::Low);
    });
    p.connect(&key("b"), 2, 1_000, ConnectInfo::default());
    p.connect(&key("b"), 3, 1_000, ConnectInfo::default());
    p.disconnect(&key("b"), 2); // stale session: ignored
    p.with_state(|s| {
        assert_eq!(
            s.pop(),
            Some((key("b"), Priority::High)),
            "high first, once"
        );
        assert_eq!(s.pop(), Some((key("a"), Priority::Low)));
        assert_eq!(s.pop(), None);
        assert!(s.robots[&key("b")].connected);
    });
}

#[test]
fn routine_heartbeats_write_nothing_until_refresh_but_changes_do() {
    let p = presence();
    p.connect(
        &key("a"),
        1,
        1_000,
        ConnectInfo {
            teleoperation: Some(Teleoperation {
                active: false,
                score: None,
            }),
            ..ConnectInfo::default()
        },
    );
    p.with_state(|s| {
        s.pop();
        let e = s.robots.get_mut(&key("a")).unwrap();
        e.written_heartbeat = Some(Timestamp::now());
        e.written_at = e.written_heartbeat;
    });
    for _ in 0..100 {
        p.heartbeat(
            &key("a"),
            1,
            HeartbeatInfo {
                teleoperation: Some(Teleoperation {
                    active: false,
                    score: None,
                }),
                ..Default::default()
            },
        );
    }
    p.tick();
    assert_eq!(
        p.with_state(|s| s.pop()),
        None,
        "unchanged heartbeats within the refresh period"
    );
    p.heartbeat(
        &key("a"),
        1,
        HeartbeatInfo {
            teleoperation: Some(Teleoperation {
                active: true,
                score: Some(0.9),
            }),
            ..Default::default()
        },
    );
    assert_eq!(p.with_state(|s| s.pop()), Some((key("a"), Priority::High)));
    let patch =
        p.with_state(|s| patch::status_patch(&p.config.gateway, &s.robots[&key("a")], None));
    assert_eq!(patch["status"]["teleoperation"]["active"], json!(true));
    assert_eq!(patch["status"]["gateway"], json!("gw"));
}

/// A session another gateway took over is forgotten without a write; a stale session id
/// forgets nothing.
#[test]
fn a_moved_session_is_forgotten_without_a_write() {
    let p = presence();
    p.connect(&key("m"), 1, 1_000, ConnectInfo::default());
    assert_eq!(p.queued(), 1);
    p.forget(&key("m"), 2);
    assert_eq!(p.connected(), 1);
    p.forget(&key("m"), 1);
    assert_eq!((p.connected(), p.queued()), (0, 0));
    p.disconnect(&key("m"), 1);
    assert_eq!(p.queued(), 0, "its end writes nothing either");
}

/// The live heartbeat time is each held robot's latest, whatever was written; robots not held
/// (never connected, disconnected) have none.
#[test]
fn last_heartbeats_are_the_held_sessions_latest() {
    let p = presence();
    let (a, b, c) = (key("a"), key("b"), key("c"));
    p.connect(&a, 1, 1_000, ConnectInfo::default());
    p.connect(&b, 2, 1_000, ConnectInfo::default());
    let connected_at = p.last_heartbeats([&a])[0].expect("held");
    std::thread::sleep(Duration::from_millis(5));
    p.heartbeat(&a, 1, HeartbeatInfo::default());
    p.heartbeat(&a, 9, HeartbeatInfo::default());
    p.disconnect(&b, 2);
    let seen = p.last_heartbeats([&a, &b, &c]);
    assert!(seen[0].expect("held") > connected_at, "{seen:?}");
    assert_eq!(seen[1..], [None, None]);
}

/// A robot that moved here is written before every transition and refresh, and claimed (in
/// the Lease annotation) until the Robot watch shows its write (or long after the write, if the
/// watch never does) or its session ends.
#[test]
fn moved_robots_go_first_and_are_claimed_until_written() {
    let p = presence();
    p.connect(&key("local"), 1, 1_000, ConnectInfo::default());
    p.connect_moved(&key("m1"), 2, 1_000, ConnectInfo::default(), true);
    p.connect_moved(&key("m2"), 3, 1_000, ConnectInfo::default(), true);
    p.with_state(|s| s.enqueue(&key("m2"), Priority::High)); // a change: stays a move
    assert_eq!(p.claims(), [key("m1"), key("m2")]);
    assert_eq!(
        p.claims_annotation().as_deref(),
        Some("lab/m1,m2"),
        "the namespace written once"
    );
    let m1 = p.with_state(|s| {
        assert_eq!(s.pop(), Some((key("m1"), Priority::Move)));
        assert_eq!(s.pop(), Some((key("m2"), Priority::Move)));
        assert_eq!(s.pop(), Some((key("local"), Priority::High)));
        assert_eq!(s.pop(), None);
        s.take_for_write(&key("m1")).unwrap()
    });
    p.written(&key("m1"), &m1, 0);
    assert_eq!(p.claims(), [key("m1"), key("m2")], "written, not yet seen");
    p.write_seen(&key("m1"), 999);
    assert_eq!(
        p.claims(),
        [key("m1"), key("m2")],
        "another session's write"
    );
    p.write_seen(&key("m1"), 1_000);
    assert_eq!(p.claims(), [key("m2")], "its write seen: no claim any more");
    let m2 = p.with_state(|s| s.take_for_write(&key("m2")).unwrap());
    p.written(&key("m2"), &m2, 0);
    let long_ago = Timestamp::now() - super::claims::CLAIM_AFTER_WRITE;
    p.with_state(|s| s.robots.get_mut(&key("m2")).unwrap().written_at = Some(long_ago));
    assert_eq!(p.claims(), [key("m2")], "until the next tick");
    p.tick();
    assert!(p.claims().is_empty(), "written long ago and never seen");
    p.with_state(|s| s.robots.get_mut(&key("m2")).unwrap().written_at = Some(Timestamp::now()));
    assert!(
        p.claims().is_empty(),
        "a later write does not claim it again"
    );
    p.disconnect(&key("m2"), 3);
    assert!(p.claims().is_empty(), "a session that ended claims nothing");
    assert_eq!(p.claims_annotation(), None);
}

/// A session that opened before the Robot cache showed the old gateway's write (it landed, or
/// reached this gateway's watch, late) is claimed and goes first once the cache shows it; not
/// when the other session is the later one, nor once this session's own write landed.
#[test]
fn a_move_the_cache_shows_late_is_claimed_then() {
    let p = presence();
    p.connect(&key("local"), 1, 1_000, ConnectInfo::default());
    p.connect(&key("late"), 2, 1_000, ConnectInfo::default());
    p.connect(&key("written"), 3, 1_000, ConnectInfo::default());
    assert!(p.claims().is_empty());
    assert!(
        !p.moved_later(&key("late"), 2_000, "gw-other"),
        "the other session is later"
    );
    assert!(
        !p.moved_later(&key("absent"), 500, "gw-other"),
        "no session here"
    );
    let written = p.with_state(|s| s.take_for_write(&key("written")).unwrap());
    p.written(&key("written"), &written, 0);
    assert!(
        !p.moved_later(&key("written"), 500, "gw-other"),
        "its own write landed first"
    );
    assert!(p.moved_later(&key("late"), 500, "gw-other"));
    assert!(
        !p.moved_later(&key("late"), 500, "gw-other"),
        "claimed once"
    );
    assert_eq!(p.claims(), [key("late")]);
    p.with_state(|s| {
        assert_eq!(s.pop(), Some((key("late"), Priority::Move)));
        assert_eq!(s.pop(), Some((key("local"), Priority::High)));
    });
}

/// A moved robot the Robot cache shows `Unknown` (marked before it reconnected here) goes
/// before the moves that still show `Online`: when the cache shows it so at its connect, or
/// later; not when the other session is later, nor while its write is in flight, nor once its
/// own write landed.
#[test]
fn a_robot_shown_gone_while_connected_here_is_written_first() {
    let p = presence();
    let gone: lekiwi_crds::Robot = serde_json::from_value(json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "Robot",
        "metadata": { "name": "gone", "namespace": "lab" },
        "spec": {},
        "status": { "phase": "Unknown", "gateway": "dead", "sessionEpoch": 500 },
    }))
    .unwrap();
    let cache = lekiwi_core::cache::Cache::listed([gone]);
    let robots = crate::watched::WatchedRobots(std::sync::Arc::new(cache));
    p.plan_phases(PhasePlanner::new(robots, Duration::from_secs(60)));
    for (n, name) in ["m1", "m2", "m3", "busy", "written"].iter().enumerate() {
        p.connect_moved(
            &key(name),
            n as u64 + 1,
            1_000,
            ConnectInfo::default(),
            true,
        );
    }
    assert!(
        !p.shown_gone(&key("m3"), 2_000, "gw-other"),
        "the other session is later"
    );
    assert!(
        !p.shown_gone(&key("absent"), 500, "gw-other"),
        "no session here"
    );
    let written = p.with_state(|s| {
        assert!(s.begin_write(&key("busy"), Priority::Move));
        s.take_for_write(&key("written")).unwrap()
    });
    p.written(&key("written"), &written, 0);
    assert!(
        !p.shown_gone(&key("busy"), 500, "gw-other"),
        "its write is in flight"
    );
    assert!(
        !p.shown_gone(&key("written"), 500, "gw-other"),
        "its own write landed"
    );
    assert!(p.shown_gone(&key("m3"), 500, "gw-other"));
    p.connect_moved(&key("gone"), 9, 1_000, ConnectInfo::default(), true);
    p.with_state(|s| {
        let order: Vec<_> = std::iter::from_fn(|| s.pop())
            .map(|(k, _)| k.name)
            .collect();
        assert_eq!(
            order,
            ["m3", "gone", "m1", "m2", "busy", "written"],
            "the robots shown gone first, in their order, each once"
        );
    });
}

/// A robot whose live session here was written, and which the Robot controller then marked
/// `Unknown` (this gateway's writes ran late), goes before every waiting write when the cache
/// shows the mark under this session's epoch, even while a write of it is in flight (that one
/// was planned before the mark); not under another epoch, not without a session.
#[test]
fn a_robot_shown_gone_under_its_own_live_session_is_written_first() {
    let p = presence();
    p.connect(&key("early"), 9, 700, ConnectInfo::default());
    assert!(
        !p.shown_gone_here(&key("early"), 700),
        "no Lease renewed: the controller marks the robot for the Lease, whatever is written"
    );
    p.lease_renewed(Duration::from_secs(60));
    for (n, name) in ["waiting", "marked", "busy", "closed"].iter().enumerate() {
        p.connect(&key(name), n as u64 + 1, 700, ConnectInfo::default());
        let entry = p.with_state(|s| s.take_for_write(&key(name)).unwrap());
        p.written(&key(name), &entry, 0);
    }
    p.disconnect(&key("closed"), 4);
    p.with_state(|s| {
        while s.pop().is_some() {}
        s.enqueue(&key("waiting"), Priority::High);
        assert!(s.begin_write(&key("busy"), Priority::Low));
    });
    assert!(
        !p.shown_gone_here(&key("marked"), 699),
        "another session's epoch"
    );
    assert!(
        !p.shown_gone_here(&key("closed"), 700),
        "no live session here"
    );
    assert!(
        !p.shown_gone_here(&key("absent"), 700),
        "never connected here"
    );
    assert!(
        p.shown_gone_here(&key("busy"), 700),
        "in flight: queued to follow"
    );
    assert!(p.shown_gone_here(&key("marked"), 700));
    p.with_state(|s| {
        let order: Vec<_> = std::iter::from_fn(|| s.pop())
            .map(|(k, _)| k.name)
            .collect();
        assert_eq!(
            order,
            ["busy", "marked", "waiting"],
            "the marked robots first, once"
        );
        assert!(
            !s.begin_write(&key("busy"), Priority::Gone),
            "still in flight"
        );
        s.end_write(&key("busy"));
        assert_eq!(
            s.pop(),
            Some((key("busy"), Priority::Gone)),
            "then written first"
        );
    });
}

/// The sweep of [`Presence::tick`] puts first every robot the Robot cache shows `Unknown` or
/// `Offline` under its live, written session here, whatever the dispatch of changes did; not
/// one shown so under another session, not one shown `Online`, not one whose session was not
/// written yet or whose write waits for a retry.
#[test]
fn the_sweep_puts_first_every_robot_shown_gone_under_its_live_session() {
    let p = presence();
    let robot = |name: &str, phase: &str, epoch: i64| -> lekiwi_crds::Robot {
        serde_json::from_value(json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "metadata": { "name": name, "namespace": "lab" },
            "spec": {},
            "status": { "phase": phase, "gateway": "gw", "sessionEpoch": epoch },
        }))
        .unwrap()
    };
    let cache = lekiwi_core::cache::Cache::listed([
        robot("gone", "Unknown", 700),
        robot("offline", "Offline", 700),
        robot("online", "Online", 700),
        robot("older", "Unknown", 600),
        robot("unwritten", "Unknown", 700),
        robot("retrying", "Unknown", 700),
    ]);
    let robots = crate::watched::WatchedRobots(std::sync::Arc::new(cache));
    p.plan_phases(PhasePlanner::new(robots, Duration::from_secs(60)));
    let names = [
        "gone",
        "offline",
        "online",
        "older",
        "unwritten",
        "retrying",
    ];
    for (n, name) in names.iter().enumerate() {
        p.connect(&key(name), n as u64 + 1, 700, ConnectInfo::default());
        if *name != "unwritten" {
            let entry = p.with_state(|s| s.take_for_write(&key(name)).unwrap());
            p.written(&key(name), &entry, 0);
        }
    }
    p.with_state(|s| {
        while s.pop().is_some() {}
        s.robots.get_mut(&key("retrying")).unwrap().retries = 1;
    });
    assert!(!p.sweep_shown_gone(), "no Lease renewed: nothing put first");
    p.lease_renewed(Duration::from_secs(60));
    assert!(p.sweep_shown_gone());
    assert!(!p.sweep_shown_gone(), "those queued first stay queued once");
    p.with_state(|s| {
        let mut first: Vec<_> = std::iter::from_fn(|| s.pop())
            .filter(|(_, priority)| *priority == Priority::Gone)
            .map(|(k, _)| k.name)
            .collect();
        first.sort();
        assert_eq!(first, ["gone", "offline"]);
    });
}

/// A moved robot the Robot controller listed on its old gateway's Lease as marked `Unknown`
/// goes before the moves, whether the list came before its session here or after, as long as
/// the cache shows its status naming that gateway; a robot listed there whose status names
/// another gateway stays a move.
#[test]
fn a_robot_marked_on_its_old_gateways_lease_is_written_first() {
    let robot = |name: &str, gateway: &str| -> lekiwi_crds::Robot {
        serde_json::from_value(json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "metadata": { "name": name, "namespace": "lab" },
            "spec": {},
            "status": { "phase": "Online", "gateway": gateway, "sessionEpoch": 500 },
        }))
        .unwrap()
    };
    let p = presence();
    let cache = lekiwi_core::cache::Cache::listed([
        robot("m1", "dead"),
        robot("m2", "dead"),
        robot("early", "dead"),
        robot("late", "dead"),
        robot("other", "alive"),
    ]);
    let robots = crate::watched::WatchedRobots(std::sync::Arc::new(cache));
    p.plan_phases(PhasePlanner::new(robots, Duration::from_secs(60)));
    let peers = p.peers().clone();
    let mut lease = lekiwi_liveness::gateways::test_lease("dead", 60);
    let mut list = |value: &str| {
        lease.metadata.annotations = Some(
            [(
                lekiwi_crds::contract::MARKED_ANNOTATION.to_owned(),
                value.to_owned(),
            )]
            .into(),
        );
        peers.update(&lease)
    };
    let connect = |name: &str, session: u64| {
        p.connect_moved(&key(name), session, 1_000, ConnectInfo::default(), true);
    };
    connect("m1", 1);
    connect("m2", 2);
    list("lab/early,other");
    connect("early", 3);
    connect("late", 4);
    connect("other", 5);
    assert_eq!(list("lab/early,other,late"), [key("late")]);
    assert!(
        !p.marked(&key("other"), "dead"),
        "its status names another gateway"
    );
    assert!(!p.marked(&key("absent"), "dead"), "no session here");
    assert!(p.marked(&key("late"), "dead"));
    assert_eq!(
        write_order(&p),
        ["early", "late", "m1", "m2", "other"],
        "the marked robots first, in their order, then the moves"
    );
}

/// The robots waiting for a write, in the order the writer takes them (the queues emptied).
fn write_order(p: &Presence) -> Vec<String> {
    p.with_state(|s| {
        std::iter::from_fn(|| s.pop())
            .map(|(k, _)| k.name)
            .collect()
    })
}

/// A change while the robot's write is in flight is written after it, never beside it: two
/// writes of one robot at once could land in the wrong order and leave the older snapshot (the
/// race that once left an agent update `Started` after it had `Succeeded`).
#[test]
fn one_write_per_robot_at_a_time_and_a_change_meanwhile_follows() {
    let p = presence();
    p.connect(&key("a"), 1, 1_000, ConnectInfo::default());
    p.with_state(|s| {
        let (k, prio) = s.pop().unwrap();
        assert!(s.begin_write(&k, prio), "nothing in flight yet");
        s.take_for_write(&k).unwrap();
        // The robot changes while its write is in flight: queued, but not written beside it.
        s.enqueue(&k, Priority::Low);
        s.enqueue(&k, Priority::High);
        let (again, prio) = s.pop().unwrap();
        assert!(!s.begin_write(&again, prio), "one write at a time");
        assert_eq!(s.pop(), None, "the change waits for the write in flight");
        s.end_write(&k);
        assert_eq!(s.pop(), Some((key("a"), Priority::High)), "then follows it");
        assert!(s.begin_write(&k, Priority::High));
        s.end_write(&k);
        assert_eq!(s.pop(), None, "nothing asked for meanwhile: nothing more");
    });
}

/// Robots whose status was written at the same moment (a fleet that reconnected at once) are
/// refreshed spread evenly over the following period, none later than one period after that
/// write, and then exactly once per period.
#[test]
fn routine_refreshes_spread_over_the_period() {
    let period = jiff::SignedDuration::from_secs(300);
    let secs = jiff::SignedDuration::from_secs;
    let written = at("2026-11-28T00:00:00Z");
    let mut first_due = Vec::new();
    for i in 0..3_000 {
        let e = Entry {
            refresh_hash: refresh_hash(&key(&format!("r{i:05}"))),
            ..entry(true, ConnectInfo::default())
        };
        let due = (0..=300)
            .find(|&s| refresh_due(&e, written, written + secs(s), period))
            .expect("due within one period of its last write");
        assert!(due > 0, "not due the moment it was written");
        first_due.push(due);
        // Written then: due again exactly one period later, not before.
        let w2 = written + secs(due);
        assert!(!refresh_due(&e, w2, w2 + secs(299), period));
        assert!(refresh_due(&e, w2, w2 + period, period));
    }
    // Ten slices of the period each get about a tenth of the fleet (300 ± 90).
    let mut slices = [0usize; 10];
    for s in first_due {
        slices[((s - 1) / 30) as usize] += 1;
    }
    assert!(
        slices.iter().all(|&n| (210..=390).contains(&n)),
        "{slices:?}"
    );
}

/// A refresh's period counts from when the write landed, not from the heartbeat it wrote
/// (which is up to an interval older): a robot just refreshed is not due again at once.
#[test]
fn a_robot_just_written_is_not_due_again() {
    let p = Presence::new(
        PresenceConfig {
            status_refresh: Duration::from_secs(3_600),
            ..(*presence().config).clone()
        },
        Metrics::default(),
    );
    let robots: Vec<RobotKey> = (0..50).map(|i| key(&format!("w{i}"))).collect();
    for (i, k) in robots.iter().enumerate() {
        p.connect(k, i as u64, 1_000, ConnectInfo::default());
        p.heartbeat(k, i as u64, HeartbeatInfo::default());
        let mut written = p.with_state(|s| Entry::clone(&s.robots[k]));
        // A heartbeat 40 minutes old: counted from it, most robots' point in the hour would
        // lie between it and now.
        written.last_heartbeat -= jiff::SignedDuration::from_mins(40);
        p.written(k, &written, 0);
    }
    p.with_state(|s| while s.pop().is_some() {});
    p.tick();
    assert_eq!(p.with_state(|s| s.pop()), None);
}

/// A switch that a rollout with analysis asked to watch is written once more, at low priority,
/// once its window spans what was asked; a switch no rollout asked to watch is written no more
/// than any robot until its routine refresh.
#[test]
fn only_a_switch_a_rollout_asked_to_watch_is_written_when_its_window_ends() {
    // A routine refresh of "plain" is right whenever its point in the period passes, and the
    // test's 10 s of wall clock held one in 10 of every 3,600 s (a failure in CI): with a
    // period of 100 days that is once in 864,000 runs.
    let p = Presence::new(
        PresenceConfig {
            status_refresh: Duration::from_secs(100 * 86_400),
            ..(*presence().config).clone()
        },
        Metrics::default(),
    );
    let robot = |name: &str, annotations: Value| -> lekiwi_crds::Robot {
        serde_json::from_value(json!({
            "apiVersion": "fleet.lekiwi.io/v1alpha1",
            "kind": "Robot",
            "metadata": { "name": name, "namespace": "lab", "annotations": annotations },
            "spec": { "release": release_json("2") },
        }))
        .unwrap()
    };
    let window = json!({ lekiwi_crds::analysis::WINDOW_ANNOTATION: "1" });
    let cache =
        lekiwi_core::cache::Cache::listed([robot("asked", window), robot("plain", json!({}))]);
    let robots = crate::watched::WatchedRobots(std::sync::Arc::new(cache));
    p.plan_phases(PhasePlanner::new(robots, Duration::from_secs(60)));
    let write_all = |p: &Presence| {
        let mut order = Vec::new();
        while let Some((k, prio)) = p.with_state(|s| s.pop()) {
            let sent = p.with_state(|s| s.take_for_write(&k)).unwrap();
            p.written(&k, &sent, 0);
            order.push((k.name, prio));
        }
        order
    };
    let names = ["asked", "plain"];
    for (session, name) in names.iter().enumerate() {
        let info = ConnectInfo {
            protocol: "websocket",
            release: Some(release("1")),
            ..ConnectInfo::default()
        };
        p.connect(&key(name), session as u64, 1_000, info);
    }
    write_all(&p);
    let secs = jiff::SignedDuration::from_secs;
    for (session, name) in names.iter().enumerate() {
        let done = UpdateOutcome {
            release: release("2"),
            phase: "done".into(),
            message: None,
            time: Timestamp::now() - secs(2),
        };
        p.update_finished(&key(name), session as u64, done);
    }
    assert_eq!(write_all(&p).len(), 2, "each switch is written");
    // Both switches were written 10 s ago by the books; a heartbeat 2 s after the switch
    // completes the asked window.
    p.with_state(|s| {
        for e in s.robots.values_mut() {
            e.written_at = Some(Timestamp::now() - secs(10));
        }
    });
    for (session, name) in names.iter().enumerate() {
        p.heartbeat(&key(name), session as u64, HeartbeatInfo::default());
    }
    p.tick();
    p.tick();
    assert_eq!(write_all(&p), [("asked".into(), Priority::Low)]);
    for (session, name) in names.iter().enumerate() {
        p.heartbeat(&key(name), session as u64, HeartbeatInfo::default());
    }
    p.tick();
    assert_eq!(write_all(&p), [], "once per switch");
}

/// Every connected robot holds an entry for its whole session: what most robots never have (a
/// switch's analysis window, an update's outcome, an agent update) is boxed, not inline.
#[test]
fn an_entry_is_small() {
    let size = std::mem::size_of::<Entry>();
    // 808 bytes (800 before the version of the session's last write; 1,336 with those three
    // inline).
    assert!(size <= 808, "a presence entry is {size} bytes");
}

/// An agent update's steps in progress are kept for the robot's next write, its outcome is
/// written at once.
#[test]
fn agent_update_steps_in_progress_wait_for_the_next_write_outcomes_do_not() {
    let p = presence();
    p.connect(&key("a"), 1, 1_000, ConnectInfo::default());
    p.with_state(|s| s.pop());
    let step = |phase: &'static str| AgentUpdateOutcome {
        version: "0.3.0".into(),
        phase,
        message: phase.into(),
        time: Timestamp::now(),
    };
    for phase in ["Sent", "Started"] {
        assert!(p.agent_update(&key("a"), 1, step(phase)), "{phase} is kept");
        assert_eq!(
            p.with_state(|s| s.pop()),
            None,
            "{phase} is not written by itself"
        );
    }
    let patch =
        p.with_state(|s| patch::status_patch(&p.config.gateway, &s.robots[&key("a")], None));
    assert_eq!(patch["status"]["agentUpdate"]["phase"], json!("Started"));
    assert!(p.agent_update(&key("a"), 1, step("Succeeded")));
    assert_eq!(p.with_state(|s| s.pop()), Some((key("a"), Priority::High)));
}

/// Robot "a" in session 1, written, whose agent reports its update to 0.3.0 `Started`.
fn update_started() -> (Presence, AgentUpdateOutcome) {
    let p = presence();
    p.connect(&key("a"), 1, 1_000, ConnectInfo::default());
    p.with_state(|s| s.pop());
    let started = AgentUpdateOutcome {
        version: "0.3.0".into(),
        phase: "Started",
        message: "switching".into(),
        time: Timestamp::now(),
    };
    assert!(p.agent_update(&key("a"), 1, started.clone()));
    (p, started)
}

/// An agent that restarted into its update and connects again before this gateway noticed
/// its old session close (the new session replaces one still open) costs one write too.
#[test]
fn an_agent_back_from_its_update_before_its_old_session_closed_is_written_once() {
    let (p, started) = update_started();
    p.connect(&key("a"), 2, 1_001, ConnectInfo::default());
    assert_eq!(
        p.with_state(|s| s.pop()),
        None,
        "the new session waits for the agent's report"
    );
    p.disconnect(&key("a"), 1);
    let succeeded = AgentUpdateOutcome {
        phase: "Succeeded",
        message: "running 0.3.0".into(),
        ..started
    };
    assert!(p.agent_update(&key("a"), 2, succeeded));
    let (k, _) = p.with_state(|s| s.pop()).expect("the report is written");
    assert!(p.with_state(|s| s.take_for_write(&k)).unwrap().connected);
    for _ in 0..=agent::RESTART_GRACE_SECONDS {
        p.tick();
    }
    assert_eq!(p.with_state(|s| s.pop()), None, "one write for the restart");
    // A session replaced with no update under way is written at once.
    p.connect(&key("a"), 3, 1_002, ConnectInfo::default());
    assert_eq!(p.with_state(|s| s.pop()), Some((key("a"), Priority::High)));
}

/// An agent restarting into its update costs the robot one status write: its session's end
/// waits for the next session, which waits for the agent's report of the update and is
/// written with it; only an agent that stays away longer than the grace is written
/// disconnected. Any other session end is written at once.
#[test]
fn an_agent_restarting_into_its_update_is_written_once() {
    let (p, started) = update_started();
    p.disconnect(&key("a"), 1);
    p.tick();
    assert_eq!(
        p.with_state(|s| s.pop()),
        None,
        "the end waits for the next session"
    );
    p.connect(&key("a"), 2, 1_001, ConnectInfo::default());
    assert_eq!(
        p.with_state(|s| s.pop()),
        None,
        "the new session waits for the agent's report"
    );
    let succeeded = AgentUpdateOutcome {
        phase: "Succeeded",
        message: "running 0.3.0".into(),
        ..started.clone()
    };
    assert!(p.agent_update(&key("a"), 2, succeeded));
    let (k, _) = p.with_state(|s| s.pop()).expect("the report is written");
    let written = p.with_state(|s| s.take_for_write(&k)).unwrap();
    assert!(written.connected, "with the new session");
    for _ in 0..=agent::RESTART_GRACE_SECONDS {
        p.tick();
    }
    assert_eq!(p.with_state(|s| s.pop()), None, "one write for the restart");
    // An agent whose report does not come is written after the wait all the same.
    p.agent_update(&key("a"), 2, started.clone());
    p.disconnect(&key("a"), 2);
    p.connect(&key("a"), 4, 1_002, ConnectInfo::default());
    for _ in 1..agent::REPORT_WAIT_SECONDS {
        p.tick();
    }
    assert_eq!(p.with_state(|s| s.pop()), None);
    p.tick();
    assert_eq!(p.with_state(|s| s.pop()), Some((key("a"), Priority::High)));
    p.with_state(|s| s.take_for_write(&key("a")));
    p.agent_update(&key("a"), 4, started.clone());
    // Still away after the grace: written disconnected then.
    p.disconnect(&key("a"), 4);
    for _ in 1..agent::RESTART_GRACE_SECONDS {
        p.tick();
    }
    assert_eq!(p.with_state(|s| s.pop()), None);
    p.tick();
    assert_eq!(p.with_state(|s| s.pop()), Some((key("a"), Priority::High)));
    // Without an update in progress a session's end is written at once.
    p.connect(&key("b"), 3, 1_000, ConnectInfo::default());
    p.with_state(|s| s.pop());
    p.disconnect(&key("b"), 3);
    assert_eq!(p.with_state(|s| s.pop()), Some((key("b"), Priority::High)));
}
