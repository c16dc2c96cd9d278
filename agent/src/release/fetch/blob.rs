//! Downloading one blob into the store: resume the partial file an earlier attempt left, stream
//! the rest while hashing it, and move it into the store once its digest matches.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use futures::FutureExt;
use hyper::body::Incoming;
use hyper::header::CONTENT_RANGE;
use hyper::{Response, StatusCode};
use lekiwi_protocol::release::blob_path;
use tokio::io::AsyncWriteExt;

use super::{Client, Fetched, Pace, next_chunk};
use crate::release::store::{Hasher, Layout};
use crate::release::{Error, Result, Wanted, blocking, io};

/// A download's partial file `blobs/tmp/<hex>.partial`: how much of the blob it holds and the
/// hash of that, so a resumed download continues the digest instead of reading it again.
struct Partial {
    path: PathBuf,
    /// For messages: `blob <digest> of <first file>`.
    what: String,
    hasher: Hasher,
    /// Bytes of the blob in the file.
    have: u64,
    /// Whether an earlier attempt had left bytes: a digest mismatch then earns a fresh try.
    resumed: bool,
}

impl Partial {
    /// What an earlier attempt (or agent) left for `w`; a file longer than the blob counts as
    /// nothing.
    async fn load(layout: &Layout, w: &Wanted) -> Result<Partial> {
        let path = layout.partial_path(&w.digest)?;
        let p = path.clone();
        let (mut hasher, mut have) = blocking(move || hash_partial(&p)).await?;
        let resumed = have > 0;
        if have > w.size {
            have = 0;
            hasher = Hasher::new();
        }
        Ok(Partial {
            path,
            what: format!("blob {} of {}", w.digest, w.path),
            hasher,
            have,
            resumed,
        })
    }

    /// Writes `body` to the file (after what it holds when `append`, else in its place) and
    /// returns the file, flushed. What arrived is kept also when the transfer broke off: the
    /// next attempt resumes it.
    async fn write_body(
        &mut self,
        body: &mut Incoming,
        url: &str,
        append: bool,
        size: u64,
        meter: (&AtomicU64, Option<&Pace>),
    ) -> Result<tokio::fs::File> {
        if !append {
            self.have = 0;
            self.hasher = Hasher::new();
        }
        let p = self.path.clone();
        let file = blocking(move || {
            std::fs::OpenOptions::new()
                .create(true)
                .write(true)
                .append(append)
                .truncate(!append)
                .open(&p)
                .map_err(io(&p))
        })
        .await?;
        // Unbuffered on purpose: each chunk reaches the file at once (tokio writes it in the
        // background), so an agent killed mid-transfer loses at most the chunk in flight.
        let mut out = tokio::fs::File::from_std(file);
        let streamed = self.stream(&mut out, body, url, size, meter).await;
        let flushed = out.flush().await.map_err(io(&self.path));
        streamed?;
        flushed?;
        Ok(out)
    }

    /// Appends the body's chunks to `out`, hashing and counting them; refuses more than `size`.
    async fn stream(
        &mut self,
        out: &mut tokio::fs::File,
        body: &mut Incoming,
        url: &str,
        size: u64,
        (counter, pace): (&AtomicU64, Option<&Pace>),
    ) -> Result<()> {
        while let Some(chunk) = next_chunk(body, url).await? {
            if self.have + chunk.len() as u64 > size {
                remove_partial(&self.path).await;
                return Err(Error::TooLarge {
                    what: self.what.clone(),
                    size,
                });
            }
            self.hasher.update(&chunk);
            out.write_all(&chunk).await.map_err(io(&self.path))?;
            self.have += chunk.len() as u64;
            counter.fetch_add(chunk.len() as u64, Ordering::Relaxed);
            if let Some(pace) = pace {
                pace.spend(chunk.len()).await;
            }
        }
        Ok(())
    }
}

