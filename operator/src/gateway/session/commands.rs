//! A session's deploy-command bookkeeping: which release the robot runs, which it should run,
//! and the deploy command already sent for it, so each command goes out once per session.

use jiff::Timestamp;
use lekiwi_protocol::{Command, ProgressPhase, Release, ServerMessage};

/// A short id of this gateway process, different after every restart.
pub(super) fn boot_id() -> &'static str {
    static BOOT: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    BOOT.get_or_init(|| format!("{:x}", Timestamp::now().as_millisecond()))
}

/// What a session knows about the robot's release and the deploy command it sent.
pub(super) struct CommandLedger {
    /// The release the agent last reported running (in `hello`, a heartbeat, or a `done`).
    current: Option<Release>,
    /// The robot's `spec.release` as the gateway's Robot watch last saw it.
    desired: Option<Release>,
    /// The last deploy command: its id and release. Not repeated within the session; a new
    /// session (reconnect) sends it again if the robot still does not run it.
    sent: Option<(String, Release)>,
    /// Deploy commands made in this session, numbering their ids.
    counter: u32,
}

impl CommandLedger {
    /// A ledger for a session whose agent said it runs `current` and should run `desired`.
    pub(super) fn new(current: Option<Release>, desired: Option<Release>) -> Self {
        Self {
            current,
            desired,
            sent: None,
            counter: 0,
        }
    }

    /// The release the robot should run, as last told.
    pub(super) fn desired(&self) -> Option<&Release> {
        self.desired.as_ref()
    }

    /// Records a new desired release (the Robot's `spec.release` changed).
    pub(super) fn set_desired(&mut self, release: Option<Release>) {
        self.desired = release;
    }

    /// Records the release a heartbeat reports; true when it is one and differs from the last
    /// known, i.e. when a deploy command may be due again (the robot switched elsewhere than
    /// asked, e.g. finished an older deploy).
    pub(super) fn reported(&mut self, release: &Option<Release>) -> bool {
        if release.is_some() && *release != self.current {
            self.current = release.clone();
            return true;
        }
        false
    }

    /// The release of the deploy command `command_id` when this progress report ends it
    /// (a final phase of the command this session sent last); a `done` makes it the current one.
    pub(super) fn finished(
        &mut self,
        command_id: &str,
        phase: Option<ProgressPhase>,
    ) -> Option<Release> {
        if !phase.is_some_and(ProgressPhase::is_final) {
            return None;
        }
        let (sent_id, release) = self.sent.as_ref()?;
        if sent_id != command_id {
            return None;
        }
        let release = release.clone();
        if phase == Some(ProgressPhase::Done) {
            self.current = Some(release.clone());
        }
        Some(release)
    }

    /// The deploy command to send now, if the robot should run another release.
    pub(super) fn next_deploy(&mut self, gateway: &str, session: u64) -> Option<ServerMessage> {
        let desired = self.desired.clone()?;
        if self.current.as_ref() == Some(&desired)
            || self.sent.as_ref().is_some_and(|(_, r)| *r == desired)
        {
            return None;
        }
        self.counter += 1;
        // Unique across gateway restarts too: agents remember finished command ids and do not
        // run one twice, and session numbers start over with every process.
        let command_id = format!("{gateway}-{}-{session}-{}", boot_id(), self.counter);
        self.sent = Some((command_id.clone(), desired.clone()));
        Some(ServerMessage::Command {
            command_id,
            command: Command::Deploy {
                manifest_url: lekiwi_protocol::release::blob_path(&desired.digest),
                release: desired,
            },
        })
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

    fn deployed(cmd: Option<ServerMessage>) -> Option<(String, String)> {
        match cmd? {
            ServerMessage::Command {
                command_id,
                command: Command::Deploy { release, .. },
            } => Some((command_id, release.version)),
            _ => None,
        }
    }

    #[test]
    fn a_deploy_goes_out_once_per_desired_release() {
        let mut ledger = CommandLedger::new(Some(release("1")), Some(release("1")));
        assert!(ledger.next_deploy("gw", 7).is_none(), "already runs it");
        ledger.set_desired(Some(release("2")));
        let (id, version) = deployed(ledger.next_deploy("gw", 7)).unwrap();
        assert_eq!(version, "2");
        assert!(id.starts_with("gw-") && id.ends_with("-7-1"), "{id}");
        assert!(ledger.next_deploy("gw", 7).is_none(), "not repeated");
        assert_eq!(ledger.finished(&id, Some(ProgressPhase::Downloading)), None);
        assert_eq!(ledger.finished("other", Some(ProgressPhase::Done)), None);
        assert_eq!(
            ledger.finished(&id, Some(ProgressPhase::Done)),
            Some(release("2"))
        );
        assert!(
            !ledger.reported(&Some(release("2"))),
            "done made it current"
        );
    }

    #[test]
    fn a_robot_that_switched_elsewhere_is_asked_again_with_a_new_id() {
        let mut ledger = CommandLedger::new(None, Some(release("2")));
        let (first, _) = deployed(ledger.next_deploy("gw", 1)).unwrap();
        assert!(ledger.reported(&Some(release("1"))));
        assert!(ledger.next_deploy("gw", 1).is_none(), "sent already for 2");
        ledger.set_desired(Some(release("3")));
        let (second, version) = deployed(ledger.next_deploy("gw", 1)).unwrap();
        assert_eq!(version, "3");
        assert_ne!(first, second);
        assert!(
            !ledger.reported(&None),
            "a heartbeat without a release changes nothing"
        );
    }
}
