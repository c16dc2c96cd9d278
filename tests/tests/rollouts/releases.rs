//! Releases end to end: `kubectl-lekiwi release push` against a real operator process — a
//! content-addressed, idempotent, incremental push; resumable and verified uploads over HTTP;
//! robots downloading blobs with their own token (and byte ranges); the API token Secret; clear
//! answers for unknown releases.

use std::collections::BTreeSet;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Output;
use std::time::Duration;

use anyhow::Context as _;
use kube::Api;
use lekiwi_protocol::release::ReleaseManifest;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, bin, connect_agent, enrollment_token, enrollment_token_file,
    http_request, namespace,
};
use serde_json::Value;
use sha2::{Digest, Sha256};

fn digest(bytes: &[u8]) -> String {
    format!("sha256:{}", hex::encode(Sha256::digest(bytes)))
}

/// An operator of the test's own namespace with its blob store in a temporary directory.
async fn start(
    cp: &ControlPlane,
    ns: &str,
    id: &str,
    extra: &[&str],
) -> anyhow::Result<(OperatorProcess, tempfile::TempDir)> {
    let blobs = tempfile::tempdir()?;
    let mut args = vec!["--blob-dir", blobs.path().to_str().unwrap()];
    args.extend_from_slice(extra);
    let mut op = OperatorProcess::start(cp, ns, id, &args)?;
    op.wait_ready().await?;
    Ok((op, blobs))
}

/// The bearer token the release API takes: a Kubernetes user's (here the admin's, whom RBAC
/// allows everything; hostile_authz.rs proves the permissions).
async fn api_token(_client: &kube::Client, _ns: &str) -> anyhow::Result<String> {
    ControlPlane::shared().admin_token()
}

/// Runs `kubectl-lekiwi release ...` against the test control plane and operator.
fn cli(cp: &ControlPlane, ns: &str, op: &OperatorProcess, args: &[&str]) -> Output {
    cli_at(
        cp,
        ns,
        &format!("http://127.0.0.1:{}", op.gateway_port),
        args,
    )
}

/// Runs `kubectl-lekiwi release ...` against the gateway at `server`.
fn cli_at(cp: &ControlPlane, ns: &str, server: &str, args: &[&str]) -> Output {
    std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .arg("release")
        .args(args)
        .args(["-n", ns])
        .args(["--server", server])
        .env_remove("LEKIWI_SERVER")
        .output()
        .expect("run kubectl-lekiwi")
}

fn text(out: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// One HTTP/1.1 request with a body (`Content-Length` always sent).
async fn http(
    port: u16,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> anyhow::Result<(u16, Vec<(String, String)>, Vec<u8>)> {
    http_request(port, method, path, headers, Some(body)).await
}

fn header<'a>(headers: &'a [(String, String)], name: &str) -> Option<&'a str> {
    headers
        .iter()
        .find(|(k, _)| k == name)
        .map(|(_, v)| v.as_str())
}

fn json(body: &[u8]) -> Value {
    serde_json::from_slice(body)
        .unwrap_or_else(|_| panic!("not JSON: {}", String::from_utf8_lossy(body)))
}

/// Stored blobs (`sha256:<hex>`) in a blob directory.
fn stored(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir.join("sha256"))
        .map(|entries| {
            entries
                .filter_map(|e| e.ok())
                .map(|e| format!("sha256:{}", e.file_name().to_string_lossy()))
                .collect()
        })
        .unwrap_or_default()
}

