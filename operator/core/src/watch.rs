//! A watch that starts before its list, so that however long the list takes, the watch after it
//! is never refused as too old.
//!
//! kube's watcher lists first and then watches from the list's resourceVersion. The API server
//! keeps only a short history of changes for watches to resume from (its watch cache: at least
//! the last 75 seconds on the Kubernetes versions without streaming lists); a list that takes
//! longer than that under load (10,000 Robots listed by every watcher at once after an API server
//! restart took 90-137 s on two cores) is followed by a watch refused at once (`410 Gone`), and
//! the list starts over, for as long as lists stay slow.
//!
//! Here the order is turned round. A list that matches nothing (`metadata.name=`), answered from
//! the API server's cache, reads where that cache stands (not etcd's revision, which other kinds'
//! writes move on and the cache of a quiet kind may not reach for minutes); the watch starts
//! there; then the full list, at least as new, is read while the watch's changes
//! are already handed on (as `Apply` and `Delete`, so readers see them during a long list). When
//! the list is in, it is merged with what the watch brought, the newer of the two by
//! resourceVersion winning for each object, and handed on as one complete relist (`Init`, each
//! object as `InitApply`, `InitDone`), which kube's reflector and [`crate::cache`] take as the
//! whole set. resourceVersions are compared as numbers, as every etcd-backed API server writes
//! them; where one is not a number, the watch's copy wins.
//!
//! The list is read whole, from the API server's cache. Each object goes through the reader's
//! `trim` as the list is decoded, one object at a time ([`crate::list`]), so what is kept is only
//! what the reader reads and the list never holds every object whole at once. (A list in pages,
//! which holds less at once, is served from etcd rather than the cache on the API servers we
//! test: a soak hour's lists of 10,201 Robots after an API server restart took 185-207 s in pages
//! of 500 against 23-56 s whole, and the robots a rollout wrote just before the restart reached
//! their gateway only with that list, 87 of them past their 180 s timeout.)
//!
//! The stream yields each failure as an error, as kube's watcher does, for the caller's backoff
//! (`WatchStreamExt::default_backoff`) to space the retries: a watch that ends or fails resumes
//! from the last version it saw; one refused as too old starts over with a new list.
//!
//! Every step has a deadline of its own ([`Deadlines`]), besides the client's read timeout: a
//! running watch yields or ends within [`Deadlines::quiet`] (the server ends it sooner), opening
//! one and finding where the cache stands take at most [`Deadlines::open`], and a whole list at
//! most [`Deadlines::list`]. Past one, the step is dropped (and whatever request it waited on
//! with it) and yields an error. In a soak hour, after an API server restart, the Robot watches
//! of all four operator processes waited in a step for good (no request in flight for them, no
//! error, the Robot stores stopped where the restart found them, rollouts timed out on robots
//! never told), while the client's own timeouts never fired.

use std::collections::HashMap;
use std::fmt::Debug;
use std::future::Future;
use std::time::{Duration, Instant};

use futures::future::BoxFuture;
use futures::stream::BoxStream;
use futures::{FutureExt, Stream, StreamExt};
use kube::api::{ListParams, VersionMatch, WatchEvent, WatchParams};
use kube::runtime::watcher::{self, Event};
use kube::{Api, Resource, ResourceExt};
use serde::de::DeserializeOwned;

/// An object's namespace and name.
pub type Key = (String, String);

/// The events of a watch, as the API server sends them.
type Changes<K> = BoxStream<'static, kube::Result<WatchEvent<K>>>;

/// What this stream yields.
type Yield<K> = watcher::Result<Event<K>>;

/// Where the stream stands.
enum State<K: Clone> {
    /// Nothing open: find the API server's current version, watch from it, list.
    Start,
    /// The list is being read while the watch already runs.
    Listing(Box<Listing<K>>),
    /// Watching from `version`; the watch is to open again when `changes` is `None`.
    Watching {
        version: String,
        changes: Option<Changes<K>>,
    },
}

/// A list in progress and the watch that runs beside it.
struct Listing<K: Clone> {
    list: BoxFuture<'static, kube::Result<Vec<K>>>,
    changes: Changes<K>,
    /// The last version the watch reached (an object's, or a bookmark's).
    version: String,
    /// For each object the watch changed since it started: its version and, unless deleted,
    /// the object as the watch brought it last.
    seen: HashMap<Key, (Option<u64>, Option<K>)>,
    started: Instant,
    /// When the list must be in (see [`Deadlines::list`]).
    deadline: tokio::time::Instant,
}

