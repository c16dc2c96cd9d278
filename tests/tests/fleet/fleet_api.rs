//! The Fleet API (`/api/v1`, issue 15) against the real API server, with users of different
//! RBAC: ServiceAccounts bound to the chart's `lekiwi-viewer` and `lekiwi-operator-user` in one
//! namespace (tokens from `kubectl create token`). A viewer lists, filters and pages robots,
//! reads one robot with its vitals, its events and telemetry within a time range (SQLite here,
//! PostgreSQL in the second test), and rollouts with their per-robot progress; it cannot pause a
//! rollout (403), an operator user can (the RobotDeployment carries what `kubectl lekiwi rollout`
//! writes); another namespace is refused; no token or a bad one gets 401; malformed parameters
//! 400, empty ones (`continue=`) are absent ones; the history of a robot that does not exist
//! 404; a burst beyond the user's budget 429 with `Retry-After` while another user is served;
//! and every route of the OpenAPI document answers.

use std::collections::BTreeSet;

use anyhow::{Context as _, Result, ensure};
use futures::SinkExt;
use k8s_openapi::api::rbac::v1::ClusterRole;
use kube::Api;
use kube::api::{DeleteParams, Patch, PatchParams, PostParams};
use lekiwi_crds::{Robot, RobotDeployment};
use lekiwi_event_store::{MAX_TIME_MS, MIN_TIME_MS, Sample, Store, StoredEvent};
use lekiwi_protocol::{AgentMessage, ServerMessage, Severity, encode};
use lekiwi_tests::postgres::Postgres;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, account, chart_roles, connect_agent, create_robot,
    enrollment_token, http_request, namespace, recv, wait_for,
};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

/// How long a listing may take to show what was just stored.
const WAIT: std::time::Duration = std::time::Duration::from_secs(10);

const DIGEST_A: &str = "sha256:aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa";

/// One request to the operator's gateway port: status, `Retry-After` if any, JSON body.
async fn call(
    op: &OperatorProcess,
    method: &str,
    path: &str,
    token: Option<&str>,
) -> Result<(u16, Option<String>, Value)> {
    let auth = token.map(|t| format!("Bearer {t}"));
    let headers: Vec<(&str, &str)> = auth.iter().map(|a| ("authorization", a.as_str())).collect();
    let body = (method == "POST").then_some(&b""[..]);
    let (code, hdrs, body) = http_request(op.gateway_port, method, path, &headers, body).await?;
    let retry = hdrs
        .into_iter()
        .find(|(k, _)| k == "retry-after")
        .map(|(_, v)| v);
    let json = serde_json::from_slice(&body).unwrap_or(Value::Null);
    Ok((code, retry, json))
}

/// `GET path` that must answer 200: its body.
async fn ok(op: &OperatorProcess, path: &str, token: &str) -> Result<Value> {
    let (code, _, body) = call(op, "GET", path, Some(token)).await?;
    ensure!(code == 200, "GET {path}: {code} {body}");
    Ok(body)
}

fn names(page: &Value) -> Vec<String> {
    page["items"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|r| {
            r["metadata"]["name"]
                .as_str()
                .unwrap_or_default()
                .to_owned()
        })
        .collect()
}

/// Five Robots in `ns`: labels `room`, phases and running releases set in status directly (the
/// operator runs only its gateway, so no controller rewrites them).
async fn robots(client: &kube::Client, ns: &str) -> Result<()> {
    let api = Api::<Robot>::namespaced(client.clone(), ns);
    let fleet = [
        ("kiwi-1", "b1", "Online", "1.0.0"),
        ("kiwi-2", "b1", "Offline", "1.0.0"),
        ("kiwi-3", "b2", "Online", "2.0.0"),
        ("kiwi-4", "b2", "Online", "1.0.0"),
        ("kiwi-5", "b3", "Pending", "2.0.0"),
    ];
    for (name, room, phase, version) in fleet {
        create_robot(client, ns, name, &[("room", room)]).await?;
        let status = json!({"status": {
            "phase": phase,
            "currentRelease": {"version": version, "digest": DIGEST_A},
            "lastHeartbeatTime": "2026-01-31T08:00:00Z",
            "telemetry": {"cpuPercent": 12.5, "batteryPercent": 80.0},
        }});
        api.patch_status(name, &PatchParams::default(), &Patch::Merge(&status))
            .await?;
    }
    Ok(())
}

