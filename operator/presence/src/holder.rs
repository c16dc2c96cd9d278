//! One live session per robot across gateway replicas: the session epoch each session gets,
//! and who holds a robot according to its status (`status.gateway`, `status.sessionEpoch`).
//!
//! A session's epoch is the time it opened in microseconds, raised above the epoch the gateway's
//! Robot watch last saw on the robot, so a later session (on any replica) has a higher epoch even
//! when the replicas' clocks differ a little. A gateway writes a robot's status only with a
//! `resourceVersion` precondition and never over a higher epoch (the fence); a gateway that sees a
//! higher epoch of another gateway on a robot it holds a session of closes that session.

use jiff::Timestamp;
use lekiwi_crds::Robot;

/// Who holds a robot according to its status, and the version of the Robot that says so.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Holder {
    /// `status.gateway`.
    pub gateway: Option<String>,
    /// `status.sessionEpoch`; `None` when written by a gateway without epochs.
    pub epoch: Option<i64>,
    /// The Robot's `metadata.resourceVersion` that this was read from.
    pub resource_version: Option<String>,
}

impl Holder {
    /// The holder the Robot's status names.
    pub fn of(robot: &Robot) -> Self {
        let status = robot.status.as_ref();
        Self {
            gateway: status.and_then(|s| s.gateway.clone().map(String::from)),
            epoch: status.and_then(|s| s.session_epoch),
            resource_version: robot.metadata.resource_version.clone(),
        }
    }

    /// Whether a write of `gateway`'s session with `epoch` (`connected`, or its disconnect)
    /// must not happen over this holder: a higher epoch belongs to a later session. A status
    /// without an epoch was written by a gateway that predates epochs: only its connection is
    /// protected, from another gateway's disconnect.
    pub fn supersedes(&self, gateway: &str, epoch: i64, connected: bool) -> bool {
        match self.epoch {
            Some(theirs) => theirs > epoch,
            None => !connected && self.gateway.as_deref().is_some_and(|g| g != gateway),
        }
    }

    /// Whether a session of this gateway (`gateway`) with `epoch` was taken over by another
    /// gateway's later session.
    pub fn took_over_from(&self, gateway: &str, epoch: i64) -> bool {
        self.gateway.as_deref().is_some_and(|g| g != gateway)
            && self.epoch.is_some_and(|theirs| theirs > epoch)
    }
}

/// The epoch of a session opening at `now`, above the `seen` epoch of the robot's status.
pub fn next_epoch(now: Timestamp, seen: Option<i64>) -> i64 {
    let now = now.as_microsecond();
    seen.map_or(now, |seen| now.max(seen.saturating_add(1)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn holder(gateway: Option<&str>, epoch: Option<i64>) -> Holder {
        Holder {
            gateway: gateway.map(str::to_owned),
            epoch,
            resource_version: Some("1".into()),
        }
    }

    #[test]
    fn a_later_epoch_fences_every_write_of_an_earlier_session() {
        let b = holder(Some("gw-b"), Some(200));
        assert!(b.supersedes("gw-a", 100, true));
        assert!(b.supersedes("gw-a", 100, false));
        assert!(!b.supersedes("gw-a", 300, true), "a later session writes");
        assert!(!b.supersedes("gw-b", 200, false), "its own session writes");
        assert!(b.took_over_from("gw-a", 100));
        assert!(
            !b.took_over_from("gw-b", 100),
            "the same gateway replaces locally"
        );
        assert!(!b.took_over_from("gw-a", 300));
    }

    #[test]
    fn a_status_without_epoch_protects_only_its_connection() {
        let old = holder(Some("gw-b"), None);
        assert!(!old.supersedes("gw-a", 1, true));
        assert!(old.supersedes("gw-a", 1, false));
        assert!(!old.supersedes("gw-b", 1, false));
        assert!(!holder(None, None).supersedes("gw-a", 1, false));
        assert!(!old.took_over_from("gw-a", 1));
    }

    #[test]
    fn epochs_rise_above_what_was_seen() {
        let now: Timestamp = "2026-11-24T08:00:00Z".parse().unwrap();
        let us = now.as_microsecond();
        assert_eq!(next_epoch(now, None), us);
        assert_eq!(next_epoch(now, Some(us - 5)), us);
        // Another replica's clock ran ahead: still later than its session.
        assert_eq!(next_epoch(now, Some(us + 5_000)), us + 5_001);
    }
}
