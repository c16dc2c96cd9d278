//! The Robot and RobotDeployment controllers and the state they share: the reconcile
//! [`Context`] and its [`Settings`], the status write both controllers make, and the
//! [`trigger`] they are woken by besides their own watch.

pub mod deployment;
mod error;
pub mod failure_log;
pub mod robot;
pub mod trigger;

pub use error::{Category, Error, Result};

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::{Stream, StreamExt};
use kube::runtime::controller::{Action, Config as ControllerConfig, Controller};
use kube::runtime::reflector::ObjectRef;
use kube::runtime::{WatchStreamExt, reflector};
use lekiwi_core::watch::watch_first;
use serde::de::DeserializeOwned;
use std::fmt::Debug;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, warn};

use k8s_openapi::api::coordination::v1::Lease;
use kube::api::{Patch, PatchParams};
use kube::runtime::events::Recorder;
use kube::runtime::reflector::Store;
use kube::{Api, Resource};

use lekiwi_core::apply::StatusApply;
use lekiwi_metrics::{ControllerName, ErrorLabels, Metrics};

/// The longest a failing object waits before its next reconcile.
const MAX_BACKOFF: Duration = Duration::from_secs(300);
/// When an object whose write met a newer version (409) is planned again; the watch usually
/// brings that version first.
const CONFLICT_RETRY: Duration = Duration::from_secs(1);

/// The controllers' section of the operator's configuration (the binary's flags of the same
/// names fill it).
#[derive(Clone, Debug)]
pub struct Settings {
    /// The operator's namespace, where its leader Lease and the gateways' Leases live
    /// (`--namespace`).
    pub namespace: String,
    /// Watch Robots and RobotDeployments only here; all namespaces when `None`
    /// (`--watch-namespace`).
    pub watch_namespace: Option<String>,
    /// The leader-election Lease's name, the source of Events not tied to a gateway
    /// (`--leader-lease`).
    pub leader_lease: String,
    /// Heartbeat age past which a robot is Offline (`--heartbeat-grace-seconds`).
    pub heartbeat_grace_seconds: u64,
    /// The most status lag a gateway's Lease may add to that grace (`--max-status-lag-seconds`).
    pub max_status_lag_seconds: u64,
    /// Reconciles run at once per controller (`--concurrency`).
    pub concurrency: u16,
    /// Where the pushed releases' manifests and blobs are, to check a deployment's release
    /// (`--blob-dir`).
    pub blob_dir: std::path::PathBuf,
}

/// What every reconcile gets.
#[derive(Clone)]
pub struct Context {
    /// The Kubernetes client.
    pub client: kube::Client,
    /// The one Event recorder of this process.
    pub recorder: Recorder,
    /// Every metric of the process (controllers record into theirs).
    pub metrics: Metrics,
    /// The controllers' settings (namespaces, concurrency, heartbeat grace, blob directory).
    pub config: Arc<Settings>,
    /// Leases of the gateways, once the Robot controller has started watching them.
    pub gateway_leases: Option<Store<Lease>>,
    /// The robots live gateways claim in their Leases (see [`robot::claims`]).
    pub gateway_claims: Arc<robot::claims::ClaimIndex>,
    /// The robots the Robot controller marked `Unknown` per dead gateway (see [`robot::marks`]).
    pub gateway_marks: Arc<robot::marks::Marks>,
    /// The phase each robot was last seen in and the budget of per-robot phase Events.
    pub robot_events: Arc<robot::events::PhaseEvents>,
    /// Robots whose new spec waits for their gateway's status write (see [`robot::deferred`]).
    pub robot_deferred: Arc<robot::deferred::Deferred>,
    /// Consecutive failures per object, for exponential backoff.
    failures: Arc<Mutex<HashMap<(String, String), u32>>>,
    /// The budget of failure lines in the log.
    failure_log: Arc<failure_log::FailureLog>,
}

impl Context {
    /// A context with no failures recorded.
    pub fn new(
        client: kube::Client,
        recorder: Recorder,
        metrics: Metrics,
        config: Arc<Settings>,
    ) -> Self {
        Self {
            client,
            recorder,
            metrics,
            config,
            gateway_leases: None,
            gateway_claims: Arc::default(),
            gateway_marks: Arc::default(),
            robot_events: Arc::default(),
            robot_deferred: Arc::default(),
            failures: Arc::default(),
            failure_log: Arc::default(),
        }
    }