/// A RobotDeployment `v2` in `ns` with per-robot progress in its status.
async fn rollout(client: &kube::Client, ns: &str) -> Result<()> {
    let api = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    let rd = json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "RobotDeployment",
        "metadata": {"name": "v2"},
        "spec": {"selector": {"matchLabels": {"room": "b2"}}, "release": {"version": "2.0.0", "digest": DIGEST_A}},
    });
    api.create(&PostParams::default(), &serde_json::from_value(rd)?)
        .await?;
    let status = json!({"status": {"phase": "Progressing", "targeted": 2, "updated": 1, "pending": 1,
        "robots": [{"robot": "kiwi-3", "batch": 0, "state": "Updated"}, {"robot": "kiwi-4", "batch": 1, "state": "Updating"}]}});
    api.patch_status("v2", &PatchParams::default(), &Patch::Merge(&status))
        .await?;
    Ok(())
}

/// Waits until the gateway's caches hold what the test made.
async fn wait_cached(op: &OperatorProcess, ns: &str, token: &str) -> Result<()> {
    lekiwi_tests::wait_for(
        "the Fleet API's caches",
        std::time::Duration::from_secs(20),
        || async {
            let robots = ok(op, &format!("/api/v1/namespaces/{ns}/robots"), token)
                .await
                .ok()?;
            let rollout = ok(op, &format!("/api/v1/namespaces/{ns}/rollouts/v2"), token)
                .await
                .ok()?;
            (names(&robots).len() == 5 && rollout["status"]["robots"].is_array()).then_some(())
        },
    )
    .await
}

/// Lists with every filter, and pages that together hold every robot once, in order.
async fn lists_filter_and_page(op: &OperatorProcess, ns: &str, viewer: &str) -> Result<()> {
    let base = format!("/api/v1/namespaces/{ns}/robots");
    let q = |query: &str| format!("{base}?{query}");
    ensure!(names(&ok(op, &q("labelSelector=room%3Db2"), viewer).await?) == ["kiwi-3", "kiwi-4"]);
    ensure!(
        names(
            &ok(
                op,
                &q("labelSelector=room%20in%20(b1%2Cb3)%2Croom!%3Db1"),
                viewer
            )
            .await?
        ) == ["kiwi-5"]
    );
    ensure!(names(&ok(op, &q("phase=Online"), viewer).await?) == ["kiwi-1", "kiwi-3", "kiwi-4"]);
    ensure!(
        names(&ok(op, &q("phase=Online&release=1.0.0"), viewer).await?) == ["kiwi-1", "kiwi-4"]
    );
    let mut seen = Vec::new();
    let mut next: Option<String> = None;
    for page in 0.. {
        ensure!(page < 5, "paging does not end: {seen:?}");
        let path = match &next {
            None => q("limit=2"),
            Some(c) => q(&format!("limit=2&continue={c}")),
        };
        let body = ok(op, &path, viewer).await?;
        ensure!(names(&body).len() <= 2, "{body}");
        seen.extend(names(&body));
        next = body["continue"].as_str().map(str::to_owned);
        if next.is_none() {
            break;
        }
    }
    ensure!(
        seen == ["kiwi-1", "kiwi-2", "kiwi-3", "kiwi-4", "kiwi-5"],
        "{seen:?}"
    );
    let summary = ok(op, &format!("/api/v1/namespaces/{ns}/summary"), viewer).await?;
    ensure!(
        summary["total"] == 5
            && summary["phases"]
                == json!({"Online": 3, "Offline": 1, "Pending": 1, "Unknown": 0, "Maintenance": 0})
            && summary["releases"] == json!({"1.0.0": 3, "2.0.0": 2}),
        "{summary}"
    );
    let summary = ok(
        op,
        &format!("/api/v1/namespaces/{ns}/summary?labelSelector=room%3Db2&release=2.0.0"),
        viewer,
    )
    .await?;
    ensure!(
        summary["total"] == 1 && summary["phases"]["Online"] == 1,
        "{summary}"
    );
    let one = ok(op, &format!("{base}/kiwi-3"), viewer).await?;
    ensure!(one["robot"]["status"]["phase"] == "Online", "{one}");
    ensure!(
        one["vitals"]["cpuPercent"] == 12.5 && one["vitals"]["batteryPercent"] == 80.0,
        "{one}"
    );
    ensure!(
        one["vitalsTime"]
            .as_str()
            .is_some_and(|t| t.starts_with("2026-01-31T08:00:00")),
        "{one}"
    );
    ensure!(one["robot"]["metadata"]["managedFields"].is_null(), "{one}");
    let (code, _, body) = call(op, "GET", &format!("{base}/kiwi-9"), Some(viewer)).await?;
    ensure!(code == 404 && body["error"] == "not_found", "{code} {body}");
    Ok(())
}

