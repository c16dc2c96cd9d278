//! The sessions this gateway holds, one per robot: how a newer connection replaces an older one
//! and how the rest of the gateway reaches a robot's session.

use std::collections::HashMap;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::mailbox::{self, Receiver, Sender};
use lekiwi_core::RobotKey;
use lekiwi_core::rate::TokenBucket;
use lekiwi_crds::AgentRef;
use lekiwi_protocol::{Release, ServerMessage};

/// Robots whose session-opening budget is tracked at most; past it the full (idle) ones go.
const MAX_OPEN_BUDGETS: usize = 50_000;

/// What the rest of the gateway tells a running session.
#[derive(Debug)]
pub enum Control {
    /// A newer connection of the same robot took over; this one closes.
    Replaced,
    /// A later session of the robot on another gateway replica took over (its status shows a
    /// higher session epoch); this one closes and leaves the status to that gateway.
    Moved,
    /// Send this to the agent.
    /// Boxed: the channel's slots are allocated per connection, so keep them pointer-sized.
    Send(Box<ServerMessage>),
    /// The robot's `spec.release` changed to `release`; the session sends a deploy command if
    /// due, unless `held`: a rollout a user aborted or undid told the robot to switch only after
    /// the request (see [`super::halt`]), and the release is not deployed in this session.
    Desired {
        release: Option<Box<Release>>,
        held: bool,
    },
    /// A user aborted or undid the rollout of this release: the session cancels a deploy of it
    /// in flight at once, before the Robot's `spec.release` changes (see
    /// [`super::halt`]).
    Halt(Box<Release>),
    /// The robot's `spec.agent` changed to this; the session sends `update_agent` if due.
    DesiredAgent(Option<Box<AgentRef>>),
    /// The robot's token Secret changed (`deleted`: it is gone); the session checks that the
    /// token it was opened with still counts and closes if not.
    Credentials {
        /// The Secret was deleted (or lost our labels).
        deleted: bool,
    },
}

/// One registered session: its id, its session epoch (see [`lekiwi_presence::holder`]) and the channel
/// that reaches it.
struct Slot {
    id: u64,
    epoch: i64,
    tx: Sender<Control>,
}

/// The sessions of this gateway, one per robot, each with the channel that reaches it, and how
/// fast each robot may open new ones.
#[derive(Default)]
pub struct Registry {
    next: AtomicU64,
    sessions: Mutex<HashMap<RobotKey, Slot>>,
    /// Sessions per minute and burst one robot may open; `None`: no limit.
    open_rate: Option<(f64, u32)>,
    opens: Mutex<HashMap<RobotKey, TokenBucket>>,
}

impl Registry {
    /// A registry that lets each robot open `per_minute` sessions a minute (`burst` at once);
    /// a `per_minute` of 0 sets no limit.
    pub fn with_open_rate(per_minute: f64, burst: u32) -> Self {
        Self {
            open_rate: (per_minute > 0.0).then_some((per_minute / 60.0, burst)),
            ..Self::default()
        }
    }

    /// Takes one session opening from `key`'s budget; `Err(seconds)` until the next one when it
    /// is spent. Only authenticated robots reach this, so the map holds at most the fleet.
    pub fn may_open(&self, key: &RobotKey) -> Result<(), u64> {
        let Some((rate, burst)) = self.open_rate else {
            return Ok(());
        };
        let mut opens = self.opens.lock().unwrap_or_else(|p| p.into_inner());
        if opens.len() >= MAX_OPEN_BUDGETS && !opens.contains_key(key) {
            opens.retain(|_, bucket| !bucket.is_full());
        }
        let bucket = opens
            .entry(key.clone())
            .or_insert_with(|| TokenBucket::new(rate, burst));
        if bucket.try_take() {
            Ok(())
        } else {
            Err(bucket.wait_seconds().max(1))
        }
    }

    /// Registers a new session for `key` with session epoch `epoch`, telling an older one that
    /// it was replaced; returns the session's id and the channel it reads its [`Control`]
    /// messages from.
    pub(super) fn register(&self, key: &RobotKey, epoch: i64) -> (u64, Receiver<Control>) {
        let id = self.next.fetch_add(1, Ordering::Relaxed) + 1;
        let (tx, rx) = mailbox::mailbox(16);
        let old = self.lock().insert(key.clone(), Slot { id, epoch, tx });
        if let Some(old) = old {
            let _ = old.tx.try_send(Control::Replaced);
        }
        (id, rx)
    }

    /// Removes the session unless a newer one replaced it already.
    pub(super) fn unregister(&self, key: &RobotKey, id: u64) {
        let mut sessions = self.lock();
        if sessions.get(key).is_some_and(|slot| slot.id == id) {
            sessions.remove(key);
        }
    }

    /// Another gateway's session holds the robot now: this gateway's session of it, if that
    /// one is later (`later_than` its epoch; see [`lekiwi_presence::holder::later`]), is told to
    /// close ([`Control::Moved`]). True when one was told.
    pub fn moved(&self, key: &RobotKey, later_than: impl FnOnce(i64) -> bool) -> bool {
        self.lock()
            .get(key)
            .filter(|slot| later_than(slot.epoch))
            .is_some_and(|slot| put(&slot.tx, Control::Moved))
    }

    /// Tells a robot's session that its desired release changed (`held`: not to be deployed,
    /// see [`Control::Desired`]); false when the robot has no session here. Never lost to a
    /// full mailbox (see [`put`]).
    pub fn notify_desired_release(
        &self,
        key: &RobotKey,
        release: Option<Release>,
        held: bool,
    ) -> bool {
        let release = release.map(Box::new);
        self.put(key, Control::Desired { release, held })
    }

