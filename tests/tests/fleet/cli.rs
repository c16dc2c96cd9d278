//! `kubectl lekiwi` as a user runs it, against the shared control plane and a real operator:
//! `robot add` credentials that a real agent connects with, an `enroll-token` a real agent
//! enrolls with, `events` from the event store, and `discover` finding real agents by probe
//! and by mDNS in under two seconds, registered or not, with or without a cluster; `robots
//! --group-by` counting a mixed fleet by agent version.

use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use lekiwi_crds::RobotPhase;
use lekiwi_tests::{
    AgentProcess, ControlPlane, OperatorProcess, bin, gateway_url, get_robot, namespace, wait_for,
};
use serde_json::Value;

const T: Duration = Duration::from_secs(30);

/// A real agent as [`AgentProcess`] starts one, but advertising over mDNS: `AgentProcess`
/// passes `--mdns false`, and the agent's flags cannot be given twice.
struct AdvertisingAgent {
    child: std::process::Child,
    status_port: u16,
    log: std::path::PathBuf,
}

impl AdvertisingAgent {
    fn start(gateway: &str, robot: &str, enrollment: &Path, state: &Path) -> Result<Self> {
        let status_port = lekiwi_tests::free_port();
        let log =
            lekiwi_tests::log_dir().join(format!("cli-agent-{}.log", robot.replace('/', "_")));
        let file = std::fs::File::create(&log)?;
        let child = Command::new(bin("lekiwi-agent"))
            .args([
                "--config",
                "/nonexistent/lekiwi-agent.yaml",
                "--gateway",
                gateway,
            ])
            .args(["--robot-name", robot, "--enrollment-token-file"])
            .arg(enrollment)
            .arg("--state-dir")
            .arg(state)
            .args(["--status-listen", &format!("127.0.0.1:{status_port}")])
            .args([
                "--mdns",
                "true",
                "--backoff-initial-ms",
                "200",
                "--backoff-max-ms",
                "2000",
            ])
            .args(["--log-format", "json"])
            .stdin(std::process::Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .context("spawn lekiwi-agent")?;
        Ok(Self {
            child,
            status_port,
            log,
        })
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for AdvertisingAgent {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs the plugin against the shared control plane.
fn plugin(cp: &ControlPlane, args: &[&str]) -> Result<Output> {
    plugin_with(&cp.kubeconfig(), args)
}

fn plugin_with(kubeconfig: &Path, args: &[&str]) -> Result<Output> {
    Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(kubeconfig)
        .args(args)
        .env_remove("LEKIWI_SERVER")
        .env_remove("LEKIWI_GATEWAY_URL")
        .output()
        .context("run kubectl-lekiwi")
}

/// Runs the plugin, requires success and returns stdout.
fn ok(cp: &ControlPlane, args: &[&str]) -> Result<String> {
    let out = plugin(cp, args)?;
    ensure!(
        out.status.success(),
        "kubectl-lekiwi {args:?} failed: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
    Ok(String::from_utf8(out.stdout)?)
}

async fn online(client: &kube::Client, ns: &str, name: &str) -> bool {
    get_robot(client, ns, name)
        .await
        .ok()
        .and_then(|r| r.status?.phase)
        == Some(RobotPhase::Online)
}

/// `discover -o json` with its wall-clock time.
fn discover(kubeconfig: &Path, args: &[&str]) -> Result<(Vec<Value>, Duration, String)> {
    let mut all = vec!["discover", "-o", "json"];
    all.extend(args);
    let start = Instant::now();
    let out = plugin_with(kubeconfig, &all)?;
    let took = start.elapsed();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    ensure!(out.status.success(), "discover {args:?} failed: {stderr}");
    let found: Vec<Value> = lekiwi_tests::list_items(&out.stdout)?;
    Ok((found, took, stderr))
}

fn entries<'a>(found: &'a [Value], robot: &str) -> Vec<&'a Value> {
    found.iter().filter(|f| f["robot"] == robot).collect()
}

#[test]
fn every_command_has_help_with_the_kubectl_flags() -> Result<()> {
    for cmd in [
        &["robots"][..],
        &["robot", "add"],
        &["enroll-token"],
        &["discover"],
        &["events"],
        &["release", "push"],
        &["rollout", "status"],
    ] {
        let out = Command::new(bin("kubectl-lekiwi"))
            .args(cmd)
            .arg("--help")
            .output()?;
        let text = String::from_utf8_lossy(&out.stdout);
        ensure!(out.status.success(), "{cmd:?} --help failed");
        for flag in [
            "--kubeconfig",
            "--context",
            "--namespace",
            "--all-namespaces",
            "--output",
        ] {
            ensure!(text.contains(flag), "{cmd:?} --help lacks {flag}:\n{text}");
        }
    }
    Ok(())
}

#[tokio::test]
async fn robot_add_events_and_discover_with_a_real_agent() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "cliadd").await?;
    let mut op = OperatorProcess::start(cp, &ns, "cliadd", &[])?;
    op.wait_ready().await?;
    let gateway = gateway_url(&op);

    // robot add: the Robot, its token Secret, and the agent's configuration.
    let out = ok(
        cp,
        &[
            "-n",
            &ns,
            "-o",
            "json",
            "robot",
            "add",
            "kiwi-r",
            "--display-name",
            "Kiwi R",
            "--label",
            "fleet.lekiwi.io/group=cli",
            "--gateway",
            &gateway,
        ],
    )?;
    let setup: Value = serde_json::from_str(&out)?;
    let robot = format!("{ns}/kiwi-r");
    assert_eq!(setup["robot"], robot.as_str());
    assert_eq!(setup["gateway"], gateway.as_str());
    let token = setup["token"].as_str().context("no token")?.to_owned();
    let join = setup["joinCommand"].as_str().context("no join command")?;
    assert!(
        join.contains(&format!("--token {token}")) && join.contains(&format!("--name {robot}")),
        "{join}"
    );
    let created = get_robot(&client, &ns, "kiwi-r").await?;
    assert_eq!(created.spec.display_name.as_deref(), Some("Kiwi R"));
    assert_eq!(
        created.metadata.labels.unwrap_or_default()["fleet.lekiwi.io/group"],
        "cli"
    );
    let secret = Api::<Secret>::namespaced(client.clone(), &ns)
        .get("kiwi-r-agent-token")
        .await?;
    let stored = String::from_utf8(secret.data.unwrap_or_default()["sha256"].0.clone())?;
    assert!(!stored.contains(&token), "only the hash is stored");

    // Adding it again is refused unless the token is to be rotated.
    let again = plugin(cp, &["-n", &ns, "robot", "add", "kiwi-r"])?;
    assert!(!again.status.success());
    let msg = String::from_utf8_lossy(&again.stderr);
    assert!(
        msg.contains("already exists") && msg.contains("--rotate-token"),
        "{msg}"
    );

    // The table output is the join command.
    let out = ok(
        cp,
        &[
            "-n",
            &ns,
            "robot",
            "add",
            "kiwi-r",
            "--rotate-token",
            "--gateway",
            &gateway,
        ],
    )?;
    assert!(
        out.starts_with("sudo lekiwi-agent join --gateway ") && out.lines().count() == 1,
        "{out}"
    );
    let words: Vec<&str> = out.split_whitespace().collect();
    let after = |flag: &str| {
        words
            .iter()
            .position(|w| *w == flag)
            .and_then(|i| words.get(i + 1))
            .copied()
    };
    assert_eq!(after("--name"), Some(robot.as_str()), "{out}");
    let new_token = after("--token").context("no --token")?;
    assert_ne!(new_token, token.as_str(), "a new token");
    let rotated = serde_json::json!({ "robot": robot, "token": new_token }).to_string();

    // A real agent with the printed credentials and a wrong enrollment token: only the robot
    // token can get it Online.
    let dir = tempfile::tempdir()?;
    let state = dir.path().join("state");
    std::fs::create_dir(&state)?;
    std::fs::set_permissions(&state, std::fs::Permissions::from_mode(0o700))?;
    std::fs::write(state.join("credentials.json"), rotated)?;
    std::fs::set_permissions(
        state.join("credentials.json"),
        std::fs::Permissions::from_mode(0o600),
    )?;
    let wrong = dir.path().join("wrong-enrollment");
    std::fs::write(&wrong, "lke_not-a-valid-token")?;
    let agent = AdvertisingAgent::start(&gateway, &robot, &wrong, &state)?;
    wait_for("the robot Online with its own token", T, || async {
        online(&client, &ns, "kiwi-r").await.then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;

    // events: what the agent produced, from the event store.
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let events_args = [
        "-n", &ns, "-o", "json", "events", "kiwi-r", "--server", &server,
    ];
    let events: Vec<Value> = wait_for("agent_started in the event store", T, || async {
        let out = ok(cp, &events_args).ok()?;
        let events: Vec<Value> = lekiwi_tests::list_items(&out).ok()?;
        events
            .iter()
            .any(|e| e["kind"] == "agent_started")
            .then_some(events)
    })
    .await?;
    assert!(
        events
            .iter()
            .all(|e| e["seq"].is_u64() && e["ts_ms"].is_i64())
    );
    let table = ok(
        cp,
        &[
            "-n",
            &ns,
            "events",
            &robot,
            "--kind",
            "agent_started",
            "--since",
            "10m",
            "--server",
            &server,
        ],
    )?;
    assert!(
        table.starts_with("SEQ") && table.contains("agent_started"),
        "{table}"
    );
    let none = ok(
        cp,
        &[
            "-n",
            &ns,
            "events",
            "kiwi-r",
            "--kind",
            "no_such_kind",
            "--server",
            &server,
        ],
    )?;
    assert_eq!(none, "No events found.\n");
    // events -w: the list, then each event as it is stored.
    let mut watch = Command::new(bin("kubectl-lekiwi"))
        .arg("--kubeconfig")
        .arg(cp.kubeconfig())
        .args([
            "-n", &ns, "-o", "json", "events", "kiwi-r", "-w", "--server", &server,
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()?;
    let printed = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let reader = {
        let printed = printed.clone();
        let mut stdout = watch.stdout.take().context("no stdout")?;
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n @ 1..) = std::io::Read::read(&mut stdout, &mut buf) {
                printed
                    .lock()
                    .unwrap()
                    .push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        })
    };
    let queued = Command::new(bin("lekiwi-agent"))
        .args(["--config", "/nonexistent/lekiwi-agent.yaml"])
        .arg("--state-dir")
        .arg(&state)
        .args(["event", "--kind", "watched_note", "--message", "seen live"])
        .output()?;
    assert!(queued.status.success(), "{queued:?}");
    let seen = wait_for("events -w printing the new event", T, || async {
        let text = printed.lock().unwrap().clone();
        text.contains("\"watched_note\"").then_some(text)
    })
    .await;
    watch.kill()?;
    watch.wait()?;
    reader.join().ok();
    let seen = seen?;
    assert_eq!(
        seen.matches("\"watched_note\"").count(),
        1,
        "printed once: {seen}"
    );
    // A robot that does not exist is said so, not shown as one without events.
    let missing = plugin(
        cp,
        &["-n", &ns, "events", "kiwi-nobody", "--server", &server],
    )?;
    let err = String::from_utf8_lossy(&missing.stderr);
    assert!(
        !missing.status.success() && err.contains(&format!("robot {ns}/kiwi-nobody not found")),
        "{err}"
    );
    // The endpoint wants the API token.
    let (code, _, _) = lekiwi_tests::http_get_with(
        op.gateway_port,
        &format!("/v1/robots/{ns}/kiwi-r/events"),
        &[("Authorization", "Bearer wrong")],
    )
    .await?;
    assert_eq!(code, 401);

    // An agent nobody registered, reachable by probe only.
    let ghost_state = dir.path().join("ghost");
    let ghost_robot = format!("{ns}/ghost");
    let ghost = AgentProcess::start(&gateway, &ghost_robot, &wrong, &ghost_state, &[])?;
    wait_for("the ghost's status endpoint", T, || async {
        ghost.status().await.ok()
    })
    .await?;

    // discover by probe: both found, the registered one marked so, within 2 s.
    let port = agent.status_port.to_string();
    let ghost_probe = format!("127.0.0.1:{}", ghost.status_port);
    let (found, took, stderr) = discover(
        &cp.kubeconfig(),
        &[
            "--probe",
            "127.0.0.1/32",
            "--port",
            &port,
            "--probe",
            &ghost_probe,
        ],
    )?;
    eprintln!("discover --probe took {took:?}; stderr: {stderr}");
    let mine = entries(&found, &robot);
    assert_eq!(mine.len(), 1, "{found:?}");
    assert_eq!(mine[0]["registered"], true);
    assert!(mine[0]["via"].as_array().unwrap().contains(&"probe".into()));
    assert_eq!(mine[0]["connected"], true);
    let theirs = entries(&found, &ghost_robot);
    assert_eq!(theirs.len(), 1, "{found:?}");
    assert_eq!(theirs[0]["registered"], false);
    assert!(took < Duration::from_secs(2), "discover took {took:?}");

    // discover by mDNS (the agent advertises), merged with the probe into one entry.
    let (found, took, stderr) = wait_for("the agent found by mDNS", T, || async {
        let (found, took, stderr) = discover(
            &cp.kubeconfig(),
            &["--probe", "127.0.0.1/32", "--port", &port],
        )
        .ok()?;
        let mine = entries(&found, &robot);
        (mine.len() == 1 && mine[0]["via"] == serde_json::json!(["mdns", "probe"]))
            .then_some((found, took, stderr))
    })
    .await?;
    eprintln!("discover with mDNS and probe took {took:?}; stderr: {stderr}");
    assert_eq!(entries(&found, &robot)[0]["registered"], true);
    assert!(took < Duration::from_secs(2), "discover took {took:?}");

    // -n narrows to one namespace; the table marks registration.
    let out = ok(
        cp,
        &[
            "-n",
            "elsewhere",
            "discover",
            "--no-mdns",
            "--probe",
            "127.0.0.1/32",
            "--port",
            &port,
        ],
    )?;
    assert_eq!(out, "No agents found.\n");
    let out = ok(
        cp,
        &[
            "-n",
            &ns,
            "discover",
            "--probe",
            "127.0.0.1/32",
            "--port",
            &port,
            "--no-mdns",
        ],
    )?;
    let line = out
        .lines()
        .find(|l| l.contains("kiwi-r"))
        .context("no row")?;
    assert_eq!(
        line.split_whitespace().collect::<Vec<_>>(),
        [
            ns.as_str(),
            "kiwi-r",
            "yes",
            &format!("127.0.0.1:{port}"),
            "probe"
        ]
    );

    // Without a reachable cluster it still lists, says so, and keeps to the time.
    let unreachable = dir.path().join("unreachable-kubeconfig");
    std::fs::write(
        &unreachable,
        "apiVersion: v1\nkind: Config\nclusters:\n- name: x\n  cluster: {server: 'https://127.0.0.1:1'}\n\
         contexts:\n- name: x\n  context: {cluster: x, user: x}\ncurrent-context: x\nusers:\n- name: x\n  user: {token: t}\n",
    )?;
    let (found, took, stderr) = discover(
        &unreachable,
        &["--no-mdns", "--probe", "127.0.0.1/32", "--port", &port],
    )?;
    assert_eq!(
        entries(&found, &robot)[0]["registered"],
        Value::Null,
        "{found:?}"
    );
    assert!(stderr.contains("REGISTERED is unknown"), "{stderr}");
    assert!(took < Duration::from_secs(2), "discover took {took:?}");
    drop(ghost);
    drop(agent);
    Ok(())
}

#[tokio::test]
async fn enroll_token_lets_a_real_agent_enroll() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "clienroll").await?;
    let mut op = OperatorProcess::start(cp, &ns, "clienroll", &[])?;
    op.wait_ready().await?;

    let out = ok(cp, &["-n", &ns, "enroll-token"])?;
    let token = out.trim().to_owned();
    assert!(
        token.starts_with("lke_") && !token.contains('\n'),
        "{out:?}"
    );
    // It is shown once: asking again without --rotate is an error, --rotate replaces it.
    let again = plugin(cp, &["-n", &ns, "enroll-token"])?;
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("--rotate"));
    let rotated: Value = serde_json::from_str(&ok(
        cp,
        &["-n", &ns, "-o", "json", "enroll-token", "--rotate"],
    )?)?;
    let token2 = rotated["token"].as_str().context("no token")?.to_owned();
    assert_ne!(token, token2);
    assert_eq!(rotated["secret"], "fleet-enrollment");
    let join = rotated["joinCommand"].as_str().context("no join command")?;
    assert!(join.contains(&format!("--token {token2}")), "{join}");