/// Malformed parameters: 400 with a JSON body that says what is wrong.
async fn bad_parameters(op: &OperatorProcess, ns: &str, viewer: &str) -> Result<()> {
    let robots = format!("/api/v1/namespaces/{ns}/robots");
    let events = format!("{robots}/kiwi-1/events");
    for (path, says) in [
        (format!("{robots}?limit=0"), "limit"),
        (format!("{robots}?limit=abc"), "limit"),
        (format!("{robots}?phase=Sleeping"), "Sleeping"),
        (
            format!("{robots}?labelSelector=room%20in%20b1"),
            "parentheses",
        ),
        (format!("{robots}?colour=red"), "colour"),
        (format!("{robots}?continue=zz"), "continue"),
        (format!("{events}?since=yesterday"), "since"),
        (
            format!("{events}?since=2026-01-02T00:00:00Z&until=2026-01-01T00:00:00Z"),
            "before",
        ),
    ] {
        let (code, _, body) = call(op, "GET", &path, Some(viewer)).await?;
        ensure!(
            code == 400 && body["error"] == "bad_request",
            "{path}: {code} {body}"
        );
        let message = body["message"].as_str().unwrap_or_default();
        ensure!(
            message.contains(says),
            "{path}: {message:?} should mention {says}"
        );
    }
    Ok(())
}

/// An empty parameter counts as absent, as the Kubernetes API server takes `continue=`; the
/// history of a robot that does not exist is 404 as the document says, even with events stored
/// under its name.
async fn empty_parameters_and_unknown_robots(
    op: &OperatorProcess,
    store: &Store,
    ns: &str,
    viewer: &str,
) -> Result<()> {
    let robots = format!("/api/v1/namespaces/{ns}/robots");
    let all = ok(op, &robots, viewer).await?;
    let blank = ok(
        op,
        &format!("{robots}?continue=&limit=&labelSelector=&phase=&release="),
        viewer,
    )
    .await?;
    ensure!(names(&blank) == names(&all), "{blank}");
    for path in [
        format!("/api/v1/namespaces/{ns}/rollouts?continue=&limit="),
        format!("/api/v1/namespaces/{ns}/summary?labelSelector=&release="),
        format!("{robots}/kiwi-1/events?continue=&since=&until=&limit="),
        format!("{robots}/kiwi-1/telemetry?continue=&metric="),
    ] {
        ok(op, &path, viewer).await?;
    }
    let gone = lekiwi_core::RobotKey::new(ns, "kiwi-gone");
    let ev = StoredEvent {
        seq: 1,
        ts_ms: jiff::Timestamp::now().as_millisecond(),
        kind: "note".into(),
        severity: "info".into(),
        message: "left behind".into(),
        data: json!({}),
    };
    store.insert_event(&gone, &ev).await?;
    for what in ["events", "telemetry"] {
        for name in ["kiwi-gone", "kiwi-never"] {
            let path = format!("{robots}/{name}/{what}");
            let (code, _, body) = call(op, "GET", &path, Some(viewer)).await?;
            ensure!(
                code == 404
                    && body["error"] == "not_found"
                    && body["message"] == format!("robot {ns}/{name} not found"),
                "{path}: {code} {body}"
            );
        }
    }
    Ok(())
}

