//! `kubectl lekiwi release push DIR --version V` and `release inspect DIGEST`: upload a directory
//! to the gateway's blob store as content-addressed blobs plus a manifest, and show a stored
//! release.
//!
//! Push hashes every file, asks the gateway which blobs it has (`HEAD /v1/blobs/{digest}`),
//! uploads the missing ones a few at a time in chunks (`PUT` with `Content-Range`), resuming
//! from the gateway's offset (`GET /v1/uploads/{digest}`) after a failure, uploads the manifest
//! last and confirms with `GET /v1/releases/{digest}` that nothing is missing. Requests carry the
//! API token, read from a Secret in the operator's namespace with the user's kube credentials.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{IsTerminal, Read, Write};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::{Args, Subcommand};
use futures::{StreamExt, TryStreamExt};
use k8s_openapi::api::core::v1::Secret;
use kube::Api;
use lekiwi_protocol::release::{ManifestFile, ReleaseManifest, blob_path, digest_hex};
use reqwest::{Method, StatusCode};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::io::{AsyncReadExt, AsyncSeekExt};

use crate::Output;

/// Where the gateway is and how to get its API token.
#[derive(Debug, Args)]
pub struct ServerArgs {
    /// Base URL of the gateway (the agents' address, over HTTP).
    #[arg(
        long,
        global = true,
        env = "LEKIWI_SERVER",
        default_value = "http://127.0.0.1:8081"
    )]
    pub server: String,
    /// Namespace of the operator, where the API token Secret lives.
    #[arg(
        long,
        global = true,
        env = "LEKIWI_OPERATOR_NAMESPACE",
        default_value = "lekiwi-system"
    )]
    pub operator_namespace: String,
    /// Name of the Secret holding the API token (`data.token`).
    #[arg(long, global = true, default_value = "lekiwi-api")]
    pub token_secret: String,
    /// PEM file of a CA to trust for an https:// gateway, besides the public roots.
    #[arg(long, global = true)]
    pub certificate_authority: Option<PathBuf>,
}

/// Release subcommands.
#[derive(Debug, Subcommand)]
pub enum ReleaseCommand {
    /// Upload a directory as a release; prints the manifest digest to put in a RobotDeployment.
    ///
    /// Every regular file under DIR becomes part of the release with its path, size and
    /// permission bits; a symbolic link or special file is an error. Blobs the gateway already
    /// has are not uploaded again; an interrupted push resumes where it stopped.
    Push {
        /// The directory to release.
        dir: PathBuf,
        /// Version name (letters, digits, `.`, `_`, `+`, `-`).
        #[arg(long)]
        version: String,
        /// Blobs uploaded at once.
        #[arg(long, default_value_t = 4)]
        parallel: usize,
        /// Bytes per upload request.
        #[arg(long, default_value_t = 8 * 1024 * 1024)]
        chunk_bytes: u64,
    },
    /// Show a stored release's manifest (`-o table|wide|json|yaml`).
    Inspect {
        /// The manifest digest, `sha256:<hex>`.
        digest: String,
    },
}

/// Runs a release subcommand.
pub async fn run(
    client: kube::Client,
    server: &ServerArgs,
    output: Output,
    cmd: ReleaseCommand,
) -> anyhow::Result<()> {
    match cmd {
        ReleaseCommand::Push {
            dir,
            version,
            parallel,
            chunk_bytes,
        } => {
            // Everything local is checked before the token is read or the gateway asked.
            let files = walk(&dir)?;
            let hashed = hash_all(files).await?;
            let manifest = ReleaseManifest::new(
                version.clone(),
                hashed.iter().map(|f| f.manifest.clone()).collect(),
            );
            manifest
                .validate()
                .with_context(|| format!("cannot make a release of {}", dir.display()))?;
            let gateway = Gateway::connect(client, server).await?;
            let pushed = push(
                &gateway,
                &manifest,
                &hashed,
                parallel.max(1),
                chunk_bytes.max(1),
            )
            .await?;
            eprintln!("{}", pushed.summary(&version));
            eprintln!(
                "add to the RobotDeployment's spec:\n  release: {{version: {version}, digest: {}}}",
                pushed.digest
            );
            println!("{}", pushed.digest);
            Ok(())
        }
        ReleaseCommand::Inspect { digest } => {
            digest_hex(&digest)?;
            let gateway = Gateway::connect(client, server).await?;
            let info = gateway.release(&digest).await?;
            print!("{}", render(&info, output)?);
            Ok(())
        }
    }
}

