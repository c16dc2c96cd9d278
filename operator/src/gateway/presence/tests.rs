//! The presence queue and its coalescing, and the typed status patch against the JSON the
//! gateway has always written.

use super::*;

use jiff::Timestamp;
use k8s_openapi::apimachinery::pkg::apis::meta::v1::Time;
use lekiwi_protocol::{Health, Release, SystemFacts, Teleoperation, Vitals};
use serde_json::{Value, json};

/// The hand-written patch the gateway sent before the typed one (kept to prove equality).
fn legacy_patch(gateway: &str, e: &Entry) -> Value {
    let time = |t: Timestamp| serde_json::to_value(Time(t)).unwrap_or(Value::Null);
    let mut status = json!({
        "connected": e.connected,
        "gateway": gateway,
        "protocol": e.info.protocol,
        "connectedSince": time(e.connected_since),
        "lastHeartbeatTime": time(e.last_heartbeat),
    });
    if !e.info.agent_version.is_empty() {
        status["agentVersion"] = json!(e.info.agent_version);
    }
    if let Some(r) = &e.info.release {
        status["currentRelease"] = json!({ "version": r.version, "digest": r.digest });
    }
    if let Some(a) = &e.info.address {
        status["address"] = json!(a);
    }
    if let Some(h) = &e.info.health {
        status["health"] = json!(h);
        if h.message.is_none() {
            status["health"] = json!({ "healthy": h.healthy });
        }
    }
    if let Some(t) = &e.info.teleoperation {
        let mut v = json!({ "active": t.active });
        if let Some(score) = t.score {
            v["score"] = json!(score.clamp(0.0, 1.0));
        }
        if let Some(since) = e.teleoperation_since {
            v["since"] = time(since);
        }
        status["teleoperation"] = v;
    }
    let sys = &e.info.system;
    let mut system = serde_json::Map::new();
    for (k, v) in [
        ("hostname", sys.hostname.as_ref().map(|x| json!(x))),
        ("os", sys.os.as_ref().map(|x| json!(x))),
        ("kernel", sys.kernel.as_ref().map(|x| json!(x))),
        ("arch", sys.arch.as_ref().map(|x| json!(x))),
        ("cpus", sys.cpus.map(|x| json!(x))),
        ("memoryBytes", sys.memory_bytes.map(|x| json!(x))),
    ] {
        if let Some(v) = v {
            system.insert(k.to_owned(), v);
        }
    }
    if !system.is_empty() {
        status["system"] = Value::Object(system);
    }
    let v = &e.vitals;
    let mut telemetry = serde_json::Map::new();
    for (k, x) in [
        ("cpuPercent", v.cpu_percent),
        ("memoryPercent", v.memory_percent),
        ("temperatureCelsius", v.temperature_c),
        ("batteryPercent", v.battery_percent),
    ] {
        if let Some(x) = x.filter(|x| x.is_finite()) {
            telemetry.insert(k.to_owned(), json!(x));
        }
    }
    if !telemetry.is_empty() {
        status["telemetry"] = Value::Object(telemetry);
    }
    if let Some(u) = &e.last_update {
        let mut v = json!({
            "release": { "version": u.release.version, "digest": u.release.digest },
            "phase": u.phase,
            "time": time(u.time),
        });
        if let Some(m) = &u.message {
            v["message"] = json!(m.chars().take(1024).collect::<String>());
        }
        status["lastUpdate"] = v;
    }
    json!({ "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot", "status": status })
}

fn at(s: &str) -> Timestamp {
    s.parse().unwrap()
}

fn release(v: &str) -> Release {
    Release {
        version: v.into(),
        digest: format!("sha256:{}", "ab".repeat(32)),
    }
}

fn entry(connected: bool, info: ConnectInfo) -> Entry {
    Entry {
        session: 7,
        connected,
        info,
        connected_since: at("2026-11-20T08:00:00Z"),
        last_heartbeat: at("2026-11-20T08:05:30.250Z"),
        written_heartbeat: None,
        teleoperation_since: None,
        vitals: Vitals::default(),
        retries: 0,
        last_update: None,
    }
}

/// A few representative robots: what the typed patch writes is what the gateway always wrote.
fn representative_robots() -> Vec<(&'static str, Entry)> {
    let mut with_vitals = entry(
        true,
        ConnectInfo {
            protocol: "websocket",
            agent_version: "0.9.1".into(),
            release: Some(release("1.4.2")),
            health: Some(Health {
                healthy: false,
                message: Some("camera missing".into()),
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
    let mut healthy = with_vitals.clone();
    healthy.info.health = Some(Health {
        healthy: true,
        message: None,
    });
    healthy.info.teleoperation = Some(Teleoperation {
        active: false,
        score: None,
    });
    healthy.teleoperation_since = None;
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
    updated.last_update = Some(UpdateOutcome {
        release: release("1.5.0"),
        phase: "rolled_back".into(),
        message: Some("é".repeat(1500)),
        time: at("2026-11-20T08:06:00Z"),
    });
    let mut done = updated.clone();
    done.connected = false;
    done.last_update = Some(UpdateOutcome {
        release: release("1.5.0"),
        phase: "done".into(),
        message: None,
        time: at("2026-11-20T08:06:00Z"),
    });
    vec![
        ("connected with vitals", with_vitals),
        ("healthy, not teleoperated", healthy),
        ("disconnected", disconnected),
        ("legacy poll", legacy_poll),
        ("update outcome", updated),
        ("disconnected after an update", done),
    ]
}

#[test]
fn typed_status_patch_matches_the_hand_written_one() {
    for (what, e) in representative_robots() {
        let typed = patch::status_patch("gw-0", &e, None);
        assert_eq!(typed, legacy_patch("gw-0", &e), "{what}");
        assert_eq!(
            serde_json::to_string(&typed).unwrap(),
            serde_json::to_string(&legacy_patch("gw-0", &e)).unwrap(),
            "{what}: the same bytes on the wire"
        );
        let guarded = patch::status_patch(
            "gw-0",
            &e,
            Some(patch::Precondition {
                resource_version: Some("4711".into()),
            }),
        );
        let mut legacy = legacy_patch("gw-0", &e);
        legacy["metadata"] = json!({ "resourceVersion": "4711" });
        assert_eq!(guarded, legacy, "{what}, guarded");
    }
}
fn key(n: &str) -> RobotKey {
    RobotKey {
        namespace: "lab".into(),
        name: n.into(),
    }
}

fn presence() -> Presence {
    Presence::new(
        PresenceConfig {
            gateway: "gw".into(),
            status_refresh: Duration::from_secs(300),
            poll_grace: Duration::from_secs(180),
            qps: 10.0,
            burst: 10,
            concurrency: 2,
        },
        Metrics::default(),
    )
}

#[test]
fn transitions_jump_the_queue_and_bursts_coalesce() {
    let p = presence();
    p.with_state(|s| {
        s.robots.insert(
            key("a"),
            Entry {
                session: 1,
                connected: true,
                info: ConnectInfo::default(),
                connected_since: Timestamp::now(),
                last_heartbeat: Timestamp::now(),
                written_heartbeat: None,
                teleoperation_since: None,
                vitals: Vitals::default(),
                retries: 0,
                last_update: None,
            },
        );
        s.enqueue(&key("a"), Priority::Low);
    });
    p.connect(&key("b"), 2, ConnectInfo::default());
    p.connect(&key("b"), 3, ConnectInfo::default());
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
        s.robots.get_mut(&key("a")).unwrap().written_heartbeat = Some(Timestamp::now());
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