/// A release directory of 50 files: nested code, config, an executable, an empty file and a
/// policy checkpoint larger than one upload chunk.
fn release_dir(root: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let mut write = |rel: &str, content: &[u8], mode: u32| -> anyhow::Result<()> {
        let path = root.join(rel);
        std::fs::create_dir_all(path.parent().unwrap())?;
        std::fs::write(&path, content)?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode))?;
        files.push(path);
        Ok(())
    };
    write("bin/run.sh", b"#!/bin/sh\nexec python3 -m kiwi\n", 0o755)?;
    write("config/robot.yaml", b"wheels: 3\narm: so100\n", 0o644)?;
    write("config/empty.flag", b"", 0o600)?;
    let checkpoint: Vec<u8> = (0..300_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    write("policy/checkpoint.safetensors", &checkpoint, 0o644)?;
    for i in 0..46 {
        write(
            &format!("kiwi/pkg{}/mod{i}.py", i % 5),
            format!("# module {i}\nVALUE = {i}\n").as_bytes(),
            0o644,
        )?;
    }
    assert_eq!(files.len(), 50);
    Ok(files)
}

#[tokio::test]
async fn push_is_content_addressed_idempotent_and_incremental() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "rel").await?;
    let (op, blobs) = start(cp, &ns, "rel-push", &[]).await?;
    let token = api_token(&client, &ns).await?;
    let dir = tempfile::tempdir()?;
    let files = release_dir(dir.path())?;
    let release = dir.path().to_str().unwrap();
    // Chunks smaller than the checkpoint: it goes up in several resumable requests.
    let push = |version: &str| {
        cli(
            cp,
            &ns,
            &op,
            &[
                "push",
                release,
                "--version",
                version,
                "--chunk-bytes",
                "65536",
            ],
        )
    };

    // First push: everything goes up; stdout is the manifest digest, stderr the snippet.
    let out = push("1.0.0");
    let (stdout, stderr) = text(&out);
    assert!(
        out.status.success(),
        "push failed: {stderr}\n{}",
        op.log_text()
    );
    let first = stdout.trim().to_owned();
    assert!(
        first.starts_with("sha256:") && first.len() == 71,
        "{stdout}"
    );
    assert!(
        stderr.contains("0 files already present (50 new blobs + manifest)"),
        "{stderr}"
    );
    assert!(
        stderr.contains(&format!("release: {{version: 1.0.0, digest: {first}}}")),
        "{stderr}"
    );

    // The manifest served back hashes to the printed digest and describes the directory.
    let auth = format!("Bearer {token}");
    let (code, _, body) = http(
        op.gateway_port,
        "GET",
        &format!("/v1/blobs/{first}?namespace={ns}"),
        &[("authorization", &auth)],
        b"",
    )
    .await?;
    assert_eq!(code, 200);
    assert_eq!(digest(&body), first);
    let manifest = ReleaseManifest::parse(&body)?;
    assert_eq!(manifest.version, "1.0.0");
    assert_eq!(manifest.files.len(), 50);
    for path in &files {
        let rel = path.strip_prefix(dir.path())?.to_str().unwrap();
        let entry = manifest
            .files
            .iter()
            .find(|f| f.path == rel)
            .with_context(|| format!("{rel} not in the manifest"))?;
        let content = std::fs::read(path)?;
        assert_eq!(entry.size, content.len() as u64, "{rel}");
        assert_eq!(entry.digest, digest(&content), "{rel}");
        let want_mode = std::fs::metadata(path)?.permissions().mode() & 0o7777;
        assert_eq!(entry.mode, want_mode, "{rel}");
    }
    let mode_of = |p: &str| manifest.files.iter().find(|f| f.path == p).unwrap().mode;
    assert_eq!(mode_of("bin/run.sh"), 0o755);
    assert_eq!(mode_of("config/empty.flag"), 0o600);
    assert!(manifest.files.iter().any(|f| f.path == "kiwi/pkg3/mod8.py"));
    let after_first = stored(blobs.path());
    assert_eq!(after_first.len(), 51, "50 distinct files and the manifest");
    assert!(after_first.contains(&first));
    let uploads: Vec<_> = std::fs::read_dir(blobs.path().join("uploads"))?.collect();
    assert!(uploads.is_empty(), "no partial upload is left");

    // Second push of the same directory: nothing is uploaded.
    let mtime = std::fs::metadata(blobs.path().join("sha256").join(&first[7..]))?.modified()?;
    let out = push("1.0.0");
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    assert_eq!(stdout.trim(), first);
    assert!(
        stderr.contains(
            "0 B uploaded, 50 files already present (0 new blobs, manifest already present)"
        ),
        "{stderr}"
    );
    assert_eq!(stored(blobs.path()), after_first);
    assert_eq!(
        std::fs::metadata(blobs.path().join("sha256").join(&first[7..]))?.modified()?,
        mtime
    );

    // Three files change and the version moves on: exactly three blobs and a manifest go up.
    let changed = [&files[1], &files[10], &files[40]];
    let mut new_digests = BTreeSet::new();
    for path in changed {
        let content = format!("# changed {}\n", path.display());
        std::fs::write(path, &content)?;
        new_digests.insert(digest(content.as_bytes()));
    }
    let out = push("1.1.0");
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let second = stdout.trim().to_owned();
    assert_ne!(second, first);
    assert!(
        stderr.contains("47 files already present (3 new blobs + manifest)"),
        "{stderr}"
    );
    let after_second = stored(blobs.path());
    let added: BTreeSet<String> = after_second.difference(&after_first).cloned().collect();
    new_digests.insert(second.clone());
    assert_eq!(
        added, new_digests,
        "the three changed files and the manifest"
    );

    // inspect shows it, as JSON and as a table.
    let out = cli(cp, &ns, &op, &["inspect", &second, "-o", "json"]);
    let (stdout, stderr) = text(&out);
    assert!(out.status.success(), "{stderr}");
    let info: Value = serde_json::from_str(&stdout)?;
    assert_eq!(info["version"], "1.1.0");
    assert_eq!(info["digest"], second.as_str());
    assert_eq!(info["missing"], serde_json::json!([]));
    assert_eq!(info["files"].as_array().map(Vec::len), Some(50));
    let out = cli(cp, &ns, &op, &["inspect", &second]);
    let (stdout, _) = text(&out);
    assert!(out.status.success());
    assert!(
        stdout.contains("Version:  1.1.0")
            && stdout
                .lines()
                .any(|l| l.starts_with("0755") && l.ends_with("bin/run.sh")),
        "{stdout}"
    );

    // A symbolic link is refused by name, before anything is uploaded.
    std::os::unix::fs::symlink(&files[0], dir.path().join("kiwi/link.sh"))?;
    let out = push("1.2.0");
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(
        stderr.contains("kiwi/link.sh") && stderr.contains("symbolic link"),
        "{stderr}"
    );
    assert!(
        !op.log_text().contains(&token),
        "the API token leaked into the log"
    );
    Ok(())
}