/// A file of the directory being released.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LocalFile {
    /// Path relative to the release directory, `/`-separated.
    pub path: String,
    /// Where it is.
    pub source: PathBuf,
    /// Permission bits.
    pub mode: u32,
}

/// Lists the regular files under `dir`, sorted by path. A symbolic link, special file or
/// non-UTF-8 name is an error naming it; an empty directory is reported on stderr (a release
/// holds files only).
pub fn walk(dir: &Path) -> anyhow::Result<Vec<LocalFile>> {
    let meta = std::fs::metadata(dir).with_context(|| format!("cannot read {}", dir.display()))?;
    if !meta.is_dir() {
        bail!("{} is not a directory", dir.display());
    }
    let mut files = Vec::new();
    walk_into(dir, "", &mut files)?;
    if files.is_empty() {
        bail!("{} holds no files: nothing to release", dir.display());
    }
    files.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(files)
}

fn walk_into(dir: &Path, prefix: &str, files: &mut Vec<LocalFile>) -> anyhow::Result<()> {
    let mut entries = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read directory {}", dir.display()))?
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("cannot read directory {}", dir.display()))?;
    entries.sort_by_key(|e| e.file_name());
    if entries.is_empty() && !prefix.is_empty() {
        eprintln!(
            "warning: empty directory {} is not part of the release (releases hold files only)",
            dir.display()
        );
    }
    for entry in entries {
        let source = entry.path();
        let name = entry
            .file_name()
            .into_string()
            .map_err(|n| anyhow::anyhow!("{}: file name {n:?} is not UTF-8", source.display()))?;
        let path = if prefix.is_empty() {
            name
        } else {
            format!("{prefix}/{name}")
        };
        let meta = std::fs::symlink_metadata(&source)
            .with_context(|| format!("cannot read {}", source.display()))?;
        let kind = meta.file_type();
        if kind.is_symlink() {
            bail!(
                "{} is a symbolic link: a release holds regular files only (copy the target instead)",
                source.display()
            );
        } else if kind.is_dir() {
            walk_into(&source, &path, files)?;
        } else if kind.is_file() {
            files.push(LocalFile {
                path,
                source,
                mode: meta.permissions().mode() & 0o7777,
            });
        } else {
            bail!(
                "{} is not a regular file (a socket, FIFO or device): a release holds regular files only",
                source.display()
            );
        }
    }
    Ok(())
}

/// A local file with its digest and size.
#[derive(Clone, Debug)]
pub struct HashedFile {
    /// Its manifest entry.
    pub manifest: ManifestFile,
    /// Where it is.
    pub source: PathBuf,
}

/// SHA-256 and size of a file, streamed.
pub fn hash_file(path: &Path) -> anyhow::Result<(String, u64)> {
    let mut file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1024 * 1024];
    let mut size = 0u64;
    loop {
        let n = file
            .read(&mut buf)
            .with_context(|| format!("cannot read {}", path.display()))?;
        if n == 0 {
            return Ok((format!("sha256:{}", hex::encode(hasher.finalize())), size));
        }
        hasher.update(&buf[..n]);
        size += n as u64;
    }
}

