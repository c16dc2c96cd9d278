//! What a command reports while it runs ([`Progress`]) and when it ends ([`Outcome`]), and the
//! throttle that keeps download progress to one report per [`PROGRESS_EVERY`].

use std::time::{Duration, Instant};

use lekiwi_protocol::{AgentMessage, Release};
use tokio::sync::mpsc::UnboundedSender;
use tracing::info;

/// Least time between two progress reports of the same phase.
pub(super) const PROGRESS_EVERY: Duration = Duration::from_millis(500);

/// Phase of a command, as reported in `progress.phase` (the protocol's own type).
pub use lekiwi_protocol::ProgressPhase as Phase;

/// One progress report of a command; the last one of a command has phase `done`, `failed` or
/// `rolled_back` and matches the [`Outcome`].
#[derive(Clone, Debug, PartialEq)]
pub struct Progress {
    /// The command reported on.
    pub command_id: String,
    /// Where the command stands; a terminal phase ends its reports.
    pub phase: Phase,
    /// Percent done, while downloading and at the end.
    pub percent: Option<f64>,
    /// What happens, for people (e.g. `downloading 3 files, 1200 bytes`).
    pub message: String,
    /// Bytes received so far.
    pub bytes_downloaded: u64,
    /// Bytes to receive in all (the blobs missing from the store).
    pub bytes_total: u64,
}

impl Progress {
    /// The durable wire message for this report.
    pub fn to_message(&self, seq: u64) -> AgentMessage {
        AgentMessage::Progress {
            seq,
            command_id: self.command_id.clone(),
            phase: self.phase.as_str().to_owned(),
            percent: self.percent,
            message: self.message.clone(),
        }
    }
}

/// How a command ended.
#[derive(Clone, Debug, PartialEq)]
pub struct Outcome {
    /// `done`, `failed` or `rolled_back`.
    pub phase: Phase,
    /// Why, or what happened.
    pub message: String,
    /// The release `current` points at now.
    pub current: Option<Release>,
    /// Bytes received from the gateway (manifest included).
    pub bytes_downloaded: u64,
    /// Blobs downloaded.
    pub files_downloaded: usize,
    /// Files of the release whose content was already in the store.
    pub files_reused: usize,
}

/// Sends progress: every phase change, and within a phase at most every [`PROGRESS_EVERY`].
pub(super) struct Reporter<'a> {
    tx: &'a UnboundedSender<Progress>,
    command_id: String,
    phase: Option<Phase>,
    last: Option<Instant>,
    pub(super) bytes_downloaded: u64,
    pub(super) bytes_total: u64,
}

impl<'a> Reporter<'a> {
    pub(super) fn new(tx: &'a UnboundedSender<Progress>, command_id: &str) -> Self {
        Self {
            tx,
            command_id: command_id.to_owned(),
            phase: None,
            last: None,
            bytes_downloaded: 0,
            bytes_total: 0,
        }
    }

    pub(super) fn send(&mut self, phase: Phase, percent: Option<f64>, message: String) {
        info!(command_id = %self.command_id, phase = %phase, %message, "release progress");
        self.phase = Some(phase);
        self.last = Some(Instant::now());
        // A closed channel means nobody listens any more; the work goes on regardless.
        let _ = self.tx.send(Progress {
            command_id: self.command_id.clone(),
            phase,
            percent,
            message,
            bytes_downloaded: self.bytes_downloaded,
            bytes_total: self.bytes_total,
        });
    }

    /// A phase change: always sent.
    pub(super) fn phase(&mut self, phase: Phase, message: impl Into<String>) {
        self.send(phase, None, message.into());
    }

    /// Download progress: sent unless the last report is younger than [`PROGRESS_EVERY`].
    pub(super) fn downloaded(&mut self, bytes: u64, message: impl FnOnce() -> String) {
        self.bytes_downloaded = bytes;
        if self.last.is_some_and(|t| t.elapsed() < PROGRESS_EVERY) {
            return;
        }
        let percent = if self.bytes_total == 0 {
            100.0
        } else {
            (bytes as f64 * 100.0 / self.bytes_total as f64).min(100.0)
        };
        self.send(Phase::Downloading, Some(percent), message());
    }
}

/// Counters of one deployment.
#[derive(Default)]
pub(super) struct Tally {
    pub(super) bytes: u64,
    pub(super) files_downloaded: usize,
    pub(super) files_reused: usize,
}
