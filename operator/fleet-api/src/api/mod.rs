//! The Fleet API: `/api/v1/...` on the gateway's HTTP port, for people, scripts and (later) the
//! dashboard. Every request carries a bearer token the API server accepts (a `TokenReview`),
//! counts against its user's budget ([`limits`]: 429 with `Retry-After`) and is allowed what RBAC
//! allows that user on the matching resource (a `SubjectAccessReview`), both answers cached
//! briefly by [`crate::kube_auth`]. Reads come from memory ([`cache`], fed by watches) or the
//! event store; rollout actions patch the RobotDeployment as `kubectl lekiwi rollout` does.
//! The routes and their document are listed once, in [`openapi`].

mod access;
pub mod graphql;
mod history;
pub mod limits;
pub mod openapi;
mod releases;
mod robots;
mod rollouts;
pub mod selector;
mod summary;

use std::sync::Arc;

use axum::extract::FromRef;
use axum::extract::rejection::QueryRejection;
use axum::http::{HeaderMap, Method, StatusCode, Uri};
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, any, delete, get, post};
use axum::{Json, Router};
use kube::Api;
use lekiwi_crds::{Robot, RobotDeployment};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use self::limits::UserLimits;
use crate::kube_auth::Access;
use crate::{ApiError, FleetState, bearer};
use lekiwi_core::cache::{self, Cache};
use lekiwi_core::http::Refusal;
use lekiwi_core::http::valid_name;

/// Items a list answers unless `limit` says otherwise.
pub const DEFAULT_LIMIT: u32 = 100;
/// Most items one page holds; a client pages with `continue`.
pub const MAX_LIMIT: u32 = 1000;

/// What the Fleet API's handlers share besides the gateway's state.
pub struct FleetApi {
    /// Every Robot the gateway watches, with its status.
    pub robots: Arc<Cache<Robot>>,
    /// Every RobotDeployment the gateway watches, with its status.
    pub rollouts: Arc<Cache<RobotDeployment>>,
    /// Each user's request budget.
    pub limits: UserLimits,
    /// The GraphQL schema and its WebSocket limits.
    pub graphql: Arc<graphql::GraphQl>,
    /// Patches RobotDeployments for rollout actions (after the caller's own permission check).
    client: kube::Client,
}

impl FleetApi {
    /// Starts the watches of `robots` and `rollouts`; at most `--api-rate` requests per second
    /// per user (`--api-burst` at once), GraphQL limited as `config` says. The returned tasks
    /// run until `cancel`.
    pub fn start(
        robots: Api<Robot>,
        rollouts: Api<RobotDeployment>,
        client: kube::Client,
        config: &crate::config::FleetApiConfig,
        cancel: &CancellationToken,
    ) -> (Self, Vec<JoinHandle<()>>) {
        let (robots, robot_task) = cache::watch(robots, trim_meta::<Robot>, cancel.clone());
        let (rollouts, rollout_task) =
            cache::watch(rollouts, trim_meta::<RobotDeployment>, cancel.clone());
        let api = Self {
            robots,
            rollouts,
            limits: UserLimits::new(config.api_rate, config.api_burst),
            graphql: Arc::new(graphql::GraphQl::new(&config.graphql)),
            client,
        };
        (api, vec![robot_task, rollout_task])
    }
}

/// What the API never answers with and memory need not hold.
fn trim_meta<K: kube::Resource>(o: &mut K) {
    o.meta_mut().managed_fields = None;
}

/// The Fleet API's routes, merged into the gateway's router.
/// Unknown paths under `/api/v1/` and wrong methods answer JSON errors too.
pub fn routes<S>() -> Router<S>
where
    S: Clone + Send + Sync + 'static,
    FleetState: FromRef<S>,
{
    use openapi::paths as p;
    let wrong = |m: MethodRouter<S>| m.fallback(wrong_method);
    Router::new()
        .route(p::OPENAPI, wrong(get(openapi::document)))
        .route(p::ACCESS, wrong(get(access::access)))
        .route(p::ROBOTS, wrong(get(robots::list_all)))
        .route(p::SUMMARY, wrong(get(summary::summary)))
        .route(p::NAMESPACED_ROBOTS, wrong(get(robots::list_namespaced)))
        .route(p::ROBOT, wrong(get(robots::one)))
        .route(p::ROBOT_EVENTS, wrong(get(history::events)))
        .route(p::ROBOT_TELEMETRY, wrong(get(history::telemetry)))
        .route(p::ROLLOUTS, wrong(get(rollouts::list_all)))
        .route(
            p::NAMESPACED_ROLLOUTS,
            wrong(get(rollouts::list_namespaced)),
        )
        .route(p::ROLLOUT, wrong(get(rollouts::one)))
        .route(p::ROLLOUT_PAUSE, wrong(post(rollouts::pause)))
        .route(p::ROLLOUT_RESUME, wrong(post(rollouts::resume)))
        .route(p::ROLLOUT_ABORT, wrong(post(rollouts::abort)))
        .route(p::ROLLOUT_UNDO, wrong(post(rollouts::undo)))
        .route(p::ROLLOUT_RESTART, wrong(post(rollouts::restart)))
        .route(p::RELEASES, wrong(get(releases::list)))
        .route(p::RELEASE, wrong(delete(releases::delete)))
        .route(
            openapi::paths::GRAPHQL,
            wrong(post(graphql::post).get(graphql::websocket)),
        )
        .route("/api/v1/{*rest}", any(unknown_path))
}

