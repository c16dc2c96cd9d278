//! `lekiwi-agent join` against a real operator serving TLS on the local control plane: a join
//! with the right pin enrolls and goes Online, writing only its drop-in, the CA and the token
//! (with their modes) beside the lab's untouched `agent.yaml`; run twice it changes nothing;
//! another gateway needs --force. A wrong pin, and a man-in-the-middle (another CA presenting
//! the gateway's name), are refused with both fingerprints.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::Duration;

use anyhow::{Result, bail};
use lekiwi_crds::RobotPhase;
use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, bin, enrollment_token, free_port,
    gateway_operator, get_robot, namespace, test_ca, wait_for,
};

/// The pin of the CA in `ca` as openssl computes it (an oracle independent of our code).
fn openssl_pin(ca: &Path) -> Result<String> {
    let out = std::process::Command::new("bash")
        .arg("-c")
        .arg(format!(
            "openssl x509 -pubkey -noout -in {} | openssl pkey -pubin -outform der | sha256sum",
            ca.display()
        ))
        .output()?;
    if !out.status.success() {
        bail!("openssl: {}", String::from_utf8_lossy(&out.stderr));
    }
    let text = String::from_utf8(out.stdout)?;
    Ok(format!(
        "sha256:{}",
        text.split_whitespace().next().unwrap_or_default()
    ))
}

/// Runs `lekiwi-agent join` with `args` (not starting the service) under `root`.
async fn join(root: &Path, args: &[&str]) -> Result<Output> {
    Ok(tokio::process::Command::new(bin("lekiwi-agent"))
        .arg("join")
        .args(["--root", root.to_str().unwrap(), "--no-start"])
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::null())
        .output()
        .await?)
}

/// Starts [`join`] with `args` in the background, so the test can play the agent or the
/// gateway meanwhile.
fn spawn_join(root: &Path, args: Vec<String>) -> tokio::task::JoinHandle<Result<Output>> {
    let root = root.to_owned();
    tokio::spawn(async move {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        join(&root, &args).await
    })
}

/// Waits until the join under `root` wrote its drop-in (before it waits for the agent);
/// returns the drop-in's path.
async fn drop_in_written(root: &Path) -> Result<PathBuf> {
    let drop_in = root.join("etc/lekiwi/agent.d/50-join.yaml");
    wait_for(
        "join wrote its drop-in",
        Duration::from_secs(15),
        || async { drop_in.exists().then_some(()) },
    )
    .await?;
    Ok(drop_in)
}

fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// An operator serving wss:// with the test CA sent after its certificate, and the CA's dir.
async fn tls_operator(ns: &str) -> Result<(OperatorProcess, tempfile::TempDir)> {
    let dir = tempfile::tempdir()?;
    test_ca(dir.path())?;
    let file = |name: &str| dir.path().join(name).to_str().unwrap().to_owned();
    let args = [
        "--tls-cert",
        &file("tls.crt"),
        "--tls-key",
        &file("tls.key"),
        "--tls-ca",
        &file("ca.crt"),
    ];
    let op = gateway_operator(ControlPlane::shared(), ns, "gw-join", &args).await?;
    Ok((op, dir))
}

