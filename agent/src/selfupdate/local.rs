//! The agent builds a robot keeps on its own disk: the one that runs now (its digest goes in
//! `hello`), the package binary (recorded in `agent/package.json` by that binary whenever it
//! runs, as no slot names it) and the build in the inactive slot. An `update_agent` for one of
//! them, a rollback above all, switches to it without downloading anything.

use std::io::Read as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Slots, read_json};

/// The package binary as it last ran: the build the service manager starts when `current` is
/// absent.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct PackageBuild {
    /// Where it was (`/usr/bin/lekiwi-agent` under systemd).
    pub path: PathBuf,
    /// The version it reported.
    pub version: String,
    /// Its `sha256:` digest then; checked again before a switch to it (a package upgrade
    /// replaces the file).
    pub digest: String,
}

/// A build of a wanted digest found on this robot.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LocalBuild {
    /// In the inactive slot (`a` or `b`).
    Slot(&'static str),
    /// The package binary (`current` removed runs it).
    Package,
}

impl LocalBuild {
    /// The slot to point `current` at (`None`: remove it).
    pub fn slot(&self) -> Option<&'static str> {
        match self {
            LocalBuild::Slot(s) => Some(s),
            LocalBuild::Package => None,
        }
    }

    /// Where it is, in words.
    pub fn describe(&self) -> String {
        match self {
            LocalBuild::Slot(s) => format!("slot {s}"),
            LocalBuild::Package => "the package binary".to_owned(),
        }
    }
}

/// `sha256:<hex>` of the file at `path`, read in 64 KiB pieces (a build is ~10 MB; the agent's
/// memory stays flat).
pub fn file_digest(path: &Path) -> std::io::Result<String> {
    let mut file = std::fs::File::open(path)?;
    let mut ctx = ring::digest::Context::new(&ring::digest::SHA256);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        ctx.update(&buf[..n]);
    }
    let mut out = String::with_capacity(71);
    out.push_str("sha256:");
    for b in ctx.finish().as_ref() {
        use std::fmt::Write as _;
        let _ = write!(out, "{b:02x}");
    }
    Ok(out)
}

/// [`file_digest`] of `exe`, the process's own binary, read once per process (`lekiwi-fleet`
/// runs hundreds of agents from one binary); another path is read each time.
fn exe_digest(exe: &Path) -> Option<String> {
    static FIRST: std::sync::OnceLock<(PathBuf, Option<String>)> = std::sync::OnceLock::new();
    let (path, digest) = FIRST.get_or_init(|| (exe.to_owned(), file_digest(exe).ok()));
    if path == exe {
        digest.clone()
    } else {
        file_digest(exe).ok()
    }
}

impl Slots {
    /// The package binary's record, if one ran here.
    pub fn package(&self) -> Option<PackageBuild> {
        read_json(&self.root.join("package.json"))
    }

    /// The digest of the build that runs now: the binary of the slot `current` names (the
    /// service manager starts it), else `exe`, the package binary, whose record this writes
    /// (when it changed). `None` when the file cannot be read.
    pub fn identify_running(&self, exe: &Path, version: &str) -> Option<String> {
        if let Some(slot) = self.current() {
            return file_digest(&self.binary(&slot)).ok();
        }
        let digest = exe_digest(exe)?;
        let record = PackageBuild {
            path: exe.to_owned(),
            version: version.to_owned(),
            digest: digest.clone(),
        };
        if self.package().as_ref() != Some(&record)
            && let Err(e) = self.write_json("package.json", &record)
        {
            tracing::warn!(error = %e, "could not record the package binary");
        }
        Some(digest)
    }

    /// A build of `digest` on this robot other than the running one: the inactive slot's (the
    /// build before the running one, or the one a rollback left), or the package binary while a
    /// slot runs. Each is hashed again, so a changed file never counts.
    pub fn find_local(&self, digest: &str) -> Option<LocalBuild> {
        let inactive = self.inactive();
        let slot_bin = self.binary(inactive);
        if slot_bin.exists() && file_digest(&slot_bin).ok().as_deref() == Some(digest) {
            return Some(LocalBuild::Slot(inactive));
        }
        // Without `current` the package binary is the running build.
        self.current()?;
        let package = self.package().filter(|p| p.digest == digest)?;
        (file_digest(&package.path).ok().as_deref() == Some(digest)).then_some(LocalBuild::Package)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_package_binary_is_recorded_and_found_while_a_slot_runs() {
        let dir = tempfile::tempdir().unwrap();
        let slots = Slots::new(dir.path());
        let exe = dir.path().join("usr-bin-lekiwi-agent");
        std::fs::write(&exe, b"package build A").unwrap();
        let a = slots.identify_running(&exe, "1.0.0").unwrap();
        assert_eq!(a, file_digest(&exe).unwrap());
        assert_eq!(slots.package().unwrap().version, "1.0.0");
        // Nothing to find while the package runs: it is the running build.
        assert_eq!(slots.find_local(&a), None);

        // B installed into slot a and switched to: B runs, A is found as the package binary.
        slots.install("a", b"slot build B").unwrap();
        slots.switch(Some("a")).unwrap();
        let b = slots.identify_running(&exe, "2.0.0").unwrap();
        assert_eq!(b, file_digest(&slots.binary("a")).unwrap());
        assert_eq!(
            slots.package().unwrap().version,
            "1.0.0",
            "not rewritten by B"
        );
        assert_eq!(slots.find_local(&a), Some(LocalBuild::Package));
        assert_eq!(slots.find_local(&b), None, "B runs");

        // C into slot b, switched to: B is found in the inactive slot, A still as the package.
        slots.install("b", b"slot build C").unwrap();
        slots.switch(Some("b")).unwrap();
        assert_eq!(slots.find_local(&b), Some(LocalBuild::Slot("a")));
        assert_eq!(slots.find_local(&a), Some(LocalBuild::Package));

        // Rolled back to the package binary: C, in the slot it left, is found for a roll
        // forward; B was in the other slot, which is not the inactive one now.
        slots.switch(None).unwrap();
        let c = file_digest(&slots.binary("b")).unwrap();
        assert_eq!(slots.inactive(), "a");
        assert_eq!(
            slots.find_local(&c),
            None,
            "C is in slot b, not the inactive slot a"
        );
        assert_eq!(slots.find_local(&b), Some(LocalBuild::Slot("a")));
        assert_eq!(slots.find_local(&a), None, "A runs");
        slots.switch(Some("b")).unwrap();

        // A package upgrade replaced the file: its old digest is no longer found.
        std::fs::write(&exe, b"package build A2").unwrap();
        assert_eq!(slots.find_local(&a), None);
        let unknown = format!("sha256:{}", "0".repeat(64));
        assert_eq!(slots.find_local(&unknown), None);
    }
}