#[tokio::test]
async fn uploads_resume_and_are_verified() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "relup").await?;
    let (mut op, blobs) = start(cp, &ns, "rel-up", &["--max-blob-bytes", "1048576"]).await?;
    let token = api_token(&client, &ns).await?;
    let auth = format!("Bearer {token}");
    let as_api = [("authorization", auth.as_str())];
    let port = op.gateway_port;
    let content: Vec<u8> = (0..100_000u32).map(|i| (i % 253) as u8).collect();
    let d = digest(&content);
    let path = format!("/v1/blobs/{d}?namespace={ns}");
    let put = |range: String, body: Vec<u8>| {
        let auth = auth.clone();
        let path = path.clone();
        async move {
            http(
                port,
                "PUT",
                &path,
                &[("authorization", &auth), ("content-range", &range)],
                &body,
            )
            .await
        }
    };

    let uploads = format!("/v1/uploads/{d}?namespace={ns}");
    // The first half: accepted, not complete, resumable from its offset.
    let (code, _, body) = put("bytes 0-49999/100000".into(), content[..50_000].to_vec()).await?;
    assert_eq!(code, 202, "{}", String::from_utf8_lossy(&body));
    assert_eq!(json(&body)["offset"], 50_000);
    let (code, _, body) = http(port, "GET", &uploads, &as_api, b"").await?;
    assert_eq!(code, 200);
    assert_eq!(json(&body)["offset"], 50_000);
    assert_eq!(json(&body)["complete"], false);
    let (code, _, _) = http(port, "HEAD", &path, &as_api, b"").await?;
    assert_eq!(code, 404, "an incomplete blob is not served");

    // A chunk at the wrong offset: 409 with where the upload stands.
    let (code, _, body) = put(
        "bytes 40000-99999/100000".into(),
        content[40_000..].to_vec(),
    )
    .await?;
    assert_eq!(code, 409);
    let answer = json(&body);
    assert_eq!(answer["offset"], 50_000);
    assert_eq!(answer["error"], "conflict");

    // The rest: stored, verified, and a repeat changes nothing.
    let (code, _, body) = put(
        "bytes 50000-99999/100000".into(),
        content[50_000..].to_vec(),
    )
    .await?;
    assert_eq!(code, 201, "{}", String::from_utf8_lossy(&body));
    assert_eq!(
        std::fs::read(blobs.path().join("sha256").join(&d[7..]))?,
        content
    );
    let (code, _, body) = http(port, "PUT", &path, &as_api, &content).await?;
    assert_eq!(code, 200, "{}", String::from_utf8_lossy(&body));
    let (code, _, body) = http(port, "GET", &uploads, &as_api, b"").await?;
    assert_eq!(
        (code, json(&body)["complete"].clone()),
        (200, Value::Bool(true))
    );

    // Content that does not match its digest is refused and not stored.
    let claimed = digest(b"the real policy");
    let (code, _, body) = http(
        port,
        "PUT",
        &format!("/v1/blobs/{claimed}?namespace={ns}"),
        &as_api,
        b"a tampered policy",
    )
    .await?;
    assert_eq!(code, 400);
    let message = json(&body)["message"]
        .as_str()
        .unwrap_or_default()
        .to_owned();
    assert!(
        message.contains(&claimed) && message.contains(&digest(b"a tampered policy")),
        "{message}"
    );
    assert!(!stored(blobs.path()).contains(&claimed));
    let (code, _, _) = http(
        port,
        "HEAD",
        &format!("/v1/blobs/{claimed}?namespace={ns}"),
        &as_api,
        b"",
    )
    .await?;
    assert_eq!(code, 404);

    // Bad digests, oversized blobs, and uploads without the API token.
    let (code, _, body) = http(
        port,
        "PUT",
        &format!("/v1/blobs/sha256:XYZ?namespace={ns}"),
        &as_api,
        b"x",
    )
    .await?;
    assert_eq!(code, 400);
    assert!(
        json(&body)["message"]
            .as_str()
            .unwrap()
            .contains("invalid digest")
    );
    let big = digest(b"big");
    let (code, _, body) = http(
        port,
        "PUT",
        &format!("/v1/blobs/{big}?namespace={ns}"),
        &[
            ("authorization", &auth),
            ("content-range", "bytes 0-9/2000000"),
        ],
        b"0123456789",
    )
    .await?;
    assert_eq!(code, 413, "{}", String::from_utf8_lossy(&body));
    let (code, _, _) = http(
        port,
        "PUT",
        &format!("/v1/blobs/{big}?namespace={ns}"),
        &[("authorization", "Bearer lka_wrong")],
        b"big",
    )
    .await?;
    assert_eq!(code, 401);
    assert!(!stored(blobs.path()).contains(&big));

    // The same Kubernetes token still works after a restart.
    op.restart()?;
    op.wait_ready().await?;
    assert_eq!(api_token(&client, &ns).await?, token);
    let (code, _, _) = http(port, "HEAD", &path, &as_api, b"").await?;
    assert_eq!(code, 200);
    Ok(())
}

