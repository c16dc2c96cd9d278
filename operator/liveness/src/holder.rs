//! One live session per robot across gateway replicas: the session epoch each session gets,
//! who holds a robot according to its status (`status.gateway`, `status.sessionEpoch`), and
//! which version of the Robot a gateway's write is fenced on.
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
    /// must not happen over this holder: it names a [`later`] session. A status without an
    /// epoch was written by a gateway that predates epochs: only its connection is protected,
    /// from another gateway's disconnect.
    pub fn supersedes(&self, gateway: &str, epoch: i64, connected: bool) -> bool {
        match self.epoch {
            Some(theirs) => later(
                theirs,
                self.gateway.as_deref().unwrap_or(""),
                epoch,
                gateway,
            ),
            None => !connected && self.gateway.as_deref().is_some_and(|g| g != gateway),
        }
    }

    /// Whether a session of this gateway (`gateway`) with `epoch` was taken over by another
    /// gateway's [`later`] session.
    pub fn took_over_from(&self, gateway: &str, epoch: i64) -> bool {
        match (self.gateway.as_deref(), self.epoch) {
            (Some(g), Some(theirs)) => g != gateway && later(theirs, g, epoch, gateway),
            _ => false,
        }
    }
}

/// Whether the session of gateway `gateway` with `epoch` is later than the session of gateway
/// `than_gateway` with `than_epoch`: a higher epoch, or the same epoch on a gateway whose name
/// sorts after. Two replicas may give their sessions of one robot the same epoch (each raises
/// it just above the one its watch shows, when their clocks run behind the replica that wrote
/// that one); without the name the two would each let the other write, and the robot's status
/// would pass from one to the other with every write.
pub fn later(epoch: i64, gateway: &str, than_epoch: i64, than_gateway: &str) -> bool {
    (epoch, gateway) > (than_epoch, than_gateway)
}

/// The epoch of a session opening at `now`, above the `seen` epoch of the robot's status.
pub fn next_epoch(now: Timestamp, seen: Option<i64>) -> i64 {
    let now = now.as_microsecond();
    seen.map_or(now, |seen| now.max(seen.saturating_add(1)))
}

/// What a write is fenced on: the Robot as the watch's cache shows it (`cached`), unless this
/// gateway's own last write of the session (`own`, a `resourceVersion`; 0 for none) is newer.
/// Then the Robot at that version is what that write made it: held by this gateway with this
/// session's `epoch`. A watch that runs behind the API server (minutes, after an API server
/// restart on a busy machine) would otherwise fence every write of a robot written since on a
/// version gone by, and each would cost a refused write and a read before the one that lands:
/// three requests for one, just when the API server has the least to spare. A newer write by
/// anyone else still meets a conflict, and the Robot is read again.
pub fn newest_holder(
    cached: Option<Holder>,
    own: u64,
    gateway: &str,
    epoch: i64,
) -> Option<Holder> {
    let cached_version = cached
        .as_ref()
        .and_then(|h| h.resource_version.as_deref()?.parse::<u64>().ok());
    if own == 0 || cached_version.is_some_and(|c| c >= own) {
        return cached;
    }
    Some(Holder {
        gateway: Some(gateway.to_owned()),
        epoch: Some(epoch),
        resource_version: Some(own.to_string()),
    })
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

    /// Two replicas' sessions with the same epoch: the gateway whose name sorts last holds the
    /// robot, and the other neither writes over it nor keeps its session.
    #[test]
    fn the_same_epoch_on_two_gateways_goes_to_the_name_that_sorts_last() {
        let b = holder(Some("gw-b"), Some(200));
        assert!(b.supersedes("gw-a", 200, true));
        assert!(b.took_over_from("gw-a", 200));
        let a = holder(Some("gw-a"), Some(200));
        assert!(!a.supersedes("gw-b", 200, true));
        assert!(!a.took_over_from("gw-b", 200));
        assert!(later(200, "gw-b", 200, "gw-a"));
        assert!(!later(200, "gw-b", 200, "gw-b"), "the same session");
        assert!(later(201, "gw-a", 200, "gw-b"), "the epoch first");
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

    /// The fence is the newer of the cache's version and the session's own last write; the
    /// cache's when it caught up, or when the session wrote nothing yet.
    #[test]
    fn a_write_is_fenced_on_the_newer_of_the_cache_and_its_own_last_write() {
        let at = |gateway: &str, epoch: i64, version: &str| Holder {
            gateway: Some(gateway.into()),
            epoch: Some(epoch),
            resource_version: Some(version.into()),
        };
        let cached = at("gw-b", 5, "100");
        // Its own write is newer: the Robot at that version is what it wrote.
        assert_eq!(
            newest_holder(Some(cached.clone()), 180, "gw-a", 7),
            Some(at("gw-a", 7, "180"))
        );
        // The cache caught up with it, or went past it (another writer): the cache's.
        for own in [0, 100, 90] {
            assert_eq!(
                newest_holder(Some(cached.clone()), own, "gw-a", 7),
                Some(cached.clone())
            );
        }
        // Not in the cache: its own write, if any, else a read of the Robot.
        assert_eq!(
            newest_holder(None, 180, "gw-a", 7),
            Some(at("gw-a", 7, "180"))
        );
        assert_eq!(newest_holder(None, 0, "gw-a", 7), None);
        // A version that is not a number never stands for a newer one.
        let odd = at("gw-b", 5, "abc");
        assert_eq!(
            newest_holder(Some(odd), 180, "gw-a", 7),
            Some(at("gw-a", 7, "180"))
        );
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
