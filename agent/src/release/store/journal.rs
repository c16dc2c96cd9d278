//! The deploy journal `deploy.json`: the deployment in progress (what recovery finishes after a
//! crash), recently finished commands (so a repeated command is not executed twice) and the
//! order releases were current in (what garbage collection keeps).

use std::collections::VecDeque;

use lekiwi_protocol::Release;
use serde::{Deserialize, Serialize};
use tracing::warn;

use super::{Layout, write_atomic};
use crate::release::{Phase, Result, io};

/// Command ids remembered so that a repeated command is not executed twice.
const RECENT_COMMANDS: usize = 64;
/// Versions remembered in activation order (for garbage collection).
const HISTORY: usize = 64;

/// Where the journal says a deployment stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(in crate::release) enum JournalPhase {
    /// Downloading or assembling; `current` untouched.
    Preparing,
    /// About to switch, or switched and restarting / health-checking.
    Switching,
    /// Switching back to `previous`.
    RollingBack,
}

/// The deployment in progress.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(in crate::release) struct Active {
    /// The command that started it, reported on until it ends.
    pub command_id: String,
    /// The release being deployed.
    pub target: Release,
    /// What `current` pointed at before: where a rollback returns to (`None`: nothing).
    pub previous: Option<Release>,
    /// How far it got; decides what recovery does after a restart.
    pub phase: JournalPhase,
    /// Why a rollback happens.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub reason: String,
}

/// A finished command.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(in crate::release) struct Finished {
    /// Its id: a command that comes again with it is answered from here, not executed.
    pub command_id: String,
    /// How it ended.
    pub phase: Phase,
    /// The final message, repeated in the answer to a repeated command.
    pub message: String,
}

/// `deploy.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub(in crate::release) struct Journal {
    /// The deployment in progress, if any.
    #[serde(default)]
    pub active: Option<Active>,
    /// Recently finished commands, oldest first.
    #[serde(default)]
    pub recent: VecDeque<Finished>,
    /// Versions in the order they were last current, oldest first.
    #[serde(default)]
    pub history: Vec<String>,
}

impl Journal {
    /// Reads the journal under `layout`: empty when there is none, and a corrupt one is set
    /// aside (as `deploy.json.corrupt`) rather than blocking every deployment.
    pub(in crate::release) fn load(layout: &Layout) -> Result<Journal> {
        let path = layout.journal();
        match std::fs::read(&path) {
            Ok(bytes) => match serde_json::from_slice(&bytes) {
                Ok(j) => Ok(j),
                Err(e) => {
                    // Atomic writes make this unlikely; do not let it block every deployment.
                    warn!(path = %path.display(), error = %e, "corrupt deploy journal; set aside");
                    let aside = layout.root.join("deploy.json.corrupt");
                    std::fs::rename(&path, &aside).map_err(io(&path))?;
                    Ok(Journal::default())
                }
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Journal::default()),
            Err(e) => Err(io(&path)(e)),
        }
    }

    /// Writes the journal under `layout`, atomically.
    pub(in crate::release) fn save(&self, layout: &Layout) -> Result<()> {
        let bytes = serde_json::to_vec_pretty(self).unwrap_or_default();
        write_atomic(&layout.journal(), &bytes)
    }

    /// Records a finished command, forgetting the oldest beyond [`RECENT_COMMANDS`].
    pub(in crate::release) fn remember(&mut self, finished: Finished) {
        self.recent.retain(|f| f.command_id != finished.command_id);
        self.recent.push_back(finished);
        while self.recent.len() > RECENT_COMMANDS {
            self.recent.pop_front();
        }
    }

    /// Marks `version` as the most recently current.
    pub(in crate::release) fn touch(&mut self, version: &str) {
        self.history.retain(|v| v != version);
        self.history.push(version.to_owned());
        if self.history.len() > HISTORY {
            let excess = self.history.len() - HISTORY;
            self.history.drain(..excess);
        }
    }
}
