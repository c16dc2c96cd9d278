//! The robots this gateway claims: sessions of robots whose status still names another gateway
//! because their first write here has not landed, or landed but this gateway's Robot watch has
//! not shown it yet. The gateway's Lease lists them
//! ([`lekiwi_crds::contract::CLAIMS_ANNOTATION`]), so the Robot controller does not mark them
//! `Unknown` when that other gateway's Lease expires (one write per moved robot, not two).
//!
//! A claim is dropped when this gateway's own watch shows the write, not when the write is
//! answered: a saturated API server sends watch events a minute or more late, to the Robot
//! controller as to this gateway, and a claim dropped at the answer would reach the controller
//! (through the Lease) long before the write does; it would plan `Unknown` from the status it
//! still has, and be refused (409) once per moved robot.
//!
//! A session learns at its start, from the gateway's Robot cache, whether its robot moved. The
//! cache can be behind: the old gateway's last write may land, or reach this gateway's watch,
//! only after the session here opened (an API server answering seconds late). Such a write,
//! older than the session, makes the robot claimed then ([`Presence::moved_later`]).
//!
//! A robot that reconnects here only after the Robot controller marked it `Unknown` (its old
//! gateway's Lease expired before this gateway's claim reached the controller) is the one robot
//! shown wrong: its write goes before every other waiting one ([`Priority::Gone`]). This gateway
//! learns that from its Robot watch ([`Presence::shown_gone`]) or, seconds sooner on a
//! saturated API server, from the list of marked robots on the old gateway's Lease
//! ([`crate::peers`], [`Presence::marked`]). A robot the controller marks under this gateway's
//! own live session (its writes ran later than the lag the controller allowed for) is shown
//! wrong the same way, and written first too ([`Presence::shown_gone_here`]).

use jiff::{SignedDuration, Timestamp};
use lekiwi_crds::contract::encode_claims;
use lekiwi_crds::{Robot, RobotPhase};

use super::queue::State;
use super::{Entry, Presence, Priority};
use crate::peers::Peers;
use lekiwi_core::RobotKey;

/// How long a claim outlives its robot's last landed write when this gateway's Robot watch
/// does not show that write (a watch that is listing again, say): the write landed, so the
/// claim is not needed for the robot's sake, and it would take room in the Lease annotation.
/// Then the claim ends for good (a later write does not bring it back).
pub const CLAIM_AFTER_WRITE: SignedDuration = SignedDuration::from_secs(120);

/// How often [`Presence::tick`] looks for robots shown gone under their live session here
/// ([`Presence::sweep_shown_gone`]).
pub const GONE_SWEEP: std::time::Duration = std::time::Duration::from_secs(5);

/// Whether this gateway's Lease, as last renewed, still lasts (see [`Presence::lease_renewed`]).
fn lease_current(s: &State) -> bool {
    s.lease_until
        .is_some_and(|until| std::time::Instant::now() < until)
}

/// Whether `robot`'s status shows it `Unknown` or `Offline`: a moved robot shown so while its
/// session here is live is written before every other ([`Presence::shown_gone`]).
pub fn is_shown_gone(robot: &Robot) -> bool {
    robot
        .status
        .as_ref()
        .and_then(|s| s.phase.as_ref())
        .is_some_and(|p| matches!(p, RobotPhase::Unknown | RobotPhase::Offline))
}

/// The gateway `robot`'s status names.
fn holder_gateway(robot: &Robot) -> Option<&str> {
    robot.status.as_ref()?.gateway.as_deref()
}

/// Ends `e`'s claim once it is [`CLAIM_AFTER_WRITE`] past its last landed write; called by
/// [`Presence::tick`] with the rest of the per-robot housekeeping.
pub(super) fn end_stale_claim(e: &mut Entry, now: Timestamp) {
    if e.moved
        && e.written_at
            .is_some_and(|at| now.duration_since(at) >= CLAIM_AFTER_WRITE)
    {
        e.moved = false;
    }
}

impl Presence {
    /// The other gateways' lists of robots marked `Unknown`, which their watch keeps.
    pub fn peers(&self) -> &Peers {
        &self.peers
    }