/// How long each step of the watch may take (see the module's documentation).
#[derive(Clone, Copy, Debug)]
pub struct Deadlines {
    /// Finding where the API server's cache stands and opening the watch there; opening it
    /// again from a version.
    pub open: Duration,
    /// A running watch's next event, bookmark or end (the server ends it within the watch's
    /// `timeout`).
    pub quiet: Duration,
    /// The whole list, from its start.
    pub list: Duration,
}

impl Deadlines {
    /// The deadlines of a watch with `config`: a running watch may stay quiet until the server
    /// ends it (`config.timeout`; without one, the API server's own, at most an hour) and a
    /// read timeout more.
    pub fn of(config: &watcher::Config) -> Self {
        let read = crate::api_client::READ_TIMEOUT;
        let server_end = config.timeout.map_or(3600, u64::from);
        Self {
            open: read * 2,
            quiet: Duration::from_secs(server_end) + read,
            // Under heavy write load a list of 10,000 Robots took over two minutes.
            list: Duration::from_secs(600),
        }
    }
}

/// The error a step yields when it ran past its deadline.
fn stalled(what: &str, deadline: Duration) -> kube::Error {
    let message = format!("{what} took longer than {deadline:?}; starting it again");
    kube::Error::Service(Box::new(std::io::Error::new(
        std::io::ErrorKind::TimedOut,
        message,
    )))
}

/// `step` within `deadline`, or `late` once past it.
async fn within<T>(
    deadline: Duration,
    step: impl Future<Output = T>,
    late: impl FnOnce() -> T,
) -> T {
    tokio::time::timeout(deadline, step)
        .await
        .unwrap_or_else(|_| late())
}

/// Watches the objects of `api` that `config`'s selectors and timeout choose (its list
/// semantic, page size and initial list strategy do not apply: the list is read whole, at least
/// as new as the watch's start). Every object goes through `trim` (to drop what the reader never
/// looks at, such as managed fields) once, as it comes in from the list or the watch. Yields the
/// events kube's watcher yields, in the order described in the module's documentation.
pub fn watch_first<K>(
    api: Api<K>,
    config: watcher::Config,
    trim: fn(&mut K),
) -> impl Stream<Item = Yield<K>> + Send
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + 'static,
{
    let deadlines = Deadlines::of(&config);
    watch_first_within(api, config, trim, deadlines)
}

/// [`watch_first`] with the steps' deadlines given.
pub fn watch_first_within<K>(
    api: Api<K>,
    config: watcher::Config,
    trim: fn(&mut K),
    deadlines: Deadlines,
) -> impl Stream<Item = Yield<K>> + Send
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + 'static,
{
    futures::stream::unfold(State::Start, move |state| {
        let (api, config) = (api.clone(), config.clone());
        async move { Some(step(&api, &config, trim, &deadlines, state).await) }
    })
    .flat_map(futures::stream::iter)
}

/// Every object `params` asks for, each trimmed as it comes in.
async fn list_all<K>(api: Api<K>, params: ListParams, trim: fn(&mut K)) -> kube::Result<Vec<K>>
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug,
{
    crate::list::list_trimmed(&api, &params, trim).await
}

