//! Reconcile requests from outside a controller's own watch that coalesce instead of being
//! dropped: a request for an object already waiting is merged into it, so the queue is bounded
//! by the number of objects and never refuses one. A trigger may also space an object's
//! requests: one handed on is followed by the next for the same object no sooner than the
//! spacing later (the first goes at once; later ones wait out the rest of the spacing and merge
//! while they wait), so a burst of outside changes costs the object one reconcile per spacing.
//!
//! Why not `Controller::watches`: the Robot controller's requests come from a timer (a gateway
//! Lease expiring produces no watch event), and the RobotDeployment controller must not plan
//! before its Robot store has listed every robot (an empty store would read as zero targeted
//! robots), which its own reflector task waits for before the controller starts; a `watches`
//! stream would only be polled once the controller runs. Why not the controller's own
//! `debounce`: it is trailing, so an object whose inputs keep changing (a deployment whose
//! robots report every moment of a rollout) would wait for a quiet moment that never comes.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::hash::Hash;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::Stream;
use kube::Resource;
use kube::runtime::reflector::ObjectRef;
use tokio::sync::Notify;
use tokio::time::Instant;

/// The sending side: cheap to clone, never blocks, never loses a request.
pub struct Trigger<K: Resource>
where
    K::DynamicType: Eq + Hash,
{
    shared: Arc<Shared<K>>,
}

impl<K: Resource> Clone for Trigger<K>
where
    K::DynamicType: Eq + Hash,
{
    fn clone(&self) -> Self {
        Self {
            shared: self.shared.clone(),
        }
    }
}

struct Shared<K: Resource>
where
    K::DynamicType: Eq + Hash,
{
    pending: Mutex<Queue<K>>,
    /// Woken on every new request; a wake-up with nobody waiting is kept for the next wait.
    wake: Notify,
    /// The least time between two requests of one object handed on (zero: no spacing).
    spacing: Duration,
}

/// Requests ready in arrival order, requests held until their spacing has passed, the set of
/// both for merging duplicates, and when objects were last handed on (less than the spacing
/// ago; as many as objects handed on within one spacing).
struct Queue<K: Resource>
where
    K::DynamicType: Eq + Hash,
{
    order: VecDeque<ObjectRef<K>>,
    waiting: HashSet<ObjectRef<K>>,
    /// By the time each may go, then arrival (`seq`).
    held: BTreeMap<(Instant, u64), ObjectRef<K>>,
    seq: u64,
    handed: HashMap<ObjectRef<K>, Instant>,
}

impl<K: Resource> Queue<K>
where
    K::DynamicType: Eq + Hash + Clone,
{
    /// Forgets hand-offs older than `spacing` and moves the held requests due by `now` to the
    /// ready ones.
    fn advance(&mut self, now: Instant, spacing: Duration) {
        self.handed.retain(|_, at| *at + spacing > now);
        while let Some(entry) = self.held.first_entry()
            && entry.key().0 <= now
        {
            self.order.push_back(entry.remove());
        }
    }

    /// The next ready request, recorded as handed on at `now`.
    fn pop(&mut self, now: Instant, spacing: Duration) -> Option<ObjectRef<K>> {
        self.advance(now, spacing);
        let next = self.order.pop_front()?;
        self.waiting.remove(&next);
        if !spacing.is_zero() {
            self.handed.insert(next.clone(), now);
        }
        Some(next)
    }
}

impl<K: Resource> Shared<K>
where
    K::DynamicType: Eq + Hash + Clone,
{
    /// The next ready request, or when the first held one may go.
    fn pop(&self) -> Result<ObjectRef<K>, Option<Instant>> {
        let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
        let now = Instant::now();
        pending
            .pop(now, self.spacing)
            .ok_or_else(|| pending.held.keys().next().map(|(at, _)| *at))
    }
}

/// A trigger and the stream of its requests, for `Controller::reconcile_on`.
pub fn trigger<K>() -> (
    Trigger<K>,
    impl Stream<Item = ObjectRef<K>> + Send + 'static,
)
where
    K: Resource + Send + Sync + 'static,
    K::DynamicType: Eq + Hash + Clone + Send + Sync,
{
    spaced_trigger(Duration::ZERO)
}