    /// Delay before retrying an object that just failed: 1 s, doubling, at most 5 minutes.
    pub fn next_backoff(&self, name: &str, namespace: &str) -> Duration {
        let mut failures = self.failures.lock().unwrap_or_else(|p| p.into_inner());
        let n = failures
            .entry((namespace.to_owned(), name.to_owned()))
            .or_insert(0);
        *n = n.saturating_add(1);
        Duration::from_secs(1u64 << (*n - 1).min(8)).min(MAX_BACKOFF)
    }

    /// Counts and logs a failed reconcile of `name` by its reason and returns how long to back
    /// off, by what can be done about the error: a conflict is planned again soon from the newer
    /// version (without growing the backoff; logged at debug), a transient failure backs off
    /// from 1 s doubling (a warning), a permanent one waits the longest backoff at once (an
    /// error: retrying cannot help until the cause is fixed). Warnings and errors are written
    /// within a budget shared by the process ([`failure_log`]); each says how many failures
    /// were `left_out` (logged at debug) since the previous one.
    pub fn reconcile_failed(
        &self,
        controller: ControllerName,
        name: &str,
        namespace: &str,
        error: &Error,
    ) -> Duration {
        self.metrics
            .controllers
            .reconcile_errors
            .get_or_create(&ErrorLabels {
                controller,
                reason: error.metric_reason(),
            })
            .inc();
        let category = error.category();
        let delay = match category {
            Category::Conflict => CONFLICT_RETRY,
            Category::Transient => self.next_backoff(name, namespace),
            Category::Permanent => MAX_BACKOFF,
        };
        // A conflict is routine; other failures get a line of their own within the budget
        // (see [`failure_log`]), and at debug beyond it.
        let line = match category {
            Category::Conflict => None,
            _ => self.failure_log.admit(),
        };
        match (category, line) {
            (Category::Conflict, _) => {
                debug!(?controller, name, namespace, %error, retry_in = ?delay, "reconcile met a newer version")
            }
            (_, None) => {
                debug!(?controller, name, namespace, %error, retry_in = ?delay, "reconcile failed")
            }
            (Category::Transient, Some(left_out)) => {
                warn!(?controller, name, namespace, %error, retry_in = ?delay, left_out, "reconcile failed")
            }
            (Category::Permanent, Some(left_out)) => {
                error!(?controller, name, namespace, %error, retry_in = ?delay, left_out, "reconcile failed; retrying cannot help until the cause is fixed")
            }
        }
        delay
    }

    /// The heartbeat age past which a robot connected through `gateway` is Offline:
    /// `--heartbeat-grace-seconds`, plus the status lag that gateway's live Lease declares (at
    /// most `--max-status-lag-seconds`): its robots' heartbeats are only as fresh as its writes.
    pub fn heartbeat_grace(&self, gateway: Option<&str>, now: jiff::Timestamp) -> Duration {
        let grace = Duration::from_secs(self.config.heartbeat_grace_seconds);
        let lag = match (gateway, &self.gateway_leases) {
            (Some(gateway), Some(leases)) => lekiwi_liveness::gateways::status_lag(
                leases,
                &self.config.namespace,
                gateway,
                now,
                Duration::from_secs(self.config.max_status_lag_seconds),
            ),
            _ => Duration::ZERO,
        };
        grace + lag
    }

    /// Forgets an object's failures after a successful reconcile.
    pub fn reset_backoff(&self, name: &str, namespace: &str) {
        let mut failures = self.failures.lock().unwrap_or_else(|p| p.into_inner());
        failures.remove(&(namespace.to_owned(), name.to_owned()));
    }
}