/// Events and telemetry of `kiwi-1`, stored in `store`, read back by time range and in pages.
async fn history(op: &OperatorProcess, store: &Store, ns: &str, viewer: &str) -> Result<()> {
    let robot = lekiwi_core::RobotKey::new(ns, "kiwi-1");
    let now = jiff::Timestamp::now().as_millisecond();
    let minutes = |m: i64| now - m * 60_000;
    for (seq, ts) in [
        (1, minutes(120)),
        (2, minutes(50)),
        (3, minutes(40)),
        (4, minutes(30)),
        (5, minutes(20)),
    ] {
        let ev = StoredEvent {
            seq,
            ts_ms: ts,
            kind: "note".into(),
            severity: "info".into(),
            message: format!("event {seq}"),
            data: json!({"n": seq}),
        };
        // Received when it happened: event ranges go by the gateway's receive time.
        store.insert_event_at(&robot, &ev, ts).await?;
    }
    let sample = |metric: &str, ts_ms, value| Sample {
        metric: metric.into(),
        ts_ms,
        value,
    };
    let batch = [
        sample("cpu_percent", minutes(90), 9.0),
        sample("cpu_percent", minutes(30), 30.0),
        sample("temperature_celsius", minutes(30), 55.0),
        sample("cpu_percent", minutes(10), 10.0),
    ];
    store.insert_telemetry(&robot, 6, &batch).await?;
    let base = format!("/api/v1/namespaces/{ns}/robots/kiwi-1");
    let seqs = |b: &Value| {
        b["items"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|e| e["seq"].as_u64().unwrap_or(0))
            .collect::<Vec<_>>()
    };
    // The last hour by default: not the event of two hours ago.
    let page = ok(op, &format!("{base}/events?limit=3"), viewer).await?;
    ensure!(seqs(&page) == [2, 3, 4], "{page}");
    let token = page["continue"].as_str().context("a continue token")?;
    let rest = ok(
        op,
        &format!("{base}/events?limit=3&continue={token}"),
        viewer,
    )
    .await?;
    ensure!(seqs(&rest) == [5] && rest["continue"].is_null(), "{rest}");
    let since = jiff::Timestamp::from_millisecond(minutes(180))?;
    let until = jiff::Timestamp::from_millisecond(minutes(35))?;
    let ranged = ok(
        op,
        &format!("{base}/events?since={since}&until={until}"),
        viewer,
    )
    .await?;
    ensure!(seqs(&ranged) == [1, 2, 3], "{ranged}");
    ensure!(
        ranged["items"][0]["message"] == "event 1" && ranged["items"][0]["data"]["n"] == 1,
        "{ranged}"
    );
    let cpu = ok(
        op,
        &format!("{base}/telemetry?metric=cpu_percent&since={since}&limit=2"),
        viewer,
    )
    .await?;
    let values: Vec<f64> = cpu["items"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|s| s["value"].as_f64())
        .collect();
    ensure!(values == [9.0, 30.0], "{cpu}");
    let token = cpu["continue"]
        .as_str()
        .context("a telemetry continue token")?;
    let more = ok(
        op,
        &format!("{base}/telemetry?metric=cpu_percent&since={since}&limit=2&continue={token}"),
        viewer,
    )
    .await?;
    ensure!(
        more["items"].as_array().map(Vec::len) == Some(1) && more["items"][0]["value"] == 10.0,
        "{more}"
    );
    let recent = ok(op, &format!("{base}/telemetry"), viewer).await?;
    ensure!(
        recent["items"].as_array().map(Vec::len) == Some(3),
        "the last hour, every metric: {recent}"
    );
    Ok(())
}

