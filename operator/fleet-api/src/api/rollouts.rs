//! `GET /api/v1/rollouts`, `/api/v1/namespaces/{namespace}/rollouts[/{name}]`: RobotDeployments
//! with their per-robot progress (`status.robots`), from the gateway's cache; and the rollout
//! actions `POST .../rollouts/{name}/pause|resume|abort|undo|restart`, allowed by `patch` on
//! `robotdeployments`, which write exactly what `kubectl lekiwi rollout ...` writes.

use std::sync::Arc;

use axum::Json;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use jiff::Timestamp;
use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::RobotDeployment;
use lekiwi_crds::deployment::{ABORT_ANNOTATION, RESTART_ANNOTATION, UNDO_ANNOTATION};
use serde::Deserialize;
use serde_json::{Value, json};
use tracing::info;

use super::robots::Page;
use super::{authorize, bad_query, check_names, continue_after, page_size, ready, resume_key};
use crate::kube_auth::Access;
use crate::{ApiError, FleetState};

/// Field manager of the API's patches (`kubectl get -o yaml --show-managed-fields`).
const FIELD_MANAGER: &str = "lekiwi-fleet-api";

/// Query of the rollout lists.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListQuery {
    /// Page size.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) limit: Option<u32>,
    /// Token of the page to resume after.
    #[serde(default, deserialize_with = "super::blank_is_none")]
    pub(crate) r#continue: Option<String>,
}

/// `GET /api/v1/rollouts` (`list robotdeployments` in all namespaces).
pub async fn list_all(
    State(state): State<FleetState>,
    query: Result<Query<ListQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<Page<Arc<RobotDeployment>>>, ApiError> {
    list(state, None, query, headers).await
}

/// `GET /api/v1/namespaces/{namespace}/rollouts` (`list robotdeployments` there).
pub async fn list_namespaced(
    State(state): State<FleetState>,
    Path(namespace): Path<String>,
    query: Result<Query<ListQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<Page<Arc<RobotDeployment>>>, ApiError> {
    check_names(&namespace, None)?;
    list(state, Some(namespace), query, headers).await
}

async fn list(
    state: FleetState,
    namespace: Option<String>,
    query: Result<Query<ListQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Json<Page<Arc<RobotDeployment>>>, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    let ns = namespace.as_deref().unwrap_or_default();
    authorize(
        &state,
        &headers,
        Some(Access::new("list", "robotdeployments", ns)),
    )
    .await?;
    page(&state, namespace.as_deref(), &query).map(Json)
}

/// The page of rollouts `query` asks for in `namespace` (all if `None`), from the cache.
pub(crate) fn page(
    state: &FleetState,
    namespace: Option<&str>,
    query: &ListQuery,
) -> Result<Page<Arc<RobotDeployment>>, ApiError> {
    let limit = page_size(query.limit)?;
    let after = resume_key(query.r#continue.as_deref())?;
    ready(&state.fleet.rollouts)?;
    let (items, more) =
        state
            .fleet
            .rollouts
            .page(namespace, after.as_ref(), limit as usize, |_| true);
    let next = more
        .then(|| {
            items
                .last()
                .map(|d| continue_after(&lekiwi_core::cache::key(d.as_ref())))
        })
        .flatten();
    Ok(Page { items, next })
}

/// `GET /api/v1/namespaces/{namespace}/rollouts/{name}` (`get robotdeployments`).
pub async fn one(
    State(state): State<FleetState>,
    Path((namespace, name)): Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<Arc<RobotDeployment>>, ApiError> {
    check_names(&namespace, Some(&name))?;
    let access = Access {
        name: Some(name.clone()),
        ..Access::new("get", "robotdeployments", &namespace)
    };
    authorize(&state, &headers, Some(access)).await?;
    ready(&state.fleet.rollouts)?;
    state
        .fleet
        .rollouts
        .get(&namespace, &name)
        .map(Json)
        .ok_or_else(|| not_found(&namespace, &name))
}

/// `POST .../rollouts/{name}/pause`: sets `spec.paused`.
pub async fn pause(
    state: State<FleetState>,
    path: Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<RobotDeployment>, ApiError> {
    act(state, path, headers, json!({"spec": {"paused": true}})).await
}

/// `POST .../rollouts/{name}/resume`: clears `spec.paused`.
pub async fn resume(
    state: State<FleetState>,
    path: Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<RobotDeployment>, ApiError> {
    act(state, path, headers, json!({"spec": {"paused": false}})).await
}

/// `POST .../rollouts/{name}/abort`: stamps the abort annotation with now.
pub async fn abort(
    state: State<FleetState>,
    path: Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<RobotDeployment>, ApiError> {
    act(state, path, headers, stamp(ABORT_ANNOTATION)).await
}

/// `POST .../rollouts/{name}/undo`: stamps the undo annotation with now.
pub async fn undo(
    state: State<FleetState>,
    path: Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<RobotDeployment>, ApiError> {
    act(state, path, headers, stamp(UNDO_ANNOTATION)).await
}

/// `POST .../rollouts/{name}/restart`: stamps the restart annotation with now.
pub async fn restart(
    state: State<FleetState>,
    path: Path<(String, String)>,
    headers: HeaderMap,
) -> Result<Json<RobotDeployment>, ApiError> {
    act(state, path, headers, stamp(RESTART_ANNOTATION)).await
}

/// The merge patch `kubectl lekiwi rollout abort|undo|restart` sends: the annotation set to now.
pub(crate) fn stamp(annotation: &str) -> Value {
    json!({"metadata": {"annotations": {annotation: Timestamp::now().to_string()}}})
}

/// Merge-patches the RobotDeployment with `patch` once the caller may `patch` it; answers the
/// object as patched.
async fn act(
    State(state): State<FleetState>,
    Path((namespace, name)): Path<(String, String)>,
    headers: HeaderMap,
    patch: Value,
) -> Result<Json<RobotDeployment>, ApiError> {
    check_names(&namespace, Some(&name))?;
    let access = Access {
        name: Some(name.clone()),
        ..Access::new("patch", "robotdeployments", &namespace)
    };
    let user = authorize(&state, &headers, Some(access)).await?;
    patch_rollout(&state, &user, &namespace, &name, &patch)
        .await
        .map(Json)
}

/// Merge-patches RobotDeployment `namespace/name` with `patch` for `user` (whose permission
/// was checked); the object as patched.
pub(crate) async fn patch_rollout(
    state: &FleetState,
    user: &str,
    namespace: &str,
    name: &str,
    patch: &Value,
) -> Result<RobotDeployment, ApiError> {
    let api: Api<RobotDeployment> = Api::namespaced(state.fleet.client.clone(), namespace);
    let params = PatchParams {
        field_manager: Some(FIELD_MANAGER.to_owned()),
        ..PatchParams::default()
    };
    let patched = api
        .patch(name, &params, &Patch::Merge(patch))
        .await
        .map_err(|e| match e {
            kube::Error::Api(s) if s.code == 404 => not_found(namespace, name),
            e => ApiError::Internal(format!("patching robotdeployment {namespace}/{name}: {e}")),
        })?;
    info!(%user, robotdeployment = %name, %namespace, %patch, "rollout action through the Fleet API");
    Ok(patched)
}

fn not_found(namespace: &str, name: &str) -> ApiError {
    ApiError::NotFound(format!("robotdeployment {namespace}/{name} not found"))
}