/// Writes `patch` (a typed [`StatusApply`] of `K`) to the object `name` by server-side apply
/// under `manager`, forcing ownership: each controller owns its status fields outright, so a
/// conflict means a stale writer (e.g. a former leader) that must lose; a fenced patch is
/// refused (409) if the object changed since it was read. `object` names it in the error.
/// Returns the object as written.
pub async fn apply_status<K, S>(
    api: &Api<K>,
    name: &str,
    object: &str,
    patch: &StatusApply<S>,
    manager: &str,
) -> Result<K>
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug,
    S: serde::Serialize + Debug,
{
    api.patch_status(
        name,
        &PatchParams::apply(manager).force(),
        &Patch::Apply(&patch),
    )
    .await
    .map_err(|source| Error::PatchStatus {
        object: object.to_owned(),
        source,
    })
}

/// A controller of `api` with this process's reconcile concurrency, fed by a watch that starts
/// before its list (a list longer than the API server's watch history does not expire it: see
/// `lekiwi_core::watch`).
pub(crate) fn controller_for<K>(api: Api<K>, ctx: &Context) -> Controller<K>
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + Sync + 'static,
{
    let writer = reflector::store::Writer::default();
    let store = writer.as_reader();
    // The Robot controller reads who wrote a status, and when, from managed fields: only the
    // field sets go.
    let changes = watch_first(
        api,
        lekiwi_core::api_client::watch_config(),
        lekiwi_core::watch::drop_field_sets::<K>,
    );
    Controller::for_stream(reflector(writer, changes).applied_objects(), store)
        .with_config(ControllerConfig::default().concurrency(ctx.config.concurrency))
}

/// Runs `controller`, also woken by `requests`, until `cancel` fires and the reconciles in
/// flight finish (within [`DRAIN`]). Failed items were already logged and counted by the error
/// policy, hence only `debug` here.
pub(crate) async fn drive<K, Ctx, Fut>(
    controller: Controller<K>,
    requests: impl Stream<Item = ObjectRef<K>> + Send + 'static,
    (reconcile, error_policy): (
        impl FnMut(Arc<K>, Arc<Ctx>) -> Fut,
        impl Fn(Arc<K>, &Error, Arc<Ctx>) -> Action,
    ),
    ctx: Arc<Ctx>,
    cancel: CancellationToken,
    what: &'static str,
) where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Debug + Send + Sync + 'static,
    Fut: Future<Output = Result<Action>> + Send + 'static,
    Ctx: Send + Sync + 'static,
{
    let stop = cancel.clone();
    let run = controller
        .reconcile_on(requests)
        .graceful_shutdown_on(async move { stop.cancelled().await })
        .run(reconcile, error_policy, ctx)
        .for_each(|res| {
            if let Err(e) = res {
                tracing::debug!(error = %e, "{what}");
            }
            futures::future::ready(())
        });
    let mut run = std::pin::pin!(run);
    tokio::select! {
        () = &mut run => return,
        () = cancel.cancelled() => {}
    }
    if tokio::time::timeout(DRAIN, run).await.is_err() {
        warn!(
            drain = ?DRAIN,
            "the controller did not stop within the drain time; its reconciles in flight are dropped"
        );
    }
}

/// How long a stopped controller's reconciles in flight have to finish before they are dropped.
/// A replica that lost its Lease must stop writing soon; and kube's runner waits for its store
/// to be ready before it sees its queue end, which a store whose list never came in (the watch
/// that fills it stops with the controller) never is: a leader that lost its Lease before its
/// RobotDeployment list came in waited for it for good, and never ran its controllers again
/// when it won the Lease back.
const DRAIN: Duration = Duration::from_secs(10);

#[cfg(test)]
mod tests {
    use super::*;

    /// A context whose client points nowhere: reconcile_failed never calls it.
    fn context() -> Context {
        let config = kube::Config::new("http://127.0.0.1:9".parse().unwrap());
        let client = kube::Client::try_from(config).unwrap();
        let recorder = Recorder::new(client.clone(), "test".into());
        let settings = Settings {
            namespace: "ops".into(),
            watch_namespace: None,
            leader_lease: "lekiwi-operator".into(),
            heartbeat_grace_seconds: 30,
            max_status_lag_seconds: 60,
            concurrency: 4,
            blob_dir: "/nonexistent".into(),
        };
        Context::new(client, recorder, Metrics::default(), Arc::new(settings))
    }