    /// Whether robot `key`, as the Robot cache shows it (`cached`), is shown gone: by its
    /// status, or by the list of robots marked `Unknown` on the Lease of the gateway that
    /// status names.
    pub(super) fn gone_or_marked(&self, key: &RobotKey, cached: &Robot) -> bool {
        is_shown_gone(cached)
            || holder_gateway(cached).is_some_and(|gw| self.peers.is_marked(gw, key))
    }

    /// The Lease of gateway `gateway` lists robot `key` as marked `Unknown` by the Robot
    /// controller: if the robot's session here is live, moved here (its status named another
    /// gateway) and not written yet, and the Robot cache shows its status naming `gateway`
    /// still, it is shown `Unknown` although connected, and its write goes before every other
    /// waiting one, as for [`Presence::shown_gone`]. `true` if it was put first.
    pub fn marked(&self, key: &RobotKey, gateway: &str) -> bool {
        let named = self
            .cached_robot(key)
            .is_some_and(|r| holder_gateway(&r) == Some(gateway));
        named
            && self.put_first(key, |s, e| {
                e.moved && e.written_at.is_none() && !s.writing.contains_key(key)
            })
    }

    /// Puts `key` before every other waiting robot ([`Priority::Gone`]) if its session here is
    /// live and `also` holds for it (given the whole state: whether a write of it is in flight,
    /// say); `true` if it did. No settling check: a session whose status names another gateway
    /// never settles (`connect_moved`, `moved_later`).
    fn put_first(&self, key: &RobotKey, also: impl Fn(&State, &Entry) -> bool) -> bool {
        let first = self.with_state(|s| {
            let first = s.robots.get(key).is_some_and(|e| e.connected && also(s, e));
            if first {
                s.enqueue(key, Priority::Gone);
            }
            first
        });
        if first {
            self.wake();
        }
        first
    }

    /// The robots claimed now, oldest session first (those the writer takes first).
    pub fn claims(&self) -> Vec<RobotKey> {
        let mut claimed: Vec<(u64, RobotKey)> = self.with_state(|s| {
            s.robots
                .iter()
                .filter(|(_, e)| e.moved && e.connected)
                .map(|(k, e)| (e.session, k.clone()))
                .collect()
        });
        claimed.sort_unstable_by_key(|(session, _)| *session);
        claimed.into_iter().map(|(_, k)| k).collect()
    }

    /// The [`lekiwi_crds::contract::CLAIMS_ANNOTATION`] value of [`Presence::claims`] (`None`
    /// when there is none), bounded in size; the gauge of claimed robots follows it.
    pub fn claims_annotation(&self) -> Option<String> {
        let claims = self.claims();
        let (value, listed) = encode_claims(
            claims
                .iter()
                .map(|k| (k.namespace.as_str(), k.name.as_str())),
        );
        self.metrics.gateway.claimed_robots.set(listed as i64);
        (listed > 0).then_some(value)
    }

    /// Returns once a robot moved here since the last call (or at once if one did meanwhile).
    pub async fn claims_changed(&self) {
        self.claims_changed.notified().await;
    }

    /// The Robot cache shows `key`'s status written by this gateway's session with epoch
    /// `epoch`: a claim on the robot has done its job and is dropped (with the Lease's next
    /// renewal). Epochs are unique to a session, so only that session's write shows it.
    pub fn write_seen(&self, key: &RobotKey, epoch: i64) {
        self.with_state(|s| {
            if let Some(e) = s.robots.get_mut(key)
                && e.epoch == epoch
            {
                e.moved = false;
            }
        });
    }

    /// The Robot cache shows `key` `Unknown` or `Offline` under another gateway's (`other`)
    /// session with epoch `epoch` while its later session here is live and not written yet
    /// (see [`lekiwi_liveness::holder::later`]): the robot is
    /// shown gone although it is connected (the Robot controller marked it `Unknown` before
    /// it reconnected here, say), so its write goes before every other waiting one, moves
    /// included (those still show `Online`): [`Priority::Gone`]. Not while its write is in
    /// flight. `true` if it was put first.
    pub fn shown_gone(&self, key: &RobotKey, epoch: i64, other: &str) -> bool {
        let gateway = self.config.gateway.as_str();
        self.put_first(key, |s, e| {
            lekiwi_liveness::holder::later(e.epoch, gateway, epoch, other)
                && e.written_at.is_none()
                && !s.writing.contains_key(key)
        })
    }

