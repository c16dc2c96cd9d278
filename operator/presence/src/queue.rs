//! The presence state behind one lock: what each robot last said, and the four write queues
//! (robots shown gone, moves, transitions, refreshes) that hold each robot at most once.

use std::collections::{HashMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use super::Entry;
use lekiwi_core::RobotKey;

/// Which queue a robot waits in for its status write: robots shown gone while connected here
/// overtake moves, which overtake other transitions, which overtake routine refreshes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Priority {
    /// A robot whose session here is live and whose status shows it `Unknown` or `Offline`:
    /// one that moved here after the Robot controller marked it, or one marked under this
    /// gateway's own session while its writes ran late. The robot shown wrong, not just
    /// through a gateway that is gone (see [`super::claims::is_shown_gone`]).
    Gone,
    /// A new session of a robot whose status names another gateway (it moved here, e.g. after
    /// its gateway died): until written, the old gateway's death could turn it `Unknown`.
    Move,
    /// Connects, disconnects and other transitions.
    High,
    /// Routine `lastHeartbeatTime` refreshes.
    Low,
}

impl Priority {
    /// Every priority, the one written first first.
    pub(super) const ALL: [Priority; 4] = [
        Priority::Gone,
        Priority::Move,
        Priority::High,
        Priority::Low,
    ];

    /// Its queue's place in `State::queues` and in [`Priority::ALL`]: lower goes first.
    pub(super) fn index(self) -> usize {
        match self {
            Priority::Gone => 0,
            Priority::Move => 1,
            Priority::High => 2,
            Priority::Low => 3,
        }
    }

    pub(super) fn label(self) -> &'static str {
        match self {
            Priority::Gone => "gone",
            Priority::Move => "move",
            Priority::High => "high",
            Priority::Low => "low",
        }
    }
}

#[derive(Default)]
pub(super) struct State {
    /// Boxed: the table keeps room for more entries than it holds, and an entry is over a KiB.
    pub(super) robots: HashMap<RobotKey, Box<Entry>>,
    /// Robots this gateway last wrote as disconnected (and then forgot): a new session of one
    /// of them is written only once it has lasted [`super::SETTLE`], so a session that opens
    /// and fails at once (a stolen token in a loop) costs the API server nothing.
    pub(super) known_offline: HashSet<RobotKey>,
    /// Each waiting robot's priority and since when it waits (kept when it is promoted).
    pub(super) queued: HashMap<RobotKey, (Priority, Instant)>,
    /// The queue of each priority, in [`Priority::ALL`]'s order (see [`Priority::index`]).
    pub(super) queues: [VecDeque<RobotKey>; 4],
    /// Robots whose status write is in flight, each with the priority it was queued at again
    /// meanwhile: one write per robot at a time, so an older snapshot never lands after a newer.
    pub(super) writing: HashMap<RobotKey, Option<Priority>>,
    /// The highest wait [`State::oldest_wait`] reported and when: what it reports decays from
    /// there at one second per second.
    pub(super) wait_peak: Option<(Duration, Instant)>,
    /// When [`super::Presence::tick`] last looked for robots shown gone under their live
    /// session here.
    pub(super) gone_swept: Option<Instant>,
    /// Until when this gateway's last renewed Lease lasts (see
    /// [`super::Presence::lease_renewed`]).
    pub(super) lease_until: Option<Instant>,
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
    /// session must be written too, so it no longer settles, and what a restart grace held
    /// back is in this write.
    pub(super) fn take_for_write(&mut self, key: &RobotKey) -> Option<Entry> {
        self.robots.get_mut(key).map(|e| {
            e.settling = false;
            e.restart_grace = 0;
            Entry::clone(e)
        })
    }

