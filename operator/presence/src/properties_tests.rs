//! Property: any well-typed `hello` and `heartbeat`, once through the status rules, map to a
//! `Robot` status that the generated CRD's schema accepts — checked offline against the
//! `openAPIV3Schema` of `lekiwi-crds`, so no API server is needed. Cases: `PROPTEST_CASES`.

use std::sync::OnceLock;

use jiff::Timestamp;
use lekiwi_protocol::rules::sanitize;
use lekiwi_protocol::{AgentMessage, Health, Release, SystemFacts, Teleoperation, Vitals};
use proptest::prelude::*;
use serde_json::Value;

use super::patch::gateway_status;
use super::{ConnectInfo, Entry};

/// The status schema of the Robot CRD as generated (and committed under `manifests/`).
fn status_schema() -> &'static Value {
    static SCHEMA: OnceLock<Value> = OnceLock::new();
    SCHEMA.get_or_init(|| {
        let crd = serde_json::to_value(&lekiwi_crds::crds()[0]).unwrap();
        crd.pointer("/spec/versions/0/schema/openAPIV3Schema/properties/status")
            .cloned()
            .unwrap()
    })
}

/// Whether `v` meets the structural-schema subset the CRD uses, as the API server judges it
/// (integers must fit int64); the first violation otherwise.
fn check(schema: &Value, v: &Value, path: &str) -> Result<(), String> {
    let fail = |why: &str| Err(format!("{path}: {why}: {v}"));
    if v.is_null() {
        return if schema["nullable"] == true {
            Ok(())
        } else {
            fail("null")
        };
    }
    let bound = |key: &str, n: f64, below: bool| {
        schema[key]
            .as_f64()
            .is_some_and(|b| if below { n < b } else { n > b })
    };
    match schema["type"].as_str() {
        Some("object") => {
            let Some(obj) = v.as_object() else {
                return fail("not an object");
            };
            for req in schema["required"].as_array().into_iter().flatten() {
                if !obj.contains_key(req.as_str().unwrap_or_default()) {
                    return fail(&format!("missing {req}"));
                }
            }
            for (k, x) in obj {
                let Some(sub) = schema["properties"].get(k) else {
                    return fail("unknown key");
                };
                check(sub, x, &format!("{path}.{k}"))?;
            }
        }
        Some("array") => {
            let Some(items) = v.as_array() else {
                return fail("not an array");
            };
            for (i, x) in items.iter().enumerate() {
                check(&schema["items"], x, &format!("{path}[{i}]"))?;
            }
        }
        Some("string") => {
            let Some(s) = v.as_str() else {
                return fail("not a string");
            };
            let chars = s.chars().count() as f64;
            if bound("maxLength", chars, false) || bound("minLength", chars, true) {
                return fail("length");
            }
            if let Some(p) = schema["pattern"].as_str()
                && !regex::Regex::new(p).unwrap().is_match(s)
            {
                return fail("pattern");
            }
            if let Some(allowed) = schema["enum"].as_array()
                && !allowed.contains(v)
            {
                return fail("enum");
            }
            if schema["format"] == "date-time" && s.parse::<Timestamp>().is_err() {
                return fail("date-time");
            }
        }
        Some("integer") if v.as_i64().is_none() => return fail("not an int64"),
        Some("integer" | "number") => {
            let Some(n) = v.as_f64() else {
                return fail("not a number");
            };
            if bound("maximum", n, false) || bound("minimum", n, true) {
                return fail("range");
            }
        }
        Some("boolean") if !v.is_boolean() => return fail("not a boolean"),
        _ => {}
    }
    Ok(())
}

fn release() -> impl Strategy<Value = Release> {
    let version = prop_oneof!["[A-Za-z0-9][A-Za-z0-9._+-]{0,130}", "\\PC{0,16}"];
    let digest = prop_oneof![
        "sha256:[0-9a-fA-F]{64}",
        "(sha256:)?[0-9a-zA-Z]{0,70}",
        "\\PC{0,16}"
    ];
    (version, digest).prop_map(|(version, digest)| Release { version, digest })
}

fn text(max: usize) -> impl Strategy<Value = Option<String>> {
    prop::option::of(prop_oneof![
        "\\PC{0,16}".boxed(),
        proptest::string::string_regex(&format!("\\PC{{{max}}}"))
            .unwrap()
            .boxed(),
        proptest::string::string_regex(&format!("[a-z]{{{}}}", max + 1))
            .unwrap()
            .boxed()
    ])
}

