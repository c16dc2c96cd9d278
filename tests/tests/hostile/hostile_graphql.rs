//! GraphQL requests meant to stall the gateway (issue 40), and the limits that stop them letting
//! the standard introspection query through. A body far over `--graphql-max-body-bytes` is
//! answered 413 with the JSON error body at once, whether its `Content-Length` says so (16 MiB,
//! never sent) or it comes chunked, read only up to the limit; a longer WebSocket message ends
//! the socket. While four of the longest allowed queries (4 MiB here, a comment the parser
//! reads for seconds) are parsed, another user's plain REST `GET` is served about as fast as
//! before them, not after them. A kilobyte of fragments that spread each other twice (2^30
//! fields) is refused as too complex at once. GraphiQL's introspection query passes the
//! default depth and complexity limits.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::api::rbac::v1::ClusterRole;
use kube::Api;
use kube::api::DeleteParams;
use lekiwi_tests::graphql::{next, open, subscribe};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, account, chart_roles_named, create_robot, gateway_operator,
    http_request, namespace,
};
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The gateway's GraphQL body limit in this test.
const MAX_BODY: usize = 4 << 20;

/// Sends `head` and then `body` on a fresh connection and reads the answer until the gateway
/// closes: status, `Content-Type`, JSON body.
async fn raw(port: u16, head: String, body: &[u8]) -> Result<(u16, String, Value)> {
    let mut stream = tokio::net::TcpStream::connect(("127.0.0.1", port)).await?;
    stream.write_all(head.as_bytes()).await?;
    stream.write_all(body).await?;
    let mut answer = Vec::new();
    tokio::time::timeout(Duration::from_secs(30), stream.read_to_end(&mut answer))
        .await
        .context("no answer within 30 s")??;
    let text = String::from_utf8_lossy(&answer);
    let (head, body) = text.split_once("\r\n\r\n").context("no response head")?;
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let media = head
        .lines()
        .find_map(|l| {
            l.to_ascii_lowercase()
                .strip_prefix("content-type:")
                .map(|v| v.trim().to_owned())
        })
        .unwrap_or_default();
    Ok((
        code,
        media,
        serde_json::from_str(body).unwrap_or(Value::Null),
    ))
}

/// A body over the limit is 413 `too_large` at once: one whose `Content-Length` says 16 MiB
/// (and sends nothing), one chunked that crosses the limit.
async fn too_large(op: &OperatorProcess, token: &str) -> Result<()> {
    let head = |framing: &str| {
        format!(
            "POST /api/v1/graphql HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\
             Authorization: Bearer {token}\r\nContent-Type: application/json\r\n{framing}\r\n\r\n"
        )
    };
    let declared = head(&format!("Content-Length: {}", 16 << 20));
    // One chunk one byte over the limit, not followed by anything: the gateway reads it all.
    let chunked = head("Transfer-Encoding: chunked");
    let mut chunk = format!("{:x}\r\n", MAX_BODY + 1).into_bytes();
    chunk.extend(std::iter::repeat_n(b' ', MAX_BODY + 1));
    for (what, head, body) in [
        ("declared", declared, &[][..]),
        ("chunked", chunked, &chunk[..]),
    ] {
        let started = Instant::now();
        let (code, media, json) = raw(op.gateway_port, head, body).await?;
        let took = started.elapsed();
        ensure!(
            code == 413
                && media == "application/json"
                && json["error"] == "too_large"
                && json["message"]
                    .as_str()
                    .is_some_and(|m| m.contains(&MAX_BODY.to_string())),
            "{what}: {code} {media} {json}"
        );
        ensure!(
            took < Duration::from_secs(5),
            "{what}: answered after {took:?}"
        );
        eprintln!("{what}: 413 after {took:?}");
    }
    Ok(())
}

/// One GraphQL `POST` of `body` as `token`: status and JSON body.
async fn post(op: &OperatorProcess, token: &str, body: &[u8]) -> Result<(u16, Value)> {
    let auth = format!("Bearer {token}");
    let headers = [
        ("authorization", auth.as_str()),
        ("content-type", "application/json"),
    ];
    let (code, _, raw) = http_request(
        op.gateway_port,
        "POST",
        "/api/v1/graphql",
        &headers,
        Some(body),
    )
    .await?;
    Ok((code, serde_json::from_slice(&raw).unwrap_or(Value::Null)))
}

/// How long one plain REST `GET` of the robots of `ns` takes.
async fn get(op: &OperatorProcess, ns: &str, token: &str) -> Result<Duration> {
    let auth = format!("Bearer {token}");
    let path = format!("/api/v1/namespaces/{ns}/robots");
    let started = Instant::now();
    let headers = [("authorization", auth.as_str())];
    let (code, _, _) = http_request(op.gateway_port, "GET", &path, &headers, None).await?;
    ensure!(code == 200, "GET {path}: {code}");
    Ok(started.elapsed())
}