    /// The Robot cache shows `key` `Unknown` or `Offline` under this gateway's own session with
    /// epoch `epoch`, and that session is live: the Robot controller marked the robot while
    /// this gateway's writes ran later than the lag it allows for (an API server that came back
    /// from a restart and took fewer writes than the robots needed, say). The robot is shown
    /// gone although connected, so its write goes before every other waiting one, as for
    /// [`Presence::shown_gone`], instead of waiting for its next refresh minutes later. A write
    /// of it in flight was planned before the mark and may be refused for it (a conflict, then
    /// a retry at its own priority): the write queued now follows it (see `State::begin_write`).
    /// `true` if it was put first.
    pub fn shown_gone_here(&self, key: &RobotKey, epoch: i64) -> bool {
        self.put_first(key, |s, e| lease_current(s) && e.epoch == epoch)
    }

    /// This gateway's Lease was renewed just now, for `duration`. Until it runs out the Robot
    /// controller counts the gateway alive, so a robot it shows gone under a live session here
    /// was marked for a heartbeat that aged in the status, which a write corrects. Once it has
    /// run out, the controller marks the robots here `Unknown` for the Lease whatever they
    /// write: they are not put first then ([`Presence::shown_gone_here`] and the sweep), or
    /// each write would only be marked again.
    pub fn lease_renewed(&self, duration: std::time::Duration) {
        self.with_state(|s| s.lease_until = Some(std::time::Instant::now() + duration));
    }

    /// Every [`GONE_SWEEP`], what [`Presence::shown_gone_here`] does for each change the Robot
    /// cache sends, done again for every robot at once: each robot whose session here is live
    /// and was written, that waits for no retry, and that the cache shows `Unknown` or
    /// `Offline` under that very session, is put first. A change the dispatch could not act on
    /// (one it missed while it read the whole cache again) is acted on here.
    pub(super) fn sweep_shown_gone_when_due(&self) {
        let due = self.with_state(|s| {
            let due = s.gone_swept.is_none_or(|at| at.elapsed() >= GONE_SWEEP);
            if due {
                s.gone_swept = Some(std::time::Instant::now());
            }
            due
        });
        if due {
            self.sweep_shown_gone();
        }
    }

    /// Puts first every robot the Robot cache shows gone under its live, written session here
    /// (see [`Presence::sweep_shown_gone_when_due`]); `true` if any was.
    pub(super) fn sweep_shown_gone(&self) -> bool {
        let swept = self.with_state(|s| {
            if !lease_current(s) {
                return false;
            }
            let gone: Vec<RobotKey> = s
                .robots
                .iter()
                .filter(|(_, e)| e.connected && e.written_at.is_some() && e.retries == 0)
                .filter(|(key, _)| s.queued.get(*key).is_none_or(|(p, _)| *p != Priority::Gone))
                .filter(|(key, e)| {
                    self.cached_robot(key).is_some_and(|r| {
                        is_shown_gone(&r)
                            && r.status.as_ref().and_then(|st| st.session_epoch) == Some(e.epoch)
                    })
                })
                .map(|(key, _)| key.clone())
                .collect();
            for key in &gone {
                s.enqueue(key, Priority::Gone);
            }
            !gone.is_empty()
        });
        if swept {
            self.wake();
        }
        swept
    }

    /// The Robot cache shows `key`'s status naming another gateway (`other`) with session
    /// epoch `epoch`: if this gateway's session of the robot is later (see
    /// [`lekiwi_liveness::holder::later`]) and not written yet, the robot moved here after all.
    /// It is claimed and its write goes first, as if the session had known at its start.
    /// `true` if it was not claimed before.
    pub fn moved_later(&self, key: &RobotKey, epoch: i64, other: &str) -> bool {
        let gateway = self.config.gateway.as_str();
        let claimed = self.with_state(|s| {
            let Some(e) = s.robots.get_mut(key) else {
                return false;
            };
            let ours_later = lekiwi_liveness::holder::later(e.epoch, gateway, epoch, other);
            if !e.connected || e.moved || !ours_later || e.written_at.is_some() {
                return false;
            }
            e.moved = true;
            e.settling = false;
            s.enqueue(key, Priority::Move);
            true
        });
        if claimed {
            self.claims_changed.notify_one();
            self.wake();
        }
        claimed
    }
}
