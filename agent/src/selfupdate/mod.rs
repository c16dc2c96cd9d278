//! The agent's own update (A/B): another build of `lekiwi-agent` is installed into the inactive
//! slot, a pending-update record is written, `current` is flipped to that slot and the agent
//! exits with [`EXIT_UPDATED`] so that its service manager starts the new build. The new build
//! commits (deletes the record) once a gateway welcomed it; if it does not, [`guard`] (run by
//! the service manager from the package's own binary) switches back.
//!
//! Layout under the state directory:
//!
//! ```text
//! agent/a/lekiwi-agent      slot a (written only while slot b or the package binary runs)
//! agent/b/lekiwi-agent      slot b
//! agent/current -> a        the slot the service manager starts; absent: /usr/bin/lekiwi-agent
//! agent/pending.json        the update not yet committed (see [`Pending`])
//! agent/fallen-back.json    the last update the guard undid, and why (see [`FallenBack`])
//! agent/package.json        the package binary's path, version and digest (see [`local`])
//! ```
//!
//! Every file is replaced by writing a temporary file, fsync and rename, and `current` by a
//! symlink renamed over it: a power cut at any point leaves either the old or the new state.
//! The outbox lives elsewhere in the state directory and is shared by every build.

pub mod guard;
pub mod local;

use std::io::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// Exit status of an agent that switched `current` to a new build and wants to be started
/// again (systemd: `RestartForceExitStatus=75`; `EX_TEMPFAIL` of sysexits.h).
pub const EXIT_UPDATED: i32 = 75;

/// Name of the binary inside a slot.
pub const BINARY: &str = "lekiwi-agent";

/// Environment variable that replaces the version this binary reports (in `hello`, events and
/// `--version` of the running agent): for wrapper scripts that ship one binary under another
/// version name, and for the update tests. Empty or unset: the version it was built as.
pub const VERSION_OVERRIDE_ENV: &str = "LEKIWI_AGENT_VERSION_OVERRIDE";

/// The version this agent reports: the build's, or [`VERSION_OVERRIDE_ENV`].
pub fn version() -> &'static str {
    static VERSION: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    VERSION.get_or_init(|| {
        std::env::var(VERSION_OVERRIDE_ENV)
            .ok()
            .filter(|v| !v.trim().is_empty())
            .unwrap_or_else(|| env!("CARGO_PKG_VERSION").to_owned())
    })
}

/// An update switched to and not yet committed: what the guard needs to undo it.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Pending {
    /// The command that asked for it (reported again by whichever agent ends it).
    pub command_id: String,
    /// Version of the new build.
    pub version: String,
    /// Its `sha256:` digest.
    pub digest: String,
    /// Version of the agent that installed it.
    pub from_version: String,
    /// The slot `current` pointed at before (`a` or `b`); `None`: no slot, the package binary.
    pub previous: Option<String>,
    /// The slot the new build is in; empty: the package binary (a switch back to it).
    pub slot: String,
    /// Unix ms by which the new build must have committed.
    pub deadline_ms: i64,
    /// Starts of the new build counted by the guard so far.
    pub starts: u32,
    /// Starts after which the guard gives up on it.
    pub max_starts: u32,
}

/// An update the guard undid: reported by the agent that runs afterwards, and remembered so
/// that the same build is not installed again.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FallenBack {
    /// The command that asked for it.
    pub command_id: String,
    /// The build that did not come back.
    pub version: String,
    /// Its digest: an `update_agent` for it is refused.
    pub digest: String,
    /// Why the guard switched back.
    pub reason: String,
    /// Whether an agent has queued the `agent_update_fallen_back` event for it.
    pub reported: bool,
}

/// The `agent/` directory of a state directory and the files in it.
#[derive(Clone, Debug)]
// shape: the A/B switch here; local.rs the builds the robot keeps on its own disk.
pub struct Slots {
    root: PathBuf,
}

/// Errors of the self-update files.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {source}")]
pub struct Error {
    /// The file or directory.
    pub path: PathBuf,
    /// What went wrong.
    pub source: std::io::Error,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error {
        path: path.to_owned(),
        source,
    }
}

impl Slots {
    /// The slots of `state_dir`.
    pub fn new(state_dir: &Path) -> Self {
        Self {
            root: state_dir.join("agent"),
        }
    }

    /// `agent/current`.
    pub fn current_link(&self) -> PathBuf {
        self.root.join("current")
    }

    /// The binary of slot `slot`.
    pub fn binary(&self, slot: &str) -> PathBuf {
        self.root.join(slot).join(BINARY)
    }

    /// The slot `current` points at, if it points at one.
    pub fn current(&self) -> Option<String> {
        let target = std::fs::read_link(self.current_link()).ok()?;
        let name = target.file_name()?.to_str()?;
        matches!(name, "a" | "b").then(|| name.to_owned())
    }