    pub(super) fn enqueue(&mut self, key: &RobotKey, priority: Priority) {
        // A robot already waiting at this priority or above stays where it is; one waiting
        // lower is promoted: it stays in its old queue too, but is skipped there because
        // `queued` names the new priority.
        let since = match self.queued.get(key) {
            Some(&(p, _)) if p.index() <= priority.index() => return,
            Some(&(_, since)) => since,
            None => Instant::now(),
        };
        self.queued.insert(key.clone(), (priority, since));
        self.queues[priority.index()].push_back(key.clone());
    }

    /// Claims the write of `key` (taken from the queues at `priority`); `false` when one is in
    /// flight already: then it is queued again at `priority` once that one ends.
    pub(super) fn begin_write(&mut self, key: &RobotKey, priority: Priority) -> bool {
        match self.writing.get_mut(key) {
            Some(again) => {
                if again.is_none_or(|p| p.index() > priority.index()) {
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
        for priority in Priority::ALL {
            let queue = &mut self.queues[priority.index()];
            while let Some(key) = queue.pop_front() {
                if self.queued.get(&key).is_some_and(|&(p, _)| p == priority) {
                    self.queued.remove(&key);
                    return Some((key, priority));
                }
            }
        }
        None
    }

    /// How long the robot next in line has waited for its status write, the longest of the
    /// three queues; held as a peak that decays at one second per second, so it does not drop
    /// to nothing while the writes of the robots that waited longest are still in flight.
    pub(super) fn oldest_wait(&mut self, now: Instant) -> Duration {
        let mut wait = Duration::ZERO;
        for priority in Priority::ALL {
            let queue = &mut self.queues[priority.index()];
            // Entries of robots promoted or dropped meanwhile are skipped by `pop` anyway.
            while let Some(key) = queue.front() {
                match self.queued.get(key) {
                    Some(&(p, since)) if p == priority => {
                        wait = wait.max(now.saturating_duration_since(since));
                        break;
                    }
                    _ => {
                        queue.pop_front();
                    }
                }
            }
        }
        let decayed = self.wait_peak.map_or(Duration::ZERO, |(peak, at)| {
            peak.saturating_sub(now.saturating_duration_since(at))
        });
        if wait >= decayed {
            self.wait_peak = Some((wait, now));
        }
        wait.max(decayed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(name: &str) -> RobotKey {
        RobotKey::new("fleet", name)
    }

    /// The wait of the robot next in line, the longest over the queues; a promoted robot keeps
    /// its wait; once the queues empty, the last peak decays at one second per second.
    #[test]
    fn the_oldest_wait_is_the_next_in_lines_and_decays() {
        let mut s = State::default();
        let t0 = Instant::now();
        let secs = Duration::from_secs;
        assert_eq!(s.oldest_wait(t0), Duration::ZERO);
        s.enqueue(&key("a"), Priority::Low);
        s.enqueue(&key("b"), Priority::Low);
        let waited = s.oldest_wait(t0 + secs(10));
        // Enqueued a moment after `t0`.
        assert!(waited > secs(9) && waited <= secs(10), "{waited:?}");
        // `a` promoted: it is skipped in the low queue and keeps its wait in the high one.
        let since = s.queued[&key("a")].1;
        s.enqueue(&key("a"), Priority::High);
        assert_eq!(s.queued[&key("a")], (Priority::High, since));
        assert_eq!(
            s.pop().map(|(k, p)| (k.name, p)),
            Some(("a".into(), Priority::High))
        );
        let waited = s.oldest_wait(t0 + secs(20));
        assert!(
            waited > secs(19) && waited <= secs(20),
            "b waits: {waited:?}"
        );
        assert_eq!(
            s.pop().map(|(k, p)| (k.name, p)),
            Some(("b".into(), Priority::Low))
        );
        assert_eq!(s.pop(), None);
        // Nothing waits: the peak of 20 s decays.
        let held = s.oldest_wait(t0 + secs(25));
        assert!(held > secs(14) && held <= secs(15), "{held:?}");
        assert_eq!(s.oldest_wait(t0 + secs(45)), Duration::ZERO);
    }
}
