//! The gateway process's life: it watches the token Secrets and Robots, builds the handlers'
//! shared state, starts the background tasks, serves plain HTTP or TLS until cancelled, and
//! drains the status writer before it returns.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use futures::StreamExt;
use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use kube::runtime::{WatchStreamExt, watcher};
use lekiwi_crds::contract::TOKEN_LABEL;
use tokio::sync::{Semaphore, watch};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::admission::EnrollAdmission;
use super::auth::Authenticator;
use super::halt::Holds;
use super::listener::{self, ConnLimits};
use super::lookup::{LookupConfig, Lookups};
use super::quota_warnings::QuotaWarnings;
use super::registry::Registry;
use super::session::{Limits, SessionContext};
use super::tls::reload;
use super::tokens::TokenIndex;
use super::{AppState, Routes, dispatch, routes};
use crate::config::Config;
use crate::error::{Error, Result};
use lekiwi_event_store::Store;
use lekiwi_fleet_api::api::FleetApi;
use lekiwi_metrics::Metrics;
use lekiwi_presence::lease;
use lekiwi_presence::watched::WatchedRobots;
use lekiwi_presence::{PhasePlanner, Presence, PresenceConfig, RateBounds};

/// At most one quota Warning Event per robot this often.
const QUOTA_WARNING_INTERVAL: Duration = Duration::from_secs(300);

/// Runs the gateway until `cancel` fires.
/// `listening` is set once the gateway accepts connections; `leader` says whether this replica
/// may collect the blob store's garbage (see [`lekiwi_fleet_api::releases::task`]).
pub async fn run(
    config: Arc<Config>,
    client: kube::Client,
    metrics: Metrics,
    store: Store,
    (listening, leader): (Arc<AtomicBool>, watch::Receiver<bool>),
    cancel: CancellationToken,
) -> Result<()> {
    let name = config.name.clone();
    let registry = Arc::new(Registry::with_open_rate(
        config.flags.session_opens_per_minute,
        config.flags.session_open_burst,
    ));
    let Some((tokens, secret_task)) =
        watch_token_secrets(&config, &client, registry.clone(), &cancel).await?
    else {
        return Ok(());
    };
    let presence = presence(&config, &name, &metrics);
    // One watch of Robots per gateway: the Fleet API's cache serves dispatch and sessions too.
    let (fleet, fleet_tasks) = FleetApi::start(
        watched(&config, &client),
        watched(&config, &client),
        client.clone(),
        &config.fleet_api,
        &cancel,
    );
    let (desired, holds, [dispatch_task, halt_task]) =
        start_dispatch(&config, &fleet, registry.clone(), &presence, &cancel).await?;
    let shared = SessionContext {
        presence: presence.clone(),
        store: store.clone(),
        auth: Authenticator::new(client.clone(), tokens).with_lookups(lookups(&config, &metrics)),
        registry,
        limits: limits(&config),
        metrics: metrics.clone(),
        gateway: name.clone(),
        cancel: cancel.clone(),
        desired: Some(desired.clone()),
        holds: Some(holds),
        quota_warnings: QuotaWarnings::new(client.clone(), &name, QUOTA_WARNING_INTERVAL),
    };
    let live = super::blob_start::LiveHeartbeats(presence.clone());
    let people = (fleet, &store, Arc::new(live) as _);
    let (blobs, api, care_task) =
        super::blob_start::blob_state(&config, (&client, &metrics), people, leader, &cancel).await;
    let state = AppState {
        shared: Arc::new(shared),
        client: client.clone(),
        poll_memo: Arc::default(),
        connections: Arc::new(Semaphore::new(config.flags.max_connections)),
        enrollments: Arc::new(EnrollAdmission::new(
            config.flags.enroll_rate,
            config.flags.enroll_burst,
        )),
        blobs: Arc::new(blobs),
        api,
    };
    close_stale_connections(&store, &name).await;
    let mut tasks = start_background(
        &config,
        &name,
        &client,
        (&presence, desired),
        &store,
        &cancel,
    );
    let more = [secret_task, dispatch_task, halt_task, care_task];
    tasks.aborted.extend(more.into_iter().chain(fleet_tasks));
    let served = serve(&config, &name, state, listening, &cancel).await?;
    cancel.cancel();
    drain(&presence, tasks).await;
    served.map_err(|source| Error::Serve {
        addr: config.flags.gateway_addr,
        source,
    })
}