impl Client {
    /// Downloads one blob into `blobs/tmp/<hex>.partial` (resuming what is there), verifies it
    /// while streaming and moves it into the store.
    pub(in crate::release) async fn fetch_blob(
        &self,
        layout: &Layout,
        w: &Wanted,
        counter: &AtomicU64,
    ) -> Result<Fetched> {
        let mut partial = Partial::load(layout, w).await?;
        if w.size == 0 {
            // An empty file: nothing to download, the (new) empty partial file is the blob.
            let p = partial.path.clone();
            blocking(move || std::fs::File::create(&p).map(drop).map_err(io(&p))).await?;
            return self.promote(layout, w, partial).await;
        }
        if partial.have == w.size {
            // Complete already (killed before the move): verify and promote.
            return self.promote(layout, w, partial).await;
        }
        let path = blob_path(&w.digest);
        let url = self.url(&path);
        let (response, sender) = self.get(&path, partial.have).boxed().await?;
        let (append, mut body) = self.continues(response, &url, &partial).await?;
        let out = partial
            .write_body(
                &mut body,
                &url,
                append,
                w.size,
                (counter, self.pace.as_deref()),
            )
            .await?;
        self.release(sender);
        if partial.have < w.size {
            return Err(Error::Transport {
                url,
                message: format!("the body ended after {} of {} bytes", partial.have, w.size),
            });
        }
        out.sync_all().await.map_err(io(&partial.path))?;
        drop(out);
        self.promote(layout, w, partial).await
    }

    /// Whether the response continues the partial file (`206` from where it ends) or replaces
    /// it (`200`), with its body; any other answer is an error.
    async fn continues(
        &self,
        response: Response<Incoming>,
        url: &str,
        partial: &Partial,
    ) -> Result<(bool, Incoming)> {
        let have = partial.have;
        let status = response.status();
        let range_start = response
            .headers()
            .get(CONTENT_RANGE)
            .and_then(|v| v.to_str().ok())
            .and_then(content_range_start);
        let body = response.into_body();
        match status {
            StatusCode::PARTIAL_CONTENT if have > 0 => {
                let from = range_start;
                if from != Some(have) {
                    return Err(Error::Transport {
                        url: url.to_owned(),
                        message: format!("asked for bytes from {have}, got {from:?}"),
                    });
                }
                Ok((true, body))
            }
            StatusCode::OK => Ok((false, body)),
            StatusCode::RANGE_NOT_SATISFIABLE => {
                // The partial is wrong (longer than the blob?): start over next attempt.
                remove_partial(&partial.path).await;
                Err(Error::Transport {
                    url: url.to_owned(),
                    message: "the gateway refused to resume; starting over".into(),
                })
            }
            _ => Err(self.status_error(url, status, body).await),
        }
    }

    /// Checks the digest of a complete partial file and moves it into the store.
    async fn promote(&self, layout: &Layout, w: &Wanted, partial: Partial) -> Result<Fetched> {
        let actual = partial.hasher.finish();
        if actual != w.digest {
            remove_partial(&partial.path).await;
            if partial.resumed {
                // The partial file from before may be what is wrong: one more try from scratch.
                return Err(Error::Transport {
                    url: self.url(&blob_path(&w.digest)),
                    message: format!(
                        "the resumed download of {} did not verify; starting over",
                        partial.what
                    ),
                });
            }
            return Err(Error::DigestMismatch {
                what: partial.what,
                expected: w.digest.clone(),
                actual,
            });
        }
        let blob = layout.blob_path(&w.digest)?;
        let from = partial.path;
        blocking(move || std::fs::rename(&from, &blob).map_err(io(&blob))).await?;
        Ok(Fetched)
    }
}

/// The first byte of `Content-Range: bytes <first>-<last>/<len>`.
pub(super) fn content_range_start(v: &str) -> Option<u64> {
    v.strip_prefix("bytes ")?
        .split('-')
        .next()?
        .trim()
        .parse()
        .ok()
}

/// Deletes a partial download (that turned out wrong); a failure only costs disk space.
async fn remove_partial(partial: &Path) {
    let p = partial.to_owned();
    let _ = blocking(move || {
        let _ = std::fs::remove_file(&p);
        Ok(())
    })
    .await;
}

/// The length of a partial file and the hash state of its content.
fn hash_partial(path: &Path) -> Result<(Hasher, u64)> {
    let mut hasher = Hasher::new();
    match std::fs::File::open(path) {
        Ok(mut f) => {
            let n = std::io::copy(&mut f, &mut hasher).map_err(io(path))?;
            Ok((hasher, n))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok((hasher, 0)),
        Err(e) => Err(io(path)(e)),
    }
}