/// A viewer cannot steer a rollout; an operator user can, writing what the plugin writes.
async fn rollout_actions(
    op: &OperatorProcess,
    client: &kube::Client,
    ns: &str,
    viewer: &str,
    user: &str,
) -> Result<()> {
    let one = ok(op, &format!("/api/v1/namespaces/{ns}/rollouts/v2"), viewer).await?;
    ensure!(one["status"]["robots"][1]["state"] == "Updating", "{one}");
    let list = ok(op, &format!("/api/v1/namespaces/{ns}/rollouts"), viewer).await?;
    ensure!(names(&list) == ["v2"], "{list}");
    let action = |a: &str| format!("/api/v1/namespaces/{ns}/rollouts/v2/{a}");
    let (code, _, body) = call(op, "POST", &action("pause"), Some(viewer)).await?;
    ensure!(
        code == 403 && body["error"] == "forbidden",
        "viewer pausing: {code} {body}"
    );
    let message = body["message"].as_str().unwrap_or_default();
    // The code is the body's `error`; the message does not repeat it.
    ensure!(
        message.starts_with("this needs ")
            && message.contains(&format!(
                "patch robotdeployments.fleet.lekiwi.io v2 in namespace {ns}"
            )),
        "{message}"
    );
    let api = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    ensure!(
        !api.get("v2").await?.spec.paused,
        "paused by a refused request"
    );
    let (code, _, body) = call(op, "POST", &action("pause"), Some(user)).await?;
    ensure!(
        code == 200 && body["spec"]["paused"] == true,
        "pause: {code} {body}"
    );
    ensure!(
        api.get("v2").await?.spec.paused,
        "the RobotDeployment is not paused"
    );
    for (a, annotation) in [
        ("abort", "fleet.lekiwi.io/abortRequestedAt"),
        ("undo", "fleet.lekiwi.io/undoRequestedAt"),
        ("restart", "fleet.lekiwi.io/restartedAt"),
    ] {
        let (code, _, body) = call(op, "POST", &action(a), Some(user)).await?;
        ensure!(code == 200, "{a}: {code} {body}");
        let stamped = api
            .get("v2")
            .await?
            .metadata
            .annotations
            .unwrap_or_default();
        let at = stamped
            .get(annotation)
            .with_context(|| format!("{a}: no {annotation}"))?;
        ensure!(at.parse::<jiff::Timestamp>().is_ok(), "{annotation}: {at}");
    }
    let (code, _, body) = call(op, "POST", &action("resume"), Some(user)).await?;
    ensure!(
        code == 200 && !api.get("v2").await?.spec.paused,
        "resume: {code} {body}"
    );
    let (code, _, _) = call(
        op,
        "POST",
        &format!("/api/v1/namespaces/{ns}/rollouts/nope/pause"),
        Some(user),
    )
    .await?;
    ensure!(code == 404, "pausing a missing rollout: {code}");
    Ok(())
}

/// 401 without a token or with one the API server refuses; 403 across namespaces and for
/// all-namespace lists a namespace binding does not grant; history needs its own permission.
async fn refusals(
    op: &OperatorProcess,
    ns: &str,
    other: &str,
    viewer: &str,
    nobody: &str,
) -> Result<()> {
    let robots = format!("/api/v1/namespaces/{ns}/robots");
    for token in [None, Some("not-a-token-the-api-server-knows")] {
        for path in [robots.as_str(), "/api/v1/openapi.json"] {
            let (code, _, body) = call(op, "GET", path, token).await?;
            ensure!(
                code == 401 && body["error"] == "unauthorized",
                "{path} with {token:?}: {code} {body}"
            );
        }
    }
    for (path, token) in [
        (format!("/api/v1/namespaces/{other}/robots"), viewer),
        ("/api/v1/robots".to_owned(), viewer),
        ("/api/v1/rollouts".to_owned(), viewer),
        (robots.clone(), nobody),
        (format!("{robots}/kiwi-1/events"), nobody),
        (format!("{robots}/kiwi-1/telemetry"), nobody),
    ] {
        let (code, _, body) = call(op, "GET", &path, Some(token)).await?;
        ensure!(
            code == 403 && body["error"] == "forbidden",
            "{path}: {code} {body}"
        );
    }
    let (code, _, _) = call(op, "GET", "/healthz", None).await?;
    ensure!(code == 200, "health needs no token");
    let (code, _, body) = call(op, "GET", "/api/v1/nothing/here", Some(viewer)).await?;
    ensure!(code == 404 && body["error"] == "not_found", "{code} {body}");
    let (code, _, body) = call(op, "DELETE", &format!("{robots}/kiwi-1"), Some(viewer)).await?;
    ensure!(
        code == 405 && body["error"] == "method_not_allowed",
        "{code} {body}"
    );
    Ok(())
}

