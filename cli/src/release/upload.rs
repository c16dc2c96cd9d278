//! Uploading one blob in chunks (`PUT` with `Content-Range`), resuming from the gateway's offset
//! after a failure.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::{Context as _, bail};
use lekiwi_protocol::release::blob_path;
use reqwest::{Method, StatusCode};
use tokio::io::{AsyncReadExt, AsyncSeekExt};

use super::gateway::{ATTEMPTS, Gateway, UploadAnswer, backoff, message, refused, transient};

/// Where a blob's bytes come from.
#[derive(Clone, Debug)]
pub(super) enum Source {
    /// A file of the release directory, read chunk by chunk.
    File(PathBuf),
    /// Bytes made here (the manifest).
    Memory(Arc<Vec<u8>>),
}

impl Source {
    async fn read(&self, offset: u64, len: u64) -> anyhow::Result<Vec<u8>> {
        match self {
            Source::Memory(bytes) => Ok(bytes[offset as usize..(offset + len) as usize].to_vec()),
            Source::File(path) => {
                let mut file = tokio::fs::File::open(path)
                    .await
                    .with_context(|| format!("cannot open {}", path.display()))?;
                file.seek(std::io::SeekFrom::Start(offset)).await?;
                let mut data = vec![0u8; len as usize];
                file.read_exact(&mut data).await.with_context(|| {
                    format!(
                        "cannot read {} (did it change while pushing?)",
                        path.display()
                    )
                })?;
                Ok(data)
            }
        }
    }
}

/// One blob to upload.
#[derive(Clone, Debug)]
pub(super) struct Blob {
    pub(super) digest: String,
    pub(super) size: u64,
    /// A file path naming it in messages.
    pub(super) name: String,
    pub(super) source: Source,
}

/// Counters the progress line reads.
#[derive(Default)]
pub(super) struct Progress {
    /// Bytes the gateway holds of the blobs being uploaded.
    pub(super) bytes: AtomicU64,
    /// Blobs finished (stored, found stored or failed).
    pub(super) blobs: AtomicU64,
}

/// What the gateway made of one chunk request.
enum Answer {
    /// The blob is stored (`201`: by this request; `200`: it already was).
    Done { stored: bool },
    /// The chunk was taken; the upload now stands at this offset.
    Accepted(u64),
    /// Worth another attempt after resuming from the gateway's offset.
    Failed(String),
}

/// One blob's upload to one gateway.
pub(super) struct Upload<'a> {
    /// Where it goes.
    pub(super) gateway: &'a Gateway,
    /// What goes.
    pub(super) blob: &'a Blob,
}

impl Upload<'_> {
    /// Uploads the blob from its offset on the gateway; returns the bytes sent and whether
    /// this upload stored it (rather than finding it stored).
    pub(super) async fn run(
        &self,
        chunk_bytes: u64,
        progress: &Progress,
    ) -> anyhow::Result<(u64, bool)> {
        let blob = self.blob;
        let mut sent = 0u64;
        let mut offset = match self.gateway.upload_offset(&blob.digest).await? {
            UploadAnswer { complete: true, .. } => return Ok((0, false)),
            UploadAnswer { offset, .. } => offset.min(blob.size),
        };
        progress.bytes.fetch_add(offset, Ordering::Relaxed);
        let mut attempt = 0;
        loop {
            let (request, len) = self.chunk_request(offset, chunk_bytes).await?;
            let failure = match answer(blob, offset, request.send().await).await? {
                Answer::Done { stored } => {
                    if stored {
                        sent += len;
                        progress.bytes.fetch_add(len, Ordering::Relaxed);
                    }
                    return Ok((sent, stored));
                }
                Answer::Accepted(at) => {
                    let advanced = at.saturating_sub(offset);
                    sent += advanced;
                    progress.bytes.fetch_add(advanced, Ordering::Relaxed);
                    offset = at;
                    attempt = 0;
                    continue;
                }
                Answer::Failed(failure) => failure,
            };
            attempt += 1;
            if attempt >= ATTEMPTS {
                bail!(
                    "uploading {}: giving up after {ATTEMPTS} attempts: {failure}",
                    blob.name
                );
            }
            tokio::time::sleep(backoff(attempt)).await;
            // Resume from what the gateway holds, whatever the failure left behind.
            match self.gateway.upload_offset(&blob.digest).await? {
                UploadAnswer { complete: true, .. } => return Ok((sent, false)),
                UploadAnswer { offset: at, .. } => {
                    let at = at.min(blob.size);
                    if at > offset {
                        progress.bytes.fetch_add(at - offset, Ordering::Relaxed);
                        sent += at - offset;
                    }
                    offset = at;
                }
            }
        }
    }

    /// The next request of an upload standing at `offset`, and how many blob bytes it carries.
    async fn chunk_request(
        &self,
        offset: u64,
        chunk_bytes: u64,
    ) -> anyhow::Result<(reqwest::RequestBuilder, u64)> {
        let (blob, gateway) = (self.blob, self.gateway);
        let path = blob_path(&blob.digest);
        Ok(if blob.size == 0 {
            (gateway.request(Method::PUT, &path).body(Vec::new()), 0)
        } else if offset == blob.size {
            // Every byte arrived but the gateway did not verify them yet: ask it to.
            let range = format!("bytes */{}", blob.size);
            let request = gateway
                .request(Method::PUT, &path)
                .header(reqwest::header::CONTENT_RANGE, range)
                .body(Vec::new());
            (request, 0)
        } else {
            let len = chunk_bytes.min(blob.size - offset);
            let data = blob.source.read(offset, len).await?;
            let range = format!("bytes {offset}-{}/{}", offset + len - 1, blob.size);
            let request = gateway
                .request(Method::PUT, &path)
                .header(reqwest::header::CONTENT_RANGE, range)
                .body(data);
            (request, len)
        })
    }
}

/// Reads the gateway's answer to a chunk of `blob` sent at `offset`; a refusal that another
/// attempt cannot fix is an error.
async fn answer(
    blob: &Blob,
    offset: u64,
    sent: reqwest::Result<reqwest::Response>,
) -> anyhow::Result<Answer> {
    let resp = match sent {
        Ok(resp) => resp,
        Err(e) => return Ok(Answer::Failed(crate::http_error(&e))),
    };
    Ok(match resp.status() {
        StatusCode::CREATED | StatusCode::OK => Answer::Done {
            stored: resp.status() == StatusCode::CREATED,
        },
        StatusCode::ACCEPTED => {
            let answer: UploadAnswer = resp.json().await?;
            Answer::Accepted(answer.offset)
        }
        StatusCode::CONFLICT => {
            // Another upload moved it on (or an earlier answer got lost).
            let answer: UploadAnswer = resp.json().await?;
            Answer::Failed(format!(
                "the upload stood at {}, not {offset}",
                answer.offset
            ))
        }
        s if transient(s) => Answer::Failed(format!("{s}: {}", message(resp).await)),
        StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN => {
            bail!("uploading {}: {}", blob.name, refused(resp, "").await)
        }
        StatusCode::BAD_REQUEST => bail!(
            "uploading {}: the gateway refused it: {} (did the file change while pushing?)",
            blob.name,
            message(resp).await
        ),
        s => bail!(
            "uploading {}: the gateway answered {s}: {}",
            blob.name,
            message(resp).await
        ),
    })
}
