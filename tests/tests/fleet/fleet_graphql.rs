//! The Fleet API's GraphQL endpoint (`/api/v1/graphql`, issue 15) against the real API server,
//! with ServiceAccounts bound to the chart's `lekiwi-viewer` and `lekiwi-operator-user`: a viewer
//! queries robots (filtered, with vitals and events, whose `seq` and `tsMs` are `BigInt`
//! strings), rollouts with their per-robot progress, and the schema (introspection); another namespace is refused; a viewer's mutation is refused and
//! an operator user's pauses the rollout; a subscription over `graphql-transport-ws` (the token
//! in `connection_init`) sees a simulated robot go Online, then Offline, another a rollout's
//! progress, and a third is over the user's cap; a user's third WebSocket is over their cap of
//! two until one of theirs closes; a too-deep query is
//! refused before it runs; no token or a bad one gets 401 (a WebSocket is closed); a `POST`
//! without a body and a `GET` without an upgrade get the JSON error body, answers the media type
//! the client accepts, as the OpenAPI document says; a burst beyond the user's budget gets 429
//! with `Retry-After`.

use std::time::Duration;

use anyhow::{Context as _, Result, bail, ensure};
use futures::{SinkExt, StreamExt};
use k8s_openapi::api::rbac::v1::ClusterRole;
use kube::Api;
use kube::api::{DeleteParams, Patch, PatchParams, PostParams};
use lekiwi_core::RobotKey;
use lekiwi_crds::{Robot, RobotDeployment};
use lekiwi_event_store::StoredEvent;
use lekiwi_tests::graphql::{Ws, connect, next, open, subscribe};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, account, chart_roles, connect_agent, create_robot,
    enrollment_token, http_request, namespace,
};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

const DIGEST: &str = "sha256:aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa";

/// One GraphQL request: HTTP status, `Retry-After` if any, JSON body.
async fn gql(
    op: &OperatorProcess,
    token: Option<&str>,
    query: &str,
) -> Result<(u16, Option<String>, Value)> {
    let auth = token.map(|t| format!("Bearer {t}"));
    let mut headers = vec![("content-type", "application/json")];
    headers.extend(auth.iter().map(|a| ("authorization", a.as_str())));
    let body = serde_json::to_vec(&json!({ "query": query }))?;
    let (code, hdrs, body) = http_request(
        op.gateway_port,
        "POST",
        "/api/v1/graphql",
        &headers,
        Some(&body),
    )
    .await?;
    let retry = hdrs
        .into_iter()
        .find(|(k, _)| k == "retry-after")
        .map(|(_, v)| v);
    Ok((
        code,
        retry,
        serde_json::from_slice(&body).unwrap_or(Value::Null),
    ))
}

/// A query that must succeed: its `data`.
async fn data(op: &OperatorProcess, token: &str, query: &str) -> Result<Value> {
    let (code, _, body) = gql(op, Some(token), query).await?;
    ensure!(
        code == 200 && body["errors"].is_null(),
        "{query}: {code} {body}"
    );
    Ok(body["data"].clone())
}

/// A query answered with a GraphQL error: the first error's `extensions.code` and message.
async fn error(op: &OperatorProcess, token: &str, query: &str) -> Result<(String, String)> {
    let (code, _, body) = gql(op, Some(token), query).await?;
    ensure!(code == 200, "{query}: {code} {body}");
    let e = &body["errors"][0];
    ensure!(e.is_object(), "{query}: no error in {body}");
    let code = e["extensions"]["code"].as_str().unwrap_or_default();
    Ok((
        code.to_owned(),
        e["message"].as_str().unwrap_or_default().to_owned(),
    ))
}

