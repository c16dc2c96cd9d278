//! The agent gateway: a WebSocket endpoint per robot (and the legacy polling endpoint) that
//! authenticates agents, keeps their presence in memory, writes `Robot` status sparingly and
//! stores every durable agent message before acknowledging it.

pub mod auth;
pub mod blob_api;
pub mod blob_store;
pub mod dispatch;
pub mod event_store;
pub mod events_api;
pub mod lease;
pub mod metrics;
pub mod poll;
pub mod presence;
pub mod rate;
pub mod session;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{ConnectInfo as PeerAddr, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use futures::StreamExt;
use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use kube::runtime::{WatchStreamExt, reflector, watcher};
use lekiwi_protocol::{AGENT_PATH, ROBOT_HEADER};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use self::auth::{Authenticator, Refusal};
use self::presence::{Presence, PresenceConfig};
use self::session::{Limits, Registry, Shared};
use crate::config::Config;
use crate::error::{Error, Result};
use crate::gateway::event_store::Store;
use crate::metrics::{KindLabels, Metrics};
use lekiwi_crds::contract::TOKEN_LABEL;

/// Errors answered over HTTP, as JSON; internal details are logged, never returned.
#[derive(Debug)]
pub enum ApiError {
    /// Missing or wrong credentials.
    Unauthorized(&'static str),
    /// A malformed request.
    BadRequest(String),
    /// The robot does not exist.
    NotFound(String),
    /// The gateway is at its connection limit.
    Unavailable(&'static str),
    /// Something failed on our side.
    Internal(String),
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, code, message) = match self {
            ApiError::Unauthorized(m) => (StatusCode::UNAUTHORIZED, "unauthorized", m.to_owned()),
            ApiError::BadRequest(m) => (StatusCode::BAD_REQUEST, "bad_request", m),
            ApiError::NotFound(m) => (StatusCode::NOT_FOUND, "not_found", m),
            ApiError::Unavailable(m) => {
                (StatusCode::SERVICE_UNAVAILABLE, "unavailable", m.to_owned())
            }
            ApiError::Internal(detail) => {
                warn!(%detail, "internal error answering a request");
                (
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "internal",
                    "internal error".to_owned(),
                )
            }
        };
        let body = serde_json::json!({ "error": code, "message": message });
        (
            status,
            [(header::CONTENT_TYPE, "application/json")],
            body.to_string(),
        )
            .into_response()
    }
}

/// The bearer token of a request, if any.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers
        .get(header::AUTHORIZATION)?
        .to_str()
        .ok()?
        .strip_prefix("Bearer ")
        .map(str::trim)
}

/// What the gateway's handlers share.
#[derive(Clone)]
pub struct GatewayState {
    /// Shared with sessions.
    pub shared: Arc<Shared>,
    /// Kubernetes client.
    pub client: kube::Client,
    /// Legacy-poll answers.
    pub releases: poll::SharedCache,
    /// Caps concurrent connections.
    pub connections: Arc<Semaphore>,
    /// Release blobs, uploads and the API token.
    pub blobs: Arc<blob_api::BlobApi>,
}

impl GatewayState {
    fn refused(&self, reason: Refusal) -> ApiError {
        self.shared
            .metrics
            .gateway
            .refused
            .get_or_create(&KindLabels {
                kind: reason.as_str(),
            })
            .inc();
        // Never log the token itself.
        warn!(reason = reason.as_str(), "refused an agent request");
        ApiError::Unauthorized(match reason {
            Refusal::MissingToken => "missing bearer token",
            Refusal::BadRobotName => "missing or invalid x-lekiwi-robot header (namespace/name)",
            Refusal::WrongToken => "invalid token",
        })
    }
}

/// The gateway's routes, separate from serving so tests can call them directly.
pub fn router(state: GatewayState) -> Router {
    Router::new()
        .route(AGENT_PATH, get(agent_ws))
        .route("/v1/poll", get(poll::poll))
        .route("/healthz", get(|| async { "ok\n" }))
        .merge(blob_api::routes())
        .merge(events_api::routes())
        .with_state(state)
}