/// While `attacker` has four of the longest allowed queries parsed (seconds each), `victim`
/// makes a plain REST `GET` every 200 ms: each is answered about as fast as the same `GET`s
/// just before (compared with them, not with a fixed figure), and several of them were made
/// while the queries were being parsed.
async fn not_starved(op: &OperatorProcess, ns: &str, attacker: &str, victim: &str) -> Result<()> {
    const QUERIES: usize = 4;
    get(op, ns, victim).await?; // the victim's token review and permission, cached
    let mut before = Vec::new();
    for _ in 0..9 {
        before.push(get(op, ns, victim).await?);
    }
    before.sort();
    let body = format!(
        r#"{{"query": "{{ __typename }} #{}"}}"#,
        "x".repeat(MAX_BODY - 100)
    );
    ensure!(body.len() <= MAX_BODY);
    let started = Instant::now();
    let parsed = AtomicBool::new(false);
    let queries = async {
        let answers =
            futures::future::join_all((0..QUERIES).map(|_| post(op, attacker, body.as_bytes())))
                .await;
        parsed.store(true, Ordering::Relaxed);
        (answers, started.elapsed())
    };
    let during = async {
        let mut during = Vec::new();
        while !parsed.load(Ordering::Relaxed) {
            tokio::time::sleep(Duration::from_millis(200)).await;
            during.push((started.elapsed(), get(op, ns, victim).await?));
        }
        anyhow::Ok(during)
    };
    let ((answers, all_parsed), during) = tokio::join!(queries, during);
    for answer in answers {
        let (code, json) = answer?;
        ensure!(
            code == 200 && json["data"]["__typename"] == "QueryRoot",
            "{code} {json}"
        );
    }
    let during = during?;
    let median = before[before.len() / 2];
    let slowest = during
        .iter()
        .map(|(_, took)| *took)
        .max()
        .unwrap_or_default();
    // The bodies arrive in well under a second; GETs made from then on overlap the parsing.
    let overlapping = during
        .iter()
        .filter(|(at, _)| *at > Duration::from_secs(1) && *at < all_parsed)
        .count();
    eprintln!(
        "GET before: median {median:?}; {} GETs while {QUERIES} queries of {MAX_BODY} bytes were \
         parsed (for {all_parsed:?}): slowest {slowest:?}",
        during.len()
    );
    let bound = median * 10 + Duration::from_millis(1500);
    ensure!(
        slowest < bound,
        "a GET took {slowest:?} while queries were parsed (before: median {median:?}): {during:?}"
    );
    ensure!(
        overlapping >= 3,
        "only {overlapping} GETs overlapped the parsing: {during:?}"
    );
    Ok(())
}

/// Fragments that spread each other twice, 30 deep: about 1.5 KB, 2^30 fields when expanded.
async fn fragment_bomb(op: &OperatorProcess, token: &str) -> Result<()> {
    let mut query = String::from("{ ...F30 } fragment F0 on QueryRoot { __typename }");
    for i in 1..=30 {
        query.push_str(&format!(
            " fragment F{i} on QueryRoot {{ ...F{p} ...F{p} }}",
            p = i - 1
        ));
    }
    let body = serde_json::to_vec(&json!({ "query": query }))?;
    let started = Instant::now();
    let (code, json) = tokio::time::timeout(Duration::from_secs(30), post(op, token, &body))
        .await
        .context("a fragment bomb unanswered after 30 s")??;
    ensure!(
        code == 200 && json["errors"][0]["message"] == "Query is too complex.",
        "{code} {json}"
    );
    eprintln!("fragment bomb refused after {:?}", started.elapsed());
    Ok(())
}

/// A WebSocket message longer than the limit ends the socket.
async fn long_message(op: &OperatorProcess, token: &str) -> Result<()> {
    let mut ws = open(op, token).await?;
    let ack = next(&mut ws, Duration::from_secs(10)).await?;
    ensure!(ack["type"] == "connection_ack", "{ack}");
    let query = format!(
        "subscription {{ robotChanges(namespace: \"x\") {{ name }} }} #{}",
        "x".repeat(MAX_BODY)
    );
    // The gateway may end the socket while the message is still being sent.
    if subscribe(&mut ws, "1", &query).await.is_err() {
        return Ok(());
    }
    match next(&mut ws, Duration::from_secs(10)).await {
        Err(_) => Ok(()),
        Ok(msg) if msg["close"].is_u64() => Ok(()),
        Ok(msg) => Err(anyhow::anyhow!(
            "a message over the limit was answered: {msg}"
        )),
    }
}

/// GraphiQL's introspection query, with `ofType` nine deep, under the default limits.
async fn introspection(op: &OperatorProcess, token: &str) -> Result<()> {
    let query = include_str!("../../fixtures/introspection.graphql");
    let body =
        serde_json::to_vec(&json!({ "query": query, "operationName": "IntrospectionQuery" }))?;
    let (code, json) = post(op, token, &body).await?;
    ensure!(code == 200 && json["errors"].is_null(), "{code} {json}");
    let types = json["data"]["__schema"]["types"]
        .as_array()
        .context("no types")?;
    ensure!(types.iter().any(|t| t["name"] == "Robot"), "{json}");
    Ok(())
}

#[tokio::test]
async fn graphql_requests_cannot_stall_the_gateway() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hostilegql").await?;
    let [viewer_role] = chart_roles_named(cp, &client, &ns, ["lekiwi-viewer"]).await?;
    let attacker = account(cp, &client, &ns, "attacker", Some(&viewer_role)).await?;
    let victim = account(cp, &client, &ns, "victim", Some(&viewer_role)).await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let limit = MAX_BODY.to_string();
    let args = ["--role", "gateway", "--graphql-max-body-bytes", &limit];
    let op = gateway_operator(cp, &ns, "hostilegql", &args).await?;
    too_large(&op, &attacker).await?;
    long_message(&op, &attacker).await?;
    fragment_bomb(&op, &attacker).await?;
    introspection(&op, &attacker).await?;
    not_starved(&op, &ns, &attacker, &victim).await?;
    Api::<ClusterRole>::all(client.clone())
        .delete(&viewer_role, &DeleteParams::default())
        .await?;
    Ok(())
}