/// Three Robots in `ns` with phases and vitals, and a RobotDeployment `v2` with progress.
async fn fleet(client: &kube::Client, ns: &str) -> Result<()> {
    let api = Api::<Robot>::namespaced(client.clone(), ns);
    for (name, room, phase) in [
        ("kiwi-1", "b1", "Online"),
        ("kiwi-2", "b2", "Offline"),
        ("kiwi-3", "b2", "Online"),
    ] {
        create_robot(client, ns, name, &[("room", room)]).await?;
        let status = json!({"status": {
            "phase": phase,
            "currentRelease": {"version": "1.0.0", "digest": DIGEST},
            "telemetry": {"cpuPercent": 12.5, "batteryPercent": 80.0},
        }});
        api.patch_status(name, &PatchParams::default(), &Patch::Merge(&status))
            .await?;
    }
    let rds = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    let rd = json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "RobotDeployment",
        "metadata": {"name": "v2"},
        "spec": {"selector": {"matchLabels": {"room": "b2"}}, "release": {"version": "2.0.0", "digest": DIGEST}},
    });
    rds.create(&PostParams::default(), &serde_json::from_value(rd)?)
        .await?;
    let status = json!({"status": {"phase": "Progressing", "targeted": 2, "updated": 1, "pending": 1,
        "robots": [{"robot": "kiwi-2", "batch": 0, "state": "Updated"}, {"robot": "kiwi-3", "batch": 1, "state": "Updating"}]}});
    rds.patch_status("v2", &PatchParams::default(), &Patch::Merge(&status))
        .await?;
    // An agent rollout: `agent` names its version, `release` is null.
    let agent = json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "RobotDeployment",
        "metadata": {"name": "agent-v3"},
        "spec": {"selector": {"matchLabels": {"room": "none"}},
            "agent": {"version": "3.0.0", "builds": [{"arch": "arm64", "digest": DIGEST}]}},
    });
    rds.create(&PostParams::default(), &serde_json::from_value(agent)?)
        .await?;
    Ok(())
}

/// Queries of robots, one robot and rollouts; introspection.
async fn queries(op: &OperatorProcess, ns: &str, viewer: &str) -> Result<()> {
    let q = format!(
        r#"{{ robots(namespace: "{ns}", labelSelector: "room=b2", phase: "Online") {{ items {{ name phase release vitals {{ cpuPercent batteryPercent }} }} continue }} }}"#
    );
    let d = lekiwi_tests::wait_for(
        "the robots in the cache",
        Duration::from_secs(20),
        || async {
            let d = data(op, viewer, &q).await.ok()?;
            (d["robots"]["items"].as_array()?.len() == 1).then_some(d)
        },
    )
    .await?;
    let robot = &d["robots"]["items"][0];
    ensure!(
        robot["name"] == "kiwi-3" && robot["phase"] == "Online" && robot["release"] == "1.0.0",
        "{d}"
    );
    ensure!(
        robot["vitals"]["cpuPercent"] == 12.5 && robot["vitals"]["batteryPercent"] == 80.0,
        "{d}"
    );
    let q = format!(r#"{{ robots(namespace: "{ns}", limit: 2) {{ items {{ name }} continue }} }}"#);
    let d = data(op, viewer, &q).await?;
    // An empty `after` is the first page, as an empty `continue=` is for REST.
    let blank = format!(
        r#"{{ robots(namespace: "{ns}", limit: 2, after: "") {{ items {{ name }} continue }} }}"#
    );
    ensure!(data(op, viewer, &blank).await? == d, "{d}");
    let after = d["robots"]["continue"]
        .as_str()
        .context("a continue token")?;
    let q = format!(
        r#"{{ robots(namespace: "{ns}", limit: 2, after: "{after}") {{ items {{ name }} continue }} }}"#
    );
    let d = data(op, viewer, &q).await?;
    ensure!(
        d["robots"]["items"] == json!([{"name": "kiwi-3"}]) && d["robots"]["continue"].is_null(),
        "{d}"
    );
    let q = format!(
        r#"{{ robot(namespace: "{ns}", name: "kiwi-1") {{ labels phase events {{ items {{ seq }} }} }} }}"#
    );
    let d = data(op, viewer, &q).await?;
    ensure!(
        d["robot"]["labels"]["room"] == "b1" && d["robot"]["events"]["items"] == json!([]),
        "{d}"
    );
    big_ints(op, ns, viewer).await?;
    let q = format!(
        r#"{{ rollout(namespace: "{ns}", name: "v2") {{ release agent paused phase targeted updated robots }}
            agentRollout: rollout(namespace: "{ns}", name: "agent-v3") {{ release agent }} }}"#
    );
    let d = lekiwi_tests::wait_for(
        "the rollout in the cache",
        Duration::from_secs(20),
        || async {
            let d = data(op, viewer, &q).await.ok()?;
            (d["rollout"]["robots"].is_array() && d["agentRollout"].is_object()).then_some(d)
        },
    )
    .await?;
    let r = &d["rollout"];
    ensure!(
        d["agentRollout"] == json!({"release": null, "agent": "3.0.0"}),
        "{d}"
    );
    ensure!(
        r["release"] == "2.0.0"
            && r["agent"].is_null()
            && r["phase"] == "Progressing"
            && r["targeted"] == 2
            && r["updated"] == 1,
        "{d}"
    );
    ensure!(
        r["robots"][1]["robot"] == "kiwi-3" && r["robots"][1]["state"] == "Updating",
        "{d}"
    );
    let d = data(
        op,
        viewer,
        "{ __schema { queryType { name } mutationType { name } subscriptionType { name } } }",
    )
    .await?;
    ensure!(
        d["__schema"]["subscriptionType"]["name"] == "SubscriptionRoot",
        "{d}"
    );
    Ok(())
}