/// One step from `state`: what it yields (often nothing or one event; a whole relist when a
/// list comes in) and the state after it.
async fn step<K>(
    api: &Api<K>,
    config: &watcher::Config,
    trim: fn(&mut K),
    deadlines: &Deadlines,
    state: State<K>,
) -> (Vec<Yield<K>>, State<K>)
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + 'static,
{
    match state {
        State::Start => {
            within(deadlines.open, start(api, config, trim, deadlines), || {
                let e = stalled("starting the watch", deadlines.open);
                (
                    vec![Err(watcher::Error::InitialListFailed(e))],
                    State::Start,
                )
            })
            .await
        }
        State::Listing(listing) => {
            let left = listing
                .deadline
                .saturating_duration_since(tokio::time::Instant::now());
            within(left, listing_step(api, config, trim, *listing), || {
                let e = stalled("the list", deadlines.list);
                (
                    vec![Err(watcher::Error::InitialListFailed(e))],
                    State::Start,
                )
            })
            .await
        }
        State::Watching {
            version,
            changes: None,
        } => reopen(api, config, deadlines, version).await,
        State::Watching {
            mut version,
            changes: Some(mut changes),
        } => {
            let next = within(deadlines.quiet, changes.next(), || {
                Some(Err(stalled("the watch's next event", deadlines.quiet)))
            })
            .await;
            let (out, next) = read(next, &mut version, trim);
            let state = match next {
                Next::Go => State::Watching {
                    version,
                    changes: Some(changes),
                },
                Next::Reopen => State::Watching {
                    version,
                    changes: None,
                },
                Next::Relist => State::Start,
            };
            (out.into_iter().collect(), state)
        }
    }
}

/// Opens the watch again from `version`.
async fn reopen<K>(
    api: &Api<K>,
    config: &watcher::Config,
    deadlines: &Deadlines,
    version: String,
) -> (Vec<Yield<K>>, State<K>)
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + 'static,
{
    let opened = within(
        deadlines.open,
        api.watch(&watch_params(config), &version),
        || Err(stalled("opening the watch", deadlines.open)),
    )
    .await;
    match opened {
        Ok(changes) => (
            Vec::new(),
            State::Watching {
                version,
                changes: Some(changes.boxed()),
            },
        ),
        Err(kube::Error::Api(status)) if status.code == 410 => {
            (vec![Err(watcher::Error::WatchError(status))], State::Start)
        }
        Err(e) => (
            vec![Err(watcher::Error::WatchStartFailed(e))],
            State::Watching {
                version,
                changes: None,
            },
        ),
    }
}

/// What a watch's next item yields (its object trimmed), and what follows it; moves `version`
/// on to the item's.
fn read<K: Resource>(
    change: Option<kube::Result<WatchEvent<K>>>,
    version: &mut String,
    trim: fn(&mut K),
) -> (Option<Yield<K>>, Next) {
    match change {
        Some(Ok(WatchEvent::Added(mut o) | WatchEvent::Modified(mut o))) => {
            note_version(version, &o);
            trim(&mut o);
            (Some(Ok(Event::Apply(o))), Next::Go)
        }
        Some(Ok(WatchEvent::Deleted(mut o))) => {
            note_version(version, &o);
            trim(&mut o);
            (Some(Ok(Event::Delete(o))), Next::Go)
        }
        Some(Ok(WatchEvent::Bookmark(b))) => {
            *version = b.metadata.resource_version;
            (None, Next::Go)
        }
        Some(Ok(WatchEvent::Error(status))) => {
            let next = if status.code == 410 {
                Next::Relist
            } else {
                Next::Reopen
            };
            (Some(Err(watcher::Error::WatchError(status))), next)
        }
        Some(Err(e)) => (Some(Err(watcher::Error::WatchFailed(e))), Next::Reopen),
        // The server ended the watch (its timeout): resume it at once.
        None => (None, Next::Reopen),
    }
}

/// What follows an event of a running watch.
enum Next {
    /// Read on.
    Go,
    /// Open the watch again from the last version.
    Reopen,
    /// The version is too old: list again.
    Relist,
}

/// Reads where the API server's cache stands, opens the watch there and starts the list.
async fn start<K>(
    api: &Api<K>,
    config: &watcher::Config,
    trim: fn(&mut K),
    deadlines: &Deadlines,
) -> (Vec<Yield<K>>, State<K>)
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + 'static,
{
    let nothing = match &config.field_selector {
        Some(fields) => format!("{fields},metadata.name="),
        None => "metadata.name=".to_owned(),
    };
    let now = ListParams {
        field_selector: Some(nothing),
        resource_version: Some("0".to_owned()),
        ..list_params(config)
    };
    let version = match api.list(&now).await {
        Ok(list) => match list.metadata.resource_version {
            Some(v) if !v.is_empty() => v,
            _ => return (vec![Err(watcher::Error::NoResourceVersion)], State::Start),
        },
        Err(e) => {
            return (
                vec![Err(watcher::Error::InitialListFailed(e))],
                State::Start,
            );
        }
    };
    let changes = match api.watch(&watch_params(config), &version).await {
        Ok(changes) => changes.boxed(),
        Err(e) => return (vec![Err(watcher::Error::WatchStartFailed(e))], State::Start),
    };
    let whole = ListParams {
        resource_version: Some(version.clone()),
        version_match: Some(VersionMatch::NotOlderThan),
        ..list_params(config)
    };
    let lister = api.clone();
    tracing::debug!(
        kind = K::kind(&()).as_ref(),
        version,
        "listing; watching already"
    );
    let listing = Listing {
        list: list_all(lister, whole, trim).boxed(),
        changes,
        version,
        seen: HashMap::new(),
        started: Instant::now(),
        deadline: tokio::time::Instant::now() + deadlines.list,
    };
    (Vec::new(), State::Listing(Box::new(listing)))
}