async fn unknown_path(uri: Uri) -> ApiError {
    ApiError::NotFound(format!(
        "no such Fleet API route: {}; see /api/v1/openapi.json",
        uri.path()
    ))
}

async fn wrong_method(method: Method, uri: Uri) -> Response {
    let body = serde_json::json!({
        "error": "method_not_allowed",
        "message": format!("{method} is not allowed on {}; see /api/v1/openapi.json", uri.path()),
    });
    (StatusCode::METHOD_NOT_ALLOWED, Json(body)).into_response()
}

/// Lets a request through when its bearer token is accepted, its user is within budget and
/// RBAC allows it `access` (any authenticated user when `None`); returns the username.
pub(crate) async fn authorize(
    state: &FleetState,
    headers: &HeaderMap,
    access: Option<Access>,
) -> Result<String, ApiError> {
    let Some(token) = bearer(headers).filter(|t| !t.is_empty()) else {
        return Err(state.refused(Refusal::MissingToken));
    };
    let user = state
        .kube_auth
        .user_of(token)
        .await
        .map_err(|d| state.denied(d))?;
    let name = user.username.unwrap_or_default();
    if let Err(seconds) = state.fleet.limits.take(&name) {
        state.count_refusal("rate_limited");
        return Err(ApiError::RateLimited(seconds));
    }
    if let Some(access) = access {
        state.check_user(headers, Some(access)).await?;
    }
    Ok(name)
}

/// An optional query parameter that counts as absent when empty (`continue=`), as the
/// Kubernetes API server takes its list parameters.
pub(crate) fn blank_is_none<'de, D, T>(d: D) -> Result<Option<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: std::str::FromStr,
    T::Err: std::fmt::Display,
{
    match <Option<String> as serde::Deserialize>::deserialize(d)? {
        Some(text) if !text.is_empty() => text.parse().map(Some).map_err(serde::de::Error::custom),
        _ => Ok(None),
    }
}

/// A malformed query string, as a 400 that says what is wrong.
pub(crate) fn bad_query(rejection: QueryRejection) -> ApiError {
    ApiError::BadRequest(rejection.body_text())
}

/// `limit` checked against 1 to [`MAX_LIMIT`], [`DEFAULT_LIMIT`] when absent.
pub(crate) fn page_size(limit: Option<u32>) -> Result<u32, ApiError> {
    match limit.unwrap_or(DEFAULT_LIMIT) {
        n @ 1..=MAX_LIMIT => Ok(n),
        n => Err(ApiError::BadRequest(format!(
            "limit must be between 1 and {MAX_LIMIT}, got {n}"
        ))),
    }
}

/// 400 unless `namespace` and `name` (when given) are valid Kubernetes names.
pub(crate) fn check_names(namespace: &str, name: Option<&str>) -> Result<(), ApiError> {
    if !valid_name(namespace) {
        return Err(ApiError::BadRequest(format!(
            "{namespace:?} is not a valid namespace"
        )));
    }
    match name {
        Some(n) if !valid_name(n) => {
            Err(ApiError::BadRequest(format!("{n:?} is not a valid name")))
        }
        _ => Ok(()),
    }
}

/// 503 until the watch behind `cache` has listed everything once.
pub(crate) fn ready<K>(cache: &Cache<K>) -> Result<(), ApiError> {
    if cache.is_ready() {
        Ok(())
    } else {
        Err(ApiError::Unavailable(
            "the gateway is still reading the fleet; retry in a moment",
        ))
    }
}

/// The opaque `continue` token that resumes after `namespace/name`.
pub(crate) fn continue_after(key: &cache::Key) -> String {
    hex::encode(format!("{}/{}", key.0, key.1))
}

/// The key a `continue` token resumes after (none for an empty one, the first page); 400 for a
/// token we did not make.
pub(crate) fn resume_key(token: Option<&str>) -> Result<Option<cache::Key>, ApiError> {
    let Some(token) = token.filter(|t| !t.is_empty()) else {
        return Ok(None);
    };
    hex::decode(token)
        .ok()
        .and_then(|b| String::from_utf8(b).ok())
        .and_then(|s| s.split_once('/').map(|(a, b)| (a.to_owned(), b.to_owned())))
        .map(Some)
        .ok_or_else(|| ApiError::BadRequest("invalid continue token".into()))
}