async fn hash_all(files: Vec<LocalFile>) -> anyhow::Result<Vec<HashedFile>> {
    tokio::task::spawn_blocking(move || {
        files
            .into_iter()
            .map(|f| {
                let (digest, size) = hash_file(&f.source)?;
                Ok(HashedFile {
                    manifest: ManifestFile {
                        path: f.path,
                        digest,
                        size,
                        mode: f.mode,
                    },
                    source: f.source,
                })
            })
            .collect()
    })
    .await?
}

/// The gateway's HTTP API with the API token.
pub(crate) struct Gateway {
    http: reqwest::Client,
    pub(crate) base: String,
    token: String,
}

/// An error answer of the gateway.
#[derive(Debug, Deserialize)]
struct ApiError {
    message: String,
}

/// The gateway's answer to an upload request.
#[derive(Debug, Deserialize)]
struct UploadAnswer {
    offset: u64,
    #[serde(default)]
    complete: bool,
}

/// A stored release as `GET /v1/releases/{digest}` answers it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ReleaseInfo {
    /// Digest of the manifest.
    pub digest: String,
    /// The manifest.
    #[serde(flatten)]
    pub manifest: ReleaseManifest,
    /// Referenced blobs the gateway lacks.
    pub missing: Vec<String>,
}

/// Attempts of a request that fails transiently (network, 5xx, 429) before giving up.
const ATTEMPTS: u32 = 6;

fn backoff(attempt: u32) -> Duration {
    Duration::from_millis(250u64 << attempt.min(5)).min(Duration::from_secs(5))
}

fn transient(status: StatusCode) -> bool {
    status.is_server_error()
        || status == StatusCode::TOO_MANY_REQUESTS
        || status == StatusCode::REQUEST_TIMEOUT
}

/// The gateway's message in an error answer, or the body as it is.
pub(crate) async fn message(resp: reqwest::Response) -> String {
    let status = resp.status();
    let text = resp.text().await.unwrap_or_default();
    match serde_json::from_str::<ApiError>(&text) {
        Ok(e) => e.message,
        Err(_) if text.trim().is_empty() => status.to_string(),
        Err(_) => text.trim().to_owned(),
    }
}

impl Gateway {
    pub(crate) async fn connect(client: kube::Client, server: &ServerArgs) -> anyhow::Result<Self> {
        let token = api_token(client, &server.operator_namespace, &server.token_secret).await?;
        let mut http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            .read_timeout(Duration::from_secs(120));
        if let Some(ca) = &server.certificate_authority {
            let pem = std::fs::read(ca).with_context(|| format!("cannot read {}", ca.display()))?;
            http = http.add_root_certificate(
                reqwest::Certificate::from_pem(&pem)
                    .with_context(|| format!("{} is not a PEM certificate", ca.display()))?,
            );
        }
        Ok(Self {
            http: http.build()?,
            base: server.server.trim_end_matches('/').to_owned(),
            token,
        })
    }

    pub(crate) fn request(&self, method: Method, path: &str) -> reqwest::RequestBuilder {
        self.http
            .request(method, format!("{}{path}", self.base))
            .bearer_auth(&self.token)
    }

    /// Sends a request that is safe to repeat, retrying transient failures.
    async fn send(
        &self,
        method: Method,
        path: &str,
        what: &str,
    ) -> anyhow::Result<reqwest::Response> {
        let mut attempt = 0;
        loop {
            let failure = match self.request(method.clone(), path).send().await {
                Ok(resp) if !transient(resp.status()) => return Ok(resp),
                Ok(resp) => format!("{}: {}", resp.status(), message(resp).await),
                Err(e) if crate::tls_refused(&e) => bail!(
                    "{what}: TLS with the gateway at {} failed ({}); check --certificate-authority",
                    self.base,
                    crate::http_error(&e)
                ),
                Err(e) => crate::http_error(&e),
            };
            attempt += 1;
            if attempt >= ATTEMPTS {
                bail!(
                    "{what}: the gateway at {} did not answer ({failure}); check --server or LEKIWI_SERVER",
                    self.base
                );
            }
            tokio::time::sleep(backoff(attempt)).await;
        }
    }

