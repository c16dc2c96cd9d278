//! In-memory copies of the fleet's resources for the Fleet API, fed by a watch each: every read
//! is answered from memory, never by a request to the API server. Objects are kept in a map
//! ordered by namespace and name, so a page of a list resumes after its `continue` key and a
//! namespace is one range of the map. Like `kube::runtime::reflector`, a relist replaces the
//! whole map at once when it is complete. Every change the watch delivers is also sent once on
//! the cache's broadcast ([`Cache::subscribe`]): the GraphQL subscriptions all share it, none
//! opens a watch of its own.

use std::collections::BTreeMap;
use std::ops::Bound;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};

use futures::StreamExt;
use kube::runtime::{WatchStreamExt, watcher};
use kube::{Api, Resource, ResourceExt};
use serde::de::DeserializeOwned;
use tokio::sync::broadcast;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

/// An object's place in the map: namespace, then name.
pub type Key = (String, String);

/// Changes a subscriber may fall behind by before it is told it lagged (and reads the cache
/// again instead): the broadcast's memory is bounded whatever the subscribers do.
pub const CHANGES_BUFFERED: usize = 4096;

/// One change the watch delivered.
#[derive(Debug)]
pub enum Change<K> {
    /// Created or modified (also every object of a relist): as it was before, if known, and as
    /// it is now.
    Applied(Option<Arc<K>>, Arc<K>),
    /// Deleted: as it was.
    Deleted(Arc<K>),
}

impl<K> Clone for Change<K> {
    fn clone(&self) -> Self {
        match self {
            Self::Applied(old, new) => Self::Applied(old.clone(), new.clone()),
            Self::Deleted(o) => Self::Deleted(o.clone()),
        }
    }
}

/// The objects of one kind the watch has delivered, ordered by [`Key`].
pub struct Cache<K> {
    objects: RwLock<BTreeMap<Key, Arc<K>>>,
    /// Set once the first list is complete.
    ready: AtomicBool,
    /// Every change, to whoever listens.
    changes: broadcast::Sender<Change<K>>,
}

impl<K> Cache<K> {
    fn new() -> Self {
        Self {
            objects: RwLock::default(),
            ready: AtomicBool::new(false),
            changes: broadcast::channel(CHANGES_BUFFERED).0,
        }
    }

    /// Every change from now on. A receiver more than [`CHANGES_BUFFERED`] changes behind gets
    /// `Lagged` and should read the current state with [`Cache::page`].
    pub fn subscribe(&self) -> broadcast::Receiver<Change<K>> {
        self.changes.subscribe()
    }

    /// Whether the first list is in.
    pub fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    /// The object `namespace/name`.
    pub fn get(&self, namespace: &str, name: &str) -> Option<Arc<K>> {
        let objects = self.objects.read().unwrap_or_else(|p| p.into_inner());
        objects
            .get(&(namespace.to_owned(), name.to_owned()))
            .cloned()
    }

    /// Up to `limit` objects of `namespace` (all namespaces if `None`) that `keep` accepts,
    /// in key order after `after`; the second value is whether more follow.
    pub fn page(
        &self,
        namespace: Option<&str>,
        after: Option<&Key>,
        limit: usize,
        keep: impl Fn(&K) -> bool,
    ) -> (Vec<Arc<K>>, bool) {
        let objects = self.objects.read().unwrap_or_else(|p| p.into_inner());
        let start = match (after, namespace) {
            (Some(key), _) => Bound::Excluded(key.clone()),
            (None, Some(ns)) => Bound::Included((ns.to_owned(), String::new())),
            (None, None) => Bound::Unbounded,
        };
        let mut found = objects
            .range((start, Bound::Unbounded))
            .take_while(|((ns, _), _)| namespace.is_none_or(|want| ns == want))
            .filter(|(_, o)| keep(o))
            .map(|(_, o)| o.clone());
        let page: Vec<_> = found.by_ref().take(limit).collect();
        let more = found.next().is_some();
        (page, more)
    }