/// A trigger that hands on an object's requests at least `spacing` apart, and the stream of
/// its requests.
pub fn spaced_trigger<K>(
    spacing: Duration,
) -> (
    Trigger<K>,
    impl Stream<Item = ObjectRef<K>> + Send + 'static,
)
where
    K: Resource + Send + Sync + 'static,
    K::DynamicType: Eq + Hash + Clone + Send + Sync,
{
    let shared = Arc::new(Shared {
        pending: Mutex::new(Queue {
            order: VecDeque::new(),
            waiting: HashSet::new(),
            held: BTreeMap::new(),
            seq: 0,
            handed: HashMap::new(),
        }),
        wake: Notify::new(),
        spacing,
    });
    let requests = futures::stream::unfold(shared.clone(), |shared| async move {
        loop {
            match shared.pop() {
                Ok(next) => return Some((next, shared)),
                Err(None) => shared.wake.notified().await,
                Err(Some(at)) => {
                    tokio::select! {
                        () = shared.wake.notified() => {}
                        () = tokio::time::sleep_until(at) => {}
                    }
                }
            }
        }
    });
    (Trigger { shared }, requests)
}

impl<K: Resource> Trigger<K>
where
    K::DynamicType: Eq + Hash + Clone,
{
    /// Asks for `object` to be reconciled: at once, or once the spacing since it was last
    /// handed on has passed; returns false when a request for it was already waiting (the two
    /// are one reconcile).
    pub fn request(&self, object: ObjectRef<K>) -> bool {
        let spacing = self.shared.spacing;
        let new = {
            let mut pending = self
                .shared
                .pending
                .lock()
                .unwrap_or_else(|p| p.into_inner());
            let new = pending.waiting.insert(object.clone());
            if new {
                let now = Instant::now();
                pending.advance(now, spacing);
                match pending.handed.get(&object).map(|at| *at + spacing) {
                    Some(due) if due > now => {
                        pending.seq += 1;
                        let seq = pending.seq;
                        pending.held.insert((due, seq), object);
                    }
                    _ => pending.order.push_back(object),
                }
            }
            new
        };
        if new {
            self.shared.wake.notify_one();
        }
        new
    }
}

#[cfg(test)]
mod tests {
    use futures::StreamExt;
    use k8s_openapi::api::core::v1::ConfigMap;

    use super::*;

    fn obj(name: &str) -> ObjectRef<ConfigMap> {
        ObjectRef::new(name).within("lab")
    }

    /// Far more requests than any channel buffer: none is lost, duplicates merge, order holds.
    #[tokio::test]
    async fn requests_coalesce_and_are_never_dropped() {
        let (trigger, requests) = trigger::<ConfigMap>();
        for round in 0..3 {
            for i in 0..5000 {
                assert_eq!(trigger.request(obj(&format!("cm-{i}"))), round == 0);
            }
        }
        let got: Vec<_> = requests.take(5000).collect().await;
        let want: Vec<_> = (0..5000).map(|i| obj(&format!("cm-{i}"))).collect();
        assert_eq!(got, want);
    }

    /// A request made while the stream waits wakes it; one made before the wait is kept.
    #[tokio::test]
    async fn a_waiting_stream_wakes_on_a_request() {
        let (trigger, requests) = trigger::<ConfigMap>();
        let mut requests = Box::pin(requests);
        let later = trigger.clone();
        let sender = tokio::spawn(async move {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
            later.request(obj("late"));
        });
        assert_eq!(requests.next().await, Some(obj("late")));
        sender.await.unwrap();
        trigger.request(obj("again"));
        assert_eq!(requests.next().await, Some(obj("again")));
    }

    /// With a spacing: an object's first request goes at once, the next waits out the rest of
    /// the spacing since the first was handed on, requests made meanwhile merge into it, and
    /// other objects are not held by it.
    #[tokio::test(start_paused = true)]
    async fn a_spaced_object_goes_at_most_once_per_spacing() {
        let spacing = std::time::Duration::from_secs(1);
        let (trigger, requests) = spaced_trigger::<ConfigMap>(spacing);
        let mut requests = Box::pin(requests);
        let start = Instant::now();
        assert!(trigger.request(obj("busy")));
        assert_eq!(requests.next().await, Some(obj("busy")));
        tokio::time::advance(std::time::Duration::from_millis(300)).await;
        assert!(trigger.request(obj("busy")));
        assert!(!trigger.request(obj("busy")), "merged while held");
        assert!(trigger.request(obj("quiet")));
        assert_eq!(requests.next().await, Some(obj("quiet")));
        assert_eq!(
            Instant::now() - start,
            std::time::Duration::from_millis(300)
        );
        assert_eq!(requests.next().await, Some(obj("busy")));
        assert_eq!(
            Instant::now() - start,
            spacing,
            "held until a spacing after the first"
        );
        // Long after: at once again.
        tokio::time::advance(spacing * 5).await;
        let before = Instant::now();
        assert!(trigger.request(obj("busy")));
        assert_eq!(requests.next().await, Some(obj("busy")));
        assert_eq!(Instant::now(), before);
    }
}