/// Starts the dispatch of Robot changes to this gateway's sessions and presence once the
/// fleet's Robot cache holds the first list, and lets presence plan phases from it; and the
/// halting of downloads a user's abort, undo or pause of a rollout stops. Returns the desired
/// releases (and holders) of the robots, which of them are held, the dispatch task and the
/// halt task.
async fn start_dispatch(
    config: &Config,
    fleet: &FleetApi,
    registry: Arc<Registry>,
    presence: &Presence,
    cancel: &CancellationToken,
) -> Result<(WatchedRobots, Holds, [JoinHandle<()>; 2])> {
    let holds = Holds(fleet.rollouts.clone());
    let name = config.name.clone();
    let robots = fleet.robots.clone();
    let halt = super::halt::start(&fleet.rollouts, robots.clone(), registry.clone(), cancel);
    let (desired, task) = dispatch::start(
        robots,
        holds.clone(),
        registry,
        presence.clone(),
        &name,
        cancel,
    )
    .await?;
    let grace = Duration::from_secs(config.heartbeat_grace_seconds);
    presence.plan_phases(PhasePlanner::new(desired.clone(), grace));
    Ok((desired, holds, [task, halt]))
}

/// The gateway's presence: the robots' states and the status writer's limits.
fn presence(config: &Config, name: &str, metrics: &Metrics) -> Presence {
    Presence::new(
        PresenceConfig {
            gateway: name.to_owned(),
            status_refresh: Duration::from_secs(config.flags.status_refresh_seconds),
            poll_grace: Duration::from_secs(config.flags.poll_grace_seconds),
            qps: config.flags.status_qps,
            adaptive: Some(RateBounds {
                min: config.flags.status_qps_min,
                max: config.flags.status_qps_max,
                slow: Duration::from_millis(config.flags.status_slow_ms),
            }),
            burst: config.flags.status_burst,
            concurrency: usize::from(config.flags.status_concurrency),
        },
        metrics.clone(),
    )
}

/// The resources of kind `K` this gateway watches: those of `--watch-namespace`, or all.
fn watched<K>(config: &Config, client: &kube::Client) -> Api<K>
where
    K: kube::Resource<Scope = k8s_openapi::NamespaceResourceScope>,
    K::DynamicType: Default,
{
    match &config.watch_namespace {
        Some(ns) => Api::namespaced(client.clone(), ns),
        None => Api::all(client.clone()),
    }
}