    /// Tells a robot's session to stop a download of `release` in flight; false when the robot
    /// has no session here. Never lost to a full mailbox (see [`put`]).
    pub fn notify_halt(&self, key: &RobotKey, release: Release) -> bool {
        self.put(key, Control::Halt(Box::new(release)))
    }

    /// Tells a robot's session that its desired agent changed; false when the robot has no
    /// session here. Never lost to a full mailbox (see [`put`]).
    pub fn notify_desired_agent(&self, key: &RobotKey, agent: Option<AgentRef>) -> bool {
        self.put(key, Control::DesiredAgent(agent.map(Box::new)))
    }

    /// Tells a robot's session that its token Secret changed; false when the robot has no
    /// session here. Never lost to a full mailbox (see [`put`]).
    pub fn notify_credentials(&self, key: &RobotKey, deleted: bool) -> bool {
        self.put(key, Control::Credentials { deleted })
    }

    /// Tells every session to check its token again; returns how many were told. After the
    /// token Secrets were listed anew, a Secret deleted while the watch was down shows only as
    /// missing from the list, never as a deletion.
    pub fn recheck_all_credentials(&self) -> usize {
        self.lock()
            .values()
            .filter(|slot| put(&slot.tx, Control::Credentials { deleted: false }))
            .count()
    }

    /// Sends a message to a robot's session; false when the robot has no session here or its
    /// channel is full.
    pub fn send(&self, key: &RobotKey, msg: ServerMessage) -> bool {
        self.try_send(key, Control::Send(Box::new(msg)))
    }

    /// Sessions open now.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// Whether no session is open.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn try_send(&self, key: &RobotKey, control: Control) -> bool {
        self.lock()
            .get(key)
            .is_some_and(|slot| slot.tx.try_send(control).is_ok())
    }

    fn put(&self, key: &RobotKey, control: Control) -> bool {
        self.lock()
            .get(key)
            .is_some_and(|slot| put(&slot.tx, control))
    }

    /// The sessions map; a panic elsewhere while holding it leaves the map itself consistent.
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<RobotKey, Slot>> {
        self.sessions.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Queues `control`, a state (what the robot should run, whether its token still counts, that
/// it moved), so that a full mailbox never loses it: a queued control of the same kind is
/// replaced ([`Control::merge`]). A session busy sending to a slow socket while the gateway
/// relists its Robots and its token Secrets could otherwise miss the one `Desired` that starts
/// its update, and wait for the next change of its Robot. False when the session is gone.
fn put(tx: &Sender<Control>, control: Control) -> bool {
    let kind = std::mem::discriminant(&control);
    tx.put(
        control,
        |queued| std::mem::discriminant(queued) == kind,
        Control::merge,
    )
    .is_ok()
}

impl Control {
    /// A newer control of the same kind, folded into the queued one: the newer wins, except
    /// that a deleted token Secret stays deleted.
    fn merge(queued: Control, newer: Control) -> Control {
        match (queued, newer) {
            (Control::Credentials { deleted: a }, Control::Credentials { deleted: b }) => {
                Control::Credentials { deleted: a || b }
            }
            (_, newer) => newer,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Another gateway's later session closes ours; an earlier one does not, nor one with the
    /// same epoch on a gateway whose name sorts before ours (`gw-m` here).
    #[test]
    fn only_a_later_session_elsewhere_moves_ours() {
        use lekiwi_presence::holder::later;
        let registry = Registry::default();
        let key = RobotKey::new("lab", "kiwi");
        let (_, mut rx) = registry.register(&key, 100);
        let session =
            |epoch: i64, gateway: &'static str| move |ours| later(epoch, gateway, ours, "gw-m");
        assert!(!registry.moved(&key, session(50, "gw-z")));
        assert!(!registry.moved(&key, session(100, "gw-a")));
        assert!(rx.try_recv().is_none());
        assert!(registry.moved(&key, session(100, "gw-z")));
        assert!(matches!(rx.try_recv(), Some(Control::Moved)));
        let (_, mut rx) = registry.register(&key, 100);
        assert!(registry.moved(&key, session(200, "gw-a")));
        assert!(matches!(rx.try_recv(), Some(Control::Moved)));
        assert!(!registry.moved(&RobotKey::new("lab", "other"), session(200, "gw-a")));
    }

    /// A session whose mailbox is full of messages still gets the latest desired release and
    /// agent, once each, and a revocation is not undone by a later recheck.
    #[test]
    fn a_full_mailbox_keeps_the_latest_state_of_each_kind() {
        let registry = Registry::default();
        let key = RobotKey::new("lab", "kiwi");
        let (_, mut rx) = registry.register(&key, 100);
        while registry.send(&key, ServerMessage::Ack { seq: 1 }) {}
        let release = |v: &str| Release {
            version: v.into(),
            digest: format!("sha256:{}", "a".repeat(64)),
        };
        assert!(registry.notify_desired_release(&key, Some(release("1.0.0")), false));
        assert!(registry.notify_credentials(&key, true));
        assert!(registry.notify_desired_release(&key, Some(release("2.0.0")), true));
        assert_eq!(registry.recheck_all_credentials(), 1);
        assert!(registry.notify_desired_agent(&key, None));
        let mut states = Vec::new();
        while let Some(c) = rx.try_recv() {
            if !matches!(c, Control::Send(_)) {
                states.push(c);
            }
        }
        assert_eq!(states.len(), 3, "{states:?}");
        assert!(
            matches!(&states[0], Control::Desired { release: Some(r), held: true } if r.version == "2.0.0"),
            "{states:?}"
        );
        assert!(matches!(states[1], Control::Credentials { deleted: true }));
        assert!(matches!(states[2], Control::DesiredAgent(None)));
    }
}
