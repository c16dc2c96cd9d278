//! `GET /api/v1/namespaces/{namespace}/releases` (`list releases`): the releases pushed to the
//! namespace, newest first, with their size and how many robots and deployments use them; and
//! `DELETE .../releases/{release}` (`delete releases`) by digest or version, refused with 409
//! while anything references the release.

use axum::Json;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde_json::json;
use tracing::info;

use super::{authorize, check_names};
use crate::kube_auth::Access;
use crate::releases::Refused;
use crate::{ApiError, FleetState};

/// `GET /api/v1/namespaces/{namespace}/releases`.
pub async fn list(
    State(state): State<FleetState>,
    Path(namespace): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    check_names(&namespace, None)?;
    authorize(
        &state,
        &headers,
        Some(Access::new("list", "releases", &namespace)),
    )
    .await?;
    super::ready(&state.fleet.robots)?;
    super::ready(&state.fleet.rollouts)?;
    let items = state
        .releases
        .list(&namespace)
        .await
        .map_err(|e| ApiError::Internal(e.to_string()))?;
    Ok(Json(json!({ "items": items })).into_response())
}

/// `DELETE /api/v1/namespaces/{namespace}/releases/{release}`.
pub async fn delete(
    State(state): State<FleetState>,
    Path((namespace, release)): Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    check_names(&namespace, None)?;
    let user = authorize(
        &state,
        &headers,
        Some(Access::new("delete", "releases", &namespace)),
    )
    .await?;
    match state.releases.delete(&namespace, &release).await {
        Ok(deleted) => {
            info!(%namespace, %user, version = %deleted.release.version, digest = %deleted.release.digest,
                blobs = deleted.blobs, bytes = deleted.bytes, "release deleted");
            Ok(Json(deleted).into_response())
        }
        Err(refused) => {
            let message = refused.message(&namespace, &release);
            match refused {
                Refused::NotFound => Err(ApiError::NotFound(message)),
                Refused::Ambiguous(_) => Err(ApiError::BadRequest(message)),
                Refused::InUse(_) | Refused::Downloading => Ok(conflict(&message)),
                Refused::NotReady => Err(ApiError::Unavailable(
                    "the gateway is still reading the fleet; retry in a moment",
                )),
                Refused::Store(e) => Err(ApiError::Internal(e.to_string())),
            }
        }
    }
}

fn conflict(message: &str) -> Response {
    (
        StatusCode::CONFLICT,
        Json(json!({ "error": "conflict", "message": message })),
    )
        .into_response()
}
