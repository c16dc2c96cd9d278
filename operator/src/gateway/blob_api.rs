//! Release blobs over HTTP on the gateway's listener: robots (with their own token) and the
//! release CLI (with the API token) download blobs and manifests, resuming by byte range; the
//! CLI uploads blobs in verified, resumable chunks with the API token.
//!
//! | Route | Who | Answers |
//! |---|---|---|
//! | `HEAD /v1/blobs/{digest}` | robot, API | 200 with `Content-Length`, 404 |
//! | `GET /v1/blobs/{digest}` | robot, API | 200, 206 for `Range: bytes=N-[M]`, 404, 416 |
//! | `PUT /v1/blobs/{digest}` | API | 201 stored, 202 `{"offset"}` chunk taken, 200 already stored, 409 `{"offset"}` wrong offset, 400 digest mismatch or bad request, 413 too large |
//! | `GET /v1/uploads/{digest}` | API | `{"offset", "complete"}` |
//! | `GET /v1/releases/{digest}` | robot, API | manifest + `"missing"`, 404, 422 not a manifest |
//! | `GET /v1/blobs-served[?robot=ns/name]` | API | bytes and downloads served per robot |
//!
//! A `PUT` without `Content-Range` is the whole blob (any partial upload is discarded); with
//! `Content-Range: bytes START-END/TOTAL` it is one chunk, which must start at the upload's
//! current offset; `bytes */TOTAL` with an empty body finishes an upload that holds every byte
//! but was not verified (the gateway stopped in between). A blob is stored only after its
//! SHA-256 matched.
//!
//! A robot authenticates as on the WebSocket (`Authorization: Bearer <robot token>` and
//! `x-lekiwi-robot: namespace/name`; an enrollment token is refused); a request without the robot
//! header must carry the API token. Bytes served are counted as they are sent: in
//! `lekiwi_gateway_blob_bytes_served_total`, per robot in memory (`/v1/blobs-served`, since this
//! process started) and in a debug log line `blob download finished` per request with `robot`
//! and `bytes` fields.

use std::collections::{BTreeMap, HashMap};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};

use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use futures::{Stream, StreamExt};
use lekiwi_protocol::ROBOT_HEADER;
use lekiwi_protocol::release::digest_hex;
use prometheus_client::metrics::counter::Counter;
use serde::{Deserialize, Serialize};
use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;
use tracing::{Instrument, debug, info_span, warn};

use super::auth::{ApiToken, Grant, Refusal, parse_robot};
use super::{ApiError, AppState, bearer};
use crate::gateway::blob_store::{BlobStore, Error as StoreError, UploadState};
use crate::gateway::event_store::RobotKey;
use crate::metrics::KindLabels;

/// Bytes read from disk per chunk of a download.
const READ_CHUNK: usize = 64 * 1024;

/// What the blob routes share.
pub struct BlobApi {
    /// The blob store.
    pub store: BlobStore,
    /// The API token uploads present.
    pub api_token: ApiToken,
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
    pub fn new(store: BlobStore, api_token: ApiToken) -> Self {
        Self {
            store,
            api_token,
            served: Mutex::default(),
        }
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
    /// The API token (the release CLI).
    Api,
    /// A robot with its own token.
    Robot(RobotKey),
}

impl Caller {
    fn name(&self) -> String {
        match self {
            Caller::Api => "api".to_owned(),
            Caller::Robot(k) => k.to_string(),
        }
    }
}

/// Authenticates a request: with the robot header as a robot (when `robots` allows), else by
/// the API token.
async fn authorize(state: &AppState, headers: &HeaderMap, robots: bool) -> Result<Caller, Failure> {
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
                state
                    .shared
                    .metrics
                    .gateway
                    .refused
                    .get_or_create(&KindLabels {
                        kind: "enrollment_token",
                    })
                    .inc();
                warn!("refused a blob request with an enrollment token");
                Err(ApiError::Unauthorized(
                    "an enrollment token cannot fetch releases: use the robot's own token",
                )
                .into())
            }
            Err(r) => Err(state.refused(r).into()),
        };
    }
    if state.blobs.api_token.check(token).await {
        Ok(Caller::Api)
    } else {
        Err(state.refused(Refusal::WrongToken).into())
    }
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

/// A byte range requested by a `Range` header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ByteRange {
    /// No (usable) range: the whole blob.
    Full,
    /// Bytes `start..=end`.
    Part { start: u64, end: u64 },
    /// A range starting at or past the end.
    Unsatisfiable,
}

