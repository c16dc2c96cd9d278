//! The releases each namespace pushed: one small record per release at
//! `releases/<namespace>/<hex>.json` beside the blobs (on the same volume, so every replica
//! sharing it sees the same list). Blobs are shared by content across namespaces; the record is
//! what makes a manifest a release *of a namespace*, with the time it was first pushed there.

use std::path::{Path, PathBuf};

use jiff::Timestamp;
use lekiwi_protocol::release::digest_hex;
use serde::{Deserialize, Serialize};

use super::{Error, Result, io, remove_if_exists};

/// One release of one namespace, as recorded when its manifest was pushed.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct ReleaseRecord {
    /// The namespace it was pushed to.
    pub namespace: String,
    /// The manifest's version.
    pub version: String,
    /// The manifest's digest.
    pub digest: String,
    /// When it was first pushed to this namespace (a push of the same manifest again keeps it).
    pub pushed: Timestamp,
}

/// The per-namespace release records under a blob store's root.
#[derive(Clone, Debug)]
pub struct ReleaseIndex {
    dir: PathBuf,
}

impl ReleaseIndex {
    /// The records under `root/releases`.
    pub fn new(root: &Path) -> Self {
        Self {
            dir: root.join("releases"),
        }
    }

    fn path(&self, namespace: &str, digest: &str) -> Result<PathBuf> {
        let hex = digest_hex(digest).map_err(Error::Digest)?;
        Ok(self.dir.join(namespace).join(format!("{hex}.json")))
    }

    /// Records `digest` (version `version`) as a release of `namespace`, pushed now, unless it
    /// is recorded already; returns whether this made the record. `namespace` must be a valid
    /// Kubernetes name (the caller checked it): it becomes a directory name.
    pub async fn register(&self, namespace: &str, version: &str, digest: &str) -> Result<bool> {
        let path = self.path(namespace, digest)?;
        if tokio::fs::try_exists(&path).await.map_err(io(&path))? {
            return Ok(false);
        }
        let dir = self.dir.join(namespace);
        tokio::fs::create_dir_all(&dir).await.map_err(io(&dir))?;
        let record = ReleaseRecord {
            namespace: namespace.to_owned(),
            version: version.to_owned(),
            digest: digest.to_owned(),
            pushed: Timestamp::now(),
        };
        let json = serde_json::to_vec(&record).unwrap_or_default();
        // Written aside and renamed: a reader never sees half a record.
        let tmp = path.with_extension(format!("tmp.{}", std::process::id()));
        tokio::fs::write(&tmp, json).await.map_err(io(&tmp))?;
        tokio::fs::rename(&tmp, &path).await.map_err(io(&path))?;
        Ok(true)
    }

    /// Forgets the release `digest` of `namespace` (nothing if it is not recorded).
    pub async fn remove(&self, namespace: &str, digest: &str) -> Result<()> {
        remove_if_exists(&self.path(namespace, digest)?).await
    }

    /// Every record of `namespace`, or of every namespace when `None`, oldest push first.
    /// A record that cannot be read is skipped with a warning.
    pub async fn list(&self, namespace: Option<&str>) -> Result<Vec<ReleaseRecord>> {
        let namespaces = match namespace {
            Some(ns) => vec![ns.to_owned()],
            None => names(&self.dir).await?,
        };
        let mut records = Vec::new();
        for ns in namespaces {
            let dir = self.dir.join(&ns);
            for name in names(&dir).await? {
                if !name.ends_with(".json") {
                    continue;
                }
                let path = dir.join(&name);
                let parsed = match tokio::fs::read(&path).await {
                    Ok(bytes) => {
                        serde_json::from_slice::<ReleaseRecord>(&bytes).map_err(|e| e.to_string())
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                    Err(e) => Err(e.to_string()),
                };
                match parsed {
                    Ok(r) => records.push(r),
                    Err(e) => {
                        tracing::warn!(path = %path.display(), error = %e, "skipping an unreadable release record");
                    }
                }
            }
        }
        records.sort_by(|a, b| {
            (a.pushed, &a.namespace, &a.digest).cmp(&(b.pushed, &b.namespace, &b.digest))
        });
        Ok(records)
    }
}

/// The entry names of a directory, none if it does not exist.
async fn names(dir: &Path) -> Result<Vec<String>> {
    let mut entries = match tokio::fs::read_dir(dir).await {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io(dir)(e)),
    };
    let mut names = Vec::new();
    while let Some(entry) = entries.next_entry().await.map_err(io(dir))? {
        if let Some(name) = entry.file_name().to_str() {
            names.push(name.to_owned());
        }
    }
    names.sort();
    Ok(names)
}