    let dir = tempfile::tempdir()?;
    let file = dir.path().join("enroll");
    std::fs::write(&file, &token2)?;
    let state = dir.path().join("state");
    let agent = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/kiwi-e"),
        &file,
        &state,
        &[],
    )?;
    wait_for("the enrolled robot Online", T, || async {
        online(&client, &ns, "kiwi-e").await.then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;
    // The gateway may show the robot Online before the agent has saved (and fsynced) the token
    // its `welcome` carried.
    let credentials = state.join("credentials.json");
    wait_for("the agent's saved credentials", T, || async {
        credentials.exists().then_some(())
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", agent.log_text()))?;
    Ok(())
}

/// `robots --group-by`: a mixed fleet counted by the agent version it runs (from status) and
/// the one its spec asks for, as a table and as JSON, read from the real API server.
#[tokio::test]
async fn robots_group_by_agent_version() -> Result<()> {
    use kube::api::{Patch, PatchParams};
    use lekiwi_crds::Robot;
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "cligroup").await?;
    let api = Api::<Robot>::namespaced(client.clone(), &ns);
    let digest = format!("sha256:{}", "b".repeat(64));
    for (name, phase, agent) in [
        ("kiwi-1", "Online", Some("0.2.0")),
        ("kiwi-2", "Offline", Some("0.1.0")),
        ("kiwi-3", "Online", Some("0.2.0")),
        ("kiwi-4", "Online", None),
    ] {
        lekiwi_tests::create_robot(&client, &ns, name, &[]).await?;
        let status = serde_json::json!({"status": {"phase": phase, "agentVersion": agent}});
        api.patch_status(name, &PatchParams::default(), &Patch::Merge(&status))
            .await?;
    }
    let spec = serde_json::json!({"spec": {"agent": {"version": "0.2.0",
        "builds": [{"arch": "amd64", "digest": digest}]}}});
    api.patch("kiwi-2", &PatchParams::default(), &Patch::Merge(&spec))
        .await?;

    let table = ok(cp, &["-n", &ns, "robots", "--group-by", "agent"])?;
    let rows: Vec<Vec<&str>> = table
        .lines()
        .map(|l| l.split_whitespace().collect())
        .collect();
    ensure!(
        rows == [
            vec!["AGENT", "ROBOTS", "ONLINE", "NAMES"],
            vec!["0.1.0", "1", "0", "kiwi-2"],
            vec!["0.2.0", "2", "2", "kiwi-1,kiwi-3"],
            vec!["-", "1", "1", "kiwi-4"],
        ],
        "{table}"
    );
    let json = ok(
        cp,
        &[
            "-n",
            &ns,
            "-o",
            "json",
            "robots",
            "--group-by",
            "desired-agent",
        ],
    )?;
    let groups: Value = lekiwi_tests::list_items::<Value>(&json)?.into();
    ensure!(
        groups
            == serde_json::json!([
                {"value": "0.2.0", "robots": 1, "online": 0, "names": ["kiwi-2"]},
                {"value": "-", "robots": 3, "online": 3, "names": ["kiwi-1", "kiwi-3", "kiwi-4"]},
            ]),
        "{json}"
    );
    Ok(())
}