/// `seq` and `tsMs` are `BigInt`s, strings of digits, not 32-bit `Int`s a typed client would
/// overflow on: an event stored with a sequence number and a time beyond 2^31 - 1 reads back
/// exactly.
async fn big_ints(op: &OperatorProcess, ns: &str, viewer: &str) -> Result<()> {
    let now = jiff::Timestamp::now().as_millisecond();
    let seq = 3_000_000_000_u64;
    let event = StoredEvent {
        seq,
        ts_ms: now,
        kind: "note".into(),
        severity: "info".into(),
        message: "late in life".into(),
        data: json!({}),
    };
    let robot = RobotKey::new(ns, "kiwi-2");
    op.event_store().await?.insert_event(&robot, &event).await?;
    let q = format!(
        r#"{{ robot(namespace: "{ns}", name: "kiwi-2") {{ events {{ items {{ seq tsMs message }} }} }}
            __type(name: "Event") {{ fields {{ name type {{ ofType {{ name kind }} }} }} }} }}"#
    );
    let d = data(op, viewer, &q).await?;
    let item = &d["robot"]["events"]["items"][0];
    ensure!(
        item["seq"] == json!(seq.to_string()) && item["tsMs"] == json!(now.to_string()),
        "{d}"
    );
    let fields = d["__type"]["fields"].as_array().context("Event's fields")?;
    for name in ["seq", "tsMs"] {
        let field = fields.iter().find(|f| f["name"] == name).context(name)?;
        ensure!(
            field["type"]["ofType"] == json!({"name": "BigInt", "kind": "SCALAR"}),
            "{field}"
        );
    }
    Ok(())
}

