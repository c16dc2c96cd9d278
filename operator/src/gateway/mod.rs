//! The agent gateway: a WebSocket endpoint per robot (and the legacy polling endpoint) that
//! authenticates agents, keeps their presence in memory, writes `Robot` status sparingly and
//! stores every durable agent message before acknowledging it.

pub mod admission;
pub mod api;
pub mod auth;
pub mod blob_api;
mod blob_start;
pub mod cache;
pub mod dashboard;
pub mod dispatch;
pub mod enroll;
pub mod events_api;
pub mod halt;
pub mod holder;
pub mod kube_auth;
pub mod lease;
pub mod listener;
pub mod lookup;
pub mod mailbox;
pub mod poll;
pub mod presence;
pub mod quota_warnings;
pub mod registry;
pub mod releases;
pub mod server;
pub mod session;
pub mod tls;
pub mod tokens;
pub mod watched;

pub use self::server::run;

use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{ConnectInfo as PeerAddr, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use futures::{FutureExt, StreamExt};
use lekiwi_protocol::{AGENT_PATH, ROBOT_HEADER};
use tokio::sync::Semaphore;
use tracing::warn;

use self::auth::{Grant, Refusal};
use self::session::SessionContext;
use lekiwi_core::RobotKey;
use lekiwi_metrics::KindLabels;

/// Errors answered over HTTP, as JSON; internal details are logged, never returned.
#[derive(Debug)]
pub enum ApiError {
    /// Missing or wrong credentials.
    Unauthorized(&'static str),
    /// Valid credentials that do not allow this (an enrollment token for an enrolled robot).
    Forbidden(String),
    /// A malformed request.
    BadRequest(String),
    /// The robot does not exist.
    NotFound(String),
    /// A request body beyond its route's limit: 413.
    TooLarge(String),
    /// The gateway is at its connection limit.
    Unavailable(&'static str),
    /// The gateway's budget of API reads for unauthenticated requests is spent: 503 with
    /// `Retry-After`.
    Throttled(&'static str),
    /// A robot opens sessions faster than its budget: 429 with `Retry-After` (seconds).
    TooManySessions(u64),
    /// More robots enroll than the gateway admits: 503 with `Retry-After` (seconds).
    EnrollmentsThrottled(u64),
    /// A person's or tool's requests to the Fleet API exceed their user's budget: 429 with
    /// `Retry-After` (seconds).
    RateLimited(u64),
    /// Something failed on our side.
    Internal(String),
}

/// A JSON error that tells the client when to come back (`Retry-After`, in seconds).
fn retry_later(status: StatusCode, code: &str, message: &str, seconds: u64) -> Response {
    let body = serde_json::json!({ "error": code, "message": message });
    (
        status,
        [
            (header::CONTENT_TYPE, "application/json".to_owned()),
            (header::RETRY_AFTER, seconds.to_string()),
        ],
        body.to_string(),
    )
        .into_response()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, code, message) = match self {
            ApiError::Unauthorized(m) => (StatusCode::UNAUTHORIZED, "unauthorized", m.to_owned()),
            ApiError::Forbidden(m) => (StatusCode::FORBIDDEN, "forbidden", m),
            ApiError::BadRequest(m) => (StatusCode::BAD_REQUEST, "bad_request", m),
            ApiError::NotFound(m) => (StatusCode::NOT_FOUND, "not_found", m),
            ApiError::TooLarge(m) => (StatusCode::PAYLOAD_TOO_LARGE, "too_large", m),
            ApiError::Unavailable(m) => {
                (StatusCode::SERVICE_UNAVAILABLE, "unavailable", m.to_owned())
            }
            ApiError::Throttled(m) => {
                return retry_later(StatusCode::SERVICE_UNAVAILABLE, "unavailable", m, 1);
            }
            ApiError::TooManySessions(seconds) => {
                return retry_later(
                    StatusCode::TOO_MANY_REQUESTS,
                    "too_many_sessions",
                    "this robot opens sessions too often; retry after Retry-After seconds",
                    seconds,
                );
            }
            ApiError::EnrollmentsThrottled(seconds) => {
                return retry_later(
                    StatusCode::SERVICE_UNAVAILABLE,
                    "unavailable",
                    "the gateway admits enrollments at a limited rate; retry after Retry-After seconds",
                    seconds,
                );
            }
            ApiError::RateLimited(seconds) => {
                return retry_later(
                    StatusCode::TOO_MANY_REQUESTS,
                    "rate_limited",
                    "too many requests from this user; retry after Retry-After seconds",
                    seconds,
                );
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
    /// Release blobs, uploads and the Kubernetes checks of people's requests.
    pub blobs: Arc<blob_api::BlobApi>,
    /// The Fleet API's caches and per-user budgets.
    pub fleet: Arc<api::FleetApi>,
    /// The releases of the blob store, who uses them, and their garbage collection.
    pub releases: Arc<releases::Releases>,
}

impl AppState {
    /// Counts and logs a refused agent request and answers it with 401.
    /// Counts a refused request in `lekiwi_gateway_refused_total{kind}`.
    pub(crate) fn count_refusal(&self, kind: &'static str) {
        self.shared
            .metrics
            .gateway
            .refused
            .get_or_create(&KindLabels { kind })
            .inc();
    }

    fn refused(&self, reason: Refusal) -> ApiError {
        self.count_refusal(reason.as_str());
        // Never log the token itself.
        warn!(reason = reason.as_str(), "refused an agent request");
        if reason == Refusal::Throttled {
            return ApiError::Throttled(
                "too many requests the gateway cannot authenticate from its cache; retry later",
            );
        }
        ApiError::Unauthorized(match reason {
            Refusal::MissingToken => "missing bearer token",
            Refusal::BadRobotName => "missing or invalid x-lekiwi-robot header (namespace/name)",
            Refusal::RobotNameTooLong => {
                "robot names are at most 63 characters (the robot's token Secret carries the name in a label)"
            }
            Refusal::WrongToken => "invalid token",
            Refusal::EnrollmentToken => {
                "an enrollment token cannot speak for a robot; use the robot's own token"
            }
            Refusal::Throttled => "retry later",
        })
    }
}

impl AppState {
    /// Lets a person's or tool's request through when the API server accepts its bearer token
    /// and RBAC allows `access` (see [`kube_auth`]): 401 for a token the API server refuses,
    /// 403 naming the missing permission, 400 when the request names no namespace (`None`).
    pub async fn check_user(
        &self,
        headers: &HeaderMap,
        access: Option<kube_auth::Access>,
    ) -> Result<(), ApiError> {
        let Some(token) = bearer(headers).filter(|t| !t.is_empty()) else {
            return Err(self.refused(Refusal::MissingToken));
        };
        let Some(access) = access else {
            return Err(ApiError::BadRequest(
                "name the namespace: ?namespace=NAME".into(),
            ));
        };
        self.blobs
            .kube_auth
            .check(token, &access)
            .await
            .map_err(|d| self.denied(d))
    }

    /// The answer to a request [`kube_auth`] did not let through: 401 for a token the API
    /// server refuses, 403 naming the missing permission, 503 when reviews are throttled.
    fn denied(&self, denied: kube_auth::Denied) -> ApiError {
        match denied {
            kube_auth::Denied::Unauthenticated => self.refused(Refusal::WrongToken),
            kube_auth::Denied::Forbidden(permission) => {
                self.count_refusal("forbidden");
                // The code (`forbidden`) is the body's `error`; GraphQL puts it before the message.
                ApiError::Forbidden(format!("this needs {permission}"))
            }
            kube_auth::Denied::Unavailable(detail) => ApiError::Internal(detail),
            kube_auth::Denied::Throttled => self.refused(Refusal::Throttled),
        }
    }

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
        .merge(events_api::routes());
    if which != Routes::Agents {
        authenticated = authenticated.merge(api::routes());
    }
    // Every route but /healthz and the dashboard's static files requires credentials: a
    // success there takes the connection out of the unauthenticated limits.
    let mut router = authenticated
        .route_layer(axum::middleware::from_fn(
            listener::authenticated_on_success,
        ))
        .route("/healthz", get(|| async { "ok\n" }));
    if which != Routes::Agents {
        router = router.merge(dashboard::routes());
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
