//! Read-only HTTP access to a robot's stored events for `kubectl lekiwi events`, with the API
//! token (the same check as the blob API's uploads).

use axum::Json;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use axum::routing::get;
use serde::Deserialize;

use super::auth::{Refusal, valid_name};
use super::{ApiError, AppState, bearer};
use crate::gateway::event_store::{RobotKey, StoredEvent};

/// Events answered per request unless the query says otherwise.
pub const DEFAULT_LIMIT: u32 = 100;
/// Most events one request answers; a client pages with `after_seq`.
pub const MAX_LIMIT: u32 = 1000;

/// The events route, merged into the gateway's [`super::router`].
pub fn routes() -> Router<AppState> {
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
/// ascending sequence order, as a JSON array of [`StoredEvent`].
async fn events(
    State(state): State<AppState>,
    Path((namespace, name)): Path<(String, String)>,
    Query(query): Query<EventsQuery>,
    headers: HeaderMap,
) -> Result<Json<Vec<StoredEvent>>, ApiError> {
    let Some(token) = bearer(&headers).filter(|t| !t.is_empty()) else {
        return Err(state.refused(Refusal::MissingToken));
    };
    if !state.blobs.api_token.check(token).await {
        return Err(state.refused(Refusal::WrongToken));
    }
    if !valid_name(&namespace) || !valid_name(&name) {
        return Err(ApiError::BadRequest(format!(
            "{namespace}/{name} is not a valid robot name"
        )));
    }
    let limit = query.limit.unwrap_or(DEFAULT_LIMIT).clamp(1, MAX_LIMIT);
    let robot = RobotKey::new(namespace, name);
    let events = state
        .shared
        .store
        .events(&robot, query.after_seq, limit)
        .await
        .map_err(|e| ApiError::Internal(format!("reading events of {robot}: {e}")))?;
    Ok(Json(events))
}
