//! Release blobs over HTTP on the gateway's listener: robots (with their own token) download
//! blobs and manifests, resuming by byte range; people and tools (the release CLI, with a
//! Kubernetes bearer token) upload blobs in verified, resumable chunks and read them back.
//!
//! | Route | Who (permission of a Kubernetes user) | Answers |
//! |---|---|---|
//! | `HEAD /v1/blobs/{digest}?namespace=NS` | robot; user: `get releases` | 200 with `Content-Length`, 404 |
//! | `GET /v1/blobs/{digest}?namespace=NS` | robot; user: `get releases` | 200, 206 for `Range: bytes=N-[M]`, 404, 416 |
//! | `PUT /v1/blobs/{digest}?namespace=NS` | user: `create releases` | 201 stored, 202 `{"offset"}` chunk taken, 200 already stored, 409 `{"offset"}` wrong offset, 400 digest mismatch or bad request, 413 too large |
//! | `GET /v1/uploads/{digest}?namespace=NS` | user: `create releases` | `{"offset", "complete"}` |
//! | `GET /v1/releases/{digest}?namespace=NS` | robot; user: `get releases` | manifest + `"missing"`, 404, 422 not a manifest |
//! | `GET /v1/blobs-served[?robot=ns/name]` | user: `get robots` in the robot's namespace (`list robots` in all namespaces without `robot`) | bytes and downloads served per robot |
//!
//! A `PUT` without `Content-Range` is the whole blob (any partial upload is discarded); with
//! `Content-Range: bytes START-END/TOTAL` it is one chunk, which must start at the upload's
//! current offset; `bytes */TOTAL` with an empty body finishes an upload that holds every byte
//! but was not verified (the gateway stopped in between). A blob is stored only after its
//! SHA-256 matched.
//!
//! A robot authenticates as on the WebSocket (`Authorization: Bearer <robot token>` and
//! `x-lekiwi-robot: namespace/name`; an enrollment token is refused). A request without the robot
//! header carries a bearer token the API server accepts and names the namespace it acts in
//! (`?namespace=`, 400 without); RBAC must allow the permission above on the group
//! `fleet.lekiwi.io` there (see [`lekiwi_fleet_api::kube_auth`]; 401 for a refused token, 403 naming the
//! permission). A robot reads only the blobs its namespace's releases
//! reference (see [`access`]); any other digest is answered as unknown (404). Bytes served are counted as they are sent: in
//! `lekiwi_gateway_blob_bytes_served_total`, per robot in memory (`/v1/blobs-served`, since this
//! process started) and in a debug log line `blob download finished` per request with `robot`
//! and `bytes` fields.

mod access;
mod download;
#[cfg(test)]
mod tests;
mod upload;

use std::collections::{BTreeMap, HashMap};
use std::sync::Mutex;

use crate::lookup::Lookups;
use axum::Router;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use lekiwi_protocol::ROBOT_HEADER;
use lekiwi_protocol::release::digest_hex;
use serde::{Deserialize, Serialize};
use serde_json::json;
use tracing::{debug, warn};

use self::download::{get_blob, head_blob};
use self::upload::put_blob;
use super::auth::{Grant, Refusal, parse_robot};
use super::{ApiError, AppState, bearer};
use lekiwi_blob_store::{BlobStore, Error as StoreError};
use lekiwi_core::RobotKey;
use lekiwi_fleet_api::kube_auth::Access;

/// What the blob routes share.
pub struct BlobApi {
    /// Where blobs and partial uploads live on disk.
    pub store: BlobStore,
    /// File lists of the release manifests robots' reads were checked against.
    manifests: access::ManifestFiles,
    /// The budget of live reads of a Robot whose blob read the Robot cache cannot allow yet.
    reads: Lookups,
    served: Mutex<HashMap<RobotKey, Served>>,
}

/// What was served to one robot since the gateway started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Served {
    /// Blob bytes sent.
    pub bytes: u64,
    /// `GET` requests of blobs answered with content (200 or 206).
    pub downloads: u64,
}

impl BlobApi {
    /// The routes' shared state.
    pub fn new(store: BlobStore) -> Self {
        Self {
            store,
            manifests: access::ManifestFiles::default(),
            reads: Lookups::default(),
            served: Mutex::default(),
        }
    }

    /// The same, with `reads` as the budget of live Robot reads (see [`access`]).
    pub fn with_reads(self, reads: Lookups) -> Self {
        Self { reads, ..self }
    }

