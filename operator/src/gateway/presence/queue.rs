//! The presence state behind one lock: what each robot last said, and the three write queues
//! (moves, transitions, refreshes) that hold each robot at most once.

use std::collections::{HashMap, HashSet, VecDeque};

use super::{Entry, Priority};
use crate::gateway::event_store::RobotKey;

#[derive(Default)]
pub(super) struct State {
    /// Boxed: the table keeps room for more entries than it holds, and an entry is over a KiB.
    pub(super) robots: HashMap<RobotKey, Box<Entry>>,
    /// Robots this gateway last wrote as disconnected (and then forgot): a new session of one
    /// of them is written only once it has lasted [`super::SETTLE`], so a session that opens
    /// and fails at once (a stolen token in a loop) costs the API server nothing.
    pub(super) known_offline: HashSet<RobotKey>,
    pub(super) queued: HashMap<RobotKey, Priority>,
    pub(super) moves: VecDeque<RobotKey>,
    pub(super) high: VecDeque<RobotKey>,
    pub(super) low: VecDeque<RobotKey>,
    /// Robots whose status write is in flight, each with the priority it was queued at again
    /// meanwhile: one write per robot at a time, so an older snapshot never lands after a newer.
    pub(super) writing: HashMap<RobotKey, Option<Priority>>,
}

impl State {
    /// The entry of `key` if `session` is its current, connected session; `None` for a stale
    /// session that a newer one replaced.
    pub(super) fn live_session(&mut self, key: &RobotKey, session: u64) -> Option<&mut Entry> {
        self.robots
            .get_mut(key)
            .filter(|e| e.session == session && e.connected)
            .map(|e| &mut **e)
    }

    /// The entry of `key` as the writer takes it to write: from now on a disconnect of its
    /// session must be written too, so it no longer settles.
    pub(super) fn take_for_write(&mut self, key: &RobotKey) -> Option<Entry> {
        self.robots.get_mut(key).map(|e| {
            e.settling = false;
            Entry::clone(e)
        })
    }

    pub(super) fn enqueue(&mut self, key: &RobotKey, priority: Priority) {
        // A robot already waiting at this priority or above stays where it is; one waiting
        // lower is promoted: it stays in its old queue too, but is skipped there because
        // `queued` names the new priority.
        if self
            .queued
            .get(key)
            .is_some_and(|&p| p.rank() >= priority.rank())
        {
            return;
        }
        self.queued.insert(key.clone(), priority);
        match priority {
            Priority::Move => self.moves.push_back(key.clone()),
            Priority::High => self.high.push_back(key.clone()),
            Priority::Low => self.low.push_back(key.clone()),
        }
    }

    /// Claims the write of `key` (taken from the queues at `priority`); `false` when one is in
    /// flight already: then it is queued again at `priority` once that one ends.
    pub(super) fn begin_write(&mut self, key: &RobotKey, priority: Priority) -> bool {
        match self.writing.get_mut(key) {
            Some(again) => {
                if again.is_none_or(|p| p.rank() < priority.rank()) {
                    *again = Some(priority);
                }
                false
            }
            None => {
                self.writing.insert(key.clone(), None);
                true
            }
        }
    }

    /// The write of `key` ended (written or not): one asked for meanwhile is queued now.
    pub(super) fn end_write(&mut self, key: &RobotKey) {
        if let Some(Some(priority)) = self.writing.remove(key)
            && self.robots.contains_key(key)
        {
            self.enqueue(key, priority);
        }
    }

    pub(super) fn pop(&mut self) -> Option<(RobotKey, Priority)> {
        for priority in [Priority::Move, Priority::High, Priority::Low] {
            let queue = match priority {
                Priority::Move => &mut self.moves,
                Priority::High => &mut self.high,
                Priority::Low => &mut self.low,
            };
            while let Some(key) = queue.pop_front() {
                if self.queued.get(&key) == Some(&priority) {
                    self.queued.remove(&key);
                    return Some((key, priority));
                }
            }
        }
        None
    }
}