/// Starts the watch of the robots' token Secrets and waits until it has listed them all;
/// `None` when `cancel` fired first. A robot token Secret that changes or goes tells that
/// robot's session in `registry`, which closes if its token no longer counts.
async fn watch_token_secrets(
    config: &Config,
    client: &kube::Client,
    registry: Arc<Registry>,
    cancel: &CancellationToken,
) -> Result<Option<(Arc<TokenIndex>, JoinHandle<()>)>> {
    // Only what authentication reads is kept (see `TokenIndex`): the gateway holds every
    // robot's token Secret, so a whole `Secret` each would cost ~2 KiB per robot of the fleet.
    let tokens = Arc::new(TokenIndex::default());
    let index = tokens.clone();
    let token_secrets = watcher(
        watched::<Secret>(config, client),
        // Listed from the API server's watch cache: a restart under load must not wait for
        // 10,000 Secrets paged out of etcd one slow page at a time; the watch that follows
        // brings every later change.
        lekiwi_core::api_client::watch_config()
            .labels(TOKEN_LABEL)
            .any_semantic(),
    )
    .default_backoff();
    let secret_watch = token_secrets.for_each(move |event| {
        // The index first: a session told below checks its token against it.
        if let Ok(event) = &event {
            index.apply(event);
        }
        match event {
            Ok(watcher::Event::Apply(s)) => credentials_changed(&registry, &s, false),
            Ok(watcher::Event::Delete(s)) => credentials_changed(&registry, &s, true),
            // A (re)list is complete and the store holds exactly the listed Secrets.
            Ok(watcher::Event::InitDone) => {
                let told = registry.recheck_all_credentials();
                if told > 0 {
                    info!(
                        sessions = told,
                        "token Secrets listed anew; every session checks its token"
                    );
                }
            }
            _ => {}
        }
        futures::future::ready(())
    });
    let secret_task = tokio::spawn(secret_watch);
    tokio::select! {
        () = cancel.cancelled() => { secret_task.abort(); Ok(None) }
        () = tokens.wait_until_ready() => Ok(Some((tokens, secret_task))),
    }
}

/// Tells the session of the robot whose token Secret `secret` is that it changed.
fn credentials_changed(registry: &Registry, secret: &Secret, deleted: bool) {
    if let Some(robot) = super::auth::robot_of_secret(secret) {
        registry.notify_credentials(&robot, deleted);
    }
}

/// The budget of API reads for requests the token cache cannot authenticate.
fn lookups(config: &Config, metrics: &Metrics) -> Lookups {
    Lookups::new(
        LookupConfig::of(config),
        metrics.gateway.auth_lookups.clone(),
    )
}

/// The limits every session enforces, from the configuration.
fn limits(config: &Config) -> Limits {
    Limits {
        max_frame_bytes: config.flags.max_frame_bytes,
        rate: config.flags.agent_rate,
        burst: config.flags.agent_burst,
        abuse_threshold: config.flags.agent_burst * 2,
        handshake_timeout: Duration::from_secs(config.flags.handshake_timeout_seconds),
        heartbeat_interval: Duration::from_secs(config.flags.heartbeat_interval_seconds),
        missed_heartbeats: config.flags.missed_heartbeats,
        send_timeout: Duration::from_secs(config.flags.send_timeout_seconds.max(1)),
    }
}

/// The gateway's long-lived tasks besides serving.
struct Background {
    /// Stops the status writer, which outlives the sessions so their disconnects still reach
    /// the API server.
    writer_cancel: CancellationToken,
    writer_task: JoinHandle<()>,
    /// Tasks that stop by being aborted once serving ended.
    aborted: Vec<JoinHandle<()>>,
}

/// Starts the status writer (which reads who holds each robot from the Robot watch's cache),
/// the presence ticker, the Lease of gateway `name`, the watch of the other gateways' Leases
/// (see [`super::peers`]) and the event store's retention.
fn start_background(
    config: &Config,
    name: &str,
    client: &kube::Client,
    (presence, holders): (&Presence, WatchedRobots),
    store: &Store,
    cancel: &CancellationToken,
) -> Background {
    let writer_cancel = CancellationToken::new();
    let writer_task = tokio::spawn(presence.clone().run_writer(
        client.clone(),
        Some(holders),
        writer_cancel.clone(),
    ));
    let ticker = tokio::spawn(tick_presence(presence.clone(), cancel.clone()));
    let lease_task = tokio::spawn(lease::renew(
        client.clone(),
        config.namespace.clone(),
        name.to_owned(),
        Duration::from_secs(config.flags.gateway_lease_seconds),
        Some(presence.clone()),
        cancel.clone(),
    ));
    let peers = lekiwi_presence::peers::watch(
        client.clone(),
        config.namespace.clone(),
        name.to_owned(),
        presence.clone(),
        cancel.clone(),
    );
    let retention = store.spawn_retention(
        Duration::from_secs(config.retention_days.saturating_mul(86_400)),
        Duration::from_secs(3600),
        cancel.clone(),
    );
    Background {
        writer_cancel,
        writer_task,
        aborted: vec![ticker, lease_task, peers, retention],
    }
}

