//! `update_agent` on a simulated robot, as the agent does it (`crate::run::agent_update`):
//! download the build over the blob API (verified, then discarded), or switch to the build kept
//! from before without a download; report `agent_update_started`, restart (the session closes
//! and the robot connects again announcing the new version), and once welcomed report
//! `agent_update_succeeded`. A failed download reports `agent_update_failed`.

use lekiwi_protocol::Severity;
use lekiwi_protocol::release::digest_hex;
use serde_json::json;

use super::disk::{Disk, hex};
use super::task::Task;
use super::{Commands, Durable, Finished, Report, Running};
use crate::release::{Error, Outcome, Phase, sha256_digest};

/// Largest agent build downloaded, in bytes (as the agent).
const MAX_AGENT_BYTES: u64 = 128 * 1024 * 1024;

/// The build an update installs.
#[derive(Clone, Debug)]
pub(super) struct AgentTarget {
    pub(super) version: String,
    pub(super) digest: String,
}

/// The agent build a robot runs, the one it kept from before, and an update that waits for a
/// gateway's welcome to be committed.
#[derive(Debug)]
pub(super) struct AgentBuild {
    pub(super) version: String,
    pub(super) digest: String,
    previous: Option<AgentTarget>,
    to_commit: Option<Box<Commit>>,
}

/// An update the new build reports once welcomed.
#[derive(Debug)]
struct Commit {
    command_id: String,
    from: String,
}

impl Default for AgentBuild {
    /// The simulator's own build, with a digest of its version (a build no blob store holds,
    /// like a package's binary).
    fn default() -> Self {
        let version = concat!("sim-", env!("CARGO_PKG_VERSION")).to_owned();
        Self {
            digest: sha256_digest(format!("lekiwi-sim build {version}").as_bytes()),
            version,
            previous: None,
            to_commit: None,
        }
    }
}

impl AgentBuild {
    /// The `agent_update_succeeded` event of an update that waited for a welcome.
    pub(super) fn commit(&mut self) -> Option<Durable> {
        let c = self.to_commit.take()?;
        Some(Durable::Event {
            kind: "agent_update_succeeded",
            severity: Severity::Info,
            message: format!("agent {} replaced {}", self.version, c.from),
            data: json!({
                "version": self.version, "from": c.from,
                "digest": self.digest, "command_id": c.command_id,
            }),
        })
    }
}

impl Commands {
    /// Starts the task that installs `target`, unless the robot runs it already or an update
    /// is not committed yet (then nothing is reported, as on the agent).
    pub(super) fn start_agent_update(
        &mut self,
        task: Task,
        disk: Disk,
        command_id: String,
        target: AgentTarget,
        url: String,
    ) {
        if target.version == self.agent.version || self.agent.to_commit.is_some() {
            tracing::info!(robot = %task.robot.name, version = %target.version, "agent update not started");
            self.disk = Some(disk);
            return;
        }
        let kept = self
            .agent
            .previous
            .as_ref()
            .is_some_and(|p| p.digest == target.digest);
        let digest = target.digest.clone();
        tokio::spawn(async move {
            let outcome = install(&task, &digest, &url, kept).await;
            task.shared
                .counters
                .agent_update(outcome.phase == Phase::Done);
            let _ = task
                .tx
                .send(Report::Finished(Box::new(Finished { disk, outcome })));
        });
        self.running = Some(Running {
            command_id,
            release: None,
            aliases: Vec::new(),
            stop: None,
            agent: Some(target),
        });
    }

    /// The install task ended: on a switch, report it, swap the builds and restart (true);
    /// else report why not.
    pub(super) fn agent_update_done(
        &mut self,
        command_id: &str,
        target: &AgentTarget,
        outcome: &Outcome,
    ) -> bool {
        let mut data = json!({
            "version": target.version, "from": self.agent.version,
            "digest": target.digest, "command_id": command_id,
            "bytes": outcome.bytes_downloaded,
        });
        if outcome.phase != Phase::Done {
            data["reason"] = outcome.message.clone().into();
            self.emit(Durable::Event {
                kind: "agent_update_failed",
                severity: Severity::Error,
                message: format!(
                    "agent update to {} failed: {}",
                    target.version, outcome.message
                ),
                data,
            });
            return false;
        }
        self.emit(Durable::Event {
            kind: "agent_update_started",
            severity: Severity::Info,
            message: format!(
                "switching from agent {} to {}; restarting",
                self.agent.version, target.version
            ),
            data,
        });
        let a = &mut self.agent;
        let before = AgentTarget {
            version: std::mem::replace(&mut a.version, target.version.clone()),
            digest: std::mem::replace(&mut a.digest, target.digest.clone()),
        };
        a.to_commit = Some(Box::new(Commit {
            command_id: command_id.to_owned(),
            from: before.version.clone(),
        }));
        a.previous = Some(before);
        let _ = self.tx.send(Report::Restart);
        true
    }
}

/// Downloads and verifies the build at `url` (nothing when the robot keeps it); `done` when it
/// can switch.
async fn install(task: &Task, digest: &str, url: &str, kept: bool) -> Outcome {
    let outcome = |phase, message, bytes| Outcome {
        phase,
        message,
        current: None,
        bytes_downloaded: bytes,
        files_downloaded: usize::from(bytes > 0),
        files_reused: 0,
    };
    if kept {
        let message = "switched to the build kept as the other slot (no download)".to_owned();
        return outcome(Phase::Done, message, 0);
    }
    match download(task, digest, url).await {
        Ok(bytes) => outcome(Phase::Done, "switched".into(), bytes),
        Err((message, bytes)) => outcome(Phase::Failed, message, bytes),
    }
}

/// The build's bytes, counted, hashed and dropped; how many, or why it failed.
async fn download(task: &Task, digest: &str, url: &str) -> Result<u64, (String, u64)> {
    digest_hex(digest).map_err(|e| (e.to_string(), 0))?;
    let _permit = task.shared.permits.acquire().await;
    let client = task.shared.client(task.robot.gateway);
    let mut stream = client
        .open_stream(url, 0, task.robot.caller())
        .await
        .map_err(|e| (e.to_string(), 0))?;
    let mut hasher = ring::digest::Context::new(&ring::digest::SHA256);
    let mut bytes = 0u64;
    while let Some(chunk) = stream.chunk().await.map_err(|e| (e.to_string(), bytes))? {
        bytes += chunk.len() as u64;
        task.shared.counters.bytes(chunk.len() as u64);
        if bytes > MAX_AGENT_BYTES {
            return Err((
                format!("agent build {url}: more than {MAX_AGENT_BYTES} bytes"),
                bytes,
            ));
        }
        hasher.update(&chunk);
    }
    stream.finish(client);
    let actual = format!("sha256:{}", hex(hasher.finish().as_ref()));
    if actual != digest {
        let e = Error::DigestMismatch {
            what: format!("agent build {url}"),
            expected: digest.to_owned(),
            actual,
        };
        return Err((e.to_string(), bytes));
    }
    Ok(bytes)
}