/// Parses a single `bytes=N-`, `bytes=N-M` or `bytes=-N` range. Several ranges, other units and
/// malformed headers are ignored (the whole blob is sent), as RFC 9110 allows.
fn parse_range(header: Option<&str>, size: u64) -> ByteRange {
    let Some(spec) = header.and_then(|h| h.trim().strip_prefix("bytes=")) else {
        return ByteRange::Full;
    };
    if spec.contains(',') {
        return ByteRange::Full;
    }
    let Some((first, last)) = spec.trim().split_once('-') else {
        return ByteRange::Full;
    };
    let (first, last) = (first.trim(), last.trim());
    if first.is_empty() {
        // The last N bytes.
        return match last.parse::<u64>() {
            Ok(0) => ByteRange::Unsatisfiable,
            Ok(_) if size == 0 => ByteRange::Unsatisfiable,
            Ok(n) => ByteRange::Part {
                start: size - n.min(size),
                end: size - 1,
            },
            Err(_) => ByteRange::Full,
        };
    }
    let Ok(start) = first.parse::<u64>() else {
        return ByteRange::Full;
    };
    let end = if last.is_empty() {
        u64::MAX
    } else {
        match last.parse::<u64>() {
            Ok(end) if end >= start => end,
            _ => return ByteRange::Full,
        }
    };
    if start >= size {
        return ByteRange::Unsatisfiable;
    }
    ByteRange::Part {
        start,
        end: end.min(size - 1),
    }
}

/// Parses `Content-Range: bytes START-END/TOTAL` into `(START, Some(END), TOTAL)`, and
/// `bytes */TOTAL` (an empty body that finishes an upload holding all its bytes) into
/// `(TOTAL, None, TOTAL)`.
fn parse_content_range(value: &str) -> Option<(u64, Option<u64>, u64)> {
    let (range, total) = value.trim().strip_prefix("bytes ")?.split_once('/')?;
    let total = total.trim().parse::<u64>().ok()?;
    if range.trim() == "*" {
        return Some((total, None, total));
    }
    let (start, end) = range.split_once('-')?;
    let (start, end) = (
        start.trim().parse::<u64>().ok()?,
        end.trim().parse::<u64>().ok()?,
    );
    (start <= end && end < total).then_some((start, Some(end), total))
}

fn blob_headers(digest: &str, len: u64) -> HeaderMap {
    let mut headers = HeaderMap::new();
    headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/octet-stream"),
    );
    headers.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    headers.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    if let Ok(etag) = HeaderValue::from_str(&format!("\"{digest}\"")) {
        headers.insert(header::ETAG, etag);
    }
    headers
}

/// `HEAD /v1/blobs/{digest}`: whether a blob is stored, and its size.
async fn head_blob(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    authorize(&state, &headers, true).await?;
    check_digest(&digest)?;
    match state.blobs.store.stat(&digest).await {
        Ok(Some(size)) => Ok((StatusCode::OK, blob_headers(&digest, size)).into_response()),
        Ok(None) => Ok(StatusCode::NOT_FOUND.into_response()),
        Err(e) => Err(store_failure(e)),
    }
}