    fn record(&self, robot: &RobotKey, bytes: u64, downloads: u64) {
        let mut served = self.served.lock().unwrap_or_else(|p| p.into_inner());
        let entry = served.entry(robot.clone()).or_default();
        entry.bytes += bytes;
        entry.downloads += downloads;
    }

    /// What was served to `robot` since the gateway started.
    pub fn served(&self, robot: &RobotKey) -> Served {
        self.served
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(robot)
            .copied()
            .unwrap_or_default()
    }
}

/// The blob, upload and release routes.
pub fn routes() -> Router<AppState> {
    Router::new()
        .route(
            "/v1/blobs/{digest}",
            get(get_blob).head(head_blob).put(put_blob),
        )
        .route("/v1/uploads/{digest}", get(upload_status))
        .route("/v1/releases/{digest}", get(get_release))
        .route("/v1/blobs-served", get(blobs_served))
}

/// An error answer in the gateway's JSON shape (`{"error", "message"}`), with the upload
/// offset where a client needs it to resume.
#[derive(Debug)]
pub struct Failure(Box<Response>);

impl IntoResponse for Failure {
    fn into_response(self) -> Response {
        *self.0
    }
}

impl From<ApiError> for Failure {
    fn from(e: ApiError) -> Self {
        Failure(Box::new(e.into_response()))
    }
}

fn failure(status: StatusCode, code: &str, message: String, offset: Option<u64>) -> Failure {
    let mut body = json!({ "error": code, "message": message });
    if let Some(offset) = offset {
        body["offset"] = json!(offset);
    }
    Failure(Box::new(
        (status, json_headers(), body.to_string()).into_response(),
    ))
}

fn json_headers() -> [(header::HeaderName, HeaderValue); 1] {
    [(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    )]
}

fn json_response(status: StatusCode, body: serde_json::Value) -> Response {
    (status, json_headers(), body.to_string()).into_response()
}

/// Maps a store error to its answer; internals are logged, not returned.
fn store_failure(e: StoreError) -> Failure {
    match e {
        StoreError::Digest(_) | StoreError::BadChunk(_) | StoreError::DigestMismatch { .. } => {
            failure(StatusCode::BAD_REQUEST, "bad_request", e.to_string(), None)
        }
        StoreError::Body { .. } => {
            failure(StatusCode::BAD_REQUEST, "bad_request", e.to_string(), None)
        }
        StoreError::OffsetMismatch { current, .. } => failure(
            StatusCode::CONFLICT,
            "conflict",
            e.to_string(),
            Some(current),
        ),
        StoreError::TooLarge { .. } => failure(
            StatusCode::PAYLOAD_TOO_LARGE,
            "too_large",
            e.to_string(),
            None,
        ),
        StoreError::NotFound(_) => failure(StatusCode::NOT_FOUND, "not_found", e.to_string(), None),
        StoreError::Manifest { .. } => failure(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_manifest",
            e.to_string(),
            None,
        ),
        StoreError::Io { .. } => ApiError::Internal(e.to_string()).into(),
    }
}

/// Who is asking.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Caller {
    /// A Kubernetes user RBAC allowed (the release CLI).
    User,
    /// A robot with its own token.
    Robot(RobotKey),
}

impl Caller {
    fn name(&self) -> String {
        match self {
            Caller::User => "user".to_owned(),
            Caller::Robot(k) => k.to_string(),
        }
    }
}

/// The namespace a user's request acts in (`?namespace=`).
#[derive(Debug, Default, Deserialize)]
struct InNamespace {
    namespace: Option<String>,
}

impl InNamespace {
    /// `verb` on `releases` in the named namespace; `None` (a 400) when none is named.
    fn releases(&self, verb: &'static str) -> Option<Access> {
        let ns = self.namespace.as_deref().filter(|n| !n.is_empty())?;
        Some(Access::new(verb, "releases", ns))
    }
}

