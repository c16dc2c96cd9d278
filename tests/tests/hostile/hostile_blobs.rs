//! Hostile robots, release blobs and terminal output (issue 12, points 3 and 14): a robot token
//! reads only the blobs that the releases of its own namespace reference (on a private control
//! plane, with one operator watching every namespace, as the chart runs it); escape sequences a
//! robot reports never reach the terminal of `kubectl lekiwi`, and logs written to a file carry
//! no colour codes.

use std::time::{Duration, Instant};

use anyhow::Context as _;
use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::Robot;
use lekiwi_tests::blobs::{OneFileRelease as Release, digest, get_bytes as get};
use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, bin, connect_agent, enrollment_token,
    enrollment_token_file, gateway_url, http_request, namespace, wait_for,
};
use serde_json::{Value, json};

/// A robot's credentials for blob requests.
struct AsRobot {
    auth: String,
    robot: String,
}

impl AsRobot {
    /// Enrolls `ns/name` through the gateway and keeps the robot token it was given.
    async fn enroll(op: &OperatorProcess, client: &kube::Client, ns: &str, name: &str) -> Self {
        let enroll = enrollment_token(client, ns)
            .await
            .expect("enrollment token");
        let robot = format!("{ns}/{name}");
        let (ws, welcome) = connect_agent(op, &enroll, &robot).await.expect("enroll");
        drop(ws);
        let token = welcome.robot_token.expect("a robot token");
        Self {
            auth: format!("Bearer {token}"),
            robot,
        }
    }

    fn headers(&self) -> [(&str, &str); 2] {
        [
            ("authorization", self.auth.as_str()),
            ("x-lekiwi-robot", self.robot.as_str()),
        ]
    }
}

