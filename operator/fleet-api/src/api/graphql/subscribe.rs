//! GraphQL subscriptions: robots whose phase, vitals, release or labels change (a namespace and
//! label selector), and rollouts whose progress changes (a namespace, optionally one name).
//! Every subscriber reads the cache's one broadcast ([`lekiwi_core::cache::Cache::subscribe`]);
//! none opens a watch. Each keeps at most one pending state per object (the latest wins,
//! first come first sent), so its memory is bounded by the objects it matches; one that falls
//! more than the broadcast's buffer behind (a slow client) reads the current state from the
//! cache again instead of slowing anyone. Its permission (`watch` on the resource in the
//! namespace) is checked again every [`TTL`]; a revoked one ends the subscription with an error.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use async_graphql::{Context, Result, Subscription};
use futures::Stream;
use kube::Resource;
use lekiwi_crds::{Robot, RobotDeployment};
use tokio::sync::broadcast::{Receiver, error::RecvError, error::TryRecvError};

use super::query::{RobotObject, RolloutObject};
use super::{Caller, allowed, refusal};
use crate::api::check_names;
use crate::api::selector::Selector;
use crate::kube_auth::{Access, TTL};
use crate::{ApiError, FleetState};
use lekiwi_core::cache::{Cache, Change, Key, key};

/// Things (subscriptions, WebSockets) held per user, capped.
pub struct PerUser {
    /// What is held, plural, for the refusal's message.
    pub what: &'static str,
    /// Most of them one user may hold at once.
    pub max: usize,
    /// How many each user holds now.
    pub held: Mutex<HashMap<String, usize>>,
}

/// One held thing; dropping it gives the slot back.
pub(crate) struct Slot {
    owner: Arc<PerUser>,
    user: String,
}

impl PerUser {
    /// A slot for `user`, or a `forbidden` refusal when they hold `max` already.
    pub(crate) fn hold(self: &Arc<Self>, user: &str) -> Result<Slot> {
        let mut held = self.held.lock().unwrap_or_else(|p| p.into_inner());
        let n = held.entry(user.to_owned()).or_default();
        if *n >= self.max {
            let message = format!(
                "this user holds {} {}, the most allowed",
                self.max, self.what
            );
            return Err(refusal(ApiError::Forbidden(message)));
        }
        *n += 1;
        Ok(Slot {
            owner: self.clone(),
            user: user.to_owned(),
        })
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut held = self.owner.held.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = held.get_mut(&self.user) {
            *n -= 1;
            if *n == 0 {
                held.remove(&self.user);
            }
        }
    }
}

/// What one subscriber follows in one cache.
struct Feed<K> {
    cache: Arc<Cache<K>>,
    rx: Receiver<Change<K>>,
    namespace: String,
    /// Whether an object is one the subscriber asked for.
    wanted: Box<dyn Fn(&K) -> bool + Send + Sync>,
    /// Whether a change (from the first state to the second) is worth telling.
    relevant: fn(Option<&K>, &K) -> bool,
    /// Objects with a state not yet sent, oldest change first; the latest state of each.
    queue: VecDeque<Key>,
    latest: HashMap<Key, Arc<K>>,
    /// The permission re-checked every [`TTL`].
    state: FleetState,
    caller: Caller,
    access: Access,
    checked: Instant,
    _slot: Slot,
}

impl<K: Resource> Feed<K> {
    /// Keeps `o` as the latest state of its object, queued if it was not already.
    fn offer(&mut self, o: Arc<K>) {
        let k = key(o.as_ref());
        if self.latest.insert(k.clone(), o).is_none() {
            self.queue.push_back(k);
        }
    }

    fn absorb(&mut self, change: Change<K>) {
        match change {
            Change::Applied(old, new) => {
                if (self.wanted)(&new) && (self.relevant)(old.as_deref(), &new) {
                    self.offer(new);
                }
            }
            Change::Deleted(o) => {
                self.latest.remove(&key(o.as_ref()));
            }
        }
    }

    /// After falling behind the broadcast: every wanted object's current state.
    fn resync(&mut self) {
        let wanted = &self.wanted;
        let (all, _) = self
            .cache
            .page(Some(&self.namespace), None, usize::MAX, |o| wanted(o));
        all.into_iter().for_each(|o| self.offer(o));
    }

    /// The next state to send; `None` when the cache's watch has ended.
    async fn next(&mut self) -> Option<Result<Arc<K>>> {
        loop {
            loop {
                match self.rx.try_recv() {
                    Ok(change) => self.absorb(change),
                    Err(TryRecvError::Lagged(_)) => self.resync(),
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Closed) => return None,
                }
            }
            if let Some(k) = self.queue.pop_front() {
                let Some(o) = self.latest.remove(&k) else {
                    continue; // deleted meanwhile
                };
                if let Err(e) = self.recheck().await {
                    return Some(Err(e));
                }
                return Some(Ok(o));
            }
            match self.rx.recv().await {
                Ok(change) => self.absorb(change),
                Err(RecvError::Lagged(_)) => self.resync(),
                Err(RecvError::Closed) => return None,
            }
        }
    }

    /// The subscriber's permission, again once [`TTL`] has passed since the last check.
    async fn recheck(&mut self) -> Result<()> {
        if self.checked.elapsed() < TTL {
            return Ok(());
        }
        let auth = &self.state.kube_auth;
        auth.check(&self.caller.token, &self.access)
            .await
            .map_err(|d| refusal(self.state.denied(d)))?;
        self.checked = Instant::now();
        Ok(())
    }

    /// The feed as a stream that ends after an error.
    fn stream<T>(self, wrap: fn(Arc<K>) -> T) -> impl Stream<Item = Result<T>> + use<K, T>
    where
        K: Send + Sync + 'static,
    {
        futures::stream::unfold(Some(self), move |feed| async move {
            let mut feed = feed?;
            match feed.next().await? {
                Ok(o) => Some((Ok(wrap(o)), Some(feed))),
                Err(e) => Some((Err(e), None)),
            }
        })
    }
}

