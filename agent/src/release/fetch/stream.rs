//! A blob read as a stream of chunks from a byte offset, for a caller that keeps no copy: the
//! fleet simulator, whose robots really transfer what a release lacks and discard it.

use futures::FutureExt;
use hyper::StatusCode;
use hyper::body::{Bytes, Incoming};
use hyper::header::CONTENT_RANGE;

use super::blob::content_range_start;
use super::{Caller, Client, Sender, next_chunk};
use crate::release::{Error, Result};

/// An open download: the body still to read, from byte [`Stream::from`] of the blob.
pub(crate) struct Stream {
    body: Incoming,
    sender: Sender,
    url: String,
    /// Where the body starts in the blob: the offset asked for (`206`), or 0 when the gateway
    /// sent the whole blob (`200`).
    pub(crate) from: u64,
}

impl Stream {
    /// The next chunk, `None` at the end of the body.
    pub(crate) async fn chunk(&mut self) -> Result<Option<Bytes>> {
        next_chunk(&mut self.body, &self.url).await
    }

    /// The body was read to its end: its connection goes back to `client`'s idle pool. (A
    /// stream dropped before its end closes its connection instead.)
    pub(crate) fn finish(self, client: &Client) {
        client.release(self.sender);
    }
}

impl Client {
    /// Opens `GET path` for `caller`, asking for the bytes from `from` on (`Range`) when it is
    /// not 0: the answer must continue there (`206`) or be the whole blob (`200`).
    pub(crate) async fn open_stream(
        &self,
        path: &str,
        from: u64,
        caller: Caller<'_>,
    ) -> Result<Stream> {
        let url = self.url(path);
        let (response, sender) = self.get_as(path, from, caller).boxed().await?;
        let status = response.status();
        let start = response
            .headers()
            .get(CONTENT_RANGE)
            .and_then(|v| v.to_str().ok())
            .and_then(content_range_start);
        let body = response.into_body();
        let from = match status {
            StatusCode::OK => 0,
            StatusCode::PARTIAL_CONTENT if from > 0 && start == Some(from) => from,
            StatusCode::PARTIAL_CONTENT | StatusCode::RANGE_NOT_SATISFIABLE => {
                return Err(Error::Transport {
                    url,
                    message: format!("asked for bytes from {from}, got {status} from {start:?}"),
                });
            }
            _ => return Err(self.status_error(&url, status, body).await),
        };
        Ok(Stream {
            body,
            sender,
            url,
            from,
        })
    }
}
