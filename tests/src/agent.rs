//! A real `lekiwi-agent` process with quick test settings, and the `hello` a real agent sends.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use anyhow::{Result, bail};
use serde_json::Value;

use lekiwi_agent::connection::{ConnectError, Credentials, Socket, Welcome, connect};

use crate::fleet::gateway_url;
use crate::http::http_get;
use crate::operator::OperatorProcess;
use crate::process::{ChildProcess, Launch};
use crate::{bin, free_port, log_dir, wait_for};

/// The flags every test agent runs with: no mDNS, quick reconnects and connect timeouts, JSON
/// logs (which the tests read), and no disk check: test agents share the build machine's disk,
/// whose fill (build output, other tenants of a shared volume) says nothing about the behaviour
/// under test and made whole rollouts skip "unhealthy" robots. The check has its unit tests.
pub const QUICK_AGENT_FLAGS: [&str; 12] = [
    "--mdns",
    "false",
    "--backoff-initial-ms",
    "200",
    "--backoff-max-ms",
    "2000",
    "--connect-timeout-s",
    "5",
    "--log-format",
    "json",
    "--health-disk-max-percent",
    "0",
];

/// A real `lekiwi-agent` process with its own state directory, for tests; SIGKILLed when dropped.
pub struct AgentProcess {
    process: ChildProcess,
    /// Its state directory (token, outbox).
    pub state_dir: PathBuf,
    /// Port of its local status endpoint.
    pub status_port: u16,
    /// Its log file (JSON lines), appended to across restarts.
    pub log: PathBuf,
}

impl AgentProcess {
    /// Starts an agent for `robot` (`namespace/name`) against `gateway`, enrolling with the
    /// token in `enrollment_token_file` when its state directory has no credentials yet. Quick
    /// test settings: backoff 200 ms to 2 s, teleoperation checks every 0.5 s, no mDNS; `extra`
    /// flags are appended and must not repeat one of these (the agent refuses repeated flags).
    pub fn start(
        gateway: &str,
        robot: &str,
        enrollment_token_file: &Path,
        state_dir: &Path,
        extra: &[&str],
    ) -> Result<Self> {
        let status_port = free_port();
        let safe = robot.replace('/', "_");
        let log = log_dir().join(format!(
            "agent-{safe}-{}.log",
            state_dir
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or("state")
        ));
        std::fs::File::create(&log)?;
        let mut args: Vec<String> = [
            "--config",
            "/nonexistent/lekiwi-agent.yaml",
            "--gateway",
            gateway,
            "--robot-name",
            robot,
            "--enrollment-token-file",
            enrollment_token_file.to_str().unwrap(),
            "--state-dir",
            state_dir.to_str().unwrap(),
            "--status-listen",
            &format!("127.0.0.1:{status_port}"),
            "--teleop-interval-s",
            "0.5",
        ]
        .iter()
        .chain(QUICK_AGENT_FLAGS.iter())
        .map(|s| s.to_string())
        .collect();
        args.extend(extra.iter().map(|s| s.to_string()));
        let process = ChildProcess::spawn(Launch {
            binary: "lekiwi-agent",
            what: "agent",
            rust_log: "info,lekiwi_agent=debug",
            args,
            env: Vec::new(),
            log: log.clone(),
            term_deadline: Duration::from_secs(10),
            term_poll: Duration::from_millis(20),
        })?;
        Ok(Self {
            process,
            state_dir: state_dir.to_owned(),
            status_port,
            log,
        })
    }

    /// Starts an agent as its service unit does, its settings from `config` and the drop-ins
    /// beside it (plus the quick test flags); `state_dir` and `status_port` must be what that
    /// configuration says.
    pub fn from_config(config: &Path, state_dir: &Path, status_port: u16) -> Result<Self> {
        let log = log_dir().join(format!(
            "agent-config-{}.log",
            state_dir
                .parent()
                .and_then(|p| p.file_name())
                .and_then(|n| n.to_str())
                .unwrap_or("state")
        ));
        std::fs::File::create(&log)?;
        let mut args = vec!["--config".to_owned(), config.to_str().unwrap().to_owned()];
        args.extend(QUICK_AGENT_FLAGS.iter().map(|s| s.to_string()));
        let process = ChildProcess::spawn(Launch {
            binary: "lekiwi-agent",
            what: "agent",
            rust_log: "info,lekiwi_agent=debug",
            args,
            env: Vec::new(),
            log: log.clone(),
            term_deadline: Duration::from_secs(10),
            term_poll: Duration::from_millis(20),
        })?;
        Ok(Self {
            process,
            state_dir: state_dir.to_owned(),
            status_port,
            log,
        })
    }

    /// SIGKILL: a crash or a power cut, nothing is cleaned up.
    pub fn kill(&mut self) {
        self.process.kill();
    }