fn reports() -> impl Strategy<Value = (Option<Release>, Option<Health>, Option<Teleoperation>)> {
    let health = (any::<bool>(), text(1024)).prop_map(|(healthy, message)| Health {
        healthy,
        message,
        reason: None,
    });
    let teleoperation = (any::<bool>(), prop::option::of(any::<f64>()))
        .prop_map(|(active, score)| Teleoperation { active, score });
    (
        prop::option::of(release()),
        prop::option::of(health),
        prop::option::of(teleoperation),
    )
}

fn hello() -> impl Strategy<Value = AgentMessage> {
    let system = (
        text(256),
        text(256),
        text(256),
        text(256),
        any::<Option<u32>>(),
        any::<Option<u64>>(),
    )
        .prop_map(
            |(hostname, os, kernel, arch, cpus, memory_bytes)| SystemFacts {
                hostname,
                os,
                kernel,
                arch,
                cpus,
                memory_bytes,
            },
        );
    // Half the digests are well formed (some in upper case), half arbitrary text.
    let digest = prop_oneof!["(sha256:)[0-9a-fA-F]{64}".prop_map(Some), text(80),];
    (text(256), digest, system, reports()).prop_map(
        |(agent_version, agent_digest, system, (current_release, health, teleoperation))| {
            AgentMessage::Hello {
                protocol_version: 1,
                agent_version: agent_version.unwrap_or_default(),
                agent_digest,
                system,
                current_release,
                last_acked_seq: None,
                health,
                teleoperation,
                features: Vec::new(),
            }
        },
    )
}

fn heartbeat() -> impl Strategy<Value = AgentMessage> {
    let vitals = any::<[Option<f64>; 4]>().prop_map(|[cpu, mem, temp, battery]| Vitals {
        cpu_percent: cpu,
        memory_percent: mem,
        temperature_c: temp,
        battery_percent: battery,
        ..Vitals::default()
    });
    (vitals, reports()).prop_map(|(vitals, (current_release, health, teleoperation))| {
        AgentMessage::Heartbeat {
            sent_at_ms: 0,
            rtt_ms: None,
            vitals,
            current_release,
            health,
            teleoperation,
        }
    })
}

/// The presence entry after `hello` and then `heartbeat` (both through the rules).
fn entry(mut hello: AgentMessage, mut heartbeat: AgentMessage) -> Entry {
    sanitize(&mut hello);
    sanitize(&mut heartbeat);
    let AgentMessage::Hello {
        agent_version,
        agent_digest,
        system,
        current_release,
        health,
        teleoperation,
        ..
    } = hello
    else {
        unreachable!()
    };
    let AgentMessage::Heartbeat {
        vitals,
        current_release: r,
        health: h,
        teleoperation: t,
        ..
    } = heartbeat
    else {
        unreachable!()
    };
    let now = Timestamp::now();
    Entry {
        session: 1,
        epoch: 1_000,
        connected: true,
        info: ConnectInfo {
            protocol: "websocket",
            agent_version,
            agent_digest,
            release: r.or(current_release),
            health: h.or(health),
            teleoperation: t.or(teleoperation),
            system,
            address: Some("192.0.2.7".into()),
        },
        connected_since: now,
        last_heartbeat: now,
        written_heartbeat: None,
        written_at: None,
        written_version: 0,
        refresh_hash: 0,
        teleoperation_since: Some(now),
        vitals,
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

proptest! {
    #[test]
    fn every_report_maps_to_a_status_the_crd_accepts(hello in hello(), heartbeat in heartbeat(), bare in any::<bool>()) {
        let mut e = entry(hello, heartbeat);
        e.presence_only = bare;
        let status = serde_json::to_value(gateway_status("gw-1", &e)).unwrap();
        if let Err(why) = check(status_schema(), &status, "status") {
            prop_assert!(false, "{why}");
        }
    }
}

#[test]
fn the_checker_refuses_what_the_api_server_refuses() {
    let schema = status_schema();
    let ok = serde_json::json!({ "system": { "memoryBytes": i64::MAX } });
    assert_eq!(check(schema, &ok, "status"), Ok(()));
    for bad in [
        serde_json::json!({ "system": { "memoryBytes": u64::MAX } }),
        serde_json::json!({ "currentRelease": { "version": "1.0", "digest": "sha256:11" } }),
        serde_json::json!({ "currentRelease": { "version": "1.0 beta", "digest": format!("sha256:{}", "a".repeat(64)) } }),
        serde_json::json!({ "agentVersion": "x".repeat(257) }),
        serde_json::json!({ "teleoperation": { "active": true, "score": 1.5 } }),
    ] {
        assert!(check(schema, &bad, "status").is_err(), "{bad}");
    }
}
