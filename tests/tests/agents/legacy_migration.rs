//! A robot on the legacy polling endpoint moves to the agent (issue 19). The test plays an old
//! poller written only from PROTOCOL.md §14 and §15: it polls with the robot's token, downloads
//! the release its Robot names, checks every file's digest and runs the release's
//! `migrate-to-agent.sh` (the script users ship, `manifests/legacy/`), which installs the agent
//! from the release, hands it the robot's token (`lekiwi-agent adopt`) and starts it. The robot
//! keeps its name, token and Secret, never leaves `Online`, and then runs the release through
//! the agent. A migration given an enrollment token is refused and starts nothing.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, Result, bail, ensure};
use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use lekiwi_crds::{RobotPhase, RobotStatus};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, bin, free_port, get_robot, http_request, log_dir, namespace,
    repo_root, wait_for,
};
use serde_json::{Value, json};
use sha2::{Digest, Sha256};

/// The old poller: one robot's name and token, and the gateway's port.
struct Poller {
    port: u16,
    robot: String,
    token: String,
}

impl Poller {
    fn headers(&self) -> Vec<(&str, String)> {
        vec![
            ("authorization", format!("Bearer {}", self.token)),
            ("x-lekiwi-robot", self.robot.clone()),
        ]
    }

    async fn get(&self, path: &str) -> Result<(u16, Vec<u8>)> {
        let owned = self.headers();
        let headers: Vec<(&str, &str)> = owned.iter().map(|(k, v)| (*k, v.as_str())).collect();
        let (code, _, body) = http_request(self.port, "GET", path, &headers, None).await?;
        Ok((code, body))
    }

    /// `GET /v1/poll` (§14) as a robot running `version`.
    async fn poll(&self, version: &str) -> Result<Value> {
        let path = format!(
            "/v1/poll?robot={}&version={version}&agent=legacy-0.9",
            self.robot
        );
        let (code, body) = self.get(&path).await?;
        ensure!(
            code == 200,
            "poll: {code} {}",
            String::from_utf8_lossy(&body)
        );
        Ok(serde_json::from_slice(&body)?)
    }

    /// Downloads the release at `manifest_url` into `dir` (§15): every file checked against its
    /// digest and given its mode.
    async fn download(&self, manifest_url: &str, dir: &Path) -> Result<usize> {
        let (code, manifest) = self.get(manifest_url).await?;
        ensure!(code == 200, "manifest: {code}");
        let manifest: Value = serde_json::from_slice(&manifest)?;
        let files = manifest["files"].as_array().context("manifest files")?;
        for file in files {
            let rel = file["path"].as_str().context("path")?;
            ensure!(
                !rel.split('/').any(|p| p == ".." || p.is_empty()),
                "bad path {rel}"
            );
            let digest = file["digest"].as_str().context("digest")?;
            let (code, bytes) = self.get(&format!("/v1/blobs/{digest}")).await?;
            ensure!(code == 200, "blob {rel}: {code}");
            let got = format!("sha256:{}", hex::encode(Sha256::digest(&bytes)));
            ensure!(got == digest, "{rel}: digest {got}, manifest says {digest}");
            let path = dir.join(rel);
            std::fs::create_dir_all(path.parent().unwrap())?;
            std::fs::write(&path, &bytes)?;
            let mode = file["mode"].as_u64().context("mode")? as u32;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode))?;
        }
        Ok(files.len())
    }
}

/// Kills the agent the migration started (its pid file) when the test ends.
struct Started(PathBuf);

impl Drop for Started {
    fn drop(&mut self) {
        if let Ok(pid) = std::fs::read_to_string(&self.0) {
            let _ = std::process::Command::new("kill")
                .args(["-9", pid.trim()])
                .status();
        }
    }
}

/// The migration release: the robot's software, plus the script and this machine's agent.
fn migration_release(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir.join("app"))?;
    std::fs::create_dir_all(dir.join("lekiwi-migrate"))?;
    std::fs::write(dir.join("app/lekiwi_host.py"), "print('lekiwi host 2.0')\n")?;
    let script = dir.join("lekiwi-migrate/migrate-to-agent.sh");
    std::fs::copy(
        repo_root().join("manifests/legacy/migrate-to-agent.sh"),
        &script,
    )?;
    let agent = dir.join(format!(
        "lekiwi-migrate/lekiwi-agent-{}",
        std::env::consts::ARCH
    ));
    std::fs::copy(bin("lekiwi-agent"), &agent)?;
    for exe in [&script, &agent] {
        std::fs::set_permissions(exe, std::fs::Permissions::from_mode(0o755))?;
    }
    Ok(())
}

