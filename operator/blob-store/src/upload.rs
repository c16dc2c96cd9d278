//! Uploads into the blob store: a body is appended to the blob's partial file at the offset the
//! client names, and a complete partial is hashed and renamed into place only if its content
//! matches its digest.

use std::io::Read;
use std::path::{Path, PathBuf};

use futures::{Stream, StreamExt};
use lekiwi_protocol::release::digest_hex;
use sha2::{Digest, Sha256};
use tokio::fs::File;
use tokio::io::{AsyncSeekExt, AsyncWriteExt};
use tokio::sync::OwnedMutexGuard;

use super::{BlobStore, Error, Result, UploadState, file_size, io, remove_if_exists};

/// The facts of one upload request, checked before its body is read.
struct Upload<'a> {
    digest: &'a str,
    /// Where the body starts in the blob.
    offset: u64,
    /// The blob's declared size for a chunk; `None` when the body is the whole blob.
    total: Option<u64>,
    /// The store's size limit.
    limit: u64,
    /// The partial file the body goes into.
    partial: PathBuf,
}

impl Upload<'_> {
    fn whole(&self) -> bool {
        self.total.is_none()
    }

    /// The offset past which the body must not run.
    fn end(&self) -> u64 {
        self.total.unwrap_or(self.limit)
    }

    fn check_range(&self) -> Result<()> {
        if self.whole() && self.offset != 0 {
            return Err(Error::BadChunk(
                "an upload without a range must start at offset 0".into(),
            ));
        }
        if let Some(t) = self.total
            && self.offset > t
        {
            return Err(Error::BadChunk(format!(
                "offset {} lies beyond the total of {t} bytes",
                self.offset
            )));
        }
        Ok(())
    }

    /// What is wrong with a chunk of `len` bytes arriving at `pos`, if anything.
    fn overrun(&self, pos: u64, len: u64) -> Option<Error> {
        let end = self.end();
        (pos + len > end).then(|| {
            if self.whole() {
                Error::TooLarge { limit: self.limit }
            } else {
                Error::BadChunk(format!(
                    "the body runs past the declared total of {end} bytes"
                ))
            }
        })
    }
}

impl BlobStore {
    /// Writes `body` into the upload of `digest` at `offset`.
    ///
    /// With `total`, the body is a chunk of a blob of `total` bytes: `offset` must equal the
    /// bytes received so far (else [`Error::OffsetMismatch`] with the current offset), and the
    /// blob is verified and stored once the upload reaches `total` (an empty body at
    /// `offset == total` finishes an upload whose bytes all arrived but whose verification was
    /// cut short). A partial longer than `total` is discarded. Without `total`, the body is
    /// the whole blob: `offset` must be 0, any earlier partial upload is discarded, and the blob
    /// is verified and stored at the body's end. If the body breaks off, what arrived is kept
    /// for resuming. A blob already stored is not written again ([`UploadState::Exists`]); the
    /// body is then not read at all.
    pub async fn write_at<S, B, E>(
        &self,
        digest: &str,
        offset: u64,
        total: Option<u64>,
        body: S,
    ) -> Result<UploadState>
    where
        S: Stream<Item = Result<B, E>>,
        B: AsRef<[u8]>,
        E: std::fmt::Display,
    {
        let hex = digest_hex(digest).map_err(Error::Digest)?.to_owned();
        let limit = self.max_blob_bytes;
        if total.is_some_and(|t| t > limit) {
            return Err(Error::TooLarge { limit });
        }
        if let Some(size) = self.stat(digest).await? {
            return Ok(UploadState::Exists { size });
        }
        let guard = self.lock(&hex).await;
        // Another upload of the same blob may have finished while this one waited.
        if let Some(size) = self.stat(digest).await? {
            return Ok(UploadState::Exists { size });
        }
        let upload = Upload {
            digest,
            offset,
            total,
            limit,
            partial: self.partial_path(&hex),
        };
        upload.check_range()?;
        let file = self.open_partial(&upload).await?;
        let (file, pos) = receive(&upload, file, body).await?;
        if total.is_some_and(|t| pos < t) {
            return Ok(UploadState::Partial { offset: pos });
        }
        file.sync_all().await.map_err(io(&upload.partial))?;
        drop(file);
        self.finish_holding(guard, hex, digest, upload.partial)
            .await
            .map(|()| UploadState::Complete { size: pos })
    }

    /// Opens the upload's partial file at its offset, after checking that the offset is where
    /// the upload stands; a whole-blob upload starts the partial afresh.
    async fn open_partial(&self, upload: &Upload<'_>) -> Result<File> {
        let upload_dir = self.upload_dir();
        tokio::fs::create_dir_all(&upload_dir)
            .await
            .map_err(io(&upload_dir))?;
        let partial = &upload.partial;
        let mut current = file_size(partial).await?.unwrap_or(0);
        if let Some(t) = upload.total
            && current > t
        {
            // Left by an upload that declared another size: useless for this one.
            remove_if_exists(partial).await?;
            current = 0;
        }
        if !upload.whole() && upload.offset != current {
            return Err(Error::OffsetMismatch {
                digest: upload.digest.to_owned(),
                given: upload.offset,
                current,
            });
        }
        let mut file = tokio::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(upload.whole())
            .open(partial)
            .await
            .map_err(io(partial))?;
        file.seek(std::io::SeekFrom::Start(upload.offset))
            .await
            .map_err(io(partial))?;
        Ok(file)
    }