fn mode(path: &Path) -> u32 {
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

#[tokio::test]
async fn a_robot_joins_with_one_command_and_a_second_run_changes_nothing() -> Result<()> {
    let client = ControlPlane::shared().client().await?;
    let ns = namespace(&client, "join").await?;
    let (op, ca_dir) = tls_operator(&ns).await?;
    let pin = openssl_pin(&ca_dir.path().join("ca.crt"))?;
    let token = enrollment_token(&client, &ns).await?;
    let gateway = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);

    // The lab's own configuration, which join must leave as it is.
    let root = tempfile::tempdir()?;
    let status_port = free_port();
    let lab = format!("statusListen: 127.0.0.1:{status_port}\nteleopIntervalS: 0.5\n");
    std::fs::create_dir_all(root.path().join("etc/lekiwi"))?;
    std::fs::write(root.path().join("etc/lekiwi/agent.yaml"), &lab)?;

    let robot = format!("{ns}/kiwi-join");
    let args = [
        "--gateway",
        &gateway,
        "--ca-cert-hash",
        &pin,
        "--token",
        &token,
        "--name",
        &robot,
        "--wait-s",
        "30",
    ];
    let joining = spawn_join(root.path(), args.iter().map(|s| s.to_string()).collect());
    let drop_in = drop_in_written(root.path()).await?;
    // The agent as its unit starts it: the lab's file and the drop-ins beside it.
    let agent = AgentProcess::from_config(
        &root.path().join("etc/lekiwi/agent.yaml"),
        &root.path().join("var/lib/lekiwi"),
        status_port,
    )?;
    let out = joining.await??;
    let said = text(&out);
    assert!(
        out.status.success(),
        "{said}\nagent log:\n{}",
        agent.log_text()
    );
    assert!(
        said.contains(&format!("robot {robot} joined: Online")),
        "{said}"
    );
    let phase = get_robot(&client, &ns, "kiwi-join").await?.status;
    assert_eq!(phase.and_then(|s| s.phase), Some(RobotPhase::Online));

    // Files: the lab's untouched, the CA public, the token private, the drop-in naming them.
    let etc = root.path().join("etc/lekiwi");
    assert_eq!(std::fs::read_to_string(etc.join("agent.yaml"))?, lab);
    assert_eq!(mode(&etc.join("ca.crt")), 0o644);
    assert_eq!(openssl_pin(&etc.join("ca.crt"))?, pin);
    assert_eq!(mode(&etc.join("enrollment-token")), 0o600);
    let written = std::fs::read_to_string(&drop_in)?;
    assert!(
        written.contains(&format!("gateway: {gateway}")),
        "{written}"
    );
    assert!(
        written.contains(&format!("robotName: {robot}")),
        "{written}"
    );

    // Twice: nothing written, the agent still connected.
    let out = join(root.path(), &args).await?;
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    assert!(!said.contains("wrote"), "{said}");
    assert_eq!(said.matches("unchanged").count(), 3, "{said}");
    assert!(said.contains("joined: Online"), "{said}");

    // Another gateway (another address of the same one, here): refused, saying what it replaces.
    let other = format!("wss://localhost:{}/v1/agent", op.gateway_port);
    let mut moved = args.to_vec();
    moved[1] = &other;
    let out = join(root.path(), &moved).await?;
    let said = text(&out);
    assert!(!out.status.success(), "{said}");
    assert!(
        said.contains(&gateway) && said.contains(&other) && said.contains("--force"),
        "{said}"
    );
    assert!(said.contains("/etc/lekiwi/agent.d/50-join.yaml"), "{said}");
    assert_eq!(std::fs::read_to_string(&drop_in)?, written);
    Ok(())
}

/// A gateway that answers late (connection refused: a Service whose endpoint is not up yet) is
/// tried again within `--wait-s`: join started 2 s before anything listens on its port (then a
/// forwarder to the gateway) still checks the pin and writes its files.
#[tokio::test]
async fn a_gateway_that_answers_late_is_tried_again() -> Result<()> {
    let client = ControlPlane::shared().client().await?;
    let ns = namespace(&client, "join-late").await?;
    let (op, ca_dir) = tls_operator(&ns).await?;
    let pin = openssl_pin(&ca_dir.path().join("ca.crt"))?;
    let token = enrollment_token(&client, &ns).await?;
    let port = free_port();
    let gateway = format!("wss://127.0.0.1:{port}/v1/agent");
    let root = tempfile::tempdir()?;
    // No status endpoint: join returns once its files are written.
    std::fs::create_dir_all(root.path().join("etc/lekiwi"))?;
    std::fs::write(
        root.path().join("etc/lekiwi/agent.yaml"),
        "statusListen: \"off\"\n",
    )?;
    let robot = format!("{ns}/kiwi-late");
    let args: Vec<String> = [
        "--gateway",
        &gateway,
        "--ca-cert-hash",
        &pin,
        "--token",
        &token,
        "--name",
        &robot,
        "--wait-s",
        "30",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let joining = spawn_join(root.path(), args);
    tokio::time::sleep(Duration::from_secs(2)).await;
    let listener = tokio::net::TcpListener::bind(("127.0.0.1", port)).await?;
    let to = op.gateway_port;
    tokio::spawn(async move {
        while let Ok((mut inbound, _)) = listener.accept().await {
            let Ok(mut outbound) = tokio::net::TcpStream::connect(("127.0.0.1", to)).await else {
                continue;
            };
            tokio::spawn(async move {
                let _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await;
            });
        }
    });
    let out = joining.await??;
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    assert!(
        said.contains("Connection refused") && said.contains("trying again"),
        "{said}"
    );
    assert!(said.contains(&format!("presents the CA {pin}")), "{said}");
    assert!(
        root.path().join("etc/lekiwi/agent.d/50-join.yaml").exists(),
        "{said}"
    );
    Ok(())
}

#[tokio::test]
async fn a_wrong_pin_is_refused_with_both_fingerprints_and_writes_nothing() -> Result<()> {
    let client = ControlPlane::shared().client().await?;
    let ns = namespace(&client, "join-pin").await?;
    let (op, ca_dir) = tls_operator(&ns).await?;
    let real = openssl_pin(&ca_dir.path().join("ca.crt"))?;
    let wrong = format!("sha256:{}", "ab".repeat(32));
    let gateway = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);
    let root = tempfile::tempdir()?;
    let args = [
        "--gateway",
        &gateway,
        "--ca-cert-hash",
        &wrong,
        "--token",
        "lke_whatever",
    ];
    let out = join(root.path(), &args).await?;
    let said = text(&out);
    assert!(!out.status.success(), "{said}");
    assert!(said.contains(&wrong) && said.contains(&real), "{said}");
    assert!(
        std::fs::read_dir(root.path())?.next().is_none(),
        "a refused join wrote files"
    );
    Ok(())
}

