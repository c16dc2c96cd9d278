//! GraphQL requests meant to stall the gateway (issue 40): a body far over
//! `--graphql-max-body-bytes` is answered 413 with the JSON error body at once, whether its
//! `Content-Length` says so (16 MiB, never sent) or it comes chunked, read only up to the limit.

use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::api::rbac::v1::ClusterRole;
use kube::Api;
use kube::api::DeleteParams;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, account, chart_roles_named, create_robot, gateway_operator,
    namespace,
};
use serde_json::Value;
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

#[tokio::test]
async fn graphql_requests_cannot_stall_the_gateway() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hostilegql").await?;
    let [viewer_role] = chart_roles_named(cp, &client, &ns, ["lekiwi-viewer"]).await?;
    let attacker = account(cp, &client, &ns, "attacker", Some(&viewer_role)).await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let limit = MAX_BODY.to_string();
    let args = ["--role", "gateway", "--graphql-max-body-bytes", &limit];
    let op = gateway_operator(cp, &ns, "hostilegql", &args).await?;
    too_large(&op, &attacker).await?;
    Api::<ClusterRole>::all(client.clone())
        .delete(&viewer_role, &DeleteParams::default())
        .await?;
    Ok(())
}