/// `GET /v1/blobs/{digest}`: the blob, streamed, whole or one byte range.
async fn get_blob(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    let caller = authorize(&state, &headers, true).await?;
    let span = info_span!("blob_download", robot = %caller.name(), %digest);
    async move {
        check_digest(&digest)?;
        let Some((mut file, size)) = state
            .blobs
            .store
            .open(&digest)
            .await
            .map_err(store_failure)?
        else {
            return Err(not_found(&digest));
        };
        let range = parse_range(
            headers.get(header::RANGE).and_then(|v| v.to_str().ok()),
            size,
        );
        let (status, start, len) = match range {
            ByteRange::Full => (StatusCode::OK, 0, size),
            ByteRange::Part { start, end } => (StatusCode::PARTIAL_CONTENT, start, end - start + 1),
            ByteRange::Unsatisfiable => {
                let mut answer = failure(
                    StatusCode::RANGE_NOT_SATISFIABLE,
                    "range_not_satisfiable",
                    format!("the blob has {size} bytes"),
                    None,
                );
                if let Ok(v) = HeaderValue::from_str(&format!("bytes */{size}")) {
                    answer.0.headers_mut().insert(header::CONTENT_RANGE, v);
                }
                return Err(answer);
            }
        };
        if start > 0 {
            file.seek(std::io::SeekFrom::Start(start))
                .await
                .map_err(|e| ApiError::Internal(format!("seek in blob {digest}: {e}")))?;
        }
        let robot = match &caller {
            Caller::Robot(key) => {
                state.blobs.record(key, 0, 1);
                Some(key.clone())
            }
            Caller::Api => None,
        };
        let stream = Counted {
            inner: ReaderStream::with_capacity(file.take(len), READ_CHUNK),
            api: state.blobs.clone(),
            metric: state.shared.metrics.gateway.blob_bytes_served.clone(),
            robot,
            caller: caller.name(),
            digest: digest.clone(),
            sent: 0,
            expected: len,
        };
        let mut headers = blob_headers(&digest, len);
        if status == StatusCode::PARTIAL_CONTENT
            && let Ok(v) =
                HeaderValue::from_str(&format!("bytes {start}-{}/{size}", start + len - 1))
        {
            headers.insert(header::CONTENT_RANGE, v);
        }
        debug!(status = status.as_u16(), start, len, "serving a blob");
        Ok((status, headers, Body::from_stream(stream)).into_response())
    }
    .instrument(span)
    .await
}

/// A download's byte stream that counts what was sent and logs the total when it ends.
struct Counted<S> {
    inner: S,
    api: Arc<BlobApi>,
    metric: Counter,
    robot: Option<RobotKey>,
    caller: String,
    digest: String,
    sent: u64,
    expected: u64,
}

impl<S> Stream for Counted<S>
where
    S: Stream<Item = std::io::Result<Bytes>> + Unpin,
{
    type Item = std::io::Result<Bytes>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let polled = Pin::new(&mut self.inner).poll_next(cx);
        if let Poll::Ready(Some(Ok(chunk))) = &polled {
            let n = chunk.len() as u64;
            self.sent += n;
            self.metric.inc_by(n);
            if let Some(robot) = &self.robot {
                self.api.record(robot, n, 0);
            }
        }
        polled
    }
}

impl<S> Drop for Counted<S> {
    fn drop(&mut self) {
        debug!(
            robot = %self.caller,
            digest = %self.digest,
            bytes = self.sent,
            complete = self.sent == self.expected,
            "blob download finished"
        );
    }
}

/// `PUT /v1/blobs/{digest}`: a whole blob, or one chunk with `Content-Range`.
async fn put_blob(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, Failure> {
    authorize(&state, &headers, false).await?;
    let span = info_span!("blob_upload", %digest);
    async move {
        let metrics = &state.shared.metrics;
        let count = |kind: &'static str| {
            metrics
                .gateway
                .blob_uploads
                .get_or_create(&KindLabels { kind })
                .inc();
        };
        let answer = upload(&state, &digest, &headers, body).await;
        match &answer {
            Ok((UploadState::Exists { .. }, _)) => count("exists"),
            Ok((UploadState::Complete { size }, _)) => {
                count("created");
                debug!(size, "stored a blob");
            }
            Ok((UploadState::Partial { .. }, _)) => count("partial"),
            Err(StoreError::OffsetMismatch { .. }) => count("conflict"),
            Err(StoreError::DigestMismatch { .. }) => count("digest_mismatch"),
            Err(StoreError::TooLarge { .. }) => count("too_large"),
            Err(StoreError::Io { .. }) => count("error"),
            Err(e) => {
                debug!(error = %e, "refused an upload");
                count("bad_request");
            }
        }
        let (outcome, received) = answer.map_err(store_failure)?;
        let (status, offset, complete) = match outcome {
            UploadState::Exists { size } => (StatusCode::OK, size, true),
            UploadState::Complete { size } => (StatusCode::CREATED, size, true),
            UploadState::Partial { offset } => (StatusCode::ACCEPTED, offset, false),
        };
        debug!(
            status = status.as_u16(),
            received, offset, "upload request done"
        );
        Ok(json_response(
            status,
            json!({ "digest": digest, "offset": offset, "complete": complete }),
        ))
    }
    .instrument(span)
    .await
}