    fn failed(ctx: &Context, code: u16) -> Duration {
        let error = Error::PatchStatus {
            object: "lab/kiwi".into(),
            source: error::api(code),
        };
        ctx.reconcile_failed(ControllerName::robot, "kiwi", "lab", &error)
    }

    /// A controller stopped before its store was ready stops within [`DRAIN`] (see there).
    #[tokio::test(start_paused = true)]
    async fn a_controller_stopped_before_its_store_is_ready_stops() {
        use k8s_openapi::api::core::v1::ConfigMap;
        let writer = reflector::store::Writer::<ConfigMap>::default();
        let controller = Controller::for_stream(
            futures::stream::pending::<Result<ConfigMap, kube::runtime::watcher::Error>>(),
            writer.as_reader(),
        );
        let cancel = CancellationToken::new();
        let stop = cancel.clone();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_secs(1)).await;
            stop.cancel();
        });
        let handlers = (
            |_: Arc<ConfigMap>, _: Arc<()>| async { Ok::<_, Error>(Action::await_change()) },
            |_: Arc<ConfigMap>, _: &Error, _: Arc<()>| Action::await_change(),
        );
        let requests = futures::stream::pending::<ObjectRef<ConfigMap>>();
        let started = tokio::time::Instant::now();
        let driven = drive(controller, requests, handlers, Arc::new(()), cancel, "test");
        let stopped = tokio::time::timeout(Duration::from_secs(120), driven).await;
        assert!(stopped.is_ok(), "still running 120 s after the stop");
        // Stopped at 1 s, dropped [`DRAIN`] later.
        let took = started.elapsed();
        assert!(
            took <= Duration::from_secs(1) + DRAIN + Duration::from_millis(100),
            "stopped {took:?} after the start"
        );
        drop(writer);
    }

    /// What a subscriber wrote, for tests of what is logged.
    #[derive(Clone, Default)]
    struct Written(Arc<Mutex<Vec<u8>>>);

    impl std::io::Write for Written {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[tokio::test(start_paused = true)]
    async fn an_api_server_outage_writes_a_few_failure_lines_not_one_per_robot() {
        let ctx = context();
        let written = Written::default();
        let writer = written.clone();
        let subscriber = tracing_subscriber::fmt()
            .with_max_level(tracing::Level::WARN)
            .with_ansi(false)
            .with_writer(move || writer.clone())
            .finish();
        let robots = 10_000;
        let error = |name: &str| Error::PatchStatus {
            object: format!("lab/{name}"),
            source: error::api(503),
        };
        tracing::subscriber::with_default(subscriber, || {
            for i in 0..robots {
                let name = format!("kiwi-{i}");
                let delay =
                    ctx.reconcile_failed(ControllerName::robot, &name, "lab", &error(&name));
                assert_eq!(delay, Duration::from_secs(1), "each robot backs off alone");
            }
        });
        let text = String::from_utf8(written.0.lock().unwrap().clone()).unwrap();
        let lines = text
            .lines()
            .filter(|l| l.contains("reconcile failed"))
            .count();
        assert_eq!(lines, failure_log::LINES_BURST as usize, "{text}");
        let labels = ErrorLabels {
            controller: ControllerName::robot,
            reason: error("kiwi-0").metric_reason(),
        };
        let counted = ctx
            .metrics
            .controllers
            .reconcile_errors
            .get_or_create(&labels)
            .get();
        assert_eq!(counted, robots, "every failure is counted");
    }

    #[tokio::test]
    async fn the_retry_follows_what_can_be_done_about_the_error() {
        let ctx = context();
        // Transient: 1 s, doubling.
        assert_eq!(failed(&ctx, 503), Duration::from_secs(1));
        assert_eq!(failed(&ctx, 503), Duration::from_secs(2));
        // A conflict is planned again soon and does not grow the backoff.
        assert_eq!(failed(&ctx, 409), CONFLICT_RETRY);
        assert_eq!(failed(&ctx, 503), Duration::from_secs(4));
        // A refused write waits the longest at once.
        assert_eq!(failed(&ctx, 422), MAX_BACKOFF);
        ctx.reset_backoff("kiwi", "lab");
        assert_eq!(failed(&ctx, 500), Duration::from_secs(1));
    }
}
