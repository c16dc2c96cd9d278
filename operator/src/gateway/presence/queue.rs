//! The presence state behind one lock: what each robot last said, and the two write queues
//! that hold each robot at most once.

use std::collections::{HashMap, HashSet, VecDeque};

use super::{Entry, Priority};
use crate::gateway::event_store::RobotKey;

#[derive(Default)]
pub(super) struct State {
    pub(super) robots: HashMap<RobotKey, Entry>,
    /// Robots this gateway last wrote as disconnected (and then forgot): a new session of one
    /// of them is written only once it has lasted [`super::SETTLE`], so a session that opens
    /// and fails at once (a stolen token in a loop) costs the API server nothing.
    pub(super) known_offline: HashSet<RobotKey>,
    pub(super) queued: HashMap<RobotKey, Priority>,
    pub(super) high: VecDeque<RobotKey>,
    pub(super) low: VecDeque<RobotKey>,
}

impl State {
    /// The entry of `key` if `session` is its current, connected session; `None` for a stale
    /// session that a newer one replaced.
    pub(super) fn live_session(&mut self, key: &RobotKey, session: u64) -> Option<&mut Entry> {
        self.robots
            .get_mut(key)
            .filter(|e| e.session == session && e.connected)
    }

    /// The entry of `key` as the writer takes it to write: from now on a disconnect of its
    /// session must be written too, so it no longer settles.
    pub(super) fn take_for_write(&mut self, key: &RobotKey) -> Option<Entry> {
        self.robots.get_mut(key).map(|e| {
            e.settling = false;
            e.clone()
        })
    }

    pub(super) fn enqueue(&mut self, key: &RobotKey, priority: Priority) {
        match self.queued.get(key) {
            Some(Priority::High) => {}
            Some(Priority::Low) if priority == Priority::Low => {}
            _ => {
                // A robot waiting as Low is promoted: it stays in `low` too, but is skipped
                // there because `queued` says High.
                self.queued.insert(key.clone(), priority);
                match priority {
                    Priority::High => self.high.push_back(key.clone()),
                    Priority::Low => self.low.push_back(key.clone()),
                }
            }
        }
    }

    pub(super) fn pop(&mut self) -> Option<(RobotKey, Priority)> {
        while let Some(key) = self.high.pop_front() {
            if self.queued.get(&key) == Some(&Priority::High) {
                self.queued.remove(&key);
                return Some((key, Priority::High));
            }
        }
        while let Some(key) = self.low.pop_front() {
            if self.queued.get(&key) == Some(&Priority::Low) {
                self.queued.remove(&key);
                return Some((key, Priority::Low));
            }
        }
        None
    }
}