/// One step while the list is read: the list came in (merged and handed on), or the watch
/// brought a change (handed on at once and remembered for the merge).
async fn listing_step<K>(
    api: &Api<K>,
    config: &watcher::Config,
    trim: fn(&mut K),
    mut l: Listing<K>,
) -> (Vec<Yield<K>>, State<K>)
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + 'static,
{
    let change = tokio::select! {
        listed = &mut l.list => {
            return match listed {
                Ok(list) => {
                    tracing::info!(
                        kind = K::kind(&()).as_ref(),
                        objects = list.len(),
                        changed_while_listing = l.seen.len(),
                        seconds = l.started.elapsed().as_secs_f64(),
                        "listed"
                    );
                    let relist = merge(list, l.seen);
                    let watching = State::Watching { version: l.version, changes: Some(l.changes) };
                    (relist, watching)
                }
                Err(e) => (vec![Err(watcher::Error::InitialListFailed(e))], State::Start),
            };
        }
        change = l.changes.next() => change,
    };
    match read(change, &mut l.version, trim) {
        // The list cannot be trusted to merge with a watch that failed: start over.
        (Some(Err(e)), _) => return (vec![Err(e)], State::Start),
        (Some(Ok(event)), _) => {
            // Remembered for the merge: the version, and the object unless deleted.
            match &event {
                Event::Apply(o) => _ = l.seen.insert(key(o), (version_of(o), Some(o.clone()))),
                Event::Delete(o) => _ = l.seen.insert(key(o), (version_of(o), None)),
                Event::Init | Event::InitApply(_) | Event::InitDone => {}
            }
            return (vec![Ok(event)], State::Listing(Box::new(l)));
        }
        (None, Next::Go) => {}
        // The server ended the watch (its timeout) before the list came in: resume it.
        (None, _) => match api.watch(&watch_params(config), &l.version).await {
            Ok(changes) => l.changes = changes.boxed(),
            Err(e) => return (vec![Err(watcher::Error::WatchStartFailed(e))], State::Start),
        },
    }
    (Vec::new(), State::Listing(Box::new(l)))
}

/// The list merged with what the watch brought meanwhile, as one relist: for each object the
/// newer copy, none for an object the watch saw deleted after the list's copy.
fn merge<K: Resource>(
    items: Vec<K>,
    mut seen: HashMap<Key, (Option<u64>, Option<K>)>,
) -> Vec<Yield<K>> {
    let mut out = Vec::with_capacity(items.len() + seen.len() + 2);
    out.push(Ok(Event::Init));
    for item in items {
        let listed = version_of(&item);
        match seen.remove(&key(&item)) {
            Some((watched, object)) if !older(watched, listed) => {
                out.extend(object.map(|o| Ok(Event::InitApply(o))));
            }
            _ => out.push(Ok(Event::InitApply(item))),
        }
    }
    // Created after the list's version.
    out.extend(
        seen.into_values()
            .filter_map(|(_, object)| object.map(|o| Ok(Event::InitApply(o)))),
    );
    out.push(Ok(Event::InitDone));
    out
}

/// Whether a copy at version `watched` is older than one at `listed` (unknown: not older).
fn older(watched: Option<u64>, listed: Option<u64>) -> bool {
    matches!((watched, listed), (Some(w), Some(l)) if w < l)
}