/// Every operation of the OpenAPI document answers (neither 404 nor 405) with its path
/// parameters filled in.
async fn openapi_routes_answer(
    op: &OperatorProcess,
    ns: &str,
    viewer: &str,
    user: &str,
) -> Result<()> {
    let doc = ok(op, "/api/v1/openapi.json", viewer).await?;
    ensure!(
        doc["openapi"].as_str().is_some_and(|v| v.starts_with("3.")),
        "{doc}"
    );
    let paths = doc["paths"].as_object().context("paths")?;
    let mut answered = BTreeSet::new();
    for (path, ops) in paths {
        for method in ops.as_object().context("operations")?.keys() {
            let name = if path.contains("/rollouts/") {
                "v2"
            } else {
                "kiwi-1"
            };
            let concrete = path.replace("{namespace}", ns).replace("{name}", name);
            let token = if method == "post" { user } else { viewer };
            let (code, _, body) = call(op, &method.to_uppercase(), &concrete, Some(token)).await?;
            ensure!(
                ![404, 405].contains(&code),
                "{method} {path} is documented but answers {code} {body}"
            );
            answered.insert(format!("{method} {path}"));
        }
    }
    ensure!(answered.len() >= 13, "{answered:?}");
    Ok(())
}

/// A burst beyond the viewer's budget: 429 with `Retry-After`, while the operator user is
/// still served.
async fn rate_limited(op: &OperatorProcess, ns: &str, viewer: &str, user: &str) -> Result<()> {
    let path = format!("/api/v1/namespaces/{ns}/robots/kiwi-1");
    let mut refused = None;
    for i in 0..200 {
        let (code, retry, body) = call(op, "GET", &path, Some(viewer)).await?;
        if code == 429 {
            refused = Some((i, retry, body));
            break;
        }
        ensure!(code == 200, "{code} {body}");
    }
    let (i, retry, body) = refused.context("200 requests in a burst and no 429")?;
    ensure!(i <= 60, "the 429 came only after {i} requests");
    ensure!(body["error"] == "rate_limited", "{body}");
    let seconds: u64 = retry.context("no Retry-After")?.parse()?;
    ensure!((1..=5).contains(&seconds), "Retry-After: {seconds}");
    ok(op, &path, user)
        .await
        .context("another user is throttled too")?;
    Ok(())
}

#[tokio::test]
async fn the_fleet_api_serves_what_rbac_allows_each_user() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "fleetapi").await?;
    let other = namespace(&client, "fleetapib").await?;
    let [viewer_role, user_role] = chart_roles(cp, &client, &ns).await?;
    let viewer = account(cp, &client, &ns, "viewer", Some(&viewer_role)).await?;
    let user = account(cp, &client, &ns, "steerer", Some(&user_role)).await?;
    let nobody = account(cp, &client, &ns, "nobody", None).await?;
    robots(&client, &ns).await?;
    rollout(&client, &ns).await?;
    // Gateway only: no controller rewrites the phases the test set. A budget of 60 at once.
    let args = ["--role", "gateway", "--api-rate", "1", "--api-burst", "60"];
    let op = lekiwi_tests::gateway_operator(cp, &ns, "fleetapi", &args).await?;
    let store = op.event_store().await?;
    wait_cached(&op, &ns, &viewer).await?;
    lists_filter_and_page(&op, &ns, &viewer).await?;
    bad_parameters(&op, &ns, &viewer).await?;
    history(&op, &store, &ns, &viewer).await?;
    empty_parameters_and_unknown_robots(&op, &store, &ns, &viewer).await?;
    rollout_actions(&op, &client, &ns, &viewer, &user).await?;
    refusals(&op, &ns, &other, &viewer, &nobody).await?;
    openapi_routes_answer(&op, &ns, &viewer, &user).await?;
    rate_limited(&op, &ns, &viewer, &user).await?;
    for role in [&viewer_role, &user_role] {
        Api::<ClusterRole>::all(client.clone())
            .delete(role, &DeleteParams::default())
            .await?;
    }
    Ok(())
}

