//! `lekiwi-agent guard`: undoes an agent update that does not come back, without any help from
//! the operator. The service manager runs it from the package's own binary
//! (`/usr/bin/lekiwi-agent`, never a slot) before every start of the agent ([`Mode::Start`])
//! and periodically while it runs ([`Mode::Check`]).
//!
//! It switches `current` back to the previous slot (or to the package binary) when the new
//! build has not committed by the record's deadline (no connection, or a hang), after more
//! than the record's number of starts (it crashes at start), or at once when the new binary
//! is for another CPU (it could only fail with "exec format error"). It writes why in
//! `fallen-back.json`, which the agent that runs next reports to the gateway.

use super::{Error, FallenBack, Pending, Slots};

/// Exit status of `guard --check` when it switched back: the running (new) agent must be
/// restarted so that the previous one runs (systemd: the guard timer's service restarts
/// `lekiwi-agent.service` on it).
pub const EXIT_FELL_BACK: i32 = 3;

/// When the guard runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Before a start of the agent: counts the start.
    Start,
    /// Periodically while the agent runs: checks the deadline only.
    Check,
}

/// Checks the pending update, if any, and undoes it when it must; returns what it undid.
pub fn run(slots: &Slots, mode: Mode, now_ms: i64) -> Result<Option<FallenBack>, Error> {
    let Some(mut pending) = slots.pending() else {
        return Ok(None);
    };
    // An empty slot is a switch back to the package binary: no `current`.
    if slots.current().unwrap_or_default() != pending.slot {
        // Written, but not switched to: before a start the switch never happened (or was
        // undone), and nothing runs the new build. A periodic check can run while the agent
        // is between writing the record and switching (it writes the record first, so a
        // crash between leaves no unguarded build): dropping it then left the new build
        // without its guard, and it never reported its update as succeeded.
        if mode == Mode::Start {
            slots.clear_pending()?;
        }
        return Ok(None);
    }
    // The package binary is this guard's own: it runs here.
    let cannot_run = (!pending.slot.is_empty())
        .then(|| unusable(&slots.binary(&pending.slot)))
        .flatten();
    let reason = if let Some(why) = cannot_run {
        Some(why)
    } else if now_ms > pending.deadline_ms {
        Some(format!(
            "no connection: agent {} did not reach the gateway and commit within the deadline \
             ({} start(s))",
            pending.version, pending.starts
        ))
    } else if mode == Mode::Start {
        pending.starts += 1;
        if pending.starts > pending.max_starts {
            Some(format!(
                "crash at start: agent {} exited {} time(s) without reaching the gateway",
                pending.version, pending.max_starts
            ))
        } else {
            slots.set_pending(&pending)?;
            None
        }
    } else {
        None
    };
    match reason {
        Some(reason) => fall_back(slots, &pending, reason).map(Some),
        None => Ok(None),
    }
}

/// Records why, switches `current` back and deletes the pending record (in this order: a crash
/// half-way leaves the record, and the next run does it again).
fn fall_back(slots: &Slots, pending: &Pending, reason: String) -> Result<FallenBack, Error> {
    let record = FallenBack {
        command_id: pending.command_id.clone(),
        version: pending.version.clone(),
        digest: pending.digest.clone(),
        reason,
        reported: false,
    };
    slots.set_fallen_back(&record)?;
    slots.switch(pending.previous.as_deref())?;
    slots.clear_pending()?;
    Ok(record)
}

/// Why `binary` cannot run here, if that can be told without running it: missing, or an ELF
/// file for another CPU (the kernel would refuse it with "exec format error").
fn unusable(binary: &std::path::Path) -> Option<String> {
    let head = match std::fs::read(binary) {
        Ok(bytes) => bytes.into_iter().take(20).collect::<Vec<_>>(),
        Err(e) => return Some(format!("missing binary: {}: {e}", binary.display())),
    };
    let machine = elf_machine(&head)?;
    let own = elf_machine_of(std::env::consts::ARCH)?;
    (machine != own).then(|| {
        format!(
            "wrong architecture (exec format error): the build is for ELF machine {machine}, \
             this robot is {} (ELF machine {own})",
            std::env::consts::ARCH
        )
    })
}

/// The `e_machine` of an ELF header, `None` when `head` is not one (e.g. a script).
fn elf_machine(head: &[u8]) -> Option<u16> {
    if head.len() < 20 || &head[..4] != b"\x7fELF" {
        return None;
    }
    let bytes = [head[18], head[19]];
    Some(match head[5] {
        2 => u16::from_be_bytes(bytes),
        _ => u16::from_le_bytes(bytes),
    })
}