    /// Verification of a large blob takes a while: it runs to the end, holding the lock, even
    /// if the client goes away meanwhile, so the next request finds the blob stored.
    async fn finish_holding(
        &self,
        guard: OwnedMutexGuard<()>,
        hex: String,
        digest: &str,
        partial: PathBuf,
    ) -> Result<()> {
        let store = self.clone();
        let digest = digest.to_owned();
        let finish = tokio::spawn(async move {
            let finished = store.finish(&hex, &digest, &partial).await;
            drop(guard);
            finished
        });
        finish.await.unwrap_or_else(|e| Err(task_failed(e)))
    }

    /// Hashes a complete partial upload and moves it into place, or deletes it on a mismatch.
    async fn finish(&self, hex: &str, digest: &str, partial: &Path) -> Result<()> {
        let actual = hash_file(partial.to_owned()).await?;
        if actual != hex {
            remove_if_exists(partial).await?;
            return Err(Error::DigestMismatch {
                expected: digest.to_owned(),
                actual: format!("sha256:{actual}"),
            });
        }
        let blob_dir = self.blob_dir();
        tokio::fs::create_dir_all(&blob_dir)
            .await
            .map_err(io(&blob_dir))?;
        let path = self.blob_path(hex);
        tokio::fs::rename(partial, &path).await.map_err(io(&path))
    }
}

/// Appends the body to the partial; returns the file and the offset the upload reached. On
/// failure the partial is left at a boundary the client knows: a broken chunk keeps what
/// arrived (the client resumes), a refused chunk is undone, a whole blob is discarded.
async fn receive<S, B, E>(upload: &Upload<'_>, mut file: File, body: S) -> Result<(File, u64)>
where
    S: Stream<Item = Result<B, E>>,
    B: AsRef<[u8]>,
    E: std::fmt::Display,
{
    let (pos, failed) = copy_body(upload, &mut file, body).await?;
    let partial = &upload.partial;
    // Let every write land before anyone measures the partial's size.
    file.flush().await.map_err(io(partial))?;
    match failed {
        None => Ok((file, pos)),
        // Kept: the client resumes from what arrived.
        Some(e @ Error::Body { .. }) if !upload.whole() => Err(e),
        Some(e) => {
            if upload.whole() {
                drop(file);
                remove_if_exists(partial).await?;
            } else {
                // Undo this chunk so the partial stays at a boundary the client knows.
                file.set_len(upload.offset).await.map_err(io(partial))?;
            }
            Err(e)
        }
    }
}

/// Writes the body's chunks until it ends, breaks off or runs past the upload's end; returns
/// the offset reached and why it stopped early, if it did. Only a failing disk is an `Err`.
async fn copy_body<S, B, E>(
    upload: &Upload<'_>,
    file: &mut File,
    body: S,
) -> Result<(u64, Option<Error>)>
where
    S: Stream<Item = Result<B, E>>,
    B: AsRef<[u8]>,
    E: std::fmt::Display,
{
    let mut pos = upload.offset;
    let mut body = std::pin::pin!(body);
    while let Some(chunk) = body.next().await {
        let chunk = match chunk {
            Ok(c) => c,
            Err(e) => {
                let failed = Error::Body {
                    received: pos - upload.offset,
                    message: e.to_string(),
                };
                return Ok((pos, Some(failed)));
            }
        };
        let bytes = chunk.as_ref();
        let len = bytes.len() as u64;
        if let Some(failed) = upload.overrun(pos, len) {
            return Ok((pos, Some(failed)));
        }
        file.write_all(bytes).await.map_err(io(&upload.partial))?;
        pos += len;
    }
    Ok((pos, None))
}

/// A blocking or spawned task that panicked or was cancelled, as a store error.
fn task_failed(e: tokio::task::JoinError) -> Error {
    Error::Io {
        path: PathBuf::new(),
        source: std::io::Error::other(e),
    }
}

/// Hex SHA-256 of a file, read on the blocking pool (a 4 GiB blob takes seconds).
async fn hash_file(path: PathBuf) -> Result<String> {
    let hashed = tokio::task::spawn_blocking(move || {
        let mut file = std::fs::File::open(&path).map_err(io(&path))?;
        let mut hasher = Sha256::new();
        let mut buf = vec![0u8; 1024 * 1024];
        loop {
            let n = file.read(&mut buf).map_err(io(&path))?;
            if n == 0 {
                return Ok(hex::encode(hasher.finalize()));
            }
            hasher.update(&buf[..n]);
        }
    })
    .await;
    hashed.unwrap_or_else(|e| Err(task_failed(e)))
}
