//! In-memory copies of the fleet's resources for the Fleet API, fed by a watch each: every read
//! is answered from memory, never by a request to the API server. Objects are kept in a map
//! ordered by namespace and name, so a page of a list resumes after its `continue` key and a
//! namespace is one range of the map; an index by label `key=value` lets a list with such a
//! selector read only the objects that carry the label. Each object's JSON is made when a list
//! first asks for it and kept until the object changes, so a list is answered by joining ready
//! bytes, and objects nobody lists cost no JSON (about 1.6 KB per Robot). The watch starts before
//! its list ([`crate::watch`]), so changes arrive while a long list is read; a relist then updates
//! each object it holds at another version than the map's and, once complete, drops those it no
//! longer holds (sent as deletions): the map never shows an object older than a change already
//! sent, which readers that act on both (the gateway's dispatch and its sessions) count on.
//! Every change the watch delivers is also sent once on the cache's broadcast
//! ([`Cache::subscribe`]): the GraphQL subscriptions all share it, none opens a watch of its
//! own.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::ops::Bound;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock, RwLock};

use crate::watch::watch_first;
use futures::StreamExt;
use kube::runtime::{WatchStreamExt, watcher};
use kube::{Api, Resource, ResourceExt};
use serde::Serialize;
use serde::de::DeserializeOwned;
use tokio::sync::broadcast;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

/// An object's place in the map: namespace, then name (the watch's own key of an object).
pub use crate::watch::{Key, key};

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

/// An object and, once a list asked for it, its JSON (as the API answers it).
struct Item<K> {
    object: Arc<K>,
    json: OnceLock<Arc<str>>,
}

impl<K: Serialize> Item<K> {
    fn new(object: K) -> Self {
        Self {
            object: Arc::new(object),
            json: OnceLock::new(),
        }
    }

    /// The object's JSON, made now if no list asked for it before.
    fn json(&self) -> Arc<str> {
        self.json
            .get_or_init(|| {
                serde_json::to_string(self.object.as_ref())
                    .unwrap_or_default()
                    .into()
            })
            .clone()
    }
}

impl<K> Clone for Item<K> {
    fn clone(&self) -> Self {
        Self {
            object: self.object.clone(),
            json: self.json.clone(),
        }
    }
}

/// The objects and the label index, changed together under one lock.
struct Objects<K> {
    map: BTreeMap<Key, Item<K>>,
    /// For each label `(key, value)`, the objects that carry it.
    by_label: HashMap<(String, String), BTreeSet<Key>>,
}

impl<K> Default for Objects<K> {
    fn default() -> Self {
        Self {
            map: BTreeMap::new(),
            by_label: HashMap::new(),
        }
    }
}

impl<K: Resource> Objects<K> {
    fn index(&mut self, k: &Key, o: &K, add: bool) {
        for (label, value) in o.labels() {
            let entry = (label.clone(), value.clone());
            if add {
                self.by_label.entry(entry).or_default().insert(k.clone());
            } else if let Some(keys) = self.by_label.get_mut(&entry) {
                keys.remove(k);
                if keys.is_empty() {
                    self.by_label.remove(&entry);
                }
            }
        }
    }

    /// Keeps `item`; the object it replaces, if any.
    fn insert(&mut self, item: Item<K>) -> Option<Arc<K>> {
        let k = key(item.object.as_ref());
        let old = self.map.insert(k.clone(), item.clone());
        if let Some(old) = &old {
            self.index(&k, &old.object, false);
        }
        self.index(&k, &item.object, true);
        old.map(|o| o.object)
    }

    /// Drops the object at `k`; the object it was, if any.
    fn remove(&mut self, k: &Key) -> Option<Arc<K>> {
        let old = self.map.remove(k)?;
        self.index(k, &old.object, false);
        Some(old.object)
    }
}

/// The objects of one kind the watch has delivered, ordered by [`Key`].
pub struct Cache<K> {
    objects: RwLock<Objects<K>>,
    /// Set once the first list is complete.
    ready: AtomicBool,
    /// Every change, to whoever listens.
    changes: broadcast::Sender<Change<K>>,
}

/// A page of a list: the items, the key of the last one, and whether more follow.
pub struct Found<T> {
    /// What the page holds, in key order.
    pub items: Vec<T>,
    /// The key of the last item (where the next page resumes).
    pub last: Option<Key>,
    /// Whether more objects follow.
    pub more: bool,
}

