//! What a command's task works with and how it reports: the robot's handles, the progress
//! reporter that paces download reports as the agent does, and a deployment's counters.

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::mpsc::UnboundedSender;
use tokio::sync::watch;

use super::shared::Shared;
use super::{Durable, Report, RobotId};
use crate::release::{Phase, Progress};

/// Least time between two download progress reports (the agent's).
const PROGRESS_EVERY: Duration = Duration::from_millis(500);

/// What a command's task works with.
pub(super) struct Task {
    pub(super) shared: Arc<Shared>,
    pub(super) robot: RobotId,
    pub(super) tx: UnboundedSender<Report>,
    /// Turns true when a `cancel` stops the task.
    pub(super) stop: watch::Receiver<bool>,
}

/// Sends a command's progress: every phase change, downloads at most every
/// [`PROGRESS_EVERY`].
pub(super) struct Reporter<'a> {
    tx: &'a UnboundedSender<Report>,
    command_id: &'a str,
    last: Instant,
    pub(super) bytes: u64,
    pub(super) total: u64,
}

impl<'a> Reporter<'a> {
    /// A reporter for the command `command_id`, nothing downloaded yet.
    pub(super) fn new(tx: &'a UnboundedSender<Report>, command_id: &'a str) -> Self {
        Self {
            tx,
            command_id,
            last: Instant::now(),
            bytes: 0,
            total: 0,
        }
    }

    pub(super) fn send(&mut self, phase: Phase, percent: Option<f64>, message: String) {
        self.last = Instant::now();
        let _ = self
            .tx
            .send(Report::Durable(Box::new(Durable::Progress(Progress {
                command_id: self.command_id.to_owned(),
                phase,
                percent,
                message,
                bytes_downloaded: self.bytes,
                bytes_total: self.total,
            }))));
    }

    pub(super) fn phase(&mut self, phase: Phase, message: impl Into<String>) {
        self.send(phase, None, message.into());
    }

    pub(super) fn downloaded(&mut self, bytes: u64, (done, files): (usize, usize)) {
        self.bytes = bytes;
        if self.last.elapsed() < PROGRESS_EVERY {
            return;
        }
        let percent = (bytes as f64 * 100.0 / self.total.max(1) as f64).min(100.0);
        self.send(
            Phase::Downloading,
            Some(percent),
            format!("{done} of {files} files"),
        );
    }
}

/// Counters of one deployment.
#[derive(Default)]
pub(super) struct Tally {
    pub(super) bytes: u64,
    pub(super) files_downloaded: usize,
    pub(super) files_reused: usize,
}