#[tokio::test]
async fn robots_download_with_their_own_token_and_ranges() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "reldl").await?;
    let (op, _blobs) = start(cp, &ns, "rel-dl", &[]).await?;
    let token = api_token(&client, &ns).await?;
    let api = format!("Bearer {token}");
    let as_api = [("authorization", api.as_str())];
    let port = op.gateway_port;

    // A robot enrolls through the gateway and gets its own token.
    let enroll = enrollment_token(&client, &ns).await?;
    let robot = format!("{ns}/kiwi-1");
    let (ws, welcome) = connect_agent(&op, &enroll, &robot).await?;
    drop(ws);
    let robot_token = welcome.robot_token.context("a robot token")?;
    let robot_auth = format!("Bearer {robot_token}");

    let content: Vec<u8> = (0..200_000u32).map(|i| (i % 241) as u8).collect();
    let d = digest(&content);
    let path = format!("/v1/blobs/{d}?namespace={ns}");
    let (code, _, _) = http(port, "PUT", &path, &as_api, &content).await?;
    assert_eq!(code, 201);

    // A robot reads only what a release of its namespace references: the blob becomes a file
    // of the release its Robot names.
    let as_robot = [
        ("authorization", robot_auth.as_str()),
        ("x-lekiwi-robot", robot.as_str()),
    ];
    let (code, _, _) = http(port, "HEAD", &path, &as_robot, b"").await?;
    assert_eq!(code, 404, "a blob no release references");
    name_release(&client, &op, &ns, "kiwi-1", &d, content.len()).await?;
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while http(port, "HEAD", &path, &as_robot, b"").await?.0 != 200 {
        assert!(
            std::time::Instant::now() < deadline,
            "the release never became readable"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (code, headers, body) = http(port, "GET", &path, &as_robot, b"").await?;
    assert_eq!(code, 200);
    assert_eq!(body, content);
    assert_eq!(header(&headers, "accept-ranges"), Some("bytes"));
    let (code, headers, body) = http(
        port,
        "GET",
        &path,
        &[as_robot[0], as_robot[1], ("range", "bytes=1000-")],
        b"",
    )
    .await?;
    assert_eq!(code, 206);
    assert_eq!(
        header(&headers, "content-range"),
        Some("bytes 1000-199999/200000")
    );
    assert_eq!(body, content[1000..]);
    let (code, _, body) = http(
        port,
        "GET",
        &path,
        &[as_robot[0], as_robot[1], ("range", "bytes=10-19")],
        b"",
    )
    .await?;
    assert_eq!((code, body.as_slice()), (206, &content[10..20]));
    let (code, headers, _) = http(
        port,
        "GET",
        &path,
        &[as_robot[0], as_robot[1], ("range", "bytes=300000-")],
        b"",
    )
    .await?;
    assert_eq!(code, 416);
    assert_eq!(header(&headers, "content-range"), Some("bytes */200000"));
    let (code, headers, _) = http(port, "HEAD", &path, &as_robot, b"").await?;
    assert_eq!(code, 200);
    assert_eq!(header(&headers, "content-length"), Some("200000"));

    // Bytes served to the robot, counted by the gateway.
    let (code, _, body) = http(
        port,
        "GET",
        &format!("/v1/blobs-served?robot={robot}"),
        &as_api,
        b"",
    )
    .await?;
    assert_eq!(code, 200);
    let served = json(&body);
    assert_eq!(served["bytes"], 200_000 + 199_000 + 10);
    assert_eq!(served["downloads"], 3);
    let total = op
        .metric("lekiwi_gateway_blob_bytes_served_total")
        .await
        .unwrap_or_default();
    assert_eq!(total, (200_000 + 199_000 + 10) as f64);

    // Refusals: no token, an enrollment token, a wrong token, a robot token without the robot
    // header, a robot token for another robot, a robot uploading.
    let enroll_auth = format!("Bearer {enroll}");
    let other_robot = format!("{ns}/kiwi-2");
    let refused: [(&str, Vec<(&str, &str)>); 5] = [
        ("no token", vec![("x-lekiwi-robot", robot.as_str())]),
        (
            "enrollment token",
            vec![
                ("authorization", enroll_auth.as_str()),
                ("x-lekiwi-robot", robot.as_str()),
            ],
        ),
        (
            "wrong token",
            vec![
                ("authorization", "Bearer lkr_wrong"),
                ("x-lekiwi-robot", robot.as_str()),
            ],
        ),
        ("robot token without header", vec![as_robot[0]]),
        (
            "another robot's name",
            vec![as_robot[0], ("x-lekiwi-robot", other_robot.as_str())],
        ),
    ];
    for (what, headers) in &refused {
        let (code, _, body) = http(port, "GET", &path, headers, b"").await?;
        assert_eq!(code, 401, "{what}: {}", String::from_utf8_lossy(&body));
        assert_eq!(json(&body)["error"], "unauthorized", "{what}");
    }
    let (code, _, _) = http(port, "PUT", &path, &as_robot, &content).await?;
    assert_eq!(code, 401, "robots cannot upload");

    // Releases: an unknown digest is a clear 404, a blob that is no manifest a 422.
    let unknown = digest(b"never pushed");
    let (code, _, body) = http(
        port,
        "GET",
        &format!("/v1/releases/{unknown}?namespace={ns}"),
        &as_robot,
        b"",
    )
    .await?;
    assert_eq!(code, 404);
    let want = format!("release {unknown} not found: push it with kubectl lekiwi release push");
    assert_eq!(json(&body)["message"], want.as_str());
    let (code, _, body) = http(
        port,
        "GET",
        &format!("/v1/releases/{d}?namespace={ns}"),
        &as_robot,
        b"",
    )
    .await?;
    assert_eq!(code, 422);
    assert!(
        json(&body)["message"]
            .as_str()
            .unwrap()
            .contains("not a valid release manifest")
    );
    let out = cli(cp, &ns, &op, &["inspect", &unknown]);
    let (_, stderr) = text(&out);
    assert!(!out.status.success());
    assert!(stderr.contains(&want), "{stderr}");

    // The per-download log line names the robot; no token is ever logged.
    let log = op.log_text();
    assert!(
        log.lines()
            .any(|l| l.contains("blob download finished") && l.contains(&robot)),
        "{log}"
    );
    for secret in [&token, &robot_token, &enroll] {
        assert!(
            !log.contains(secret.as_str()),
            "a token leaked into the log"
        );
    }
    Ok(())
}

/// Pushes a release manifest listing the blob `file` (of `size` bytes) and names it in the
/// Robot `name`'s `spec.release`; returns the manifest's digest.
async fn name_release(
    client: &kube::Client,
    op: &OperatorProcess,
    ns: &str,
    name: &str,
    file: &str,
    size: usize,
) -> anyhow::Result<String> {
    use lekiwi_protocol::release::ManifestFile;
    let token = format!("Bearer {}", api_token(client, ns).await?);
    let manifest = ReleaseManifest::new(
        "1.0.0",
        vec![ManifestFile {
            path: "policy.bin".into(),
            digest: file.to_owned(),
            size: size as u64,
            mode: 0o644,
        }],
    )
    .to_bytes();
    let md = digest(&manifest);
    let path = format!("/v1/blobs/{md}?namespace={ns}");
    let (code, _, _) = http(
        op.gateway_port,
        "PUT",
        &path,
        &[("authorization", token.as_str())],
        &manifest,
    )
    .await?;
    assert!(code == 201 || code == 200, "manifest upload: {code}");
    let patch = serde_json::json!({"spec": {"release": {"version": "1.0.0", "digest": md}}});
    Api::<lekiwi_crds::Robot>::namespaced(client.clone(), ns)
        .patch(
            name,
            &kube::api::PatchParams::default(),
            &kube::api::Patch::Merge(&patch),
        )
        .await?;
    Ok(md)
}

/// What rustls says of a certificate signed by a CA it does not trust.
const UNTRUSTED: &str = "UnknownIssuer";

/// Everything over TLS with a private CA: `release push` to an https:// gateway with
/// `--certificate-authority`, a real agent on wss:// with `--ca-file` that downloads the
/// release's blobs over https:// from the same gateway and switches to it; an agent that does
/// not trust the CA never connects.
#[tokio::test]
async fn releases_travel_over_tls_with_a_private_ca() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "reltls").await?;
    let certs = tempfile::tempdir()?;
    lekiwi_tests::test_ca(certs.path())?;
    let ca = certs.path().join("ca.crt");
    let (cert, key) = (certs.path().join("tls.crt"), certs.path().join("tls.key"));
    let (op, _blobs) = start(
        cp,
        &ns,
        "rel-tls",
        &[
            "--tls-cert",
            cert.to_str().unwrap(),
            "--tls-key",
            key.to_str().unwrap(),
        ],
    )
    .await?;
    let port = op.gateway_port;

    let dir = tempfile::tempdir()?;
    std::fs::create_dir_all(dir.path().join("release/lekiwi"))?;
    std::fs::write(
        dir.path().join("release/lekiwi/config.yaml"),
        "speed: 0.3\n",
    )?;
    std::fs::write(dir.path().join("release/policy.bin"), vec![7u8; 300_000])?;
    let release = dir.path().join("release");
    let push = ["push", release.to_str().unwrap(), "--version", "1.0.0"];
    let server = format!("https://127.0.0.1:{port}");
    let refused = cli_at(cp, &ns, &server, &push);
    let (_, err) = text(&refused);
    assert!(
        !refused.status.success(),
        "an untrusted certificate was accepted"
    );
    assert!(
        err.contains(UNTRUSTED) && err.contains("--certificate-authority"),
        "{err}"
    );
    let ca_flag = ["--certificate-authority", ca.to_str().unwrap()];
    let pushed = cli_at(cp, &ns, &server, &[&push[..], &ca_flag].concat());
    let (out, err) = text(&pushed);
    assert!(pushed.status.success(), "{err}");
    let digest = out.trim().to_owned();

    let token_file = dir.path().join("enroll-token");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let url = format!("wss://127.0.0.1:{port}/v1/agent");
    let robot = format!("{ns}/kiwi-tls");
    let agent = lekiwi_tests::AgentProcess::start(
        &url,
        &robot,
        &token_file,
        &dir.path().join("state"),
        &["--ca-file", ca.to_str().unwrap()],
    )?;
    let untrusting = lekiwi_tests::AgentProcess::start(
        &url,
        &format!("{ns}/kiwi-untrusting"),
        &token_file,
        &dir.path().join("state-untrusting"),
        &[],
    )?;
    let robots = Api::<lekiwi_crds::Robot>::namespaced(client.clone(), &ns);
    lekiwi_tests::wait_for("kiwi-tls enrolled", Duration::from_secs(20), || async {
        robots.get_opt("kiwi-tls").await.ok()?.map(|_| ())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", agent.log_text()))?;
    let patch = serde_json::json!({"spec": {"release": {"version": "1.0.0", "digest": digest}}});
    robots
        .patch(
            "kiwi-tls",
            &kube::api::PatchParams::default(),
            &kube::api::Patch::Merge(&patch),
        )
        .await?;
    lekiwi_tests::wait_for("1.0.0 running", Duration::from_secs(30), || async {
        let r = robots.get("kiwi-tls").await.ok()?;
        (r.status?.current_release?.version == "1.0.0").then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", agent.log_text()))?;
    let current = dir.path().join("state/current");
    assert_eq!(
        std::fs::read(current.join("policy.bin"))?,
        vec![7u8; 300_000]
    );
    assert_eq!(
        std::fs::read_to_string(current.join("lekiwi/config.yaml"))?,
        "speed: 0.3\n"
    );

    // The agent without the CA tried, was refused for the certificate, and never got in.
    lekiwi_tests::wait_for(
        "the untrusting agent's certificate error",
        Duration::from_secs(20),
        || async { untrusting.log_text().contains(UNTRUSTED).then_some(()) },
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}\n{}", untrusting.log_text()))?;
    assert!(robots.get_opt("kiwi-untrusting").await?.is_none());
    Ok(())
}