impl<K> Cache<K> {
    fn new() -> Self {
        Self {
            objects: RwLock::new(Objects::default()),
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
            .map
            .get(&(namespace.to_owned(), name.to_owned()))
            .map(|i| i.object.clone())
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
        let found = self.scan((namespace, after, None), limit, keep, |i| i.object.clone());
        (found.items, found.more)
    }

    /// Like [`Cache::page`]; only objects labelled `label` (a `(key, value)` every accepted
    /// object must carry) are read when one is given.
    pub fn page_objects(
        &self,
        place: (Option<&str>, Option<&Key>, Option<(&str, &str)>),
        limit: usize,
        keep: impl Fn(&K) -> bool,
    ) -> Found<Arc<K>> {
        self.scan(place, limit, keep, |i| i.object.clone())
    }

    /// Like [`Cache::page_objects`], the objects' JSON as the API answers them (made for those
    /// no list asked for before).
    pub fn page_json(
        &self,
        (namespace, after, label): (Option<&str>, Option<&Key>, Option<(&str, &str)>),
        limit: usize,
        keep: impl Fn(&K) -> bool,
    ) -> Found<Arc<str>>
    where
        K: Serialize,
    {
        self.scan((namespace, after, label), limit, keep, Item::json)
    }

    /// Like [`Cache::page_json`], each JSON with its object (for what a list adds to it).
    pub fn page_json_objects(
        &self,
        place: (Option<&str>, Option<&Key>, Option<(&str, &str)>),
        limit: usize,
        keep: impl Fn(&K) -> bool,
    ) -> Found<(Arc<K>, Arc<str>)>
    where
        K: Serialize,
    {
        self.scan(place, limit, keep, |i| (i.object.clone(), i.json()))
    }

    fn scan<T>(
        &self,
        (namespace, after, label): (Option<&str>, Option<&Key>, Option<(&str, &str)>),
        limit: usize,
        keep: impl Fn(&K) -> bool,
        take: impl Fn(&Item<K>) -> T,
    ) -> Found<T> {
        let objects = self.objects.read().unwrap_or_else(|p| p.into_inner());
        let start = match (after, namespace) {
            (Some(key), _) => Bound::Excluded(key.clone()),
            (None, Some(ns)) => Bound::Included((ns.to_owned(), String::new())),
            (None, None) => Bound::Unbounded,
        };
        let in_namespace = |k: &Key| namespace.is_none_or(|want| k.0 == want);
        let candidates: Box<dyn Iterator<Item = (&Key, &Item<K>)>> = match label {
            None => Box::new(objects.map.range((start, Bound::Unbounded))),
            Some((l, v)) => {
                let keys = objects.by_label.get(&(l.to_owned(), v.to_owned()));
                Box::new(
                    keys.into_iter()
                        .flat_map(move |keys| keys.range((start.clone(), Bound::Unbounded)))
                        .filter_map(|k| objects.map.get_key_value(k)),
                )
            }
        };
        let mut found = candidates
            .take_while(|(k, _)| in_namespace(k))
            .filter(|(_, i)| keep(&i.object));
        let mut items = Vec::new();
        let mut last = None;
        for (k, item) in found.by_ref().take(limit) {
            items.push(take(item));
            last = Some(k);
        }
        let more = found.next().is_some();
        Found {
            items,
            last: last.cloned(),
            more,
        }
    }
}

impl<K: Resource + Serialize> Cache<K> {
    /// A cache that holds `objects` as a complete first list and follows no watch (tests, and
    /// what must not change).
    pub fn listed(objects: impl IntoIterator<Item = K>) -> Self {
        let cache = Self::new();
        let mut relist = None;
        cache.apply(watcher::Event::Init, &mut relist);
        for o in objects {
            cache.apply(watcher::Event::InitApply(o), &mut relist);
        }
        cache.apply(watcher::Event::InitDone, &mut relist);
        cache
    }

    /// Takes one event of the watch; `relist` holds the keys a relist in progress delivered.
    fn apply(&self, event: watcher::Event<K>, relist: &mut Option<Relist>) {
        match event {
            watcher::Event::Apply(o) => self.applied(o),
            watcher::Event::Delete(o) => {
                let mut objects = self.objects.write().unwrap_or_else(|p| p.into_inner());
                objects.remove(&key(&o));
                let _ = self.changes.send(Change::Deleted(Arc::new(o)));
            }
            watcher::Event::Init => *relist = Some(Relist::default()),
            watcher::Event::InitApply(o) => {
                if let Some(r) = relist.as_mut() {
                    r.seen.insert(key(&o));
                }
                // The watch that runs beside the list may have brought this very version.
                self.applied_unless_held(o);
            }
            watcher::Event::InitDone => {
                if let Some(Relist { seen }) = relist.take() {
                    let mut objects = self.objects.write().unwrap_or_else(|p| p.into_inner());
                    let gone: Vec<Key> = objects
                        .map
                        .keys()
                        .filter(|k| !seen.contains(*k))
                        .cloned()
                        .collect();
                    for k in gone {
                        if let Some(old) = objects.remove(&k) {
                            let _ = self.changes.send(Change::Deleted(old));
                        }
                    }
                }
                self.ready.store(true, Ordering::Release);
            }
        }
    }

