//! The directory being released: its regular files with their modes, hashed for the manifest.

use std::io::Read;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use lekiwi_protocol::release::ManifestFile;
use sha2::{Digest, Sha256};

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

/// Hashes every file off the async runtime, in order.
pub(super) async fn hash_all(files: Vec<LocalFile>) -> anyhow::Result<Vec<HashedFile>> {
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
