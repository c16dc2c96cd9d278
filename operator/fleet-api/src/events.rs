//! Read-only HTTP access to a robot's stored events for `kubectl lekiwi events`, for a
//! Kubernetes user RBAC allows `get` on `robots/events` (group `fleet.lekiwi.io`) in the robot's
//! namespace (see [`crate::kube_auth`]).

use axum::Json;
use axum::Router;
use axum::extract::{FromRef, Path, Query, State};
use axum::http::HeaderMap;
use axum::routing::get;
use serde::Deserialize;

use crate::kube_auth::Access;
use crate::{ApiError, FleetState};
use lekiwi_core::RobotKey;
use lekiwi_core::http::valid_name;
use lekiwi_event_store::StoredEvent;

/// Events answered per request unless the query says otherwise.
pub const DEFAULT_LIMIT: u32 = 100;
/// Most events one request answers; a client pages with `after_seq`.
pub const MAX_LIMIT: u32 = 1000;

/// The events route, merged into the gateway's router.
pub fn routes<S>() -> Router<S>
where
    S: Clone + Send + Sync + 'static,
    FleetState: FromRef<S>,
{
    Router::new().route("/v1/robots/{namespace}/{name}/events", get(events))
}

/// Query of the events route.
#[derive(Debug, Deserialize)]
struct EventsQuery {
    /// Only events with a sequence number above this one.
    after_seq: Option<u64>,
    /// At most this many (1 to [`MAX_LIMIT`]).
    limit: Option<u32>,
}

/// `GET /v1/robots/{namespace}/{name}/events?after_seq=&limit=`: the robot's stored events in
/// ascending sequence order, as a JSON array of [`StoredEvent`]; 404 for a robot the gateway
/// does not hold.
async fn events(
    State(state): State<FleetState>,
    Path((namespace, name)): Path<(String, String)>,
    Query(query): Query<EventsQuery>,
    headers: HeaderMap,
) -> Result<Json<Vec<StoredEvent>>, ApiError> {
    if !valid_name(&namespace) || !valid_name(&name) {
        return Err(ApiError::BadRequest(format!(
            "{namespace}/{name} is not a valid robot name"
        )));
    }
    let access = Access {
        subresource: Some("events"),
        name: Some(name.clone()),
        ..Access::new("get", "robots", &namespace)
    };
    state.check_user(&headers, Some(access)).await?;
    // As the Fleet API's history routes: a robot the gateway does not hold is not found, not
    // an empty history, whatever the store still keeps under its name.
    crate::api::ready(&state.fleet.robots)?;
    if state.fleet.robots.get(&namespace, &name).is_none() {
        return Err(ApiError::NotFound(format!(
            "robot {namespace}/{name} not found"
        )));
    }
    let limit = query.limit.unwrap_or(DEFAULT_LIMIT).clamp(1, MAX_LIMIT);
    let robot = RobotKey::new(namespace, name);
    let events = state
        .store
        .events(&robot, query.after_seq, limit)
        .await
        .map_err(|e| ApiError::Internal(format!("reading events of {robot}: {e}")))?;
    Ok(Json(events))
}