    /// Takes `o` as a watch would deliver it (tests of what follows the changes; with the
    /// `test-util` feature).
    #[cfg(any(test, feature = "test-util"))]
    pub fn apply_for_tests(&self, o: K) {
        self.applied(o);
    }

    /// Like [`Cache::applied`], unless the map holds `o` at its version already (checked under
    /// the same lock).
    fn applied_unless_held(&self, o: K) {
        self.keep(o, true);
    }

    /// Keeps `o` and then sends the change, under the map's lock: whoever reads the change
    /// finds the map as new as it.
    fn applied(&self, o: K) {
        self.keep(o, false);
    }

    fn keep(&self, o: K, unless_held: bool) {
        let mut objects = self.objects.write().unwrap_or_else(|p| p.into_inner());
        let version = o.meta().resource_version.as_deref();
        let held = unless_held
            && version.is_some()
            && objects
                .map
                .get(&key(&o))
                .is_some_and(|i| i.object.meta().resource_version.as_deref() == version);
        if !held {
            let new = Item::new(o);
            let old = objects.insert(new.clone());
            let _ = self.changes.send(Change::Applied(old, new.object));
        }
    }
}

/// A relist in progress: the keys it delivered so far.
#[derive(Default)]
struct Relist {
    seen: HashSet<Key>,
}

/// Starts watching `api`; every object goes through `trim` (to drop what the API never
/// answers, such as managed fields) before it is kept. The task runs until `cancel`.
pub fn watch<K>(
    api: Api<K>,
    trim: fn(&mut K),
    cancel: CancellationToken,
) -> (Arc<Cache<K>>, JoinHandle<()>)
where
    K: Resource<DynamicType = ()>
        + Clone
        + DeserializeOwned
        + Serialize
        + std::fmt::Debug
        + Send
        + Sync
        + 'static,
{
    let cache = Arc::new(Cache::new());
    let filled = cache.clone();
    let task = tokio::spawn(async move {
        let stream = watch_first(api, crate::api_client::watch_config(), trim).default_backoff();
        let mut stream = std::pin::pin!(stream);
        let mut relist = None;
        loop {
            tokio::select! {
                () = cancel.cancelled() => return,
                event = stream.next() => match event {
                    Some(Ok(event)) => filled.apply(event, &mut relist),
                    // Spaced by the watcher's backoff; a list or watch that keeps failing leaves
                    // every reader of the cache (deploys, blob access, the Fleet API) behind.
                    Some(Err(e)) => tracing::warn!(
                        kind = K::kind(&()).as_ref(),
                        error = %e,
                        "watch failed; retrying"
                    ),
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

    /// While a relist is in progress, each object it delivers is in the map by the time its
    /// change is sent (a reader told of the change finds it there); once the relist is
    /// complete, the objects it did not hold are dropped and sent as deleted.
    #[test]
    fn a_relist_shows_each_change_at_once_and_drops_the_rest_at_its_end() {
        let cache = Cache::listed([labelled("b", "r1", "x1"), labelled("b", "r2", "x1")]);
        let mut changes = cache.subscribe();
        let mut relist = None;
        cache.apply(watcher::Event::Init, &mut relist);
        cache.apply(
            watcher::Event::InitApply(labelled("b", "r1", "x2")),
            &mut relist,
        );
        let Ok(Change::Applied(Some(old), new)) = changes.try_recv() else {
            panic!("the relisted object is sent with the one it replaces");
        };
        assert_eq!(old.labels()["room"], "x1");
        assert_eq!(new.labels()["room"], "x2");
        let now = cache.get("b", "r1").expect("in the map");
        assert_eq!(
            now.labels()["room"],
            "x2",
            "the map is as new as the change"
        );
        let x2 = cache.page_objects((Some("b"), None, Some(("room", "x2"))), 10, |_| true);
        assert_eq!(x2.items.len(), 1, "the label index follows too");
        assert!(cache.get("b", "r2").is_some(), "kept until the relist ends");
        cache.apply(watcher::Event::InitDone, &mut relist);
        assert!(cache.get("b", "r2").is_none(), "not in the new list");
        let Ok(Change::Deleted(gone)) = changes.try_recv() else {
            panic!("an object the relist no longer holds is sent as deleted");
        };
        assert_eq!(gone.name_any(), "r2");
        assert!(changes.try_recv().is_err(), "nothing else changed");
        assert_eq!(cache.page(None, None, 10, |_| true).0.len(), 1);
    }

    /// A relist that brings an object at the version the map holds (the watch beside the list
    /// brought it first) sends no change; at another version it does.
    #[test]
    fn a_relisted_object_the_map_holds_at_its_version_sends_no_change() {
        let mut held = labelled("b", "r1", "x1");
        held.metadata.resource_version = Some("7".into());
        let cache = Cache::listed([held.clone()]);
        let mut changes = cache.subscribe();
        let mut relist = None;
        cache.apply(watcher::Event::Init, &mut relist);
        cache.apply(watcher::Event::InitApply(held), &mut relist);
        assert!(
            changes.try_recv().is_err(),
            "the same version again is no change"
        );
        let mut newer = labelled("b", "r1", "x2");
        newer.metadata.resource_version = Some("8".into());
        cache.apply(watcher::Event::InitApply(newer), &mut relist);
        let Ok(Change::Applied(Some(_), now)) = changes.try_recv() else {
            panic!("a newer version is a change");
        };
        assert_eq!(now.labels()["room"], "x2");
        cache.apply(watcher::Event::InitDone, &mut relist);
        assert_eq!(cache.get("b", "r1").unwrap().labels()["room"], "x2");
    }

    fn labelled(ns: &str, name: &str, room: &str) -> Robot {
        let mut r = robot(ns, name);
        r.metadata.labels = Some([("room".to_owned(), room.to_owned())].into());
        r
    }

    /// An object's JSON, once a list made it, is what the API answers after the object's next
    /// change too: the new object's, never the one made before.
    #[test]
    fn a_listed_objects_json_follows_its_change() {
        let cache = Cache::listed([labelled("b", "r1", "x1")]);
        let json = |c: &Cache<Robot>| {
            let found = c.page_json((Some("b"), None, None), 10, |_| true);
            assert_eq!(found.items.len(), 1);
            found.items[0].to_string()
        };
        assert!(json(&cache).contains(r#""room":"x1""#));
        let mut relist = None;
        let changed = labelled("b", "r1", "x2");
        cache.apply(watcher::Event::Apply(changed.clone()), &mut relist);
        assert_eq!(json(&cache), serde_json::to_string(&changed).unwrap());
    }

    /// A list through the label index finds what a scan of every object finds, pages the same,
    /// follows relabelling and deletion, and answers each object's JSON.
    #[test]
    fn the_label_index_answers_what_a_scan_answers() {
        let cache = Cache::new();
        let mut relist = None;
        cache.apply(watcher::Event::Init, &mut relist);
        for i in 0..1000 {
            let r = labelled(
                ["a", "b"][i % 2],
                &format!("r{i:04}"),
                &format!("x{}", i % 10),
            );
            cache.apply(watcher::Event::InitApply(r), &mut relist);
        }
        cache.apply(watcher::Event::InitDone, &mut relist);
        cache.apply(
            watcher::Event::Apply(labelled("b", "r0003", "x4")),
            &mut relist,
        );
        cache.apply(
            watcher::Event::Delete(labelled("b", "r0013", "x3")),
            &mut relist,
        );
        let in_x3 = |r: &Robot| r.labels().get("room").is_some_and(|v| v == "x3");
        let mut after: Option<Key> = None;
        loop {
            let place = (Some("b"), after.as_ref(), Some(("room", "x3")));
            let indexed = cache.page_json(place, 7, in_x3);
            let scanned = cache.page_objects((Some("b"), after.as_ref(), None), 7, in_x3);
            let json: Vec<String> = scanned
                .items
                .iter()
                .map(|r| serde_json::to_string(r.as_ref()).unwrap())
                .collect();
            let indexed_json: Vec<String> = indexed.items.iter().map(|j| j.to_string()).collect();
            assert_eq!(indexed_json, json);
            assert_eq!((&indexed.last, indexed.more), (&scanned.last, scanned.more));
            assert!(
                !json
                    .iter()
                    .any(|j| j.contains("r0003") || j.contains("r0013"))
            );
            if !indexed.more {
                break;
            }
            after = indexed.last;
        }
        let x4 = cache.page_json((Some("b"), None, Some(("room", "x4"))), 1000, |_| true);
        assert!(x4.items.iter().any(|j| j.contains("r0003")));
        assert_eq!(
            cache
                .page_json((None, None, Some(("room", "nope"))), 10, |_| true)
                .items
                .len(),
            0
        );
    }
}