/// Drops the field sets of `o`'s managed fields (the bulk of them), keeping who wrote, how and
/// when.
pub fn drop_field_sets<K: Resource>(o: &mut K) {
    for entry in o.meta_mut().managed_fields.iter_mut().flatten() {
        entry.fields_v1 = None;
    }
}

/// The key of `o`.
pub fn key<K: Resource>(o: &K) -> Key {
    (o.namespace().unwrap_or_default(), o.name_any())
}

/// `o`'s resourceVersion as a number, if it is one (as every etcd-backed API server writes it).
pub fn version_of<K: Resource>(o: &K) -> Option<u64> {
    o.resource_version()?.parse().ok()
}

/// Moves `version` on to `o`'s, if it has one.
fn note_version<K: Resource>(version: &mut String, o: &K) {
    if let Some(v) = o.resource_version().filter(|v| !v.is_empty()) {
        *version = v;
    }
}

fn list_params(config: &watcher::Config) -> ListParams {
    ListParams {
        label_selector: config.label_selector.clone(),
        field_selector: config.field_selector.clone(),
        ..ListParams::default()
    }
}

fn watch_params(config: &watcher::Config) -> WatchParams {
    WatchParams {
        label_selector: config.label_selector.clone(),
        field_selector: config.field_selector.clone(),
        timeout: config.timeout,
        bookmarks: config.bookmarks,
        ..WatchParams::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_crds::{Robot, RobotSpec};

    fn robot(name: &str, version: &str, room: &str) -> Robot {
        let mut r = Robot::new(name, RobotSpec::default());
        r.metadata.namespace = Some("lab".into());
        r.metadata.resource_version = Some(version.into());
        r.metadata.labels = Some([("room".to_owned(), room.to_owned())].into());
        r
    }

    fn described(events: &[Yield<Robot>]) -> Vec<String> {
        events
            .iter()
            .map(|e| match e {
                Ok(Event::Init) => "init".to_owned(),
                Ok(Event::InitApply(r)) => {
                    format!(
                        "{}@{}:{}",
                        r.name_any(),
                        r.resource_version().unwrap(),
                        r.labels()["room"]
                    )
                }
                Ok(Event::InitDone) => "done".to_owned(),
                other => format!("{other:?}"),
            })
            .collect()
    }

    /// The newer copy of each object wins, by number (not text: "9" < "10"); an object the
    /// watch saw deleted after the list's copy is left out, one it saw created is added, and
    /// the list's copy wins over an older one the watch brought.
    #[test]
    fn the_newer_copy_wins_and_deletions_after_the_list_hold() {
        let listed = vec![
            robot("a", "9", "list"),
            robot("b", "12", "list"),
            robot("c", "9", "list"),
            robot("d", "5", "list"),
        ];
        let seen: HashMap<Key, (Option<u64>, Option<Robot>)> = [
            (robot("a", "10", "watch"), true),
            (robot("b", "11", "watch"), true),
            (robot("c", "13", "watch"), false),
            (robot("e", "14", "watch"), true),
        ]
        .into_iter()
        .map(|(r, alive)| (key(&r), (version_of(&r), alive.then_some(r))))
        .collect();
        let mut merged = described(&merge(listed, seen));
        assert_eq!(merged.first().map(String::as_str), Some("init"));
        assert_eq!(merged.last().map(String::as_str), Some("done"));
        merged.sort();
        assert_eq!(
            merged,
            [
                "a@10:watch",
                "b@12:list",
                "d@5:list",
                "done",
                "e@14:watch",
                "init"
            ]
        );
    }

    /// Where a version is not a number, the watch's copy (the later one to arrive) wins.
    #[test]
    fn an_unreadable_version_leaves_the_watchs_copy() {
        assert!(!older(None, Some(3)));
        assert!(!older(Some(3), None));
        assert!(older(Some(3), Some(4)));
        assert!(!older(Some(4), Some(4)));
    }

    /// An API server that answers the first list and opens the watch, then sends the headers of
    /// the whole list (or, with `list`, the whole list) and nothing more: no error, no end. It
    /// counts the first lists, or with `list` the watches opened.
    async fn stalling_server(
        list: bool,
    ) -> (String, std::sync::Arc<std::sync::atomic::AtomicUsize>) {
        use std::sync::atomic::{AtomicUsize, Ordering};
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let starts = std::sync::Arc::new(AtomicUsize::new(0));
        let counted = starts.clone();
        tokio::spawn(async move {
            while let Ok((mut conn, _)) = listener.accept().await {
                let starts = counted.clone();
                tokio::spawn(async move {
                    let mut head = Vec::new();
                    let mut buf = [0u8; 4096];
                    while let Ok(n) = conn.read(&mut buf).await {
                        if n == 0 {
                            return;
                        }
                        head.extend_from_slice(&buf[..n]);
                        let Some(end) = head.windows(4).position(|w| w == b"\r\n\r\n") else {
                            continue;
                        };
                        let line = String::from_utf8_lossy(&head[..end]).to_string();
                        head.drain(..end + 4);
                        let watch = line.contains("watch=true");
                        if (list && watch) || (!list && line.contains("fieldSelector")) {
                            starts.fetch_add(1, Ordering::SeqCst);
                        }
                        if line.contains("fieldSelector") || (list && !watch) {
                            let body = r#"{"kind":"RobotList","apiVersion":"fleet.lekiwi.io/v1alpha1","metadata":{"resourceVersion":"7"},"items":[]}"#;
                            let answer = format!(
                                "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n{body}",
                                body.len()
                            );
                            _ = conn.write_all(answer.as_bytes()).await;
                        } else {
                            // The watch, or the whole list: headers, then silence.
                            let answer = "HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ntransfer-encoding: chunked\r\n\r\n";
                            _ = conn.write_all(answer.as_bytes()).await;
                            std::future::pending::<()>().await;
                        }
                    }
                });
            }
        });
        (format!("http://{addr}"), starts)
    }

    /// A watch of Robots at `url` whose steps have 1 s deadlines (`list` for the whole list),
    /// from a client with no read timeout: only the deadlines can end a stalled step.
    fn watch_without_read_timeout(
        url: &str,
        list: Duration,
    ) -> impl Stream<Item = Yield<Robot>> + Send {
        let mut config = kube::Config::new(url.parse().unwrap());
        config.read_timeout = None;
        let client = kube::Client::try_from(config).unwrap();
        let deadlines = Deadlines {
            open: Duration::from_secs(1),
            quiet: Duration::from_secs(1),
            list,
        };
        let api: Api<Robot> = Api::namespaced(client, "lab");
        watch_first_within(api, watcher::Config::default(), drop_field_sets, deadlines)
    }

    /// A list the API server never finishes is dropped at the list's deadline and the watch
    /// starts over, even when the client's own timeouts never fire (none here).
    #[tokio::test]
    async fn a_list_that_never_ends_is_started_again_at_its_deadline() {
        let (url, starts) = stalling_server(false).await;
        let stream = watch_without_read_timeout(&url, Duration::from_secs(2));
        let mut stream = std::pin::pin!(stream);
        for round in 1..=2 {
            let next = tokio::time::timeout(Duration::from_secs(20), stream.next())
                .await
                .expect("the stream waited on the list for good");
            let Some(Err(watcher::Error::InitialListFailed(e))) = next else {
                panic!("round {round}: {next:?}");
            };
            assert!(e.to_string().contains("took longer"), "{e}");
            assert_eq!(starts.load(std::sync::atomic::Ordering::SeqCst), round);
        }
    }

    /// A watch that brings nothing and does not end is opened again at its deadline.
    #[tokio::test]
    async fn a_watch_gone_quiet_is_opened_again_at_its_deadline() {
        let (url, opened) = stalling_server(true).await;
        let stream = watch_without_read_timeout(&url, Duration::from_secs(1));
        let mut stream = std::pin::pin!(stream);
        let mut failed = 0;
        while failed < 2 {
            let next = tokio::time::timeout(Duration::from_secs(20), stream.next())
                .await
                .expect("the stream waited on a quiet watch for good");
            match next {
                Some(Ok(_)) => {}
                Some(Err(watcher::Error::WatchFailed(e))) => {
                    assert!(e.to_string().contains("took longer"), "{e}");
                    failed += 1;
                }
                other => panic!("{other:?}"),
            }
        }
        // The one opened with the list, and one after each quiet spell but the last.
        assert!(opened.load(std::sync::atomic::Ordering::SeqCst) >= 2);
    }
}
