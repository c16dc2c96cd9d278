//! A session's mailbox: a bounded queue with one sender (the registry) and one receiver (the
//! session). It does what a `tokio::sync::mpsc` channel of capacity 16 did here, in about a
//! tenth of the memory: a tokio channel allocates a block of 32 slots and cache-line-padded
//! state when it is created, about 1.2 KiB, and a gateway holds one per connection for as long
//! as the connection lives, while almost every session receives nothing at all.
//!
//! Two kinds of message go through it: events, which a full mailbox refuses
//! ([`Sender::try_send`]), and states, which it never loses ([`Sender::put`]): a newer state
//! replaces the queued one of its kind, so each kind is queued once at most.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::Notify;

/// A mailbox holding at most `capacity` messages; the receiver sees the end once the sender is
/// gone and the queue is empty.
pub fn mailbox<T>(capacity: usize) -> (Sender<T>, Receiver<T>) {
    let shared = Arc::new(Shared {
        state: Mutex::new(State {
            queue: VecDeque::new(),
            capacity,
            sender_gone: false,
            receiver_gone: false,
        }),
        wake: Notify::new(),
    });
    (Sender(shared.clone()), Receiver(shared))
}

struct Shared<T> {
    state: Mutex<State<T>>,
    /// Wakes the receiver; a wake-up with nobody waiting is kept for its next wait.
    wake: Notify,
}

struct State<T> {
    queue: VecDeque<T>,
    capacity: usize,
    sender_gone: bool,
    receiver_gone: bool,
}

impl<T> Shared<T> {
    /// The state; a panic elsewhere while holding it leaves the queue itself consistent.
    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The sending half (not `Clone`: one sender per mailbox).
pub struct Sender<T>(Arc<Shared<T>>);

/// The receiving half.
pub struct Receiver<T>(Arc<Shared<T>>);

impl<T> Sender<T> {
    /// Queues `message` without waiting; gives it back when the mailbox is full or its
    /// receiver is gone.
    pub fn try_send(&self, message: T) -> Result<(), T> {
        {
            let mut state = self.0.lock();
            if state.receiver_gone || state.queue.len() >= state.capacity {
                return Err(message);
            }
            state.queue.push_back(message);
        }
        self.0.wake.notify_one();
        Ok(())
    }
}

impl<T> Sender<T> {
    /// Queues `message` as a state rather than an event: a queued message `same` holds for
    /// (the same kind) leaves the queue and `merge(queued, message)` joins its end instead;
    /// with none, `message` joins the end even when the mailbox is full. A kind always put
    /// this way is queued once at most, so the queue holds at most the capacity plus the
    /// number of such kinds. Gives `message` back only when the receiver is gone.
    pub fn put(
        &self,
        message: T,
        same: impl Fn(&T) -> bool,
        merge: impl FnOnce(T, T) -> T,
    ) -> Result<(), T> {
        {
            let mut state = self.0.lock();
            if state.receiver_gone {
                return Err(message);
            }
            let queued = state.queue.iter().position(&same);
            let message = match queued.and_then(|i| state.queue.remove(i)) {
                Some(queued) => merge(queued, message),
                None => message,
            };
            state.queue.push_back(message);
        }
        self.0.wake.notify_one();
        Ok(())
    }
}

impl<T> Drop for Sender<T> {
    fn drop(&mut self) {
        self.0.lock().sender_gone = true;
        self.0.wake.notify_one();
    }
}

impl<T> Receiver<T> {
    /// The next message, waiting for one; `None` once the sender is gone and nothing is left.
    /// Cancel safe: a message is only taken off the queue by a call that returns it.
    pub async fn recv(&mut self) -> Option<T> {
        loop {
            {
                let mut state = self.0.lock();
                if let Some(message) = state.queue.pop_front() {
                    return Some(message);
                }
                if state.sender_gone {
                    return None;
                }
            }
            // A send between the check above and this wait leaves a wake-up for it.
            self.0.wake.notified().await;
        }
    }

    /// The next message if one is queued, without waiting.
    pub fn try_recv(&mut self) -> Option<T> {
        self.0.lock().queue.pop_front()
    }
}

impl<T> Drop for Receiver<T> {
    fn drop(&mut self) {
        let mut state = self.0.lock();
        state.receiver_gone = true;
        state.queue.clear();
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[tokio::test]
    async fn delivers_in_order_up_to_capacity_then_ends_with_the_sender() {
        let (tx, mut rx) = mailbox(2);
        assert!(tx.try_send(1).is_ok());
        assert!(tx.try_send(2).is_ok());
        assert_eq!(tx.try_send(3), Err(3), "full");
        assert_eq!(rx.recv().await, Some(1));
        assert!(tx.try_send(4).is_ok(), "room again");
        drop(tx);
        assert_eq!(
            rx.recv().await,
            Some(2),
            "queued messages outlive the sender"
        );
        assert_eq!(rx.recv().await, Some(4));
        assert_eq!(rx.recv().await, None);
    }

    #[tokio::test]
    async fn a_waiting_receiver_wakes_for_a_message_and_for_the_end() {
        let (tx, mut rx) = mailbox(16);
        let waiting = tokio::spawn(async move { (rx.recv().await, rx.recv().await) });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(tx.try_send("hello").is_ok());
        drop(tx);
        let got = tokio::time::timeout(Duration::from_secs(5), waiting).await;
        assert_eq!(got.unwrap().unwrap(), (Some("hello"), None));
    }

    #[tokio::test]
    async fn a_cancelled_wait_loses_nothing() {
        let (tx, mut rx) = mailbox(16);
        // A wait given up (as a `select!` does with the branch that did not win)...
        let gave_up = tokio::time::timeout(Duration::from_millis(10), rx.recv()).await;
        assert!(gave_up.is_err());
        // ...leaves the message sent afterwards for the next wait.
        assert!(tx.try_send(7).is_ok());
        let got = tokio::time::timeout(Duration::from_secs(5), rx.recv()).await;
        assert_eq!(got.unwrap(), Some(7));
    }

    #[test]
    fn a_gone_receiver_refuses_messages() {
        let (tx, rx) = mailbox(16);
        drop(rx);
        assert_eq!(tx.try_send(1), Err(1));
        assert_eq!(tx.put(2, |_| true, |_, new| new), Err(2));
    }

    /// A state put into a full mailbox is kept; a newer state of the same kind replaces it
    /// (merged, at the end of the queue), so the queue grows by one per kind at most.
    #[tokio::test]
    async fn a_state_is_never_lost_and_queued_once_per_kind() {
        let (tx, mut rx) = mailbox(2);
        let even = |n: &i32| n % 2 == 0;
        assert!(tx.try_send(1).is_ok());
        assert!(tx.try_send(3).is_ok());
        assert_eq!(tx.try_send(5), Err(5), "full for events");
        assert!(
            tx.put(10, even, |_, new| new).is_ok(),
            "a state still goes in"
        );
        assert!(tx.try_send(7).is_err());
        assert!(tx.put(20, even, |old, new| old + new).is_ok(), "merged");
        let mut got = Vec::new();
        while let Some(n) = rx.try_recv() {
            got.push(n);
        }
        assert_eq!(
            got,
            vec![1, 3, 30],
            "one state, the merge of both, after the events"
        );
    }

    #[test]
    fn it_is_small() {
        // What a session holds for its whole life, against ~1.2 KiB for a tokio channel.
        assert!(std::mem::size_of::<Shared<super::super::registry::Control>>() <= 128);
    }
}