/// Someone else at the gateway's address: a certificate for the same name from another CA.
#[tokio::test]
async fn a_man_in_the_middle_with_another_ca_is_refused_with_both_fingerprints() -> Result<()> {
    let real = tempfile::tempdir()?;
    test_ca(real.path())?;
    let real_pin = openssl_pin(&real.path().join("ca.crt"))?;
    let evil = tempfile::tempdir()?;
    test_ca(evil.path())?;
    let evil_pin = openssl_pin(&evil.path().join("ca.crt"))?;
    assert_ne!(real_pin, evil_pin);

    let port = free_port();
    let f = |name: &str| evil.path().join(name).to_str().unwrap().to_owned();
    let mut server = tokio::process::Command::new("openssl")
        .args([
            "s_server",
            "-quiet",
            "-accept",
            &format!("127.0.0.1:{port}"),
        ])
        .args(["-cert", &f("tls.crt"), "-key", &f("tls.key")])
        .args(["-cert_chain", &f("ca.crt")])
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .kill_on_drop(true)
        .spawn()?;
    wait_for("the impostor listens", Duration::from_secs(10), || async {
        tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .ok()
            .map(|_| ())
    })
    .await?;
    let root = tempfile::tempdir()?;
    let gateway = format!("wss://127.0.0.1:{port}/v1/agent");
    let args = [
        "--gateway",
        &gateway,
        "--ca-cert-hash",
        &real_pin,
        "--token",
        "lke_whatever",
    ];
    let out = join(root.path(), &args).await?;
    let said = text(&out);
    server.kill().await?;
    assert!(!out.status.success(), "{said}");
    assert!(
        said.contains(&real_pin) && said.contains(&evil_pin),
        "{said}"
    );
    assert!(said.contains("answers in its place"), "{said}");
    assert!(std::fs::read_dir(root.path())?.next().is_none());
    Ok(())
}

/// The chart's gateway objects as the plugin finds them: a Service labelled as the gateway with
/// a port named `gateway`, and the CA ConfigMap.
async fn chart_objects(client: &kube::Client, ns: &str, ca: &Path, port: u16) -> Result<()> {
    use k8s_openapi::api::core::v1::{ConfigMap, Service};
    use kube::api::PostParams;
    let labels = serde_json::json!({ "app.kubernetes.io/component": "gateway" });
    let svc: Service = serde_json::from_value(serde_json::json!({
        "metadata": { "name": "lekiwi-operator-gateway", "labels": labels },
        "spec": { "ports": [{ "name": "gateway", "port": port }] }
    }))?;
    kube::Api::<Service>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &svc)
        .await?;
    let map: ConfigMap = serde_json::from_value(serde_json::json!({
        "metadata": { "name": "lekiwi-operator-gateway-ca", "labels": labels },
        "data": { "ca.crt": std::fs::read_to_string(ca)? }
    }))?;
    kube::Api::<ConfigMap>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &map)
        .await?;
    Ok(())
}