/// Authenticates a request: with the robot header as a robot (when `robots` allows), else as a
/// Kubernetes user who must be allowed `access` (see [`FleetState::check_user`](lekiwi_fleet_api::FleetState::check_user)).
async fn authorize(
    state: &AppState,
    headers: &HeaderMap,
    robots: bool,
    access: Option<Access>,
) -> Result<Caller, Failure> {
    let Some(token) = bearer(headers).filter(|t| !t.is_empty()) else {
        return Err(state.refused(Refusal::MissingToken).into());
    };
    let robot = headers.get(ROBOT_HEADER).and_then(|v| v.to_str().ok());
    if let (true, Some(robot)) = (robots, robot) {
        return match state
            .shared
            .auth
            .authenticate(Some(token), Some(robot))
            .await
        {
            Ok(Grant::Robot(key)) => Ok(Caller::Robot(key)),
            Ok(Grant::Enroll(_)) => {
                state.count_refusal(Refusal::EnrollmentToken.as_str());
                warn!("refused a blob request with an enrollment token");
                Err(ApiError::Unauthorized(
                    "an enrollment token cannot fetch releases: use the robot's own token",
                )
                .into())
            }
            Err(r) => Err(state.refused(r).into()),
        };
    }
    state.api.check_user(headers, access).await?;
    Ok(Caller::User)
}

fn check_digest(digest: &str) -> Result<(), Failure> {
    digest_hex(digest)
        .map(|_| ())
        .map_err(|e| store_failure(StoreError::Digest(e)))
}

fn not_found(digest: &str) -> Failure {
    failure(
        StatusCode::NOT_FOUND,
        "not_found",
        format!("blob {digest} not found"),
        None,
    )
}

/// `GET /v1/uploads/{digest}`: where an upload stands, to resume it.
async fn upload_status(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    Query(ns): Query<InNamespace>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    authorize(&state, &headers, false, ns.releases("create")).await?;
    check_digest(&digest)?;
    let store = &state.blobs.store;
    let (offset, complete) = match store.stat(&digest).await.map_err(store_failure)? {
        Some(size) => (size, true),
        None => (
            store.partial_offset(&digest).await.map_err(store_failure)?,
            false,
        ),
    };
    Ok(json_response(
        StatusCode::OK,
        json!({ "digest": digest, "offset": offset, "complete": complete }),
    ))
}

/// `GET /v1/releases/{digest}`: the manifest with the blobs it references that are missing.
async fn get_release(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    Query(ns): Query<InNamespace>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    let caller = authorize(&state, &headers, true, ns.releases("get")).await?;
    check_digest(&digest)?;
    // A release of another namespace is answered as an unknown one.
    let found = if access::may_read(&state, &caller, &digest).await {
        state.blobs.store.release(&digest).await
    } else {
        Err(StoreError::NotFound(digest.clone()))
    };
    match found {
        Ok(info) => {
            debug!(robot = %caller.name(), %digest, missing = info.missing.len(), "served a release");
            Ok(json_response(
                StatusCode::OK,
                serde_json::to_value(&info).unwrap_or_default(),
            ))
        }
        Err(StoreError::NotFound(_)) => Err(failure(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("release {digest} not found: push it with kubectl lekiwi release push"),
            None,
        )),
        Err(e) => Err(store_failure(e)),
    }
}

/// Query of `/v1/blobs-served`.
#[derive(Debug, Deserialize)]
struct ServedQuery {
    /// `namespace/name`; all robots when absent.
    robot: Option<String>,
}

/// `GET /v1/blobs-served[?robot=ns/name]`: bytes and downloads served per robot since start.
async fn blobs_served(
    State(state): State<AppState>,
    Query(q): Query<ServedQuery>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    let Some(robot) = q.robot else {
        authorize(
            &state,
            &headers,
            false,
            Some(Access::new("list", "robots", "")),
        )
        .await?;
        return Ok(all_served(&state));
    };
    let Some((Some(namespace), name)) = parse_robot(&robot) else {
        return Err(ApiError::BadRequest("robot must be given as namespace/name".into()).into());
    };
    let access = Access {
        name: Some(name.clone()),
        ..Access::new("get", "robots", &namespace)
    };
    authorize(&state, &headers, false, Some(access)).await?;
    let served = state.blobs.served(&RobotKey::new(namespace, name));
    Ok(json_response(
        StatusCode::OK,
        json!({ "robot": robot, "bytes": served.bytes, "downloads": served.downloads }),
    ))
}

/// Every robot's bytes and downloads served.
fn all_served(state: &AppState) -> Response {
    let all: BTreeMap<String, Served> = state
        .blobs
        .served
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .iter()
        .map(|(k, v)| (k.to_string(), *v))
        .collect();
    json_response(StatusCode::OK, json!({ "robots": all }))
}