/// Names `manifest` in the Robot's `spec.release`.
async fn assign(client: &kube::Client, robot: &str, manifest: &str) -> anyhow::Result<()> {
    let (ns, name) = robot.split_once('/').context("ns/name")?;
    let patch = json!({"spec": {"release": {"version": "1.0.0", "digest": manifest}}});
    Api::<Robot>::namespaced(client.clone(), ns)
        .patch(name, &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    Ok(())
}

/// The `message` of a JSON error answer, with `digest` replaced by `<d>`.
fn message(body: &[u8], digest: &str) -> String {
    let v: Value = serde_json::from_slice(body).expect("JSON error body");
    v["message"]
        .as_str()
        .unwrap_or_default()
        .replace(digest, "<d>")
}

#[tokio::test]
async fn a_robot_reads_only_the_blobs_of_its_own_namespaces_releases() -> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    let client = cp.client().await?;
    let home = namespace(&client, "blobop").await?;
    let (x, y) = (
        namespace(&client, "blobx").await?,
        namespace(&client, "bloby").await?,
    );
    let dir = tempfile::tempdir()?;
    let blob_dir = dir.path().to_str().context("utf-8")?;
    let mut op = OperatorProcess::start_cluster_wide(
        &cp,
        &home,
        "op",
        &["--install-crds", "--blob-dir", blob_dir],
    )?;
    op.wait_ready().await?;
    let port = op.gateway_port;
    let api = format!("Bearer {}", cp.admin_token()?);

    let a = AsRobot::enroll(&op, &client, &x, "kiwi-a").await;
    let b = AsRobot::enroll(&op, &client, &y, "kiwi-b").await;
    let (rel_x, rel_y) = (
        Release::new("1.0.0", b"X's policy"),
        Release::new("1.0.0", b"Y's policy"),
    );
    rel_x.push(port, &api, &x).await?;
    rel_y.push(port, &api, &y).await?;
    assign(&client, &a.robot, &rel_x.manifest).await?;
    assign(&client, &b.robot, &rel_y.manifest).await?;

    // Each robot reads its own release once the gateway's Robot watch has seen it.
    let deadline = Instant::now() + Duration::from_secs(15);
    for (who, rel) in [(&a, &rel_x), (&b, &rel_y)] {
        let path = format!("/v1/blobs/{}", rel.file);
        while get(port, &path, &who.headers()).await.0 != 200 {
            assert!(
                Instant::now() < deadline,
                "{} never read its release",
                who.robot
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let (code, body) = get(port, &path, &who.headers()).await;
        assert_eq!((code, body), (200, rel.content.clone()));
        let manifest = format!("/v1/blobs/{}", rel.manifest);
        let (code, body) = get(port, &manifest, &who.headers()).await;
        assert_eq!((code, body), (200, rel.manifest_bytes.clone()));
        let (code, _) = get(
            port,
            &format!("/v1/releases/{}", rel.manifest),
            &who.headers(),
        )
        .await;
        assert_eq!(code, 200);
    }

    // The other namespace's manifest and file are answered exactly as unknown digests.
    let unknown = digest(b"never pushed");
    let (_, unknown_blob) = get(port, &format!("/v1/blobs/{unknown}"), &a.headers()).await;
    let (_, unknown_rel) = get(port, &format!("/v1/releases/{unknown}"), &a.headers()).await;
    for (who, rel) in [(&a, &rel_y), (&b, &rel_x)] {
        for d in [&rel.file, &rel.manifest] {
            let (code, body) = get(port, &format!("/v1/blobs/{d}"), &who.headers()).await;
            assert_eq!(code, 404, "{} read {d} of another namespace", who.robot);
            assert_eq!(message(&body, d), message(&unknown_blob, &unknown));
            let (code, _, _) = http_request(
                port,
                "HEAD",
                &format!("/v1/blobs/{d}"),
                &who.headers(),
                None,
            )
            .await?;
            assert_eq!(code, 404, "HEAD {d} as {}", who.robot);
            let range = [who.headers()[0], who.headers()[1], ("range", "bytes=1-")];
            let (code, _) = get(port, &format!("/v1/blobs/{d}"), &range).await;
            assert_eq!(code, 404, "a range of {d} as {}", who.robot);
        }
        let path = format!("/v1/releases/{}", rel.manifest);
        let (code, body) = get(port, &path, &who.headers()).await;
        assert_eq!(
            code, 404,
            "{} read the release of another namespace",
            who.robot
        );
        assert_eq!(
            message(&body, &rel.manifest),
            message(&unknown_rel, &unknown)
        );
    }
    let refused = op
        .metric(r#"lekiwi_gateway_refused_total{kind="blob_not_referenced"}"#)
        .await
        .unwrap_or_default();
    assert!(refused >= 10.0, "refusals counted: {refused}");

    // A Kubernetes user allowed `get releases` (release push and inspect) reads them all.
    for d in [&rel_x.file, &rel_y.file, &rel_y.manifest] {
        let path = format!("/v1/blobs/{d}?namespace={x}");
        let (code, _) = get(port, &path, &[("authorization", &api)]).await;
        assert_eq!(code, 200, "the admin reads {d}");
    }

    // When Y's robot is switched to X's release, it may read that release and no longer its old one.
    assign(&client, &b.robot, &rel_x.manifest).await?;
    let path = format!("/v1/blobs/{}", rel_x.file);
    let deadline = Instant::now() + Duration::from_secs(15);
    while get(port, &path, &b.headers()).await.0 != 200 {
        assert!(
            Instant::now() < deadline,
            "the new release never became readable"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (code, _) = get(port, &format!("/v1/blobs/{}", rel_y.file), &b.headers()).await;
    assert_eq!(code, 404, "a release no Robot of Y names any more");
    Ok(())
}

/// What a hostile robot reports: clear the screen, set the window title, colour the rest.
const HOSTILE: &str = "\x1b[2Jscreen cleared\x1b]0;pwned\x07 \x1b[31mred\u{9b}1m";

/// `kubectl-lekiwi -n ns ARGS...` (with `op`'s gateway for `events`): stdout, as bytes.
fn plugin(cp: &ControlPlane, ns: &str, op: &OperatorProcess, args: &[&str]) -> Vec<u8> {
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let gateway = ["--server", &server];
    let events = args.contains(&"events");
    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args(["-n", ns])
        .args(args)
        .args(if events { &gateway[..] } else { &[] })
        .env_remove("LEKIWI_SERVER")
        .output()
        .expect("run kubectl-lekiwi");
    assert!(
        out.status.success(),
        "kubectl-lekiwi {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
}

#[tokio::test]
async fn robot_text_reaches_the_cli_escaped_and_logs_have_no_colour() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hostout").await?;
    let mut op = OperatorProcess::start(cp, &ns, "op", &[])?;
    op.wait_ready().await?;
    let dir = tempfile::tempdir()?;
    let token = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token).await?;
    let robot = format!("{ns}/kiwi-h");
    let agent = AgentProcess::start(
        &gateway_url(&op),
        &robot,
        &token,
        &dir.path().join("s"),
        &[],
    )?;
    agent.wait_connected(Duration::from_secs(20)).await?;
    agent.emit("note", HOSTILE, &json!({ "detail": HOSTILE }))?;

    let json_args = ["-o", "json", "events", "kiwi-h", "--kind", "note"];
    let stored: Vec<Value> = wait_for("the hostile event stored", Duration::from_secs(20), || {
        let out = plugin(cp, &ns, &op, &json_args);
        async move {
            let events: Vec<Value> = lekiwi_tests::list_items(&out).ok()?;
            (!events.is_empty()).then_some(events)
        }
    })
    .await?;
    assert_eq!(
        stored[0]["message"], HOSTILE,
        "stored as sent, escaped in JSON"
    );
    for output in [
        "table",
        "wide",
        "json",
        "yaml",
        "jsonpath={.items[*].message}",
    ] {
        let out = plugin(cp, &ns, &op, &["-o", output, "events", "kiwi-h"]);
        assert!(!out.contains(&0x1b), "-o {output} printed a raw ESC");
        assert!(
            !out.contains(&0x07) && !out.windows(2).any(|w| w == [0xc2, 0x9b]),
            "-o {output} printed a raw BEL or CSI: {}",
            String::from_utf8_lossy(&out).escape_debug()
        );
        if output == "table" || output == "wide" {
            let text = String::from_utf8(out)?;
            assert!(
                text.contains(r"\u{1b}[2Jscreen cleared\u{1b}]0;pwned\u{7}"),
                "{text}"
            );
        }
    }
    let robots = plugin(cp, &ns, &op, &["-o", "wide", "robots"]);
    assert!(!robots.contains(&0x1b));

    // Logs captured to a file (the operator's by the harness; an agent with text logs here, as
    // under journald) carry no colour codes.
    let log = op.log_text();
    assert!(log.contains("INFO"), "{log}");
    assert!(!log.contains('\x1b'), "the operator's log has ANSI codes");
    let out = std::fs::File::create(dir.path().join("agent.log"))?;
    let mut text_agent = std::process::Command::new(bin("lekiwi-agent"))
        .args([
            "--config",
            "/nonexistent.yaml",
            "--gateway",
            "ws://127.0.0.1:9/v1/agent",
        ])
        .args(["--robot-name", &robot, "--enrollment-token-file"])
        .arg(&token)
        .arg("--state-dir")
        .arg(dir.path().join("text"))
        .args(["--status-listen", "127.0.0.1:0", "--mdns", "false"])
        .args(["--log-format", "text"])
        .env("RUST_LOG", "debug")
        .env_remove("NO_COLOR")
        .stdout(out.try_clone()?)
        .stderr(out)
        .spawn()?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    text_agent.kill()?;
    text_agent.wait()?;
    let log = std::fs::read_to_string(dir.path().join("agent.log"))?;
    assert!(log.contains("DEBUG") || log.contains("INFO"), "{log}");
    assert!(
        !log.contains('\x1b'),
        "the agent's text log has ANSI codes:\n{log}"
    );
    Ok(())
}