    fn apply(&self, event: watcher::Event<K>, relist: &mut Option<BTreeMap<Key, Arc<K>>>)
    where
        K: Resource,
    {
        let mut objects = self.objects.write().unwrap_or_else(|p| p.into_inner());
        match event {
            watcher::Event::Apply(o) => {
                let o = Arc::new(o);
                let old = objects.insert(key(o.as_ref()), o.clone());
                let _ = self.changes.send(Change::Applied(old, o));
            }
            watcher::Event::Delete(o) => {
                objects.remove(&key(&o));
                let _ = self.changes.send(Change::Deleted(Arc::new(o)));
            }
            watcher::Event::Init => *relist = Some(BTreeMap::new()),
            watcher::Event::InitApply(o) => {
                let o = Arc::new(o);
                let old = objects.get(&key(o.as_ref())).cloned();
                if let Some(fresh) = relist.as_mut() {
                    fresh.insert(key(o.as_ref()), o.clone());
                }
                let _ = self.changes.send(Change::Applied(old, o));
            }
            watcher::Event::InitDone => {
                if let Some(fresh) = relist.take() {
                    *objects = fresh;
                }
                self.ready.store(true, Ordering::Release);
            }
        }
    }
}

/// The key of `o`.
pub fn key<K: Resource>(o: &K) -> Key {
    (o.namespace().unwrap_or_default(), o.name_any())
}

/// Starts watching `api`; every object goes through `trim` (to drop what the API never
/// answers, such as managed fields) before it is kept. The task runs until `cancel`.
pub fn watch<K>(
    api: Api<K>,
    trim: fn(&mut K),
    cancel: CancellationToken,
) -> (Arc<Cache<K>>, JoinHandle<()>)
where
    K: Resource + Clone + DeserializeOwned + std::fmt::Debug + Send + Sync + 'static,
{
    let cache = Arc::new(Cache::new());
    let filled = cache.clone();
    let task = tokio::spawn(async move {
        let stream = watcher(api, watcher::Config::default().any_semantic())
            .default_backoff()
            .modify(trim);
        let mut stream = std::pin::pin!(stream);
        let mut relist = None;
        loop {
            tokio::select! {
                () = cancel.cancelled() => return,
                event = stream.next() => match event {
                    Some(Ok(event)) => filled.apply(event, &mut relist),
                    Some(Err(e)) => tracing::debug!(error = %e, "Fleet API watch error; retrying"),
                    None => return,
                },
            }
        }
    });
    (cache, task)
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::{Robot, RobotSpec};

    fn robot(ns: &str, name: &str) -> Robot {
        let mut r = Robot::new(name, RobotSpec::default());
        r.metadata.namespace = Some(ns.into());
        r
    }

    #[test]
    fn pages_resume_after_their_key_within_a_namespace() {
        let cache = Cache::new();
        let mut relist = None;
        cache.apply(watcher::Event::Init, &mut relist);
        for (ns, n) in [
            ("a", "r1"),
            ("b", "r1"),
            ("b", "r2"),
            ("b", "r3"),
            ("c", "r0"),
        ] {
            cache.apply(watcher::Event::InitApply(robot(ns, n)), &mut relist);
        }
        assert!(!cache.is_ready());
        cache.apply(watcher::Event::InitDone, &mut relist);
        assert!(cache.is_ready());
        let names = |v: &[Arc<Robot>]| v.iter().map(|r| r.name_any()).collect::<Vec<_>>();
        let (first, more) = cache.page(Some("b"), None, 2, |_| true);
        assert_eq!(
            (names(&first), more),
            (vec!["r1".into(), "r2".into()], true)
        );
        let after = ("b".to_owned(), "r2".to_owned());
        let (rest, more) = cache.page(Some("b"), Some(&after), 2, |_| true);
        assert_eq!((names(&rest), more), (vec!["r3".into()], false));
        let (all, _) = cache.page(None, None, 10, |r| r.name_any() != "r2");
        assert_eq!(all.len(), 4);
        cache.apply(watcher::Event::Delete(robot("b", "r1")), &mut relist);
        assert!(cache.get("b", "r1").is_none());
    }
}