async fn agent_ws(
    State(state): State<GatewayState>,
    PeerAddr(peer): PeerAddr<SocketAddr>,
    headers: HeaderMap,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    let permit = state.connections.clone().try_acquire_owned().map_err(|_| {
        ApiError::Unavailable("the gateway is at its connection limit; retry later")
    })?;
    let robot = headers.get(ROBOT_HEADER).and_then(|v| v.to_str().ok());
    let grant = state
        .shared
        .auth
        .authenticate(bearer(&headers), robot)
        .await
        .map_err(|r| state.refused(r))?;
    // Frames up to 4x the protocol limit are read and answered with an error frame; beyond
    // that the WebSocket layer closes the connection (1009) without buffering them.
    let hard_cap = state.shared.limits.max_frame_bytes * 4;
    let shared = state.shared.clone();
    Ok(ws
        .max_message_size(hard_cap)
        .max_frame_size(hard_cap)
        // Frames are small (a heartbeat is ~200 bytes); bigger ones are read in several chunks.
        .read_buffer_size(2 * 1024)
        .write_buffer_size(0)
        .on_upgrade(move |socket| async move {
            let (sink, stream) = socket.split();
            session::run(shared, grant, Some(peer.ip().to_string()), sink, stream).await;
            drop(permit);
        }))
}

/// The blob routes' state: the store's directories and the API token Secret are made now when
/// possible; if not, the gateway still serves agents and the blob routes retry (uploads answer
/// 500, a missing token Secret is made at the next API-token request).
async fn blob_api(
    config: &Config,
    client: &kube::Client,
    cancel: CancellationToken,
) -> blob_api::BlobApi {
    let store = crate::gateway::blob_store::BlobStore::new(&config.blob_dir, config.max_blob_bytes);
    match store.ensure_dirs().await {
        Ok(()) => info!(dir = %config.blob_dir.display(), "release blob store ready"),
        Err(e) => warn!(error = %e, "cannot prepare the release blob store"),
    }
    tokio::spawn(remove_stale_uploads(
        store.clone(),
        Duration::from_secs(config.stale_upload_hours.saturating_mul(3600)),
        cancel,
    ));
    let token = auth::ApiToken::new(client.clone(), &config.namespace, &config.api_token_secret);
    if let Err(e) = token.refresh().await {
        warn!(
            secret = %config.api_token_secret,
            namespace = %config.namespace,
            error = %e,
            "cannot read or create the API token Secret; retrying on use"
        );
    }
    blob_api::BlobApi::new(store, token)
}

/// Deletes the blob uploads nobody resumed for `max_age`, now and every hour, until `cancel`.
async fn remove_stale_uploads(
    store: crate::gateway::blob_store::BlobStore,
    max_age: Duration,
    cancel: CancellationToken,
) {
    let mut every = tokio::time::interval(Duration::from_secs(3600));
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = every.tick() => {}
        }
        match store.remove_stale_uploads(max_age).await {
            Ok((0, _)) => {}
            Ok((files, bytes)) => info!(files, bytes, "removed interrupted blob uploads"),
            Err(e) => warn!(error = %e, "cannot remove interrupted blob uploads"),
        }
    }
}

