//! Blob uploads: `PUT /v1/blobs/{digest}`, a whole blob or one `Content-Range` chunk, checked
//! against the store's limit and counted by outcome.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::Response;
use futures::StreamExt;
use lekiwi_protocol::release::{MAX_MANIFEST_BYTES, digest_hex};
use serde_json::json;
use tracing::{Instrument, debug, info, info_span, warn};

use super::{Failure, InNamespace, authorize, json_response, store_failure};
use crate::AppState;
use lekiwi_blob_store::{Error as StoreError, UploadState};
use lekiwi_core::http::valid_name;
use lekiwi_metrics::KindLabels;

/// Parses `Content-Range: bytes START-END/TOTAL` into `(START, Some(END), TOTAL)`, and
/// `bytes */TOTAL` (an empty body that finishes an upload holding all its bytes) into
/// `(TOTAL, None, TOTAL)`.
pub(super) fn parse_content_range(value: &str) -> Option<(u64, Option<u64>, u64)> {
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

/// `PUT /v1/blobs/{digest}`: a whole blob, or one chunk with `Content-Range`.
pub(super) async fn put_blob(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    Query(ns): Query<InNamespace>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, Failure> {
    authorize(&state, &headers, false, ns.releases("create")).await?;
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
        if let (UploadState::Exists { size } | UploadState::Complete { size }, Some(ns)) =
            (outcome, ns.namespace.as_deref())
        {
            record_release(&state, ns, &digest, size).await;
        }
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

/// Records a stored blob that is a release manifest as a release of `namespace` (a push of the
/// manifest, new or again, is what makes it one there) and wakes garbage collection.
async fn record_release(state: &AppState, namespace: &str, digest: &str, size: u64) {
    if size > MAX_MANIFEST_BYTES as u64 || !valid_name(namespace) {
        return;
    }
    let store = &state.blobs.store;
    let Ok(manifest) = store.manifest(digest).await else {
        return;
    };
    match store
        .index()
        .register(namespace, &manifest.version, digest)
        .await
    {
        Ok(true) => {
            info!(%namespace, version = %manifest.version, "release pushed");
            state.api.releases.pushed.notify_one();
        }
        Ok(false) => {}
        Err(e) => warn!(%namespace, error = %e, "cannot record a pushed release"),
    }
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
    let received = Arc::new(AtomicU64::new(0));
    let counter = received.clone();
    let stream = body.into_data_stream().inspect(move |chunk| {
        if let Ok(bytes) = chunk {
            metric.inc_by(bytes.len() as u64);
            counter.fetch_add(bytes.len() as u64, Ordering::Relaxed);
        }
    });
    let outcome = state
        .blobs
        .store
        .write_at(digest, offset, total, stream)
        .await?;
    Ok((outcome, received.load(Ordering::Relaxed)))
}