/// `kubectl lekiwi robot add` prints the join command (the pin from the cluster's CA
/// ConfigMap); run on the robot as printed, it adopts the robot's own token and goes Online.
#[tokio::test]
async fn the_join_command_robot_add_prints_joins_the_robot() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "join-add").await?;
    let (op, ca_dir) = tls_operator(&ns).await?;
    chart_objects(&client, &ns, &ca_dir.path().join("ca.crt"), op.gateway_port).await?;
    let gateway = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);
    let out = tokio::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args([
            "-n",
            &ns,
            "--gateway-namespace",
            &ns,
            "robot",
            "add",
            "kiwi-add",
        ])
        .args(["--gateway", &gateway])
        .env_remove("LEKIWI_SERVER")
        .output()
        .await?;
    let said = text(&out);
    assert!(out.status.success(), "{said}");
    let line = String::from_utf8(out.stdout)?;
    assert_eq!(line.lines().count(), 1, "{line}");
    let pin = openssl_pin(&ca_dir.path().join("ca.crt"))?;
    assert!(line.contains(&format!("--ca-cert-hash {pin}")), "{line}");
    let words: Vec<&str> = line.split_whitespace().collect();
    assert_eq!(words[..3], ["sudo", "lekiwi-agent", "join"], "{line}");

    let root = tempfile::tempdir()?;
    let status_port = free_port();
    std::fs::create_dir_all(root.path().join("etc/lekiwi"))?;
    std::fs::write(
        root.path().join("etc/lekiwi/agent.yaml"),
        format!("statusListen: 127.0.0.1:{status_port}\n"),
    )?;
    let mut args: Vec<String> = words[3..].iter().map(|s| s.to_string()).collect();
    args.extend(["--wait-s".to_owned(), "30".to_owned()]);
    let joining = spawn_join(root.path(), args);
    drop_in_written(root.path()).await?;
    let state = root.path().join("var/lib/lekiwi");
    assert_eq!(mode(&state.join("credentials.json")), 0o600);
    assert!(!root.path().join("etc/lekiwi/enrollment-token").exists());
    let agent = AgentProcess::from_config(
        &root.path().join("etc/lekiwi/agent.yaml"),
        &state,
        status_port,
    )?;
    let out = joining.await??;
    let said = text(&out);
    assert!(
        out.status.success(),
        "{said}\nagent log:\n{}",
        agent.log_text()
    );
    assert!(
        said.contains(&format!("robot {ns}/kiwi-add joined: Online")),
        "{said}"
    );
    Ok(())
}

/// Every file under /etc/lekiwi that the README, NOTES, the `.deb`'s config, the robot pages of
/// the book and `--help` name is one the agent reads, by the one name `lekiwi_protocol::join`
/// gives it.
#[test]
fn every_page_names_the_agents_files_by_one_path() -> Result<()> {
    use lekiwi_protocol::join::{CA_FILE, CONFIG_FILE, DROP_IN_DIR, ENROLLMENT_TOKEN_FILE};
    let allowed = [
        CONFIG_FILE.to_owned(),
        DROP_IN_DIR.to_owned(),
        format!("{DROP_IN_DIR}/"),
        format!("{DROP_IN_DIR}/*.yaml"),
        lekiwi_protocol::join::JOIN_DROP_IN.to_owned(),
        CA_FILE.to_owned(),
        ENROLLMENT_TOKEN_FILE.to_owned(),
    ];
    let root = lekiwi_tests::repo_root();
    let mut texts: Vec<(String, String)> = [
        "README.md",
        "charts/lekiwi-operator/templates/NOTES.txt",
        "agent/debian/agent.yaml",
        "scripts/deb.sh",
        "docs/src/robots/index.md",
        "docs/src/robots/install.md",
        "docs/src/robots/joining.md",
        "docs/src/robots/agent.md",
        "docs/src/install/helm.md",
    ]
    .iter()
    .map(|p| Ok((p.to_string(), std::fs::read_to_string(root.join(p))?)))
    .collect::<Result<_>>()?;
    for args in [&["--help"][..], &["join", "--help"]] {
        let out = std::process::Command::new(bin("lekiwi-agent"))
            .args(args)
            .output()?;
        texts.push((
            format!("lekiwi-agent {args:?}"),
            String::from_utf8(out.stdout)?,
        ));
    }
    for (name, text) in texts {
        for (at, _) in text.match_indices("/etc/lekiwi/") {
            let path: String = text[at..]
                .chars()
                .take_while(|c| !c.is_whitespace() && !"`'\"),;:]".contains(*c))
                .collect();
            let path = path.trim_end_matches('.');
            assert!(
                allowed.iter().any(|a| a == path),
                "{name} names {path}, not one of {allowed:?}"
            );
        }
    }
    Ok(())
}