/// Runs the downloaded release's script the way the old poller runs an install step: root of
/// the robot under `robot_root`, the agent started in the background by `start`.
fn migrate(release: &Path, robot_root: &Path, env: &[(&str, String)]) -> Result<(bool, String)> {
    let out = std::process::Command::new("sh")
        .arg(release.join("lekiwi-migrate/migrate-to-agent.sh"))
        .env("LEKIWI_CONFIG", robot_root.join("etc/lekiwi/agent.yaml"))
        .env("LEKIWI_STATE_DIR", robot_root.join("var/lib/lekiwi"))
        .env("LEKIWI_BIN_DIR", robot_root.join("usr/local/bin"))
        .envs(env.iter().map(|(k, v)| (k, v)))
        .output()?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    Ok((out.status.success(), text))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_polling_robot_moves_to_the_agent_and_keeps_its_identity() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "legacy").await?;
    let blobs = tempfile::tempdir()?;
    let blob_dir = blobs.path().to_str().unwrap();
    // The grace must exceed the status refresh (as `--help` says): with the default refresh
    // (300 s) a grace of 60 s let the Robot controller mark the polling robot Offline whenever
    // the wait for the offer below took a minute (a CI failure, twice).
    let args = [
        "--blob-dir",
        blob_dir,
        "--heartbeat-grace-seconds",
        "60",
        "--status-refresh-seconds",
        "15",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "gw-legacy", &args)?;
    op.wait_ready().await?;
    lekiwi_tests::create_robot(&client, &ns, "old-1", &[]).await?;
    let token = lekiwi_tests::robot_token(&client, &ns, "old-1").await?;
    let secrets = Api::<Secret>::namespaced(client.clone(), &ns);
    let secret_version = secrets
        .get("old-1-agent-token")
        .await?
        .metadata
        .resource_version;

    // The migration release, pushed with the real CLI; the robot is pointed at it.
    let work = tempfile::tempdir()?;
    let source = work.path().join("source");
    migration_release(&source)?;
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let release =
        lekiwi_tests::push_release(&cp.kubeconfig(), &ns, &server, None, &source, "2.0.0")?;
    lekiwi_tests::set_release(&client, &ns, "old-1", &json!(release)).await?;

    // The old poller polls; the robot is Online as a polling robot.
    let poller = Poller {
        port: op.gateway_port,
        robot: format!("{ns}/old-1"),
        token: token.clone(),
    };
    // The gateway answers from its Robot watch, which may not have the patch yet (a CI
    // failure), and keeps that answer for `poll::CACHE_TTL` (60 s): poll again, as a real poller
    // would, until it offers the release.
    let answer = lekiwi_tests::wait_for(
        "the poll to offer 2.0.0",
        lekiwi_gateway::poll::CACHE_TTL + Duration::from_secs(30),
        || async {
            let answer = poller.poll("1.0.0").await.ok()?;
            (answer["update_available"] == true).then_some(answer)
        },
    )
    .await?;
    assert_eq!(answer["target_digest"], release.digest.as_str());
    let online = |protocol: &'static str| {
        move |s: &RobotStatus| {
            s.phase == Some(RobotPhase::Online) && s.protocol.as_deref() == Some(protocol)
        }
    };
    status_when(&client, &ns, "Online by polls", 10, online("poll")).await?;
    let phases = watch_phases(client.clone(), ns.clone());

    // It downloads the release and runs the script, as its install step.
    let release_dir = work.path().join("robot/opt/legacy/releases/2.0.0");
    let manifest_url = answer["manifest_url"].as_str().context("manifest_url")?;
    let files = poller.download(manifest_url, &release_dir).await?;
    assert_eq!(files, 3);
    let robot_root = work.path().join("robot");
    let token_file = robot_root.join("etc/legacy/token");
    std::fs::create_dir_all(token_file.parent().unwrap())?;
    std::fs::write(&token_file, format!("{token}\n"))?;
    let pid_file = robot_root.join("agent.pid");
    let _agent = Started(pid_file.clone());
    let agent_log = log_dir().join(format!("legacy-migration-{ns}.log"));
    let start = format!(
        "nohup \"$LEKIWI_BIN_DIR/lekiwi-agent\" --status-listen 127.0.0.1:{} --mdns false \
         --log-format json --backoff-initial-ms 200 --backoff-max-ms 2000 >'{}' 2>&1 & \
         echo $! >'{}'",
        free_port(),
        agent_log.display(),
        pid_file.display()
    );
    let gateway = format!("ws://127.0.0.1:{}/v1/agent", op.gateway_port);
    let env = [
        ("LEKIWI_ROBOT", poller.robot.clone()),
        ("LEKIWI_TOKEN_FILE", token_file.display().to_string()),
        ("LEKIWI_GATEWAY_URL", gateway.clone()),
        ("LEKIWI_START_COMMAND", start),
    ];
    let (ok, text) = migrate(&release_dir, &robot_root, &env)?;
    assert!(ok, "the migration failed:\n{text}");
    assert!(text.contains("done: ") && !text.contains(&token), "{text}");
    let creds = robot_root.join("var/lib/lekiwi/credentials.json");
    let mode = std::fs::metadata(&creds)?.permissions().mode();
    assert_eq!(mode & 0o777, 0o600);

    // The agent connects as the same robot, with the same token: no enrollment (this namespace
    // has no enrollment token at all), the Secret untouched.
    let status = status_when(
        &client,
        &ns,
        "connected by the agent",
        30,
        online("websocket"),
    )
    .await
    .with_context(|| std::fs::read_to_string(&agent_log).unwrap_or_default())?;
    let version = agent_version()?;
    assert_eq!(status.agent_version.as_deref(), Some(version.as_str()));
    let after = secrets
        .get("old-1-agent-token")
        .await?
        .metadata
        .resource_version;
    assert_eq!(
        after, secret_version,
        "the robot's token Secret was not rewritten"
    );

    // A late poll is answered and changes nothing while the agent's session is open.
    let answer = poller.poll("1.0.0").await?;
    assert_eq!(answer["target_digest"], release.digest.as_str());

    // The agent then runs the robot's release itself.
    let runs = |s: &RobotStatus| s.current_release.as_ref() == Some(&release);
    let status = status_when(&client, &ns, "the release run by the agent", 60, runs)
        .await
        .with_context(|| std::fs::read_to_string(&agent_log).unwrap_or_default())?;
    // The late poll (protocol poll, agent legacy-0.9) did not overwrite the agent's facts.
    assert_eq!(status.protocol.as_deref(), Some("websocket"));
    assert_eq!(status.agent_version.as_deref(), Some(version.as_str()));
    let seen = phases.stop().await;
    assert!(
        seen.iter().all(|p| p == "Online"),
        "the robot left Online during its migration: {seen:?}"
    );
    eprintln!(
        "migration: {} phase samples, all Online; agent {version}",
        seen.len()
    );

    refused_with_an_enrollment_token(&release_dir, work.path(), &gateway)?;
    Ok(())
}

