//! Commands from the gateway (deploy, rollback, cancel): one deployment task at a time, which
//! owns the release store while it runs; the latest command waits behind it.

use lekiwi_protocol::{AgentMessage, Command, Release};
use tracing::{error, info};

use super::{Agent, Error};
use crate::outbox::Lane;
use crate::release::{Outcome, Phase, Releases};

/// What a deployment task hands back: the release store, and the outcome (none for a
/// recovery that found nothing to do).
pub(super) type Joined = Result<(Releases, Option<Outcome>), tokio::task::JoinError>;

/// The build an update task installs.
#[derive(Clone, Debug)]
pub(super) struct AgentTarget {
    pub(super) version: String,
    pub(super) digest: String,
}

/// A deployment task and what it is for.
pub(super) struct Deploying {
    pub(super) task: tokio::task::JoinHandle<(Releases, Option<Outcome>)>,
    /// Its command id (empty for a recovery).
    command_id: String,
    /// The release it deploys or rolls back to (none for a recovery).
    release: Option<Release>,
    /// Later command ids for the same release (a reconnect re-sends the command): they get the
    /// same final report.
    aliases: Vec<String>,
    /// Cancels it (none for a recovery, which finishes what an agent restart interrupted).
    stop: Option<tokio::sync::watch::Sender<bool>>,
    /// The agent build it installs, for an `update_agent` task.
    agent: Option<AgentTarget>,
}

impl Deploying {
    /// The task of an `update_agent` command.
    pub(super) fn agent(
        task: tokio::task::JoinHandle<(Releases, Option<Outcome>)>,
        command_id: String,
        target: AgentTarget,
    ) -> Self {
        Self {
            task,
            command_id,
            release: None,
            aliases: Vec::new(),
            stop: None,
            agent: Some(target),
        }
    }
}

impl Agent {
    /// A command from the gateway: start it, or queue it behind the one running.
    pub(super) fn on_command(&mut self, command_id: String, command: Command) -> Result<(), Error> {
        info!(%command_id, ?command, "command received");
        if self.deploying.is_some() {
            return self.on_command_while_deploying(command_id, command);
        }
        match command {
            Command::Cancel => {
                self.report_final(&command_id, Phase::Done, "nothing to cancel".into())?
            }
            other => self.start_command(command_id, other),
        }
        Ok(())
    }

    /// A command while a deployment runs: the same release joins it, a cancel drops what is
    /// queued and stops the deployment, anything else is queued (replacing what was).
    fn on_command_while_deploying(
        &mut self,
        command_id: String,
        command: Command,
    ) -> Result<(), Error> {
        let target = match &command {
            Command::Deploy { release, .. } | Command::Rollback { release } => {
                Some(release.clone())
            }
            Command::Cancel | Command::UpdateAgent { .. } => None,
        };
        if let Some(running) = self.deploying.as_mut()
            && target.is_some()
            && running.release == target
        {
            // The same release again (a reconnect re-sends it): report to both ids.
            running.aliases.push(command_id);
            return Ok(());
        }
        match command {
            Command::Cancel => {
                if let Some((queued_id, _)) = self.queued.take() {
                    self.report_final(
                        &queued_id,
                        Phase::Cancelled,
                        "cancelled before it started".into(),
                    )?;
                }
                let running = self.deploying.as_ref();
                let message = match running.and_then(|d| d.stop.as_ref().map(|s| (d, s))) {
                    Some((d, stop)) => {
                        // The deployment reports `cancelled` (or `rolled_back`) itself.
                        stop.send_replace(true);
                        format!("cancelling command {}", d.command_id)
                    }
                    None => "a recovery after an agent restart is not interrupted".to_owned(),
                };
                self.report_final(&command_id, Phase::Done, message)?;
            }
            other => {
                if let Some((old, _)) = self.queued.replace((command_id, other)) {
                    self.report_final(&old, Phase::Failed, "superseded by a newer command".into())?;
                }
            }
        }
        Ok(())
    }

    /// Queues the final progress report of a command that will not (or did not) run itself.
    fn report_final(
        &mut self,
        command_id: &str,
        phase: Phase,
        message: String,
    ) -> Result<(), Error> {
        let ts = lekiwi_protocol::now_ms();
        self.outbox
            .push(Lane::Critical, ts, |seq| AgentMessage::Progress {
                seq,
                command_id: command_id.to_owned(),
                phase: phase.as_str().to_owned(),
                percent: None,
                message,
            })?;
        Ok(())
    }

    /// Moves the release store into a task that runs `command`.
    fn start_command(&mut self, command_id: String, command: Command) {
        let Some(mut releases) = self.releases.take() else {
            return;
        };
        let tx = self.progress_tx.clone();
        let id = command_id.clone();
        let stop = releases.cancel_handle();
        let (release, task) = match command {
            Command::Deploy {
                release,
                manifest_url,
            } => (
                Some(release.clone()),
                tokio::spawn(async move {
                    let o = releases.deploy(&id, &release, &manifest_url, &tx).await;
                    (releases, Some(o))
                }),
            ),
            Command::Rollback { release } => (
                Some(release.clone()),
                tokio::spawn(async move {
                    let o = releases.rollback(&id, &release, &tx).await;
                    (releases, Some(o))
                }),
            ),
            Command::UpdateAgent {
                version,
                digest,
                url,
            } => {
                let target = AgentTarget { version, digest };
                self.deploying = self.start_agent_update(releases, command_id, target, url);
                return;
            }
            Command::Cancel => {
                self.releases = Some(releases);
                return;
            }
        };
        self.deploying = Some(Deploying {
            task,
            command_id,
            release,
            aliases: Vec::new(),
            stop: Some(stop),
            agent: None,
        });
    }

    /// Runs the recovery of an interrupted deployment, if the journal has one.
    pub(super) fn start_recovery(&mut self) {
        let Some(mut releases) = self.releases.take() else {
            return;
        };
        let tx = self.progress_tx.clone();
        self.deploying = Some(Deploying {
            task: tokio::spawn(async move {
                let o = releases.recover(&tx).await;
                (releases, o)
            }),
            command_id: String::new(),
            release: None,
            aliases: Vec::new(),
            stop: None,
            agent: None,
        });
    }

    /// A deployment task ended: take the store back, report to aliases, start what is queued.
    pub(super) fn on_deploy_done(&mut self, joined: Joined) -> Result<(), Error> {
        let Some(done) = self.deploying.take() else {
            return Ok(());
        };
        let (mut releases, outcome) = match joined {
            Ok(x) => x,
            Err(e) => {
                // The task panicked: the store's journal makes the next start recover.
                error!(error = %e, "deployment task failed; restart the agent to recover");
                return Ok(());
            }
        };
        if let Some(access) = self.pending_access.take() {
            releases.set_gateway(access)?;
        }
        self.current_release = releases.current();
        self.releases = Some(releases);
        if let Some(o) = &outcome {
            info!(
                command_id = %done.command_id,
                phase = %o.phase,
                bytes = o.bytes_downloaded,
                files_downloaded = o.files_downloaded,
                files_reused = o.files_reused,
                message = %o.message,
                "deployment finished"
            );
            for alias in &done.aliases {
                self.report_final(alias, o.phase, o.message.clone())?;
            }
            if let Some(target) = &done.agent {
                self.agent_update_done(&done.command_id, target, o)?;
            }
        }
        self.publish_release();
        if let Some((id, cmd)) = self.queued.take() {
            self.start_command(id, cmd);
        }
        Ok(())
    }
}