/// Checks an upload's headers and writes its body; also returns the bytes received.
async fn upload(
    state: &AppState,
    digest: &str,
    headers: &HeaderMap,
    body: Body,
) -> Result<(UploadState, u64), StoreError> {
    digest_hex(digest).map_err(StoreError::Digest)?;
    let limit = state.blobs.store.max_blob_bytes();
    let length = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    let (offset, total) = match headers.get(header::CONTENT_RANGE) {
        None => {
            if length.is_some_and(|l| l > limit) {
                return Err(StoreError::TooLarge { limit });
            }
            (0, None)
        }
        Some(value) => {
            let (start, end, total) = value
                .to_str()
                .ok()
                .and_then(parse_content_range)
                .ok_or_else(|| {
                    StoreError::BadChunk(
                        "Content-Range must be `bytes START-END/TOTAL` with START <= END < TOTAL, \
                         or `bytes */TOTAL` with an empty body"
                            .into(),
                    )
                })?;
            if total > limit {
                return Err(StoreError::TooLarge { limit });
            }
            let want = end.map_or(0, |end| end - start + 1);
            if let Some(l) = length
                && l != want
            {
                return Err(StoreError::BadChunk(format!(
                    "Content-Length {l} does not match the Content-Range's {want} bytes"
                )));
            }
            (start, Some(total))
        }
    };
    let metric = state.shared.metrics.gateway.blob_bytes_received.clone();
    let received = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let counter = received.clone();
    let stream = body.into_data_stream().inspect(move |chunk| {
        if let Ok(bytes) = chunk {
            metric.inc_by(bytes.len() as u64);
            counter.fetch_add(bytes.len() as u64, std::sync::atomic::Ordering::Relaxed);
        }
    });
    let outcome = state
        .blobs
        .store
        .write_at(digest, offset, total, stream)
        .await?;
    Ok((outcome, received.load(std::sync::atomic::Ordering::Relaxed)))
}

/// `GET /v1/uploads/{digest}`: where an upload stands, to resume it.
async fn upload_status(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    authorize(&state, &headers, false).await?;
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
    headers: HeaderMap,
) -> Result<Response, Failure> {
    let caller = authorize(&state, &headers, true).await?;
    match state.blobs.store.release(&digest).await {
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
    authorize(&state, &headers, false).await?;
    if let Some(robot) = q.robot {
        let Some((Some(namespace), name)) = parse_robot(&robot) else {
            return Err(
                ApiError::BadRequest("robot must be given as namespace/name".into()).into(),
            );
        };
        let served = state.blobs.served(&RobotKey::new(namespace, name));
        return Ok(json_response(
            StatusCode::OK,
            json!({ "robot": robot, "bytes": served.bytes, "downloads": served.downloads }),
        ));
    }
    let all: BTreeMap<String, Served> = state
        .blobs
        .served
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .iter()
        .map(|(k, v)| (k.to_string(), *v))
        .collect();
    Ok(json_response(StatusCode::OK, json!({ "robots": all })))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges() {
        let r = |h: &str| parse_range(Some(h), 100);
        assert_eq!(parse_range(None, 100), ByteRange::Full);
        assert_eq!(r("bytes=10-"), ByteRange::Part { start: 10, end: 99 });
        assert_eq!(r("bytes=10-19"), ByteRange::Part { start: 10, end: 19 });
        assert_eq!(r("bytes=90-500"), ByteRange::Part { start: 90, end: 99 });
        assert_eq!(r("bytes=-5"), ByteRange::Part { start: 95, end: 99 });
        assert_eq!(r("bytes=-500"), ByteRange::Part { start: 0, end: 99 });
        assert_eq!(r("bytes=100-"), ByteRange::Unsatisfiable);
        assert_eq!(r("bytes=-0"), ByteRange::Unsatisfiable);
        assert_eq!(r("bytes=0-1,5-6"), ByteRange::Full);
        assert_eq!(r("bytes=5-1"), ByteRange::Full);
        assert_eq!(r("items=1-2"), ByteRange::Full);
        assert_eq!(parse_range(Some("bytes=0-"), 0), ByteRange::Unsatisfiable);
    }

    #[test]
    fn content_ranges() {
        assert_eq!(parse_content_range("bytes 0-9/20"), Some((0, Some(9), 20)));
        assert_eq!(
            parse_content_range("bytes 10-19/20"),
            Some((10, Some(19), 20))
        );
        assert_eq!(parse_content_range("bytes */20"), Some((20, None, 20)));
        assert_eq!(parse_content_range("bytes 10-20/20"), None);
        assert_eq!(parse_content_range("bytes 5-4/20"), None);
        assert_eq!(parse_content_range("bytes 0-9/*"), None);
    }
}
