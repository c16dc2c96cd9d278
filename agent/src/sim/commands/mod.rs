//! Commands on a simulated robot, carried out as the agent carries them out
//! (`crate::run::commands`): one task at a time runs a `deploy`, `rollback` or `update_agent`
//! and holds the robot's in-memory [`Disk`] while it runs; the latest other command waits behind
//! it; a `cancel` drops what waits and stops what runs; a command for the release already being
//! deployed joins it. Everything the robot reports goes through one channel ([`Report`]) that
//! the session (or, between sessions, the reconnect loop) drains into the durable outbox, so
//! a deploy goes on while the robot is offline and its reports reach the next session.

mod agent_update;
mod args;
mod deploy;
mod disk;
mod download;
mod shared;
mod task;

use std::sync::Arc;
use std::time::Duration;

use lekiwi_protocol::{AgentMessage, Command, Release, Severity};
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};
use tokio::sync::watch;

pub use args::{CommandArgs, Fault, Hook};
pub use shared::CommandSummary;
pub(super) use shared::Shared;

use crate::release::{Caller, Outcome, Phase, Progress};
use agent_update::{AgentBuild, AgentTarget};
use disk::Disk;

/// Who a task works for: the robot's name (for its faults), `namespace/name` and token (for
/// the blob API), and the gateway it talks to.
#[derive(Clone, Debug)]
pub(super) struct RobotId {
    pub(super) name: String,
    pub(super) robot: String,
    pub(super) token: String,
    pub(super) gateway: usize,
}

impl RobotId {
    fn caller(&self) -> Caller<'_> {
        Caller {
            token: &self.token,
            robot: &self.robot,
        }
    }
}

/// Something a robot's commands have for its session.
#[derive(Debug)]
pub(super) enum Report {
    /// A durable message to send.
    Durable(Box<Durable>),
    /// The running task ended: the disk comes back with the outcome.
    Finished(Box<Finished>),
    /// The robot goes offline for this long (`--offline-mid-download-share`).
    Offline(Duration),
    /// The agent switched builds and restarts (`update_agent`).
    Restart,
}

/// A durable message of the commands: a `progress` or an `event`.
#[derive(Debug)]
pub(super) enum Durable {
    /// A progress report.
    Progress(Progress),
    /// An agent update's event (`agent_update_*`).
    Event {
        kind: &'static str,
        severity: Severity,
        message: String,
        data: serde_json::Value,
    },
}

impl Durable {
    /// The wire message with sequence number `seq`.
    pub(super) fn message(&self, seq: u64) -> AgentMessage {
        match self {
            Durable::Progress(p) => p.to_message(seq),
            Durable::Event {
                kind,
                severity,
                message,
                data,
            } => AgentMessage::Event {
                seq,
                ts_ms: lekiwi_protocol::now_ms(),
                kind: (*kind).to_owned(),
                severity: *severity,
                message: message.clone(),
                data: data.clone(),
            },
        }
    }
}

/// What a task hands back.
#[derive(Debug)]
pub(super) struct Finished {
    disk: Disk,
    outcome: Outcome,
}

/// What a report asks of the session.
pub(super) enum Handled {
    /// Queue this durable message and send it.
    Durable(Box<Durable>),
    /// A task ended; a heartbeat tells the gateway the release now current.
    Finished,
    /// Drop the session and stay away this long.
    Offline(Duration),
    /// Close the session and connect again as the new agent build.
    Restart,
}

/// A task running, and what it is for.
struct Running {
    command_id: String,
    /// The release it deploys or rolls back to (none for an agent update).
    release: Option<Release>,
    /// Later command ids for the same release: they get the same final report.
    aliases: Vec<String>,
    /// Cancels it (none for an agent update, which is not interrupted).
    stop: Option<watch::Sender<bool>>,
    /// The build an agent update installs.
    agent: Option<AgentTarget>,
}

/// One robot's commands; see the module docs.
// shape: deploy, rollback and cancel here; agent_update.rs the simulated agent update.
pub(super) struct Commands {
    shared: Arc<Shared>,
    /// The disk, while no task holds it.
    disk: Option<Disk>,
    /// The release `current` points at, as of the last task's end.
    current: Option<Release>,
    running: Option<Running>,
    /// The next command, received while one ran (the latest wins).
    queued: Option<(String, Command)>,
    tx: UnboundedSender<Report>,
    rx: UnboundedReceiver<Report>,
    /// The agent build that runs.
    agent: AgentBuild,
}

impl Commands {
    /// A robot on the fleet's factory release, running the simulator's own build.
    pub(super) fn new(shared: Arc<Shared>) -> Self {
        let disk = Disk::new(shared.factory.clone());
        let (tx, rx) = unbounded_channel();
        Self {
            current: disk.current().map(|k| k.release.clone()),
            disk: Some(disk),
            shared,
            running: None,
            queued: None,
            tx,
            rx,
            agent: AgentBuild::default(),
        }
    }

    /// The release the robot runs, for `hello` and heartbeats.
    pub(super) fn current(&self) -> Option<&Release> {
        self.current.as_ref()
    }

    /// The agent build that runs: its version and digest, for `hello`.
    pub(super) fn agent(&self) -> (&str, &str) {
        (&self.agent.version, &self.agent.digest)
    }

    /// The next report (never ends: the robot holds a sender itself).
    pub(super) async fn next(&mut self) -> Report {
        match self.rx.recv().await {
            Some(r) => r,
            None => std::future::pending().await,
        }
    }