/// Another namespace and history without permission are refused per field; a viewer cannot
/// pause; an operator user can.
async fn refusals_and_mutations(
    op: &OperatorProcess,
    client: &kube::Client,
    (ns, other): (&str, &str),
    (viewer, user, nobody): (&str, &str, &str),
) -> Result<()> {
    let (code, message) = error(
        op,
        viewer,
        &format!(r#"{{ robots(namespace: "{other}") {{ items {{ name }} }} }}"#),
    )
    .await?;
    // The code starts the message once ("forbidden: this needs ..."), not twice.
    ensure!(
        code == "forbidden"
            && message.starts_with("forbidden: this needs ")
            && message.contains(&format!("list robots.fleet.lekiwi.io in namespace {other}")),
        "{message}"
    );
    let (code, _) = error(
        op,
        nobody,
        &format!(r#"{{ robot(namespace: "{ns}", name: "kiwi-1") {{ name }} }}"#),
    )
    .await?;
    ensure!(code == "forbidden", "{code}");
    let pause =
        format!(r#"mutation {{ pauseRollout(namespace: "{ns}", name: "v2") {{ name paused }} }}"#);
    let (code, message) = error(op, viewer, &pause).await?;
    ensure!(
        code == "forbidden"
            && message.contains(&format!(
                "patch robotdeployments.fleet.lekiwi.io v2 in namespace {ns}"
            )),
        "{message}"
    );
    let api = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    ensure!(
        !api.get("v2").await?.spec.paused,
        "paused by a refused mutation"
    );
    let d = data(op, user, &pause).await?;
    ensure!(d["pauseRollout"]["paused"] == true, "{d}");
    ensure!(
        api.get("v2").await?.spec.paused,
        "the RobotDeployment is not paused"
    );
    let d = data(op, user, &format!(r#"mutation {{ abortRollout(namespace: "{ns}", name: "v2") {{ name }} undoRollout(namespace: "{ns}", name: "v2") {{ name }} resumeRollout(namespace: "{ns}", name: "v2") {{ paused }} }}"#)).await?;
    ensure!(d["resumeRollout"]["paused"] == false, "{d}");
    let stamped = api
        .get("v2")
        .await?
        .metadata
        .annotations
        .unwrap_or_default();
    ensure!(
        stamped.contains_key("fleet.lekiwi.io/undoRequestedAt")
            && stamped.contains_key("fleet.lekiwi.io/abortRequestedAt")
            && !api.get("v2").await?.spec.paused,
        "{stamped:?}"
    );
    Ok(())
}

/// Too deep (though cheap) is refused before it runs, too complex as well; no token or a bad one is 401.
async fn limits(op: &OperatorProcess, ns: &str, viewer: &str) -> Result<()> {
    let deep = format!(
        r#"{{ robots(namespace: "{ns}", limit: 1) {{ items {{ events(limit: 1) {{ items {{ seq }} }} }} }} }}"#
    );
    let (code, _, body) = gql(op, Some(viewer), &deep).await?;
    let message = body["errors"][0]["message"].as_str().unwrap_or_default();
    ensure!(
        code == 200 && message.contains("nested too deep") && body["data"].is_null(),
        "{code} {body}"
    );
    let costly = format!(
        r#"{{ robots(namespace: "{ns}", limit: 1000) {{ items {{ events(limit: 1000) {{ continue }} }} }} }}"#
    );
    let (code, _, body) = gql(op, Some(viewer), &costly).await?;
    let message = body["errors"][0]["message"].as_str().unwrap_or_default();
    ensure!(
        code == 200 && message.contains("too complex"),
        "{code} {body}"
    );
    for token in [None, Some("not-a-token-the-api-server-knows")] {
        let (code, _, body) = gql(op, token, "{ __typename }").await?;
        ensure!(
            code == 401 && body["error"] == "unauthorized",
            "{token:?}: {code} {body}"
        );
    }
    Ok(())
}

/// A socket that never sends `connection_init` is closed with 4408 after the configured 2 s
/// (and so holds no connection slot for long); one that did is still served after that.
async fn init_timeout(op: &OperatorProcess, viewer: &str) -> Result<()> {
    let started = std::time::Instant::now();
    let mut silent = connect(op).await?;
    let mut greeted = open(op, viewer).await?;
    ensure!(next(&mut greeted, Duration::from_secs(5)).await?["type"] == "connection_ack");
    let closed = next(&mut silent, Duration::from_secs(10)).await?;
    let waited = started.elapsed();
    ensure!(closed["close"] == 4408, "{closed}");
    ensure!(
        closed["reason"] == "Connection initialisation timeout",
        "{closed}"
    );
    ensure!(
        waited >= Duration::from_millis(1900) && waited < Duration::from_secs(8),
        "closed after {waited:?}"
    );
    greeted
        .send(Message::text(json!({"type": "ping"}).to_string()))
        .await?;
    let pong = next(&mut greeted, Duration::from_secs(5)).await?;
    ensure!(pong["type"] == "pong", "{pong}");
    Ok(())
}

/// Reads changes until `name` is in `phase`; every change must match the selector (not
/// kiwi-1).
async fn until_phase(ws: &mut Ws, name: &str, phase: &str) -> Result<()> {
    let mut seen = Vec::new();
    for _ in 0..20 {
        let msg = next(ws, Duration::from_secs(30)).await?;
        ensure!(msg["type"] == "next", "{msg} after {seen:?}");
        let change = &msg["payload"]["data"]["robotChanges"];
        ensure!(
            change["name"] != "kiwi-1",
            "kiwi-1 is outside the selector: {msg}"
        );
        if change["name"] == name && change["phase"] == phase {
            return Ok(());
        }
        seen.push(change.clone());
    }
    bail!("no {name}={phase}: {seen:?}")
}

/// A subscription sees a simulated robot go Online and then Offline; a bad token is closed.
async fn subscription(
    op: &OperatorProcess,
    client: &kube::Client,
    ns: &str,
    token: &str,
) -> Result<()> {
    let mut bad = open(op, "not-a-token").await?;
    let closed = next(&mut bad, Duration::from_secs(30))
        .await
        .context("closing a bad token")?;
    ensure!(
        closed["close"] == 1002
            && closed["reason"]
                .as_str()
                .is_some_and(|r| r.starts_with("unauthorized")),
        "{closed}"
    );
    let mut ws = open(op, token).await?;
    let ack = next(&mut ws, Duration::from_secs(30))
        .await
        .context("the ack")?;
    ensure!(ack["type"] == "connection_ack", "{ack}");
    let query = format!(
        r#"subscription {{ robotChanges(namespace: "{ns}", labelSelector: "room!=b1") {{ name phase }} }}"#
    );
    subscribe(&mut ws, "1", &query).await?;
    // Subscribed once a change of kiwi-2 (toggled until one arrives) comes through.
    let api = Api::<Robot>::namespaced(client.clone(), ns);
    let mut subscribed = false;
    // The shared API server, on a loaded machine, has been seen to deliver watch events 20 s
    // late (the gateway's cache, read back below on failure, lagged as much): up to a minute.
    for phase in ["Unknown", "Offline"].iter().cycle().take(60) {
        let status = json!({"status": {"phase": phase}});
        api.patch_status("kiwi-2", &PatchParams::default(), &Patch::Merge(&status))
            .await?;
        if let Ok(msg) = next(&mut ws, Duration::from_secs(1)).await {
            ensure!(
                msg["payload"]["data"]["robotChanges"]["name"] == "kiwi-2",
                "{msg}"
            );
            subscribed = true;
            break;
        }
    }
    if !subscribed {
        let status = json!({"status": {"phase": "Maintenance"}});
        api.patch_status("kiwi-2", &PatchParams::default(), &Patch::Merge(&status))
            .await?;
        tokio::time::sleep(Duration::from_secs(3)).await;
        let q = format!(r#"{{ robot(namespace: "{ns}", name: "kiwi-2") {{ phase }} }}"#);
        bail!(
            "no change of kiwi-2 arrived; the cache says {:?}",
            gql(op, Some(token), &q).await?
        );
    }
    let enroll = enrollment_token(client, ns).await?;
    let agent = connect_agent(op, &enroll, &format!("{ns}/kiwi-sim")).await?;
    until_phase(&mut ws, "kiwi-sim", "Online").await?;
    drop(agent);
    until_phase(&mut ws, "kiwi-sim", "Offline").await?;
    rollout_progress(&mut ws, client, ns).await
}

/// On the same WebSocket: a second subscription (rollout progress) sees a status change of the
/// rollout; a third is over the user's cap (two) and refused.
async fn rollout_progress(ws: &mut Ws, client: &kube::Client, ns: &str) -> Result<()> {
    let query = format!(
        r#"subscription {{ rolloutProgress(namespace: "{ns}", name: "v2") {{ name updated phase }} }}"#
    );
    subscribe(ws, "2", &query).await?;
    let api = Api::<RobotDeployment>::namespaced(client.clone(), ns);
    let mut progressed = false;
    for updated in 2..62 {
        let status = json!({"status": {"updated": updated}});
        api.patch_status("v2", &PatchParams::default(), &Patch::Merge(&status))
            .await?;
        let Ok(msg) = next(ws, Duration::from_secs(1)).await else {
            continue;
        };
        if msg["id"] == "2" {
            let rollout = &msg["payload"]["data"]["rolloutProgress"];
            ensure!(
                rollout["name"] == "v2" && rollout["updated"].as_i64() >= Some(2),
                "{msg}"
            );
            progressed = true;
            break;
        }
    }
    ensure!(progressed, "no rollout progress arrived");
    subscribe(ws, "3", &query).await?;
    for _ in 0..20 {
        let msg = next(ws, Duration::from_secs(30))
            .await
            .context("the third subscription's answer")?;
        if msg["id"] == "3" {
            let error = &msg["payload"]["errors"][0];
            let message = error["message"].as_str().unwrap_or_default();
            ensure!(
                error["extensions"]["code"] == "forbidden" && message.contains("2 subscriptions"),
                "{msg}"
            );
            return Ok(());
        }
    }
    bail!("the third subscription was neither refused nor answered")
}

/// A user holds at most two WebSockets (the cap this gateway runs with): a third's
/// `connection_init` is refused with 1002 and the reason; once one of the two is closed, a new
/// one is accepted (its slot given back).
async fn connection_cap(op: &OperatorProcess, token: &str) -> Result<()> {
    let mut held = Vec::new();
    for _ in 0..2 {
        let mut ws = open(op, token).await?;
        let ack = next(&mut ws, Duration::from_secs(30)).await?;
        ensure!(ack["type"] == "connection_ack", "{ack}");
        held.push(ws);
    }
    let mut third = open(op, token).await?;
    let closed = next(&mut third, Duration::from_secs(30)).await?;
    ensure!(
        closed["close"] == 1002
            && closed["reason"]
                == "forbidden: this user holds 2 GraphQL WebSockets, the most allowed",
        "{closed}"
    );
    let mut first = held.remove(0);
    first.close(None).await?;
    while first.next().await.is_some() {}
    let accepted = lekiwi_tests::wait_for(
        "a WebSocket once one was closed",
        Duration::from_secs(10),
        || async {
            let mut ws = open(op, token).await.ok()?;
            let ack = next(&mut ws, Duration::from_secs(5)).await.ok()?;
            (ack["type"] == "connection_ack").then_some(ws)
        },
    )
    .await;
    ensure!(
        accepted.is_ok(),
        "no WebSocket was accepted after one closed"
    );
    Ok(())
}

/// What the HTTP side answers besides a query: a `POST` without a body and a `GET` that is no
/// WebSocket upgrade get the Fleet API's JSON error; an answer's media type is one the OpenAPI
/// document lists, `application/graphql-response+json` when the client's `Accept` names it.
async fn http_answers(op: &OperatorProcess, viewer: &str) -> Result<()> {
    let auth = format!("Bearer {viewer}");
    let media = |hdrs: &[(String, String)]| {
        hdrs.iter()
            .find(|(k, _)| k == "content-type")
            .map(|(_, v)| v.clone())
            .unwrap_or_default()
    };
    let path = "/api/v1/graphql";
    // Every case is tried; the failure lists each wrong answer.
    let mut wrong = Vec::new();
    for (method, body) in [("POST", Some(&b""[..])), ("POST", None), ("GET", None)] {
        let headers = [("authorization", auth.as_str())];
        let (code, hdrs, raw) = http_request(op.gateway_port, method, path, &headers, body).await?;
        let json: Value = serde_json::from_slice(&raw).unwrap_or(Value::Null);
        if !(code == 400
            && media(&hdrs) == "application/json"
            && json["error"] == "bad_request"
            && json["message"].as_str().is_some_and(|m| !m.is_empty()))
        {
            let raw = String::from_utf8_lossy(&raw);
            wrong.push(format!("{method} {body:?}: {code} {hdrs:?} {raw:?}"));
        }
    }
    let doc = openapi(op, viewer).await?;
    let documented = doc["paths"][path]["post"]["responses"]["200"]["content"]
        .as_object()
        .map(|c| c.keys().cloned().collect::<Vec<_>>())
        .unwrap_or_default();
    let body = serde_json::to_vec(&json!({"query": "{ __typename }"}))?;
    for (accept, want) in [
        (None, "application/json"),
        (Some("application/json"), "application/json"),
        (
            Some("application/graphql-response+json, application/json;q=0.9"),
            "application/graphql-response+json",
        ),
    ] {
        let mut headers = vec![("authorization", auth.as_str())];
        headers.extend(accept.map(|a| ("accept", a)));
        let (code, hdrs, raw) =
            http_request(op.gateway_port, "POST", path, &headers, Some(&body)).await?;
        let answer: Value = serde_json::from_slice(&raw)?;
        ensure!(
            code == 200 && answer["data"]["__typename"] == "QueryRoot",
            "{code} {answer}"
        );
        if media(&hdrs) != want || !documented.iter().any(|d| d == want) {
            let answered = media(&hdrs);
            wrong.push(format!(
                "Accept {accept:?}: answered {answered}, documented {documented:?}"
            ));
        }
    }
    ensure!(wrong.is_empty(), "{wrong:#?}");
    Ok(())
}

/// The OpenAPI document.
async fn openapi(op: &OperatorProcess, token: &str) -> Result<Value> {
    let auth = format!("Bearer {token}");
    let headers = [("authorization", auth.as_str())];
    let (code, _, raw) = http_request(
        op.gateway_port,
        "GET",
        "/api/v1/openapi.json",
        &headers,
        None,
    )
    .await?;
    ensure!(code == 200, "{code}");
    Ok(serde_json::from_slice(&raw)?)
}

/// A burst beyond the viewer's budget: 429 with `Retry-After`.
async fn rate_limited(op: &OperatorProcess, viewer: &str) -> Result<()> {
    for i in 0..200 {
        let (code, retry, body) = gql(op, Some(viewer), "{ __typename }").await?;
        if code == 429 {
            ensure!(i <= 60 && body["error"] == "rate_limited", "{i}: {body}");
            let seconds: u64 = retry.context("no Retry-After")?.parse()?;
            ensure!((1..=5).contains(&seconds), "Retry-After: {seconds}");
            return Ok(());
        }
        ensure!(code == 200, "{code} {body}");
    }
    bail!("200 requests in a burst and no 429")
}

#[tokio::test]
async fn graphql_serves_what_rbac_allows_and_streams_changes() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "fleetgql").await?;
    let other = namespace(&client, "fleetgqlb").await?;
    let [viewer_role, user_role] = chart_roles(cp, &client, &ns).await?;
    let viewer = account(cp, &client, &ns, "viewer", Some(&viewer_role)).await?;
    let user = account(cp, &client, &ns, "steerer", Some(&user_role)).await?;
    let nobody = account(cp, &client, &ns, "nobody", None).await?;
    fleet(&client, &ns).await?;
    let args = [
        "--role",
        "gateway",
        "--api-rate",
        "1",
        "--api-burst",
        "60",
        "--graphql-max-depth",
        "4",
        "--graphql-max-subscriptions-per-user",
        "2",
        "--graphql-max-connections-per-user",
        "2",
        "--graphql-init-timeout-seconds",
        "2",
    ];
    let op = lekiwi_tests::gateway_operator(cp, &ns, "fleetgql", &args).await?;
    queries(&op, &ns, &viewer).await?;
    http_answers(&op, &viewer).await?;
    refusals_and_mutations(&op, &client, (&ns, &other), (&viewer, &user, &nobody)).await?;
    limits(&op, &ns, &viewer).await?;
    init_timeout(&op, &viewer).await?;
    subscription(&op, &client, &ns, &user).await?;
    connection_cap(&op, &nobody).await?;
    rate_limited(&op, &viewer).await?;
    for role in [&viewer_role, &user_role] {
        Api::<ClusterRole>::all(client.clone())
            .delete(role, &DeleteParams::default())
            .await?;
    }
    Ok(())
}
