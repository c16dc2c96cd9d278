//! A namespace of the shared control plane with its own operator (controller + gateway, blob
//! store in a temp dir) and an enrollment token file: what rollout tests start from.

use std::path::{Path, PathBuf};

use anyhow::Result;
use kube::Client;
use lekiwi_crds::ReleaseRef;

use crate::{ControlPlane, OperatorProcess, enrollment_token_file, namespace, push_release};

/// See the module docs. Test files wrap it in their own `Site` (with agents) and deref to it.
pub struct OperatorSite {
    /// The shared control plane.
    pub cp: &'static ControlPlane,
    /// A client of it.
    pub client: Client,
    /// The test's namespace.
    pub ns: String,
    /// The operator, ready.
    pub op: OperatorProcess,
    /// Scratch space: blobs, the token file, robots' state.
    pub dir: tempfile::TempDir,
    /// A file holding an enrollment token of `ns`.
    pub token_file: PathBuf,
}

impl OperatorSite {
    /// A fresh namespace named after `prefix` and an operator of that name, started and ready.
    pub async fn start(prefix: &str) -> Result<Self> {
        Self::start_with(prefix, &[]).await
    }

    /// As [`Self::start`], the operator started with `extra` flags too.
    pub async fn start_with(prefix: &str, extra: &[&str]) -> Result<Self> {
        let cp = ControlPlane::shared();
        let client = cp.client().await?;
        let ns = namespace(&client, prefix).await?;
        let dir = tempfile::tempdir()?;
        let blobs = dir.path().join("blobs");
        std::fs::create_dir_all(&blobs)?;
        let blob_dir = blobs.to_str().expect("a UTF-8 temp path");
        let mut args = vec!["--blob-dir", blob_dir];
        args.extend_from_slice(extra);
        let mut op = OperatorProcess::start(cp, &ns, prefix, &args)?;
        op.wait_ready().await?;
        let token_file = dir.path().join("enroll");
        enrollment_token_file(&client, &ns, &token_file).await?;
        Ok(Self {
            cp,
            client,
            ns,
            op,
            dir,
            token_file,
        })
    }

    /// Pushes `dir` as `version` with the real CLI; returns the release.
    pub fn push(&self, dir: &Path, version: &str) -> Result<ReleaseRef> {
        let server = format!("http://127.0.0.1:{}", self.op.gateway_port);
        push_release(&self.cp.kubeconfig(), &self.ns, &server, None, dir, version)
    }
}

/// `Deref`/`DerefMut` from a test's `Site` (a struct with a field `base: OperatorSite`) to its
/// `OperatorSite`, so `site.ns`, `site.op` and `site.push(..)` read as before.
#[macro_export]
macro_rules! deref_to_operator_site {
    ($site:ty) => {
        impl std::ops::Deref for $site {
            type Target = $crate::OperatorSite;

            fn deref(&self) -> &$crate::OperatorSite {
                &self.base
            }
        }

        impl std::ops::DerefMut for $site {
            fn deref_mut(&mut self) -> &mut $crate::OperatorSite {
                &mut self.base
            }
        }
    };
}