/// Runs the gateway until `cancel` fires.
/// `listening` is set once the gateway accepts connections.
pub async fn run(
    config: Arc<Config>,
    client: kube::Client,
    metrics: Metrics,
    store: Store,
    listening: Arc<std::sync::atomic::AtomicBool>,
    cancel: CancellationToken,
) -> Result<()> {
    let name = config.gateway_name();
    let secrets: Api<Secret> = match &config.watch_namespace {
        Some(ns) => Api::namespaced(client.clone(), ns),
        None => Api::all(client.clone()),
    };
    let (secret_store, writer) = reflector::store();
    // Keep only what authentication reads: at 10,000 robots the managed fields and annotations
    // of the token Secrets would cost more memory than the hashes themselves.
    let token_secrets = watcher(secrets, watcher::Config::default().labels(TOKEN_LABEL))
        .default_backoff()
        .modify(|secret: &mut Secret| {
            secret.metadata.managed_fields = None;
            secret.metadata.annotations = None;
            secret.metadata.owner_references = None;
        });
    let secret_watch = reflector(writer, token_secrets)
        .touched_objects()
        .for_each(|_| futures::future::ready(()));
    let secret_task = tokio::spawn(secret_watch);
    tokio::select! {
        () = cancel.cancelled() => { secret_task.abort(); return Ok(()); }
        r = secret_store.wait_until_ready() => if r.is_err() { return Err(Error::TaskStopped("token secret reflector")); }
    }

    let presence = Presence::new(
        PresenceConfig {
            gateway: name.clone(),
            status_refresh: Duration::from_secs(config.status_refresh_seconds),
            poll_grace: Duration::from_secs(config.poll_grace_seconds),
            qps: config.status_qps,
            burst: config.status_burst,
            concurrency: 8,
        },
        metrics.clone(),
    );
    let registry = Arc::new(Registry::default());
    let robots: Api<lekiwi_crds::Robot> = match &config.watch_namespace {
        Some(ns) => Api::namespaced(client.clone(), ns),
        None => Api::all(client.clone()),
    };
    let (desired, dispatch_task) =
        dispatch::start(robots, registry.clone(), cancel.clone()).await?;
    let shared = Shared {
        presence: presence.clone(),
        store: store.clone(),
        auth: Authenticator::new(client.clone(), secret_store),
        registry,
        limits: Limits {
            max_frame_bytes: config.max_frame_bytes,
            rate: config.agent_rate,
            burst: config.agent_burst,
            abuse_threshold: config.agent_burst * 2,
            handshake_timeout: Duration::from_secs(config.handshake_timeout_seconds),
            heartbeat_interval: Duration::from_secs(config.heartbeat_interval_seconds),
            missed_heartbeats: config.missed_heartbeats,
        },
        metrics: metrics.clone(),
        gateway: name.clone(),
        cancel: cancel.clone(),
        desired: Some(desired),
    };
    let state = GatewayState {
        shared: Arc::new(shared),
        client: client.clone(),
        releases: Arc::default(),
        connections: Arc::new(Semaphore::new(config.max_connections)),
        blobs: Arc::new(blob_api(&config, &client, cancel.clone()).await),
    };

    // The writer outlives the sessions so their disconnects still reach the API server.
    // Connection records a crashed earlier run of this gateway left open are closed now.
    match store
        .close_open_connections(
            &name,
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
    let writer_cancel = CancellationToken::new();
    let writer_task = tokio::spawn(
        presence
            .clone()
            .run_writer(client.clone(), writer_cancel.clone()),
    );
    let ticker = {
        let presence = presence.clone();
        let cancel = cancel.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tokio::select! {
                    () = cancel.cancelled() => return,
                    _ = tick.tick() => presence.tick(),
                }
            }
        })
    };
    let lease_task = tokio::spawn(lease::renew(
        client.clone(),
        config.namespace.clone(),
        name.clone(),
        Duration::from_secs(config.gateway_lease_seconds),
        cancel.clone(),
    ));
    let retention = store.spawn_retention(
        Duration::from_secs(config.retention_days.saturating_mul(86_400)),
        Duration::from_secs(3600),
        cancel.clone(),
    );

    let app = router(state).into_make_service_with_connect_info::<SocketAddr>();
    let addr = config.gateway_addr;
    let served = match (&config.tls_cert, &config.tls_key) {
        (Some(cert), Some(key)) => {
            let _ = rustls::crypto::ring::default_provider().install_default();
            let tls = axum_server::tls_rustls::RustlsConfig::from_pem_file(cert, key)
                .await
                .map_err(|source| Error::Serve { addr, source })?;
            let handle = axum_server::Handle::new();
            let h = handle.clone();
            let c = cancel.clone();
            tokio::spawn(async move {
                c.cancelled().await;
                h.graceful_shutdown(Some(Duration::from_secs(5)));
            });
            let server = axum_server::bind_rustls(addr, tls).handle(handle.clone());
            let l = listening.clone();
            tokio::spawn(async move {
                if handle.listening().await.is_some() {
                    l.store(true, std::sync::atomic::Ordering::Release);
                }
            });
            info!(%addr, gateway = %name, tls = true, "gateway listening");
            server.serve(app).await
        }
        _ => {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .map_err(|source| Error::Serve { addr, source })?;
            info!(addr = %listener.local_addr().map(|a| a.to_string()).unwrap_or_default(), gateway = %name, tls = false, "gateway listening");
            listening.store(true, std::sync::atomic::Ordering::Release);
            let c = cancel.clone();
            axum::serve(listener, app)
                .with_graceful_shutdown(async move { c.cancelled().await })
                .await
        }
    };
    cancel.cancel();
    // Let the writer flush the sessions' disconnects (bounded) before the process goes.
    let flush = async {
        while presence.queued() > 0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let _ = tokio::time::timeout(Duration::from_secs(5), flush).await;
    writer_cancel.cancel();
    let _ = writer_task.await;
    for t in [ticker, lease_task, retention, secret_task, dispatch_task] {
        t.abort();
    }
    served.map_err(|source| Error::Serve { addr, source })
}
