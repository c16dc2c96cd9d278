//! The robot-facing gateway: a WebSocket endpoint per robot (and the legacy polling endpoint)
//! that authenticates agents, tells their presence to the status writer (`lekiwi_presence`),
//! sends them what their Robot asks for and stores every durable agent message before
//! acknowledging it.

pub mod admission;
pub mod auth;
pub mod blob_api;
mod blob_start;
pub mod config;
pub mod dispatch;
pub mod enroll;
pub mod error;
pub mod halt;
pub mod listener;
pub mod lookup;
pub mod mailbox;
pub mod poll;
pub mod quota_warnings;
pub mod registry;
pub mod server;
pub mod session;
pub mod tls;
pub mod tokens;

pub use self::error::{Error, Result};
pub use self::server::run;
pub use lekiwi_core::http::{ApiError, bearer};

use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{ConnectInfo as PeerAddr, FromRef, State};
use axum::http::HeaderMap;
use axum::response::Response;
use axum::routing::get;
use futures::{FutureExt, StreamExt};
use lekiwi_protocol::{AGENT_PATH, ROBOT_HEADER};
use tokio::sync::Semaphore;
use tracing::warn;

use self::auth::{Grant, Refusal};
use self::session::SessionContext;
use lekiwi_core::RobotKey;
use lekiwi_fleet_api::FleetState;
use lekiwi_metrics::KindLabels;

/// What the gateway's HTTP handlers share (axum's router state).
#[derive(Clone)]
pub struct AppState {
    /// What every WebSocket session shares; the HTTP routes use its store, auth and metrics.
    pub shared: Arc<SessionContext>,
    /// Reads Robots the Robot watch does not hold yet (legacy polls).
    pub client: kube::Client,
    /// What each robot's legacy polls were answered with lately.
    pub poll_memo: Arc<poll::PollMemo>,
    /// One permit per open WebSocket connection; none left means 503.
    pub connections: Arc<Semaphore>,
    /// Enrollments admitted per second; beyond, 503 with `Retry-After`.
    pub enrollments: Arc<admission::EnrollAdmission>,
    /// Release blobs and uploads.
    pub blobs: Arc<blob_api::BlobApi>,
    /// The Fleet API's state: the fleet's caches, people's authentication, the releases.
    pub api: FleetState,
}

impl FromRef<AppState> for FleetState {
    fn from_ref(state: &AppState) -> Self {
        state.api.clone()
    }
}

impl AppState {
    /// Counts a refused request in `lekiwi_gateway_refused_total{kind}`.
    pub(crate) fn count_refusal(&self, kind: &'static str) {
        self.shared
            .metrics
            .gateway
            .refused
            .get_or_create(&KindLabels { kind })
            .inc();
    }

    /// Counts and logs a refused agent request and answers it with 401 (503 when throttled).
    fn refused(&self, reason: Refusal) -> ApiError {
        self.count_refusal(reason.as_str());
        // Never log the token itself.
        warn!(reason = reason.as_str(), "refused an agent request");
        reason.answer()
    }
}

impl AppState {
    /// Refuses (403) an enrollment token for a robot that has its own token and no permission
    /// to enroll again, before the upgrade.
    async fn may_enroll(&self, robot: &RobotKey) -> Result<(), ApiError> {
        match self.shared.auth.may_enroll(robot).await {
            Ok(()) => Ok(()),
            Err(enroll::Error::Refused(r)) => {
                self.count_refusal(r.as_str());
                warn!(robot = %robot.name, namespace = %robot.namespace, reason = r.as_str(), "refused an enrollment");
                Err(ApiError::Forbidden(r.message(robot)))
            }
            Err(enroll::Error::Kube(e)) => {
                Err(ApiError::Internal(format!("enrollment check: {e}")))
            }
        }
    }
}

/// Which of the gateway's routes a listener serves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Routes {
    /// Every route: one address for robots and people (no `--api-addr`).
    All,
    /// The robots' port when the API has its own: the WebSocket, legacy polls, the release
    /// blob and events APIs; no Fleet API, no dashboard.
    Agents,
    /// The API's own port: the Fleet API, the dashboard, the release blob and events APIs;
    /// no agent WebSocket or polls.
    People,
}

/// The gateway's routes, separate from serving so tests can call them directly.
pub fn router(state: AppState) -> Router {
    routes(state, Routes::All)
}

/// The routes `which` listener serves.
pub fn routes(state: AppState, which: Routes) -> Router {
    let mut authenticated = Router::new();
    if which != Routes::People {
        authenticated = authenticated
            .route(AGENT_PATH, get(agent_ws))
            .route("/v1/poll", get(poll::poll));
    }
    authenticated = authenticated
        .merge(blob_api::routes())
        .merge(lekiwi_fleet_api::events::routes());
    if which != Routes::Agents {
        authenticated = authenticated.merge(lekiwi_fleet_api::api::routes());
    }
    // Every route but /healthz and the dashboard's static files requires credentials: a
    // success there takes the connection out of the unauthenticated limits.
    let mut router = authenticated
        .route_layer(axum::middleware::from_fn(
            listener::authenticated_on_success,
        ))
        .route("/healthz", get(|| async { "ok\n" }));
    if which != Routes::Agents {
        router = router.merge(lekiwi_fleet_api::dashboard::routes());
    }
    router.with_state(state)
}

async fn agent_ws(
    State(state): State<AppState>,
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
    if let Grant::Enroll(robot) = &grant {
        if let Err(seconds) = state.enrollments.admit() {
            state.count_refusal("enrollment_throttled");
            return Err(ApiError::EnrollmentsThrottled(seconds));
        }
        state.may_enroll(robot).await?;
    }
    if let Err(seconds) = state.shared.registry.may_open(grant.robot()) {
        state.count_refusal("too_many_sessions");
        return Err(ApiError::TooManySessions(seconds));
    }
    // Frames up to 4x the protocol limit are read and answered with an error frame; beyond
    // that the WebSocket layer closes the connection (1009) without buffering them.
    let hard_cap = state.shared.limits.max_frame_bytes * 4;
    let shared = state.shared.clone();
    let token_hash = lekiwi_crds::contract::hash_token(bearer(&headers).unwrap_or_default());
    Ok(ws
        .max_message_size(hard_cap)
        .max_frame_size(hard_cap)
        // Frames are small (a heartbeat is ~200 bytes): the read buffer lives as long as the
        // connection, so it is sized for them; a bigger frame grows it as far as it needs.
        .read_buffer_size(512)
        .write_buffer_size(0)
        // The socket is split and the session's future made before the returned future, which
        // is that future itself (`map`, not an `async` block: one that awaits a captured future
        // keeps a second, moved-out copy of it). Whatever the returned future holds, it holds
        // for the life of the connection.
        .on_upgrade(move |socket| {
            let (sink, stream) = socket.split();
            let address = Some(peer.ip().to_string());
            session::run(shared, grant, token_hash, address, sink, stream)
                .map(move |()| drop(permit))
        }))
}