    /// A report waiting, if any (between sessions).
    pub(super) fn try_next(&mut self) -> Option<Report> {
        self.rx.try_recv().ok()
    }

    /// Applies `report`; what the session must do about it.
    pub(super) fn handle(&mut self, robot: &RobotId, report: Report) -> Handled {
        match report {
            Report::Durable(d) => Handled::Durable(d),
            Report::Finished(f) => {
                self.on_finished(robot, *f);
                Handled::Finished
            }
            Report::Offline(d) => Handled::Offline(d),
            Report::Restart => Handled::Restart,
        }
    }

    /// A gateway welcomed the robot: an agent update waiting for that is committed.
    pub(super) fn welcomed(&mut self) {
        if let Some(event) = self.agent.commit() {
            self.emit(event);
        }
    }

    fn emit(&self, durable: Durable) {
        // The receiver lives as long as `self`.
        let _ = self.tx.send(Report::Durable(Box::new(durable)));
    }

    /// The final report of a command that does not run itself.
    fn report_final(&self, command_id: &str, phase: Phase, message: String) {
        self.emit(Durable::Progress(Progress {
            command_id: command_id.to_owned(),
            phase,
            percent: None,
            message,
            bytes_downloaded: 0,
            bytes_total: 0,
        }));
    }

    /// A command from the gateway: start it, or settle it against the one running.
    pub(super) fn on_command(&mut self, robot: &RobotId, command_id: String, command: Command) {
        tracing::debug!(robot = %robot.name, %command_id, ?command, "command received");
        self.shared.counters.command();
        if self.running.is_some() {
            return self.while_running(command_id, command);
        }
        match command {
            Command::Cancel => {
                self.report_final(&command_id, Phase::Done, "nothing to cancel".into())
            }
            other => self.start(robot, command_id, other),
        }
    }

    /// A command while a task runs: the same release joins it, a cancel drops what waits and
    /// stops the task, anything else waits (replacing what waited).
    fn while_running(&mut self, command_id: String, command: Command) {
        let target = match &command {
            Command::Deploy { release, .. } | Command::Rollback { release } => Some(release),
            Command::Cancel | Command::UpdateAgent { .. } => None,
        };
        if let Some(running) = self.running.as_mut()
            && target.is_some()
            && running.release.as_ref() == target
        {
            running.aliases.push(command_id);
            return;
        }
        if !matches!(command, Command::Cancel) {
            if let Some((old, _)) = self.queued.replace((command_id, command)) {
                self.report_final(&old, Phase::Failed, "superseded by a newer command".into());
            }
            return;
        }
        if let Some((queued, _)) = self.queued.take() {
            self.report_final(
                &queued,
                Phase::Cancelled,
                "cancelled before it started".into(),
            );
        }
        let message = match self.running.as_ref() {
            Some(Running {
                stop: Some(stop),
                command_id: running,
                ..
            }) => {
                // The task reports `cancelled` (or `rolled_back`) itself.
                stop.send_replace(true);
                format!("cancelling command {running}")
            }
            _ => "an agent update is not interrupted".to_owned(),
        };
        self.report_final(&command_id, Phase::Done, message);
    }

    /// Starts `command` in a task that holds the disk.
    fn start(&mut self, robot: &RobotId, command_id: String, command: Command) {
        let Some(disk) = self.disk.take() else {
            return;
        };
        let (stop_tx, stop) = watch::channel(false);
        let task = task::Task {
            shared: self.shared.clone(),
            robot: robot.clone(),
            tx: self.tx.clone(),
            stop,
        };
        let (release, url) = match command {
            Command::Deploy {
                release,
                manifest_url,
            } => (release, Some(manifest_url)),
            Command::Rollback { release } => (release, None),
            Command::UpdateAgent {
                version,
                digest,
                url,
            } => {
                let target = AgentTarget { version, digest };
                return self.start_agent_update(task, disk, command_id, target, url);
            }
            Command::Cancel => {
                self.disk = Some(disk);
                return;
            }
        };
        let id = command_id.clone();
        let target = release.clone();
        tokio::spawn(async move {
            let mut disk = disk;
            let outcome = deploy::run(&task, &mut disk, &id, &target, url.as_deref()).await;
            let _ = task
                .tx
                .send(Report::Finished(Box::new(Finished { disk, outcome })));
        });
        self.running = Some(Running {
            command_id,
            release: Some(release),
            aliases: Vec::new(),
            stop: Some(stop_tx),
            agent: None,
        });
    }

    /// A task ended: take the disk back, report to the aliases, start what waits.
    fn on_finished(&mut self, robot: &RobotId, finished: Finished) {
        let Finished { disk, outcome } = finished;
        self.current = disk.current().map(|k| k.release.clone());
        self.disk = Some(disk);
        let Some(done) = self.running.take() else {
            return;
        };
        for alias in &done.aliases {
            self.report_final(alias, outcome.phase, outcome.message.clone());
        }
        if let Some(target) = &done.agent
            && self.agent_update_done(&done.command_id, target, &outcome)
        {
            // The agent restarts: what waited dies with it (the gateway sends it again).
            self.queued = None;
            return;
        }
        if let Some((id, command)) = self.queued.take() {
            self.start(robot, id, command);
        }
    }
}

#[cfg(test)]
mod tests;