    /// SIGTERM and wait (up to 10 s) for the exit status.
    pub fn terminate(&mut self) -> Result<std::process::ExitStatus> {
        self.process.terminate()
    }

    /// Starts it again with the same flags and state directory (log appended).
    pub fn restart(&mut self) -> Result<()> {
        self.process.restart()
    }

    /// Its process id.
    pub fn pid(&self) -> u32 {
        self.process.pid()
    }

    /// The JSON log lines so far (lines that are not JSON are skipped).
    pub fn log_lines(&self) -> Vec<Value> {
        self.log_text()
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect()
    }

    /// The log as text, for failure messages.
    pub fn log_text(&self) -> String {
        self.process.log_text()
    }

    /// `GET /status` of its local endpoint.
    pub async fn status(&self) -> Result<Value> {
        let (code, body) = http_get(self.status_port, "/status").await?;
        if code != 200 {
            bail!("/status answered {code}: {body}");
        }
        Ok(serde_json::from_str(&body)?)
    }

    /// Waits until its `/status` says it is connected to the gateway; the error carries its log.
    pub async fn wait_connected(&self, within: Duration) -> Result<()> {
        wait_for("the agent connected", within, || async {
            self.status()
                .await
                .ok()
                .filter(|s| s["connected"] == true)
                .map(|_| ())
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}\nagent log:\n{}", self.log_text()))
    }

    /// Queues an event with `lekiwi-agent event` (works whether or not the agent runs) and
    /// returns its sequence number.
    pub fn emit(&self, kind: &str, message: &str, data: &Value) -> Result<u64> {
        let out = Command::new(bin("lekiwi-agent"))
            .args(["--config", "/nonexistent/lekiwi-agent.yaml"])
            .args(["--state-dir", self.state_dir.to_str().unwrap()])
            .args(["event", "--kind", kind, "--message", message])
            .args(["--data", &data.to_string()])
            .output()?;
        if !out.status.success() {
            bail!(
                "lekiwi-agent event failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(String::from_utf8_lossy(&out.stdout).trim().parse()?)
    }
}

/// Connects to `op`'s gateway as an agent would, with the standard [`hello`] and 10 s to be
/// welcomed: as `robot` (`namespace/name`, or a bare name when enrolling) with `token`.
pub async fn connect_agent(
    op: &OperatorProcess,
    token: &str,
    robot: &str,
) -> Result<(Socket, Welcome), ConnectError> {
    let creds = Credentials {
        token: token.to_owned(),
        robot: robot.to_owned(),
    };
    connect(&gateway_url(op), &creds, &hello(), Duration::from_secs(10)).await
}

/// A `hello` as a real agent sends it.
pub fn hello() -> lekiwi_protocol::AgentMessage {
    lekiwi_protocol::AgentMessage::Hello {
        protocol_version: lekiwi_protocol::PROTOCOL_VERSION,
        agent_version: "0.1.0-test".into(),
        agent_digest: None,
        system: lekiwi_protocol::SystemFacts {
            arch: Some("aarch64".into()),
            cpus: Some(4),
            ..Default::default()
        },
        current_release: None,
        last_acked_seq: None,
        health: Some(lekiwi_protocol::Health {
            healthy: true,
            message: None,
            reason: None,
        }),
        teleoperation: Some(lekiwi_protocol::Teleoperation {
            active: false,
            score: Some(0.0),
        }),
        features: Vec::new(),
    }
}

/// How long [`recv`] waits for the gateway's next frame.
pub const FRAME_TIMEOUT: Duration = Duration::from_secs(10);

/// A bare `heartbeat`: no readings, nothing changed.
pub fn heartbeat() -> lekiwi_protocol::AgentMessage {
    lekiwi_protocol::AgentMessage::Heartbeat {
        sent_at_ms: 42,
        rtt_ms: None,
        vitals: lekiwi_protocol::Vitals::default(),
        current_release: None,
        health: None,
        teleoperation: None,
    }
}

/// The gateway's next protocol message on `ws` (skipping pings), within [`FRAME_TIMEOUT`];
/// `None` once the session is closed or nothing came.
pub async fn recv(ws: &mut Socket) -> Option<lekiwi_protocol::ServerMessage> {
    use futures::StreamExt;
    use tokio_tungstenite::tungstenite::Message;
    loop {
        match tokio::time::timeout(FRAME_TIMEOUT, ws.next())
            .await
            .ok()??
        {
            Ok(Message::Text(t)) => {
                return Some(
                    lekiwi_protocol::decode(t.as_str(), usize::MAX).expect("server frame decodes"),
                );
            }
            Ok(Message::Close(_)) | Err(_) => return None,
            Ok(_) => continue,
        }
    }
}
