//! Reconcile requests from outside a controller's own watch that coalesce instead of being
//! dropped: a request for an object already waiting is merged into it, so the queue is bounded
//! by the number of objects and never refuses one.
//!
//! Why not `Controller::watches`: the Robot controller's requests come from a timer (a gateway
//! Lease expiring produces no watch event), and the RobotDeployment controller must not plan
//! before its Robot store has listed every robot (an empty store would read as zero targeted
//! robots), which its own reflector task waits for before the controller starts; a `watches`
//! stream would only be polled once the controller runs.

use std::collections::{HashSet, VecDeque};
use std::hash::Hash;
use std::sync::{Arc, Mutex};

use futures::Stream;
use kube::Resource;
use kube::runtime::reflector::ObjectRef;
use tokio::sync::Notify;

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
}

/// Requests in arrival order, and the same set for merging duplicates.
struct Queue<K: Resource>
where
    K::DynamicType: Eq + Hash,
{
    order: VecDeque<ObjectRef<K>>,
    waiting: HashSet<ObjectRef<K>>,
}

impl<K: Resource> Shared<K>
where
    K::DynamicType: Eq + Hash + Clone,
{
    fn pop(&self) -> Option<ObjectRef<K>> {
        let mut pending = self.pending.lock().unwrap_or_else(|p| p.into_inner());
        let next = pending.order.pop_front()?;
        pending.waiting.remove(&next);
        Some(next)
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
    let shared = Arc::new(Shared {
        pending: Mutex::new(Queue {
            order: VecDeque::new(),
            waiting: HashSet::new(),
        }),
        wake: Notify::new(),
    });
    let requests = futures::stream::unfold(shared.clone(), |shared| async move {
        loop {
            if let Some(next) = shared.pop() {
                return Some((next, shared));
            }
            shared.wake.notified().await;
        }
    });
    (Trigger { shared }, requests)
}

impl<K: Resource> Trigger<K>
where
    K::DynamicType: Eq + Hash + Clone,
{
    /// Asks for `object` to be reconciled; returns false when a request for it was already
    /// waiting (the two are one reconcile).
    pub fn request(&self, object: ObjectRef<K>) -> bool {
        let new = {
            let mut pending = self
                .shared
                .pending
                .lock()
                .unwrap_or_else(|p| p.into_inner());
            let new = pending.waiting.insert(object.clone());
            if new {
                pending.order.push_back(object);
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
}