/// Closes the connection records an earlier run of gateway `name` left open when it crashed.
async fn close_stale_connections(store: &Store, name: &str) {
    match store
        .close_open_connections(
            name,
            jiff::Timestamp::now().as_millisecond(),
            "gateway_restarted",
        )
        .await
    {
        Ok(0) => {}
        Ok(n) => info!(
            records = n,
            "closed connection records left open by an earlier run"
        ),
        Err(e) => warn!(error = %e, "cannot close stale connection records"),
    }
}

/// Lets presence notice silent robots, once a second until `cancel`.
async fn tick_presence(presence: Presence, cancel: CancellationToken) {
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            () = cancel.cancelled() => return,
            _ = tick.tick() => presence.tick(),
        }
    }
}

/// Serves the gateway's routes with TLS when a certificate and key are configured, else in
/// plain HTTP, until `cancel` fires: all on the gateway address, or the Fleet API and dashboard
/// apart on `--api-addr`. The outer error is a failure to start, the inner one of serving.
async fn serve(
    config: &Config,
    name: &str,
    state: AppState,
    listening: Arc<AtomicBool>,
    cancel: &CancellationToken,
) -> Result<std::io::Result<()>> {
    let addr = config.flags.gateway_addr;
    let metrics = state.shared.metrics.gateway.clone();
    let tls_metrics = reload::TlsMetrics {
        reloads: metrics.tls_reloads.clone(),
        expiry: metrics.tls_certificate_expiry.clone(),
    };
    let tls = reload::acceptor(config, tls_metrics, cancel).await?;
    let bind = |addr| async move {
        tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|source| Error::Serve { addr, source })
    };
    let gateway = bind(addr).await?;
    let api = match config.flags.api_addr {
        Some(api_addr) => Some(bind(api_addr).await?),
        None => None,
    };
    let local =
        |l: &tokio::net::TcpListener| l.local_addr().map(|a| a.to_string()).unwrap_or_default();
    info!(addr = %local(&gateway), gateway = %name, tls = tls.is_some(), api = %api.as_ref().map(local).unwrap_or_else(|| "same address".into()), "gateway listening");
    listening.store(true, Ordering::Release);
    let limits = ConnLimits {
        header_timeout: Duration::from_secs(config.flags.header_timeout_seconds.max(1)),
        tls_handshake_timeout: Duration::from_secs(
            config.flags.tls_handshake_timeout_seconds.max(1),
        ),
        max_header_bytes: config.flags.max_header_bytes,
        per_address: config.flags.max_unauthenticated_per_address,
        unauthenticated: config.flags.max_unauthenticated_connections.max(1),
    };
    let dropped = metrics.connections_dropped;
    let Some(api) = api else {
        let app = routes(state, Routes::All);
        return Ok(listener::serve(gateway, app, tls, limits, dropped, cancel.clone()).await);
    };
    let agents = routes(state.clone(), Routes::Agents);
    let people = routes(state, Routes::People);
    let served = tokio::try_join!(
        listener::serve(
            gateway,
            agents,
            tls.clone(),
            limits.clone(),
            dropped.clone(),
            cancel.clone()
        ),
        listener::serve(api, people, tls, limits, dropped, cancel.clone()),
    );
    Ok(served.map(|_| ()))
}

/// Lets the status writer flush the sessions' disconnects (bounded) before the process goes,
/// then stops the background tasks.
async fn drain(presence: &Presence, tasks: Background) {
    let flush = async {
        while presence.queued() > 0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let _ = tokio::time::timeout(Duration::from_secs(5), flush).await;
    tasks.writer_cancel.cancel();
    let _ = tasks.writer_task.await;
    for t in tasks.aborted {
        t.abort();
    }
}
