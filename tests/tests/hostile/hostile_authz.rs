//! People and tools reach the gateway's HTTP API with Kubernetes credentials, allowed what RBAC
//! allows them, namespace by namespace (issue 12, point 4): a ServiceAccount bound to the
//! chart's `lekiwi-release-pusher` in namespace A pushes a release into A with the real CLI (its
//! token from TokenRequest, in a kubeconfig); the same token is refused (403, naming the
//! permission) in namespace B; a viewer of A cannot read events of a robot in B; a token the API
//! server refuses gets 401; and no cluster-wide API token Secret exists any more.

use std::path::Path;
use std::process::{Command, Output};
use std::time::Duration;

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::api::core::v1::Secret;
use k8s_openapi::api::rbac::v1::ClusterRole;
use kube::Api;
use kube::api::DeleteParams;

use lekiwi_tests::{
    ControlPlane, OperatorProcess, account, bin, chart_roles_named, gateway_operator, http_request,
    namespace,
};

/// `kubectl-lekiwi --kubeconfig KUBECONFIG ARGS --server <op's gateway>`.
fn plugin(kubeconfig: &Path, op: &OperatorProcess, args: &[&str]) -> Output {
    Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(kubeconfig)
        .args(args)
        .args(["--server", &format!("http://127.0.0.1:{}", op.gateway_port)])
        .env_remove("LEKIWI_SERVER")
        .env_remove("LEKIWI_TOKEN")
        .output()
        .expect("run kubectl-lekiwi")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A request to the gateway with `token`: status and body.
async fn call(
    op: &OperatorProcess,
    method: &str,
    path: &str,
    token: &str,
) -> Result<(u16, String)> {
    let auth = format!("Bearer {token}");
    let body = (method == "PUT").then_some(&b"x"[..]);
    let (code, _, body) = http_request(
        op.gateway_port,
        method,
        path,
        &[("authorization", &auth)],
        body,
    )
    .await?;
    Ok((code, String::from_utf8_lossy(&body).into_owned()))
}

#[tokio::test]
async fn kubernetes_rbac_decides_who_pushes_releases_and_reads_events_where() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let a = namespace(&client, "authza").await?;
    let b = namespace(&client, "authzb").await?;
    let [pusher_role, viewer_role] =
        chart_roles_named(cp, &client, &a, ["lekiwi-release-pusher", "lekiwi-viewer"]).await?;
    let pusher = account(cp, &client, &a, "pusher", Some(&pusher_role)).await?;
    let viewer = account(cp, &client, &a, "viewer", Some(&viewer_role)).await?;
    let op = gateway_operator(cp, &a, "authz", &[]).await?;
    let dir = tempfile::tempdir()?;
    let kubeconfig = dir.path().join("kubeconfig-pusher");
    cp.kubeconfig_with_token(&pusher, &kubeconfig)?;
    let release = dir.path().join("release");
    std::fs::create_dir_all(&release)?;
    for i in 0..24 {
        std::fs::write(
            release.join(format!("part-{i}.bin")),
            format!("part {i} of {a}"),
        )?;
    }
    let release = release.to_str().context("utf-8")?;
    let push = ["release", "push", release, "--version", "1.0.0"];

    // The pusher's kubeconfig token pushes into A.
    let pushed = plugin(&kubeconfig, &op, &[&["-n", &a][..], &push].concat());
    ensure!(
        pushed.status.success(),
        "push into A: {}\n{}",
        stderr(&pushed),
        op.log_text()
    );
    let digest = String::from_utf8(pushed.stdout)?.trim().to_owned();
    ensure!(digest.starts_with("sha256:"), "{digest}");
    // 24 blobs and a manifest, each asked for and uploaded: a handful of reviews, the rest cached.
    let reviews = op.metrics().await?;
    let count = |series: &str| lekiwi_tests::sample(&reviews, series).unwrap_or_default();
    let token_reviews =
        count(r#"lekiwi_gateway_kube_reviews_total{kind="token_review",result="accepted"}"#);
    let access_reviews =
        count(r#"lekiwi_gateway_kube_reviews_total{kind="access_review",result="allowed"}"#);
    let hits = count(r#"lekiwi_gateway_kube_review_cache_hits_total{kind="access_review"}"#);
    ensure!(
        (1.0..=8.0).contains(&token_reviews)
            && (1.0..=12.0).contains(&access_reviews)
            && hits >= 30.0,
        "reviews: {token_reviews} token, {access_reviews} access, {hits} cached\n{reviews}"
    );

    // The same token (given with --token this time) in namespace B: 403 naming the permission.
    let refused = plugin(
        &cp.kubeconfig(),
        &op,
        &[&push[..], &["-n", &b, "--token", &pusher]].concat(),
    );
    let err = stderr(&refused);
    ensure!(!refused.status.success(), "push into B succeeded: {err}");
    ensure!(
        err.contains("403") && err.contains(&format!("releases.fleet.lekiwi.io in namespace {b}")),
        "{err}"
    );
    let put = format!("/v1/blobs/{digest}?namespace={b}");
    let (code, body) = call(&op, "PUT", &put, &pusher).await?;
    ensure!(code == 403, "PUT into B: {code} {body}");
    ensure!(
        body.contains(&format!("create releases.fleet.lekiwi.io in namespace {b}")),
        "{body}"
    );
    let (code, body) = call(
        &op,
        "GET",
        &format!("/v1/releases/{digest}?namespace={a}"),
        &pusher,
    )
    .await?;
    ensure!(
        code == 200 && body.contains("1.0.0"),
        "inspect in A: {code} {body}"
    );
    // A request of a user that names no namespace is refused as malformed.
    let (code, body) = call(&op, "GET", &format!("/v1/releases/{digest}"), &pusher).await?;
    ensure!(
        code == 400 && body.contains("namespace"),
        "no namespace: {code} {body}"
    );

    // A viewer of A reads A's robots' events, not B's (a robot that does not exist is 404
    // once the permission is granted, so A's is made).
    lekiwi_tests::create_robot(&client, &a, "kiwi", &[]).await?;
    lekiwi_tests::wait_for(
        "the gateway holding robot kiwi",
        Duration::from_secs(30),
        || async {
            let (code, _) = call(&op, "GET", &format!("/v1/robots/{a}/kiwi/events"), &viewer)
                .await
                .ok()?;
            (code == 200).then_some(())
        },
    )
    .await?;
    let (code, body) = call(&op, "GET", &format!("/v1/robots/{a}/kiwi/events"), &viewer).await?;
    ensure!(code == 200, "events in A: {code} {body}");
    let (code, body) = call(&op, "GET", &format!("/v1/robots/{b}/kiwi/events"), &viewer).await?;
    ensure!(code == 403, "events in B: {code} {body}");
    ensure!(
        body.contains(&format!(
            "get robots/events.fleet.lekiwi.io kiwi in namespace {b}"
        )),
        "{body}"
    );
    let events = plugin(
        &cp.kubeconfig(),
        &op,
        &["events", &format!("{b}/kiwi"), "--token", &viewer],
    );
    let err = stderr(&events);
    ensure!(!events.status.success() && err.contains("403"), "{err}");
    // The pusher may not read events (it is not a viewer).
    let (code, _) = call(&op, "GET", &format!("/v1/robots/{a}/kiwi/events"), &pusher).await?;
    ensure!(code == 403, "a pusher reading events: {code}");

    // A token the API server does not accept: 401, for the API and for the CLI.
    let garbage = "not-a-token-the-api-server-knows";
    let (code, body) = call(&op, "PUT", &put.replace(&b, &a), garbage).await?;
    ensure!(code == 401, "garbage token: {code} {body}");
    let refused = plugin(
        &cp.kubeconfig(),
        &op,
        &[&push[..], &["-n", &a, "--token", garbage]].concat(),
    );
    let err = stderr(&refused);
    ensure!(!refused.status.success() && err.contains("401"), "{err}");

    // No cluster-wide API token any more: the operator made no Secret lekiwi-api.
    let secret = Api::<Secret>::namespaced(client.clone(), &a)
        .get_opt("lekiwi-api")
        .await?;
    ensure!(secret.is_none(), "the old API token Secret exists");
    for role in [&pusher_role, &viewer_role] {
        Api::<ClusterRole>::all(client.clone())
            .delete(role, &DeleteParams::default())
            .await?;
    }
    Ok(())
}