    async fn has_blob(&self, digest: &str) -> anyhow::Result<bool> {
        let resp = self
            .send(Method::HEAD, &blob_path(digest), "checking blobs")
            .await?;
        match resp.status() {
            StatusCode::OK => Ok(true),
            StatusCode::NOT_FOUND => Ok(false),
            StatusCode::UNAUTHORIZED => bail!(
                "the gateway at {} refused the API token (401): is --server the gateway of the operator in --operator-namespace?",
                self.base
            ),
            s => bail!("checking blob {digest}: the gateway answered {s}"),
        }
    }

    async fn upload_offset(&self, digest: &str) -> anyhow::Result<UploadAnswer> {
        let resp = self
            .send(
                Method::GET,
                &format!("/v1/uploads/{digest}"),
                "resuming an upload",
            )
            .await?;
        if !resp.status().is_success() {
            bail!("resuming the upload of {digest}: {}", message(resp).await);
        }
        Ok(resp.json().await?)
    }

    async fn release(&self, digest: &str) -> anyhow::Result<ReleaseInfo> {
        let resp = self
            .send(
                Method::GET,
                &format!("/v1/releases/{digest}"),
                "reading the release",
            )
            .await?;
        if !resp.status().is_success() {
            bail!("{}", message(resp).await);
        }
        resp.json()
            .await
            .with_context(|| format!("reading release {digest}"))
    }