/// The ELF `e_machine` of a Rust architecture name.
fn elf_machine_of(arch: &str) -> Option<u16> {
    match arch {
        "x86_64" => Some(62),
        "aarch64" => Some(183),
        "arm" => Some(40),
        "x86" => Some(3),
        "riscv64" => Some(243),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn installed(dir: &std::path::Path, binary: &[u8], deadline_ms: i64) -> Slots {
        let slots = Slots::new(dir);
        slots.install("a", binary).unwrap();
        slots.switch(Some("a")).unwrap();
        slots
            .set_pending(&Pending {
                command_id: "c1".into(),
                version: "2".into(),
                digest: format!("sha256:{}", "b".repeat(64)),
                from_version: "1".into(),
                previous: None,
                slot: "a".into(),
                deadline_ms,
                starts: 0,
                max_starts: 2,
            })
            .unwrap();
        slots
    }

    #[test]
    fn a_record_not_switched_to_yet_is_kept_while_the_agent_runs() {
        let dir = tempfile::tempdir().unwrap();
        let slots = installed(dir.path(), b"#!/bin/sh\n", 1_000);
        // The agent wrote the record for slot `a` and has not switched yet.
        slots.switch(None).unwrap();
        assert_eq!(run(&slots, Mode::Check, 10).unwrap(), None);
        assert!(
            slots.pending().is_some(),
            "kept for the switch that follows"
        );
        slots.switch(Some("a")).unwrap();
        assert_eq!(run(&slots, Mode::Start, 10).unwrap(), None);
        assert_eq!(slots.pending().unwrap().starts, 1, "guarded once switched");
        // Before a start, a record whose switch never happened is dropped.
        slots.switch(None).unwrap();
        assert_eq!(run(&slots, Mode::Start, 10).unwrap(), None);
        assert_eq!(slots.pending(), None);
    }

    #[test]
    fn nothing_pending_is_nothing_to_do() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(run(&Slots::new(dir.path()), Mode::Start, 0).unwrap(), None);
    }

    #[test]
    fn too_many_starts_switch_back_to_the_package_binary() {
        let dir = tempfile::tempdir().unwrap();
        let slots = installed(dir.path(), b"#!/bin/sh\nexit 1\n", 1_000);
        assert_eq!(run(&slots, Mode::Start, 10).unwrap(), None);
        assert_eq!(run(&slots, Mode::Check, 10).unwrap(), None);
        assert_eq!(run(&slots, Mode::Start, 10).unwrap(), None);
        let undone = run(&slots, Mode::Start, 10).unwrap().unwrap();
        assert!(undone.reason.starts_with("crash at start"), "{undone:?}");
        assert_eq!(slots.current(), None);
        assert_eq!(slots.pending(), None);
        assert_eq!(slots.fallen_back(), Some(undone));
    }

    #[test]
    fn a_passed_deadline_is_caught_by_the_periodic_check() {
        let dir = tempfile::tempdir().unwrap();
        let slots = installed(dir.path(), b"#!/bin/sh\nsleep 100\n", 1_000);
        assert_eq!(run(&slots, Mode::Check, 999).unwrap(), None);
        let undone = run(&slots, Mode::Check, 1_001).unwrap().unwrap();
        assert!(undone.reason.starts_with("no connection"), "{undone:?}");
    }

    #[test]
    fn a_switch_back_to_the_package_binary_is_guarded_too() {
        let dir = tempfile::tempdir().unwrap();
        let slots = installed(dir.path(), b"#!/bin/sh\n", 1_000);
        // B in slot a runs; a rollback to the package binary removed `current`.
        let mut back = slots.pending().unwrap();
        back.slot = String::new();
        back.previous = Some("a".into());
        slots.set_pending(&back).unwrap();
        slots.switch(None).unwrap();
        assert_eq!(run(&slots, Mode::Start, 10).unwrap(), None);
        assert_eq!(slots.pending().unwrap().starts, 1, "the start was counted");
        let undone = run(&slots, Mode::Check, 1_001).unwrap().unwrap();
        assert!(undone.reason.starts_with("no connection"), "{undone:?}");
        assert_eq!(slots.current().as_deref(), Some("a"), "back on slot a");
    }

    #[test]
    fn a_binary_for_another_cpu_is_undone_before_it_starts() {
        let mut elf = b"\x7fELF\x02\x01\x01".to_vec();
        elf.resize(18, 0);
        let other = if std::env::consts::ARCH == "aarch64" {
            62u16
        } else {
            183
        };
        elf.extend_from_slice(&other.to_le_bytes());
        let dir = tempfile::tempdir().unwrap();
        let slots = installed(dir.path(), &elf, i64::MAX);
        let undone = run(&slots, Mode::Start, 0).unwrap().unwrap();
        assert!(
            undone.reason.starts_with("wrong architecture"),
            "{undone:?}"
        );
    }
}