    /// The slot a new build goes into: the one `current` does not point at.
    pub fn inactive(&self) -> &'static str {
        match self.current().as_deref() {
            Some("a") => "b",
            _ => "a",
        }
    }

    /// Writes `bytes` as the (executable) binary of `slot`, fsync'd.
    pub fn install(&self, slot: &str, bytes: &[u8]) -> Result<PathBuf, Error> {
        use std::os::unix::fs::OpenOptionsExt as _;
        let dir = self.root.join(slot);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let tmp = dir.join(format!(".{BINARY}.tmp"));
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .mode(0o755)
            .open(&tmp)
            .map_err(io(&tmp))?;
        f.write_all(bytes).map_err(io(&tmp))?;
        f.sync_all().map_err(io(&tmp))?;
        let path = dir.join(BINARY);
        std::fs::rename(&tmp, &path).map_err(io(&path))?;
        fsync_dir(&dir)?;
        Ok(path)
    }

    /// Points `current` at `slot` (`None`: removes it, so the package binary runs), atomically.
    pub fn switch(&self, slot: Option<&str>) -> Result<(), Error> {
        let link = self.current_link();
        match slot {
            Some(slot) => {
                let tmp = self.root.join("current.new");
                let _ = std::fs::remove_file(&tmp);
                std::os::unix::fs::symlink(slot, &tmp).map_err(io(&tmp))?;
                std::fs::rename(&tmp, &link).map_err(io(&link))?;
            }
            None => match std::fs::remove_file(&link) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&link)(e)),
                _ => {}
            },
        }
        fsync_dir(&self.root)
    }

    /// The update not yet committed, if any (an unreadable record counts as none).
    pub fn pending(&self) -> Option<Pending> {
        read_json(&self.root.join("pending.json"))
    }

    /// Writes (or replaces) the pending-update record.
    pub fn set_pending(&self, pending: &Pending) -> Result<(), Error> {
        self.write_json("pending.json", pending)
    }

    /// Deletes the pending-update record: the update is committed or undone.
    pub fn clear_pending(&self) -> Result<(), Error> {
        let path = self.root.join("pending.json");
        match std::fs::remove_file(&path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io(&path)(e)),
            _ => fsync_dir(&self.root),
        }
    }

    /// The last update the guard undid, if any.
    pub fn fallen_back(&self) -> Option<FallenBack> {
        read_json(&self.root.join("fallen-back.json"))
    }

    /// Writes the record of an undone update.
    pub fn set_fallen_back(&self, record: &FallenBack) -> Result<(), Error> {
        self.write_json("fallen-back.json", record)
    }

    fn write_json(&self, name: &str, value: &impl Serialize) -> Result<(), Error> {
        std::fs::create_dir_all(&self.root).map_err(io(&self.root))?;
        let path = self.root.join(name);
        let tmp = self.root.join(format!(".{name}.tmp"));
        let bytes = serde_json::to_vec_pretty(value).unwrap_or_default();
        let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
        f.write_all(&bytes).map_err(io(&tmp))?;
        f.sync_all().map_err(io(&tmp))?;
        std::fs::rename(&tmp, &path).map_err(io(&path))?;
        fsync_dir(&self.root)
    }
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Option<T> {
    let bytes = std::fs::read(path).ok()?;
    serde_json::from_slice(&bytes).ok()
}

fn fsync_dir(dir: &Path) -> Result<(), Error> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io(dir))
}

/// The build name (`amd64`, `arm64`) of a CPU architecture as `uname -m` or Rust name it;
/// `None` for one without agent builds.
pub fn build_arch(machine: &str) -> Option<&'static str> {
    match machine {
        "x86_64" | "amd64" => Some("amd64"),
        "aarch64" | "arm64" => Some("arm64"),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pending(slot: &str, previous: Option<&str>) -> Pending {
        Pending {
            command_id: "c1".into(),
            version: "2".into(),
            digest: format!("sha256:{}", "b".repeat(64)),
            from_version: "1".into(),
            previous: previous.map(str::to_owned),
            slot: slot.into(),
            deadline_ms: 0,
            starts: 0,
            max_starts: 3,
        }
    }

    #[test]
    fn slots_alternate_and_current_flips_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let slots = Slots::new(dir.path());
        assert_eq!(slots.current(), None);
        assert_eq!(slots.inactive(), "a");
        let bin = slots.install("a", b"#!/bin/sh\n").unwrap();
        assert!(bin.ends_with("agent/a/lekiwi-agent"));
        slots.switch(Some("a")).unwrap();
        assert_eq!(slots.current().as_deref(), Some("a"));
        assert_eq!(slots.inactive(), "b");
        slots.switch(Some("b")).unwrap();
        assert_eq!(slots.current().as_deref(), Some("b"));
        slots.switch(None).unwrap();
        assert_eq!(slots.current(), None);
        slots.switch(None).unwrap();
    }

    #[test]
    fn records_round_trip_and_clear() {
        let dir = tempfile::tempdir().unwrap();
        let slots = Slots::new(dir.path());
        assert_eq!(slots.pending(), None);
        slots.set_pending(&pending("a", None)).unwrap();
        assert_eq!(slots.pending(), Some(pending("a", None)));
        slots.clear_pending().unwrap();
        slots.clear_pending().unwrap();
        assert_eq!(slots.pending(), None);
    }

    #[test]
    fn architectures_map_to_build_names() {
        assert_eq!(build_arch("x86_64"), Some("amd64"));
        assert_eq!(build_arch("aarch64"), Some("arm64"));
        assert_eq!(build_arch("riscv64"), None);
    }
}