#[tokio::test]
async fn history_reads_come_from_postgresql_too() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "fleetapipg").await?;
    let [viewer_role, user_role] = chart_roles(cp, &client, &ns).await?;
    let viewer = account(cp, &client, &ns, "viewer", Some(&viewer_role)).await?;
    let pg = Postgres::start()?;
    let url = pg.create_database("fleet")?;
    let store_flag = format!("--store-url={url}");
    let args = ["--role", "gateway", store_flag.as_str()];
    let op = lekiwi_tests::gateway_operator(cp, &ns, "fleetapipg", &args).await?;
    let store = Store::connect(&url).await?;
    ensure!(store.backend() == "postgres");
    // The history of a robot the gateway does not hold is 404.
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    lekiwi_tests::wait_for(
        "kiwi-1 in the gateway's cache",
        std::time::Duration::from_secs(20),
        || async {
            let path = format!("/api/v1/namespaces/{ns}/robots/kiwi-1");
            ok(&op, &path, &viewer).await.ok()
        },
    )
    .await?;
    history(&op, &store, &ns, &viewer).await?;
    for role in [&viewer_role, &user_role] {
        Api::<ClusterRole>::all(client.clone())
            .delete(role, &DeleteParams::default())
            .await?;
    }
    Ok(())
}

/// A robot whose clock is off (by ten minutes, by a year), or that sends times no clock shows
/// (2^63-1, -2^63), has the events it just sent in the default listing (the last hour by the
/// gateway's clock), each with the time it sent (the extremes clamped to what RFC 3339 writes).
#[tokio::test]
async fn fresh_events_are_listed_whatever_the_robots_clock() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "fleetapiclock").await?;
    let [viewer_role, user_role] = chart_roles(cp, &client, &ns).await?;
    let viewer = account(cp, &client, &ns, "viewer", Some(&viewer_role)).await?;
    let args = ["--role", "gateway"];
    let op = lekiwi_tests::gateway_operator(cp, &ns, "fleetapiclock", &args).await?;
    let enroll = enrollment_token(&client, &ns).await?;
    let (mut ws, _) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-clock")).await?;
    let now = jiff::Timestamp::now().as_millisecond();
    let (minutes, year) = (60_000, 365 * 86_400_000);
    let claims = [
        now + 10 * minutes,
        now - 10 * minutes,
        now + year,
        now - year,
        i64::MAX,
        i64::MIN,
    ];
    for (seq, ts_ms) in (1..).zip(claims) {
        let event = AgentMessage::Event {
            seq,
            ts_ms,
            kind: "note".into(),
            severity: Severity::Info,
            message: format!("sent at {ts_ms}"),
            data: Value::Null,
        };
        ws.send(Message::text(encode(&event))).await?;
        ensure!(
            recv(&mut ws).await == Some(ServerMessage::Ack { seq }),
            "event {seq} acked"
        );
    }
    drop(ws);
    let stored = [
        claims[0],
        claims[1],
        claims[2],
        claims[3],
        MAX_TIME_MS,
        MIN_TIME_MS,
    ];
    let want: Vec<(u64, i64)> = (1..).zip(stored).collect();
    let path = format!("/api/v1/namespaces/{ns}/robots/kiwi-clock/events");
    let listing = wait_for("every event in the default listing", WAIT, || async {
        let (code, _, body) = call(&op, "GET", &path, Some(&viewer)).await.ok()?;
        let listed: Vec<(u64, i64)> = body["items"]
            .as_array()?
            .iter()
            .filter_map(|e| Some((e["seq"].as_u64()?, e["ts_ms"].as_i64()?)))
            .collect();
        (code == 200 && listed == want).then_some(body)
    })
    .await;
    let listed = match listing {
        Ok(body) => body,
        Err(e) => {
            let (code, _, body) = call(&op, "GET", &path, Some(&viewer)).await?;
            anyhow::bail!("{e}; the listing answers {code} {body}")
        }
    };
    ensure!(listed["continue"].is_null(), "{listed}");
    for role in [&viewer_role, &user_role] {
        Api::<ClusterRole>::all(client.clone())
            .delete(role, &DeleteParams::default())
            .await?;
    }
    Ok(())
}