/// Polls robot `old-1` until its status satisfies `ok`, for at most `secs` seconds.
async fn status_when(
    client: &kube::Client,
    ns: &str,
    what: &str,
    secs: u64,
    ok: impl Fn(&RobotStatus) -> bool,
) -> Result<RobotStatus> {
    let ok = &ok;
    wait_for(what, Duration::from_secs(secs), move || async move {
        let s = get_robot(client, ns, "old-1").await.ok()?.status?;
        ok(&s).then_some(s)
    })
    .await
}

/// The version the workspace's agent reports (`lekiwi-agent --version`: "lekiwi-agent X").
fn agent_version() -> Result<String> {
    let out = std::process::Command::new(bin("lekiwi-agent"))
        .arg("--version")
        .output()?;
    let text = String::from_utf8(out.stdout)?;
    match text.split_whitespace().nth(1) {
        Some(v) => Ok(v.to_owned()),
        None => bail!("lekiwi-agent --version printed {text:?}"),
    }
}

/// A migration handed the fleet's enrollment token instead of the robot's own is refused,
/// names the mistake, and starts nothing.
fn refused_with_an_enrollment_token(release: &Path, work: &Path, gateway: &str) -> Result<()> {
    let root = work.join("wrong");
    std::fs::create_dir_all(&root)?;
    let token_file = root.join("token");
    std::fs::write(&token_file, "lke_0123456789abcdef\n")?;
    let marker = root.join("started");
    let env = [
        ("LEKIWI_ROBOT", "lab/old-2".to_owned()),
        ("LEKIWI_TOKEN_FILE", token_file.display().to_string()),
        ("LEKIWI_GATEWAY_URL", gateway.to_owned()),
        (
            "LEKIWI_START_COMMAND",
            format!("touch '{}'", marker.display()),
        ),
    ];
    let (ok, text) = migrate(release, &root, &env)?;
    assert!(
        !ok,
        "a migration with an enrollment token succeeded:\n{text}"
    );
    assert!(text.contains("enrollment token"), "{text}");
    assert!(!marker.exists(), "the agent was started anyway");
    assert!(!root.join("var/lib/lekiwi/credentials.json").exists());
    Ok(())
}

/// Samples the robot's phase every 200 ms until stopped.
struct Phases {
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Vec<String>>,
}

impl Phases {
    async fn stop(self) -> Vec<String> {
        let _ = self.stop.send(());
        self.task.await.unwrap_or_default()
    }
}

fn watch_phases(client: kube::Client, ns: String) -> Phases {
    let (stop, mut stopped) = tokio::sync::oneshot::channel();
    let task = tokio::spawn(async move {
        let mut seen = Vec::new();
        loop {
            if let Ok(robot) = get_robot(&client, &ns, "old-1").await {
                let phase = robot.status.and_then(|s| s.phase);
                seen.push(phase.map_or("-".to_owned(), |p| format!("{p:?}")));
            }
            tokio::select! {
                _ = &mut stopped => return seen,
                _ = tokio::time::sleep(Duration::from_millis(200)) => {}
            }
        }
    });
    Phases { stop, task }
}
