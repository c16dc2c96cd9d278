//! A session's command bookkeeping: which release the robot runs, which it should run, and the
//! command in flight, so each command goes out once per session and a change of mind stops
//! what no longer should happen (`cancel`) or undoes a finished switch (`rollback`).

use jiff::Timestamp;
use lekiwi_protocol::{Command, ProgressPhase, Release, ServerMessage};

/// A short id of this gateway process, different after every restart.
pub(super) fn boot_id() -> &'static str {
    static BOOT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    BOOT.get_or_init(|| format!("{:x}", Timestamp::now().as_millisecond()))
}

/// What a session knows about the robot's release and the commands it sent.
pub(super) struct CommandLedger {
    /// The release the agent last reported running (in `hello`, a heartbeat, or a `done`).
    current: Option<Release>,
    /// The robot's `spec.release` as the gateway's Robot watch last saw it.
    desired: Option<Release>,
    /// The last deploy (or rollback) command: its id and release. Not repeated within the
    /// session; a new session (reconnect) sends it again if the robot still does not run it.
    sent: Option<(String, Release)>,
    /// Whether `sent` has not reported a final phase yet.
    in_flight: bool,
    /// The release the robot ran when `sent` went out: a return to it is a `rollback`.
    before: Option<Release>,
    /// Commands cancelled in this session, with their releases: their final report (normally
    /// `cancelled`) is still recorded as the robot's last update.
    cancelled: Vec<(String, Release)>,
    /// A release whose download a user's abort or undo stopped (see [`Self::halt`]): not
    /// deployed again in this session until `desired` changes.
    halted: Option<Release>,
    /// Commands made in this session, numbering their ids.
    counter: u32,
}

impl CommandLedger {
    /// A ledger for a session whose agent said it runs `current` and should run `desired`.
    pub(super) fn new(current: Option<Release>, desired: Option<Release>) -> Self {
        Self {
            current,
            desired,
            sent: None,
            in_flight: false,
            before: None,
            cancelled: Vec::new(),
            halted: None,
            counter: 0,
        }
    }

    /// Records a new desired release (the Robot's `spec.release` changed).
    pub(super) fn set_desired(&mut self, release: Option<Release>) {
        // A finished command for another release is history: asked for again later (a
        // rollout restarted after its rollback), that release goes out again.
        if !self.in_flight
            && self
                .sent
                .as_ref()
                .is_some_and(|(_, r)| release.as_ref() != Some(r))
        {
            self.sent = None;
        }
        if release != self.desired {
            self.halted = None;
        }
        self.desired = release;
    }

    /// Stops the command in flight when it is for `release` (a user's abort or undo of
    /// its rollout, seen before the Robot's `spec.release` changes): the `cancel` to send, if
    /// one is due. `release` is not deployed again in this session until `spec.release`
    /// changes, which the controller's plan does next.
    pub(super) fn halt(
        &mut self,
        release: Release,
        gateway: &str,
        session: u64,
    ) -> Option<ServerMessage> {
        let in_flight = self.in_flight;
        let stopped = self.sent.take_if(|(_, r)| in_flight && *r == release);
        self.halted = Some(release);
        let (id, release) = stopped?;
        self.in_flight = false;
        self.cancelled.push((id, release));
        Some(self.command(gateway, session, Command::Cancel).1)
    }

    /// Records the release a heartbeat reports; true when it is one and differs from the last
    /// known, i.e. when a command may be due again (the robot switched elsewhere than asked,
    /// e.g. finished an older deploy).
    pub(super) fn reported(&mut self, release: &Option<Release>) -> bool {
        if release.is_some() && *release != self.current {
            self.current = release.clone();
            return true;
        }
        false
    }

    /// The release of the command `command_id` when this progress report ends it (a final
    /// phase of the command this session sent last, or of one it cancelled), and whether this
    /// session cancelled it; a `done` of the last one makes its release the current one. (A
    /// cancelled command that finished anyway is left to the next heartbeat, which asks for the
    /// desired release again.)
    pub(super) fn finished(
        &mut self,
        command_id: &str,
        phase: Option<ProgressPhase>,
    ) -> Option<(Release, bool)> {
        if !phase.is_some_and(ProgressPhase::is_final) {
            return None;
        }
        if let Some(i) = self.cancelled.iter().position(|(id, _)| id == command_id) {
            return Some((self.cancelled.swap_remove(i).1, true));
        }
        let (sent_id, release) = self.sent.as_ref()?;
        if sent_id != command_id || !self.in_flight {
            return None;
        }
        self.in_flight = false;
        let release = release.clone();
        if phase == Some(ProgressPhase::Done) {
            self.current = Some(release.clone());
        }
        Some((release, false))
    }

