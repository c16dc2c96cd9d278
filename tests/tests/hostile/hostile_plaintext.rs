//! Plain text off this machine is refused unless asked for: the real `lekiwi-agent` refuses a
//! `ws://` gateway on another host at start (and only warns, loudly, with
//! `--insecure-allow-plaintext`), and `kubectl lekiwi` refuses to send a Kubernetes token over
//! `http://` to another host. The "other host" is 0.0.0.0: not a loopback address by the rule, yet
//! on Linux a connection to it stays on this machine, so even the agent that is allowed to try
//! (or a regression that stops refusing) sends nothing off the machine.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use anyhow::{Context as _, Result, ensure};
use lekiwi_tests::{ControlPlane, bin};

const REMOTE_WS: &str = "ws://0.0.0.0:9/v1/agent";
const ZERO_DIGEST: &str = "sha256:0000000000000000000000000000000000000000000000000000000000000000";

fn agent(state: &std::path::Path) -> Command {
    let mut cmd = Command::new(bin("lekiwi-agent"));
    cmd.args(["--config", "/nonexistent/lekiwi-agent.yaml"])
        .args(["--gateway", REMOTE_WS])
        .args(["--robot-name", "plaintext/kiwi"])
        .args(["--enrollment-token", "lke_unused"])
        .arg("--state-dir")
        .arg(state)
        .args(["--status-listen", "off", "--mdns", "false"])
        .args(["--connect-timeout-s", "1", "--log-format", "text"])
        .env_remove("LEKIWI_INSECURE_ALLOW_PLAINTEXT")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null());
    cmd
}

/// Runs `cmd` to its end, killing it (and failing) if it is still running after `limit`: an
/// agent that does not refuse would otherwise keep trying to reach the gateway.
fn exits_within(mut cmd: Command, limit: Duration) -> Result<std::process::Output> {
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .context("spawn")?;
    let deadline = std::time::Instant::now() + limit;
    while child.try_wait()?.is_none() {
        if std::time::Instant::now() > deadline {
            child.kill()?;
            let out = child.wait_with_output()?;
            anyhow::bail!(
                "still running after {limit:?}:\n{}",
                String::from_utf8_lossy(&out.stdout)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok(child.wait_with_output()?)
}

#[test]
fn the_agent_refuses_plain_ws_to_another_host_at_start() -> Result<()> {
    let state = tempfile::tempdir()?;
    let out = exits_within(agent(state.path()), Duration::from_secs(5))?;
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    ensure!(!out.status.success(), "the agent ran:\n{text}");
    for needle in [
        "plain ws:// to 0.0.0.0",
        "wss://",
        "--insecure-allow-plaintext",
    ] {
        ensure!(text.contains(needle), "no {needle:?} in:\n{text}");
    }
    // It stopped at the configuration: nothing was written to the state directory.
    ensure!(
        std::fs::read_dir(state.path())?.next().is_none(),
        "state written"
    );
    Ok(())
}

#[test]
fn with_the_flag_the_agent_runs_and_warns_loudly() -> Result<()> {
    for allow in [&["--insecure-allow-plaintext"][..], &[]] {
        let state = tempfile::tempdir()?;
        let mut cmd = agent(state.path());
        cmd.args(allow)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        if allow.is_empty() {
            // The environment variable does the same as the flag.
            cmd.env("LEKIWI_INSECURE_ALLOW_PLAINTEXT", "true");
        }
        let mut child = cmd.spawn().context("spawn lekiwi-agent")?;
        let (tx, rx) = mpsc::channel();
        let stdout = child.stdout.take().context("stdout")?;
        let stderr = child.stderr.take().context("stderr")?;
        for pipe in [
            Box::new(stdout) as Box<dyn std::io::Read + Send>,
            Box::new(stderr),
        ] {
            let tx = tx.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(pipe)
                    .lines()
                    .map_while(std::result::Result::ok)
                {
                    let _ = tx.send(line);
                }
            });
        }
        let deadline = std::time::Instant::now() + Duration::from_secs(2);
        let mut seen = Vec::new();
        let warned = loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) if line.contains("WARN") && line.contains("INSECURE") => break Some(line),
                Ok(line) => seen.push(line),
                Err(_) => break None,
            }
        };
        let running = child.try_wait()?.is_none();
        child.kill()?;
        child.wait()?;
        let line = warned.with_context(|| format!("{allow:?}: no warning in:\n{seen:?}"))?;
        ensure!(
            line.contains("0.0.0.0") && line.contains("wss://"),
            "{line}"
        );
        ensure!(running, "{allow:?}: the agent exited:\n{seen:?}");
    }
    Ok(())
}

#[test]
fn the_cli_refuses_to_send_the_token_over_plain_http_to_another_host() -> Result<()> {
    let cp = ControlPlane::shared();
    let dir = tempfile::tempdir()?;
    std::fs::write(dir.path().join("run.sh"), "#!/bin/sh\n")?;
    let release_dir = dir.path().to_str().context("utf-8 path")?;
    for args in [
        &["release", "push", release_dir, "--version", "1.0.0"][..],
        &["release", "inspect", ZERO_DIGEST],
        &["events", "plaintext/kiwi"],
    ] {
        let out = Command::new(bin("kubectl-lekiwi"))
            .arg("--kubeconfig")
            .arg(cp.kubeconfig())
            .args(args)
            .args(["--server", "http://0.0.0.0:9"])
            .env_remove("LEKIWI_SERVER")
            .output()
            .context("run kubectl-lekiwi")?;
        let err = String::from_utf8_lossy(&out.stderr);
        ensure!(!out.status.success(), "{args:?} succeeded: {err}");
        for needle in [
            "refusing to send your Kubernetes token over plain http:// to 0.0.0.0",
            "https://",
            "--certificate-authority",
            "--insecure-allow-plaintext",
        ] {
            ensure!(err.contains(needle), "{args:?}: no {needle:?} in:\n{err}");
        }
    }
    Ok(())
}
