//! Blob downloads: `HEAD` and `GET /v1/blobs/{digest}`, whole or one byte range, counting the
//! bytes sent per robot as they go.

use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use axum::body::{Body, Bytes};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use futures::Stream;
use prometheus_client::metrics::counter::Counter;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;
use tracing::{Instrument, debug, info_span};

use super::{
    BlobApi, Caller, Failure, InNamespace, access, authorize, check_digest, failure, not_found,
    store_failure,
};
use crate::{ApiError, AppState};
use lekiwi_blob_store::readers::ReadGuard;
use lekiwi_core::RobotKey;

/// Bytes read from disk per chunk of a download.
const READ_CHUNK: usize = 64 * 1024;

/// A byte range requested by a `Range` header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ByteRange {
    /// No (usable) range: the whole blob.
    Full,
    /// Bytes `start..=end`.
    Part { start: u64, end: u64 },
    /// A range starting at or past the end.
    Unsatisfiable,
}

/// Parses a single `bytes=N-`, `bytes=N-M` or `bytes=-N` range. Several ranges, other units and
/// malformed headers are ignored (the whole blob is sent), as RFC 9110 allows.
pub(super) fn parse_range(header: Option<&str>, size: u64) -> ByteRange {
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
pub(super) async fn head_blob(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    Query(ns): Query<InNamespace>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    let caller = authorize(&state, &headers, true, ns.releases("get")).await?;
    check_digest(&digest)?;
    if !access::may_read(&state, &caller, &digest).await {
        return Ok(StatusCode::NOT_FOUND.into_response());
    }
    match state.blobs.store.stat(&digest).await {
        Ok(Some(size)) => Ok((StatusCode::OK, blob_headers(&digest, size)).into_response()),
        Ok(None) => Ok(StatusCode::NOT_FOUND.into_response()),
        Err(e) => Err(store_failure(e)),
    }
}

/// `GET /v1/blobs/{digest}`: the blob, streamed, whole or one byte range.
pub(super) async fn get_blob(
    State(state): State<AppState>,
    Path(digest): Path<String>,
    Query(ns): Query<InNamespace>,
    headers: HeaderMap,
) -> Result<Response, Failure> {
    let caller = authorize(&state, &headers, true, ns.releases("get")).await?;
    let span = info_span!("blob_download", robot = %caller.name(), %digest);
    async move {
        check_digest(&digest)?;
        if !access::may_read(&state, &caller, &digest).await {
            return Err(not_found(&digest));
        }
        let Some((mut file, size, read)) = state
            .blobs
            .store
            .open_read(&digest)
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
            Caller::User => None,
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
            _read: read,
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
    /// Keeps garbage collection off the blob until the download ends.
    _read: ReadGuard,
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