    /// The commands to send now, in order: a `cancel` when the command in flight is for a
    /// release the robot should no longer run; then a `rollback` when the robot should return
    /// to the release it ran before this session's last command, else a `deploy` when it
    /// should run another release. Unset `spec.release` asks for nothing.
    pub(super) fn next_commands(&mut self, gateway: &str, session: u64) -> Vec<ServerMessage> {
        let Some(desired) = self.desired.clone() else {
            return Vec::new();
        };
        let mut out = Vec::new();
        let in_flight = self.in_flight;
        if let Some((id, release)) = self.sent.take_if(|(_, r)| in_flight && *r != desired) {
            self.in_flight = false;
            self.cancelled.push((id, release));
            out.push(self.command(gateway, session, Command::Cancel).1);
        }
        if self.current.as_ref() == Some(&desired)
            || self.sent.as_ref().is_some_and(|(_, r)| *r == desired)
            || self.halted.as_ref() == Some(&desired)
        {
            return out;
        }
        let command = if self.before.as_ref() == Some(&desired) {
            Command::Rollback {
                release: desired.clone(),
            }
        } else {
            Command::Deploy {
                manifest_url: lekiwi_protocol::release::blob_path(&desired.digest),
                release: desired.clone(),
            }
        };
        let (id, msg) = self.command(gateway, session, command);
        self.before = self.current.clone();
        self.sent = Some((id, desired));
        self.in_flight = true;
        out.push(msg);
        out
    }

