//! `GET /api/v1/namespaces/{namespace}/access`: who the caller is and which Fleet API actions
//! RBAC allows them in that namespace, so a client (the dashboard) can disable what would be
//! refused. Each answer is the same SubjectAccessReview the action's own route makes (cached the
//! same way), so the two never disagree; the route itself needs only an accepted token.

use axum::Json;
use axum::extract::{Path, State};
use axum::http::HeaderMap;
use serde::Serialize;

use super::{authorize, check_names};
use crate::kube_auth::{Access, Denied};
use crate::{ApiError, FleetState, bearer};

/// What the caller may do in one namespace.
#[derive(Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct AccessView {
    /// The username the API server's TokenReview gave.
    pub user: String,
    /// The namespace asked about.
    pub namespace: String,
    /// Each action and whether RBAC allows it.
    pub allowed: Allowed,
}

/// The Fleet API's actions, each with the permission its route checks.
#[derive(Debug, Serialize)]
#[serde(rename_all = "camelCase")]
pub struct Allowed {
    /// `list robots`: the robot lists.
    pub list_robots: bool,
    /// `get robots`: one robot and its vitals.
    pub get_robots: bool,
    /// `get robots/events`: stored events.
    pub get_events: bool,
    /// `get robots/telemetry`: stored telemetry.
    pub get_telemetry: bool,
    /// `list robotdeployments`: the rollout lists.
    pub list_rollouts: bool,
    /// `patch robotdeployments`: pause, resume, undo, restart.
    pub patch_rollouts: bool,
}

/// `GET /api/v1/namespaces/{namespace}/access` (any authenticated user).
pub async fn access(
    State(state): State<FleetState>,
    Path(namespace): Path<String>,
    headers: HeaderMap,
) -> Result<Json<AccessView>, ApiError> {
    check_names(&namespace, None)?;
    let user = authorize(&state, &headers, None).await?;
    let sub = |subresource| Access {
        subresource: Some(subresource),
        ..Access::new("get", "robots", &namespace)
    };
    let allowed = Allowed {
        list_robots: may(&state, &headers, Access::new("list", "robots", &namespace)).await?,
        get_robots: may(&state, &headers, Access::new("get", "robots", &namespace)).await?,
        get_events: may(&state, &headers, sub("events")).await?,
        get_telemetry: may(&state, &headers, sub("telemetry")).await?,
        list_rollouts: may(
            &state,
            &headers,
            Access::new("list", "robotdeployments", &namespace),
        )
        .await?,
        patch_rollouts: may(
            &state,
            &headers,
            Access::new("patch", "robotdeployments", &namespace),
        )
        .await?,
    };
    Ok(Json(AccessView {
        user,
        namespace,
        allowed,
    }))
}

/// Whether RBAC allows the caller `access`; a refusal is an answer here, not an error (and is
/// not counted as a refused request).
async fn may(state: &FleetState, headers: &HeaderMap, access: Access) -> Result<bool, ApiError> {
    let token = bearer(headers).unwrap_or_default();
    match state.kube_auth.check(token, &access).await {
        Ok(()) => Ok(true),
        Err(Denied::Forbidden(_)) => Ok(false),
        Err(denied) => Err(state.denied(denied)),
    }
}