    /// Uploads one blob from its offset on the gateway; returns the bytes sent and whether
    /// this upload stored it (rather than finding it stored).
    async fn upload(
        &self,
        blob: &Blob,
        chunk_bytes: u64,
        progress: &Progress,
    ) -> anyhow::Result<(u64, bool)> {
        let path = blob_path(&blob.digest);
        let mut sent = 0u64;
        let mut offset = match self.upload_offset(&blob.digest).await? {
            UploadAnswer { complete: true, .. } => return Ok((0, false)),
            UploadAnswer { offset, .. } => offset.min(blob.size),
        };
        progress.bytes.fetch_add(offset, Ordering::Relaxed);
        let mut attempt = 0;
        loop {
            let (request, len) = if blob.size == 0 {
                (self.request(Method::PUT, &path).body(Vec::new()), 0)
            } else if offset == blob.size {
                // Every byte arrived but the gateway did not verify them yet: ask it to.
                let range = format!("bytes */{}", blob.size);
                let request = self
                    .request(Method::PUT, &path)
                    .header(reqwest::header::CONTENT_RANGE, range)
                    .body(Vec::new());
                (request, 0)
            } else {
                let len = chunk_bytes.min(blob.size - offset);
                let data = blob.source.read(offset, len).await?;
                let range = format!("bytes {offset}-{}/{}", offset + len - 1, blob.size);
                let request = self
                    .request(Method::PUT, &path)
                    .header(reqwest::header::CONTENT_RANGE, range)
                    .body(data);
                (request, len)
            };
            let failure = match request.send().await {
                Ok(resp) => match resp.status() {
                    StatusCode::CREATED | StatusCode::OK => {
                        let stored = resp.status() == StatusCode::CREATED;
                        if stored {
                            sent += len;
                            progress.bytes.fetch_add(len, Ordering::Relaxed);
                        }
                        return Ok((sent, stored));
                    }
                    StatusCode::ACCEPTED => {
                        let answer: UploadAnswer = resp.json().await?;
                        let advanced = answer.offset.saturating_sub(offset);
                        sent += advanced;
                        progress.bytes.fetch_add(advanced, Ordering::Relaxed);
                        offset = answer.offset;
                        attempt = 0;
                        continue;
                    }
                    StatusCode::CONFLICT => {
                        // Another upload moved it on (or an earlier answer got lost).
                        let answer: UploadAnswer = resp.json().await?;
                        format!("the upload stood at {}, not {offset}", answer.offset)
                    }
                    s if transient(s) => format!("{s}: {}", message(resp).await),
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
                },
                Err(e) => crate::http_error(&e),
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
            match self.upload_offset(&blob.digest).await? {
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
}

/// Reads the API token from its Secret with the user's credentials.
async fn api_token(client: kube::Client, namespace: &str, name: &str) -> anyhow::Result<String> {
    let api: Api<Secret> = Api::namespaced(client, namespace);
    let secret = match api.get_opt(name).await {
        Ok(Some(s)) => s,
        Ok(None) => bail!(
            "Secret {namespace}/{name} with the API token not found: is the LeKiwi operator running in namespace {namespace}? (see --operator-namespace, --token-secret)"
        ),
        Err(kube::Error::Api(s)) if s.code == 403 => bail!(
            "not allowed to read Secret {namespace}/{name}: pushing releases needs `get` on the API token Secret ({})",
            s.message
        ),
        Err(e) => {
            return Err(e).with_context(|| format!("cannot read Secret {namespace}/{name}"));
        }
    };
    secret
        .data
        .as_ref()
        .and_then(|d| d.get("token"))
        .and_then(|t| String::from_utf8(t.0.clone()).ok())
        .map(|t| t.trim().to_owned())
        .filter(|t| !t.is_empty())
        .with_context(|| format!("Secret {namespace}/{name} has no data.token"))
}

/// Where a blob's bytes come from.
#[derive(Clone, Debug)]
enum Source {
    File(PathBuf),
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
struct Blob {
    digest: String,
    size: u64,
    /// A file path naming it in messages.
    name: String,
    source: Source,
}

/// Counters the progress line reads.
#[derive(Default)]
struct Progress {
    bytes: AtomicU64,
    blobs: AtomicU64,
}

/// What a push did.
#[derive(Debug, PartialEq, Eq)]
pub struct Pushed {
    /// Digest of the manifest.
    pub digest: String,
    /// Bytes uploaded, manifest included.
    pub bytes: u64,
    /// Files whose content the gateway already had.
    pub present_files: usize,
    /// Blobs this push stored (the manifest not counted).
    pub new_blobs: usize,
    /// Whether this push stored the manifest.
    pub manifest_uploaded: bool,
}

impl Pushed {
    /// The summary line, e.g. `release 1.2.0: 0 B uploaded, 50 files already present (0 new
    /// blobs, manifest already present)`.
    pub fn summary(&self, version: &str) -> String {
        let manifest = if self.manifest_uploaded {
            " + manifest"
        } else {
            ", manifest already present"
        };
        format!(
            "release {version}: {} uploaded, {} files already present ({} new blobs{manifest})",
            human(self.bytes),
            self.present_files,
            self.new_blobs
        )
    }
}

/// Bytes for people: `0 B`, `512 B`, `1.5 KiB`, `3.2 GiB`.
pub fn human(bytes: u64) -> String {
    const UNITS: [&str; 4] = ["KiB", "MiB", "GiB", "TiB"];
    if bytes < 1024 {
        return format!("{bytes} B");
    }
    let mut value = bytes as f64 / 1024.0;
    let mut unit = 0;
    while value >= 1024.0 && unit < UNITS.len() - 1 {
        value /= 1024.0;
        unit += 1;
    }
    format!("{value:.1} {}", UNITS[unit])
}

async fn push(
    gateway: &Gateway,
    manifest: &ReleaseManifest,
    files: &[HashedFile],
    parallel: usize,
    chunk_bytes: u64,
) -> anyhow::Result<Pushed> {
    // One blob per distinct content.
    let mut blobs: BTreeMap<String, Blob> = BTreeMap::new();
    for f in files {
        blobs
            .entry(f.manifest.digest.clone())
            .or_insert_with(|| Blob {
                digest: f.manifest.digest.clone(),
                size: f.manifest.size,
                name: f.manifest.path.clone(),
                source: Source::File(f.source.clone()),
            });
    }
    let present: BTreeSet<String> = futures::stream::iter(blobs.keys().cloned())
        .map(|d| async move { Ok::<_, anyhow::Error>(gateway.has_blob(&d).await?.then_some(d)) })
        .buffer_unordered(8)
        .try_filter_map(|d| async move { Ok(d) })
        .try_collect()
        .await?;
    let missing: Vec<Blob> = blobs
        .into_values()
        .filter(|b| !present.contains(&b.digest))
        .collect();
    let present_files = files
        .iter()
        .filter(|f| present.contains(&f.manifest.digest))
        .count();

    let progress = Arc::new(Progress::default());
    let total_bytes: u64 = missing.iter().map(|b| b.size).sum();
    let total_blobs = missing.len() as u64;
    let ticker = std::io::stderr().is_terminal().then(|| {
        let progress = progress.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_secs(1));
            loop {
                tick.tick().await;
                eprint!(
                    "\ruploading: {} / {}, {} / {total_blobs} files   ",
                    human(progress.bytes.load(Ordering::Relaxed)),
                    human(total_bytes),
                    progress.blobs.load(Ordering::Relaxed)
                );
                let _ = std::io::stderr().flush();
            }
        })
    });
    let uploaded = futures::stream::iter(missing)
        .map(|blob| {
            let progress = progress.clone();
            async move {
                let done = gateway.upload(&blob, chunk_bytes, &progress).await;
                progress.blobs.fetch_add(1, Ordering::Relaxed);
                done
            }
        })
        .buffer_unordered(parallel)
        .try_collect::<Vec<(u64, bool)>>()
        .await;
    if let Some(t) = ticker {
        t.abort();
        eprint!("\r\x1b[2K");
    }
    let uploaded = uploaded?;
    let mut bytes: u64 = uploaded.iter().map(|(b, _)| b).sum();
    let new_blobs = uploaded.iter().filter(|(_, stored)| *stored).count();

    // The manifest last: once it is stored, every blob it names is too.
    let manifest_bytes = manifest.to_bytes();
    let digest = format!("sha256:{}", hex::encode(Sha256::digest(&manifest_bytes)));
    let mut manifest_uploaded = false;
    if !gateway.has_blob(&digest).await? {
        let blob = Blob {
            digest: digest.clone(),
            size: manifest_bytes.len() as u64,
            name: "the manifest".into(),
            source: Source::Memory(Arc::new(manifest_bytes)),
        };
        let (sent, stored) = gateway.upload(&blob, chunk_bytes, &progress).await?;
        bytes += sent;
        manifest_uploaded = stored;
    }
    let info = gateway.release(&digest).await?;
    if !info.missing.is_empty() {
        bail!(
            "the gateway lacks {} blobs of release {digest} after the push: {}",
            info.missing.len(),
            info.missing.join(", ")
        );
    }
    Ok(Pushed {
        digest,
        bytes,
        present_files,
        new_blobs,
        manifest_uploaded,
    })
}

/// Renders a release in the chosen format.
pub fn render(info: &ReleaseInfo, output: Output) -> anyhow::Result<String> {
    Ok(match output {
        Output::Json => serde_json::to_string_pretty(info)? + "\n",
        Output::Yaml => serde_yaml::to_string(info)?,
        Output::Table | Output::Wide => table(info, output == Output::Wide),
    })
}

fn table(info: &ReleaseInfo, wide: bool) -> String {
    let mut out = format!(
        "Version:  {}\nDigest:   {}\nFiles:    {} ({})\nMissing:  {}\n\n",
        info.manifest.version,
        info.digest,
        info.manifest.files.len(),
        human(info.manifest.total_bytes()),
        if info.missing.is_empty() {
            "none".to_owned()
        } else {
            info.missing.join(", ")
        }
    );
    let mut rows = vec![vec![
        "MODE".to_owned(),
        "SIZE".to_owned(),
        "DIGEST".to_owned(),
        "PATH".to_owned(),
    ]];
    for f in &info.manifest.files {
        let digest = if wide {
            f.digest.clone()
        } else {
            f.digest.chars().take(7 + 12).collect()
        };
        rows.push(vec![
            format!("{:04o}", f.mode),
            f.size.to_string(),
            digest,
            f.path.clone(),
        ]);
    }
    let widths: Vec<usize> = (0..4)
        .map(|i| rows.iter().map(|r| r[i].len()).max().unwrap_or(0))
        .collect();
    for row in rows {
        let line: Vec<String> = row
            .iter()
            .enumerate()
            .map(|(i, cell)| format!("{cell:<w$}", w = widths[i]))
            .collect();
        out.push_str(line.join("   ").trim_end());
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn walks_regular_files_with_modes_and_refuses_links() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::create_dir_all(root.join("a/b")).unwrap();
        std::fs::write(root.join("run.sh"), "#!/bin/sh\n").unwrap();
        std::fs::set_permissions(root.join("run.sh"), std::fs::Permissions::from_mode(0o755))
            .unwrap();
        std::fs::write(root.join("a/b/c.txt"), "c").unwrap();
        std::fs::set_permissions(
            root.join("a/b/c.txt"),
            std::fs::Permissions::from_mode(0o640),
        )
        .unwrap();
        let files = walk(root).unwrap();
        let got: Vec<(&str, u32)> = files.iter().map(|f| (f.path.as_str(), f.mode)).collect();
        assert_eq!(got, vec![("a/b/c.txt", 0o640), ("run.sh", 0o755)]);
        let (digest, size) = hash_file(&root.join("a/b/c.txt")).unwrap();
        assert_eq!(size, 1);
        assert_eq!(
            digest,
            format!("sha256:{}", hex::encode(Sha256::digest(b"c")))
        );

        std::os::unix::fs::symlink(root.join("run.sh"), root.join("a/link")).unwrap();
        let err = walk(root).unwrap_err().to_string();
        assert!(
            err.contains("a/link") && err.contains("symbolic link"),
            "{err}"
        );
    }

    #[test]
    fn summaries_and_sizes_read_well() {
        assert_eq!(human(0), "0 B");
        assert_eq!(human(1023), "1023 B");
        assert_eq!(human(1536), "1.5 KiB");
        assert_eq!(human(5 * 1024 * 1024 * 1024), "5.0 GiB");
        let again = Pushed {
            digest: "sha256:00".into(),
            bytes: 0,
            present_files: 50,
            new_blobs: 0,
            manifest_uploaded: false,
        };
        assert_eq!(
            again.summary("1.0.0"),
            "release 1.0.0: 0 B uploaded, 50 files already present (0 new blobs, manifest already present)"
        );
        let changed = Pushed {
            bytes: 3000,
            present_files: 47,
            new_blobs: 3,
            manifest_uploaded: true,
            ..again
        };
        assert!(
            changed
                .summary("1.1.0")
                .ends_with("(3 new blobs + manifest)")
        );
    }

    #[test]
    fn tables_show_modes_and_short_digests() {
        let info = ReleaseInfo {
            digest: format!("sha256:{}", "b".repeat(64)),
            manifest: ReleaseManifest::new(
                "1.0.0",
                vec![ManifestFile {
                    path: "bin/run".into(),
                    digest: format!("sha256:{}", "a".repeat(64)),
                    size: 10,
                    mode: 0o755,
                }],
            ),
            missing: vec![],
        };
        let text = render(&info, Output::Table).unwrap();
        assert!(text.contains("Version:  1.0.0"), "{text}");
        assert!(
            text.contains("0755   10     sha256:aaaaaaaaaaaa   bin/run"),
            "{text}"
        );
        let json: serde_json::Value =
            serde_json::from_str(&render(&info, Output::Json).unwrap()).unwrap();
        assert_eq!(json["files"][0]["mode"], 0o755);
        assert_eq!(json["missing"], serde_json::json!([]));
    }
}