    /// A command with a new id, unique across gateway restarts too: agents remember finished
    /// command ids and do not run one twice, and session numbers start over with every process.
    fn command(
        &mut self,
        gateway: &str,
        session: u64,
        command: Command,
    ) -> (String, ServerMessage) {
        self.counter += 1;
        let command_id = format!("{gateway}-{}-{session}-{}", boot_id(), self.counter);
        let msg = ServerMessage::Command {
            command_id: command_id.clone(),
            command,
        };
        (command_id, msg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn release(version: &str) -> Release {
        Release {
            version: version.into(),
            digest: format!("sha256:{}", "a".repeat(64)),
        }
    }

    /// The one deploy among `cmds`: its id and version.
    fn deployed(cmds: Vec<ServerMessage>) -> Option<(String, String)> {
        let [cmd] = <[ServerMessage; 1]>::try_from(cmds).ok()?;
        match cmd {
            ServerMessage::Command {
                command_id,
                command: Command::Deploy { release, .. },
            } => Some((command_id, release.version)),
            _ => None,
        }
    }

    /// The actions of `cmds`, with their releases' versions.
    fn actions(cmds: &[ServerMessage]) -> Vec<String> {
        cmds.iter()
            .map(|c| match c {
                ServerMessage::Command { command, .. } => match command {
                    Command::Deploy { release, .. } => format!("deploy {}", release.version),
                    Command::Rollback { release } => format!("rollback {}", release.version),
                    Command::Cancel => "cancel".to_owned(),
                    Command::UpdateAgent { version, .. } => format!("update_agent {version}"),
                },
                other => format!("{other:?}"),
            })
            .collect()
    }

    #[test]
    fn a_deploy_goes_out_once_per_desired_release() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("1")));
        assert!(ledger.next_commands("gw", 7).is_empty(), "already runs it");
        ledger.set_desired(Some(release("2")));
        let (id, version) = deployed(ledger.next_commands("gw", 7)).unwrap();
        assert_eq!(version, "2");
        assert!(id.starts_with("gw-") && id.ends_with("-7-1"), "{id}");
        assert!(ledger.next_commands("gw", 7).is_empty(), "not repeated");
        assert_eq!(ledger.finished(&id, Some(ProgressPhase::Downloading)), None);
        assert_eq!(ledger.finished("other", Some(ProgressPhase::Done)), None);
        assert_eq!(
            ledger.finished(&id, Some(ProgressPhase::Done)),
            Some((release("2"), false))
        );
        assert!(
            !ledger.reported(&Some(release("2"))),
            "done made it current"
        );
    }

    #[test]
    fn a_robot_that_switched_elsewhere_is_asked_again_with_a_new_id() {
        let mut ledger = CommandLedger::new(None, Some(release("2")));
        let (first, _) = deployed(ledger.next_commands("gw", 1)).unwrap();
        assert!(ledger.reported(&Some(release("1"))));
        assert!(
            ledger.next_commands("gw", 1).is_empty(),
            "sent already for 2"
        );
        ledger.set_desired(Some(release("3")));
        let cmds = ledger.next_commands("gw", 1);
        assert_eq!(
            actions(&cmds),
            ["cancel", "deploy 3"],
            "2 is still in flight"
        );
        let (second, version) = deployed(cmds[1..].to_vec()).unwrap();
        assert_eq!(version, "3");
        assert_ne!(first, second);
        assert!(
            !ledger.reported(&None),
            "a heartbeat without a release changes nothing"
        );
    }

    #[test]
    fn a_change_of_mind_cancels_the_deploy_in_flight_and_a_resume_sends_it_again() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("2")));
        let (first, _) = deployed(ledger.next_commands("gw", 1)).unwrap();
        ledger.set_desired(Some(release("1")));
        let cmds = ledger.next_commands("gw", 1);
        assert_eq!(actions(&cmds), ["cancel"], "the robot still runs 1");
        assert!(ledger.next_commands("gw", 1).is_empty(), "cancelled once");
        assert_eq!(
            ledger.finished(&first, Some(ProgressPhase::Cancelled)),
            Some((release("2"), true)),
            "the cancelled command's end is still recorded, as a cancelled one's"
        );
        ledger.set_desired(Some(release("2")));
        let (again, version) = deployed(ledger.next_commands("gw", 1)).unwrap();
        assert_eq!(version, "2");
        assert_ne!(first, again);
    }

    #[test]
    fn a_release_that_failed_goes_out_again_when_asked_for_again() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("2")));
        let (first, _) = deployed(ledger.next_commands("gw", 1)).unwrap();
        assert!(ledger.next_commands("gw", 1).is_empty(), "not repeated");
        // Its health check fails: the agent switches back by itself.
        ledger.finished(&first, Some(ProgressPhase::RolledBack));
        assert!(
            ledger.next_commands("gw", 1).is_empty(),
            "still wanted, not retried at once"
        );
        // The rollout is rolled back, then restarted.
        ledger.set_desired(Some(release("1")));
        assert!(ledger.next_commands("gw", 1).is_empty(), "runs 1 already");
        ledger.set_desired(Some(release("2")));
        let (again, version) = deployed(ledger.next_commands("gw", 1)).unwrap();
        assert_eq!(version, "2");
        assert_ne!(first, again);
    }

    #[test]
    fn a_return_to_the_release_before_a_finished_switch_is_a_rollback() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("2")));
        let (id, _) = deployed(ledger.next_commands("gw", 1)).unwrap();
        ledger.finished(&id, Some(ProgressPhase::Done));
        ledger.set_desired(Some(release("1")));
        assert_eq!(actions(&ledger.next_commands("gw", 1)), ["rollback 1"]);
        ledger.set_desired(None);
        assert!(
            ledger.next_commands("gw", 1).is_empty(),
            "unset asks nothing"
        );
    }

    #[test]
    fn an_abort_halts_the_download_at_once_and_it_stays_halted_until_the_spec_moves() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("2")));
        let (first, _) = deployed(ledger.next_commands("gw", 1)).unwrap();
        assert_eq!(ledger.halt(release("3"), "gw", 1), None, "another release");
        let cancel = ledger.halt(release("2"), "gw", 1).expect("in flight");
        assert_eq!(actions(&[cancel]), ["cancel"]);
        assert_eq!(ledger.halt(release("2"), "gw", 1), None, "cancelled once");
        assert!(ledger.reported(&Some(release("0"))));
        assert!(
            ledger.next_commands("gw", 1).is_empty(),
            "not deployed again while spec.release still names it"
        );
        assert_eq!(
            ledger.finished(&first, Some(ProgressPhase::Cancelled)),
            Some((release("2"), true))
        );
        // The controller writes the robot back to what it runs; nothing more is due.
        ledger.set_desired(Some(release("1")));
        ledger.reported(&Some(release("1")));
        assert!(ledger.next_commands("gw", 1).is_empty());
        // A restart of the rollout asks for 2 again.
        ledger.set_desired(Some(release("2")));
        assert_eq!(deployed(ledger.next_commands("gw", 1)).unwrap().1, "2");
    }

    #[test]
    fn a_halt_seen_after_the_spec_moved_changes_nothing() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("2")));
        deployed(ledger.next_commands("gw", 1)).unwrap();
        ledger.set_desired(Some(release("1")));
        assert_eq!(actions(&ledger.next_commands("gw", 1)), ["cancel"]);
        assert_eq!(
            ledger.halt(release("2"), "gw", 1),
            None,
            "already cancelled"
        );
        ledger.set_desired(Some(release("2")));
        assert_eq!(deployed(ledger.next_commands("gw", 1)).unwrap().1, "2");
    }
}
