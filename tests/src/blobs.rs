//! Release blobs as tests push and read them over the gateway's HTTP API: a release of one file
//! (the file, its manifest, their digests) and a GET that answers status and body bytes.

use anyhow::{Result, ensure};
use lekiwi_protocol::release::{ManifestFile, ReleaseManifest};
use sha2::{Digest, Sha256};

use crate::http::http_request;

/// `sha256:<hex>` of `bytes`, as blobs are named.
pub fn digest(bytes: &[u8]) -> String {
    format!("sha256:{}", hex::encode(Sha256::digest(bytes)))
}

/// A release of one file, `policy.bin`: the file's bytes and digest, the manifest's digest and
/// bytes.
pub struct OneFileRelease {
    pub file: String,
    pub manifest: String,
    pub manifest_bytes: Vec<u8>,
    pub content: Vec<u8>,
}

impl OneFileRelease {
    pub fn new(version: &str, content: &[u8]) -> Self {
        let file = digest(content);
        let manifest_bytes = ReleaseManifest::new(
            version,
            vec![ManifestFile {
                path: "policy.bin".into(),
                digest: file.clone(),
                size: content.len() as u64,
                mode: 0o644,
            }],
        )
        .to_bytes();
        Self {
            file,
            manifest: digest(&manifest_bytes),
            manifest_bytes,
            content: content.to_vec(),
        }
    }

    /// Uploads the file and the manifest to the gateway on `port` with `auth` (a Kubernetes
    /// user's `Bearer` header), into namespace `ns`; each must be stored (201).
    pub async fn push(&self, port: u16, auth: &str, ns: &str) -> Result<()> {
        for (d, bytes) in [
            (&self.file, &self.content),
            (&self.manifest, &self.manifest_bytes),
        ] {
            let path = format!("/v1/blobs/{d}?namespace={ns}");
            let headers = [("authorization", auth)];
            let (code, _, _) = http_request(port, "PUT", &path, &headers, Some(bytes)).await?;
            ensure!(code == 201, "upload of {d}: {code}");
        }
        Ok(())
    }
}

/// GET `path` from the gateway on `port` with `headers`: the status and the body's bytes.
pub async fn get_bytes(port: u16, path: &str, headers: &[(&str, &str)]) -> (u16, Vec<u8>) {
    let (code, _, body) = http_request(port, "GET", path, headers, None)
        .await
        .expect("request");
    (code, body)
}