/// Where a feed reads (a cache of the gateway's state) and the resource RBAC names it by.
type Source<K> = (fn(&FleetState) -> Arc<Cache<K>>, &'static str);

/// The subscriber's permission, budget and slot, then a feed of `cache` in `namespace`.
async fn feed<K: Resource>(
    ctx: &Context<'_>,
    (cache, resource): Source<K>,
    namespace: String,
    wanted: Box<dyn Fn(&K) -> bool + Send + Sync>,
    relevant: fn(Option<&K>, &K) -> bool,
) -> Result<Feed<K>> {
    check_names(&namespace, None).map_err(refusal)?;
    let access = Access::new("watch", resource, &namespace);
    tracing::debug!(%namespace, resource, "GraphQL subscription requested");
    let (state, caller) = allowed(ctx, access.clone()).await?;
    if let Err(seconds) = state.fleet.limits.take(&caller.user) {
        state.count_refusal("rate_limited");
        return Err(refusal(ApiError::RateLimited(seconds)));
    }
    let slot = state.fleet.graphql.subscriptions.hold(&caller.user)?;
    tracing::debug!(user = %caller.user, %namespace, resource, "GraphQL subscription started");
    let cache = cache(state);
    Ok(Feed {
        rx: cache.subscribe(),
        cache,
        namespace,
        wanted,
        relevant,
        queue: VecDeque::new(),
        latest: HashMap::new(),
        state: state.clone(),
        caller: caller.clone(),
        access,
        checked: Instant::now(),
        _slot: slot,
    })
}

/// A robot change worth telling: new, or its phase, vitals, release or labels changed.
fn robot_changed(old: Option<&Robot>, new: &Robot) -> bool {
    let Some(old) = old else { return true };
    let (a, b) = (old.status.as_ref(), new.status.as_ref());
    a.map(|s| s.phase) != b.map(|s| s.phase)
        || a.map(|s| &s.telemetry) != b.map(|s| &s.telemetry)
        || a.map(|s| &s.current_release) != b.map(|s| &s.current_release)
        || old.metadata.labels != new.metadata.labels
}

/// A rollout change worth telling: new, paused or resumed, or its status changed.
fn rollout_changed(old: Option<&RobotDeployment>, new: &RobotDeployment) -> bool {
    old.is_none_or(|old| old.status != new.status || old.spec.paused != new.spec.paused)
}

/// The subscriptions (over the `graphql-transport-ws` WebSocket only).
pub struct SubscriptionRoot;

#[Subscription]
impl SubscriptionRoot {
    /// Robots of `namespace` matching `labelSelector` (all if absent), each time one's phase,
    /// vitals, running release or labels change (new robots too); needs `watch robots` there.
    /// Only the latest state of each robot is sent when the client reads slower than they change.
    async fn robot_changes(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        label_selector: Option<String>,
    ) -> Result<impl Stream<Item = Result<RobotObject>> + use<>> {
        let selector = Selector::parse(label_selector.as_deref().unwrap_or_default())
            .map_err(|e| refusal(ApiError::BadRequest(e)))?;
        let empty = Default::default();
        let wanted = Box::new(move |r: &Robot| {
            selector.matches(r.metadata.labels.as_ref().unwrap_or(&empty))
        });
        let robots = |s: &FleetState| s.fleet.robots.clone();
        let feed = feed(ctx, (robots, "robots"), namespace, wanted, robot_changed).await?;
        Ok(feed.stream(RobotObject))
    }

    /// Rollouts of `namespace` (or the one named `name`) each time one's progress changes
    /// (status, or paused/resumed); needs `watch robotdeployments` there.
    async fn rollout_progress(
        &self,
        ctx: &Context<'_>,
        namespace: String,
        name: Option<String>,
    ) -> Result<impl Stream<Item = Result<RolloutObject>> + use<>> {
        if let Some(n) = &name {
            check_names(&namespace, Some(n)).map_err(refusal)?;
        }
        let wanted = Box::new(move |d: &RobotDeployment| {
            name.as_deref()
                .is_none_or(|n| d.meta().name.as_deref() == Some(n))
        });
        let rollouts = |s: &FleetState| s.fleet.rollouts.clone();
        let feed = feed(
            ctx,
            (rollouts, "robotdeployments"),
            namespace,
            wanted,
            rollout_changed,
        )
        .await?;
        Ok(feed.stream(RolloutObject))
    }
}