/// A busy client (many requests at once with one token) is never refused when the cached
/// review of its token expires: the review budget (here one) is for unknown tokens.
#[tokio::test]
async fn a_busy_client_outlives_its_cached_review() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "fleetapittl").await?;
    let token = account(cp, &client, &ns, "busy", None).await?;
    let args = [
        "--role",
        "gateway",
        "--auth-lookup-qps",
        "0.01",
        "--auth-lookup-burst",
        "1",
    ];
    let op = lekiwi_tests::gateway_operator(cp, &ns, "fleetapittl", &args).await?;
    ok(&op, "/api/v1/openapi.json", &token).await?;
    // Past the 10 s the review is cached for, 20 requests at once.
    tokio::time::sleep(std::time::Duration::from_millis(10_500)).await;
    let calls = (0..20).map(|_| call(&op, "GET", "/api/v1/openapi.json", Some(&token)));
    let codes: Vec<u16> = futures::future::try_join_all(calls)
        .await?
        .into_iter()
        .map(|(code, _, _)| code)
        .collect();
    ensure!(codes.iter().all(|c| *c == 200), "{codes:?}");
    // An unknown token still meets the spent budget.
    let (code, retry, body) =
        call(&op, "GET", "/api/v1/openapi.json", Some("unknown-token")).await?;
    ensure!(code == 503 && retry.is_some(), "{code} {body}");
    Ok(())
}

/// With `--api-addr` the Fleet API and the dashboard have a port of their own: the robots'
/// port answers 404 for them and still serves agents; the API's port still wants a token and
/// serves no agent WebSocket.
#[tokio::test]
async fn the_api_on_its_own_port_is_not_served_on_the_robots_port() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "apiport").await?;
    let [viewer_role, _] = chart_roles(cp, &client, &ns).await?;
    let viewer = account(cp, &client, &ns, "viewer", Some(&viewer_role)).await?;
    let api_port = lekiwi_tests::free_ports(1)[0];
    let api_addr = format!("127.0.0.1:{api_port}");
    let op = lekiwi_tests::gateway_operator(cp, &ns, "apiport", &["--api-addr", &api_addr]).await?;
    let auth = format!("Bearer {viewer}");
    let get = |port: u16, path: String, token: bool| {
        let auth = auth.clone();
        async move {
            let headers = [("authorization", auth.as_str())];
            let headers = if token { &headers[..] } else { &[] };
            let (code, _, _) = http_request(port, "GET", &path, headers, None).await?;
            anyhow::Ok(code)
        }
    };
    let robots = format!("/api/v1/namespaces/{ns}/robots");
    let gateway = op.gateway_port;
    wait_for("the Fleet API on its port", WAIT, || async {
        (get(api_port, robots.clone(), true).await.ok() == Some(200)).then_some(())
    })
    .await?;
    assert_eq!(get(api_port, robots.clone(), false).await?, 401);
    assert_eq!(get(api_port, "/dashboard/".into(), false).await?, 200);
    assert_eq!(get(api_port, "/v1/agent".into(), true).await?, 404);
    assert_eq!(get(gateway, robots.clone(), true).await?, 404);
    assert_eq!(get(gateway, "/dashboard/".into(), false).await?, 404);
    let enroll = enrollment_token(&client, &ns).await?;
    let (_ws, welcome) = connect_agent(&op, &enroll, &format!("{ns}/kiwi-port")).await?;
    assert_eq!(welcome.robot, format!("{ns}/kiwi-port"));
    Ok(())
}
