//! `kubectl lekiwi release push DIR --version V`, `release inspect DIGEST`, `release list` and
//! `release delete VERSION|DIGEST`: upload a directory to the gateway's blob store as
//! content-addressed blobs plus a manifest, show a stored release, list the namespace's releases
//! with who uses them, and delete one nothing uses.
//!
//! Push hashes every file, asks the gateway which blobs it has (`HEAD /v1/blobs/{digest}`),
//! uploads the missing ones a few at a time in chunks (`PUT` with `Content-Range`), resuming
//! from the gateway's offset (`GET /v1/uploads/{digest}`) after a failure, uploads the manifest
//! last and confirms with `GET /v1/releases/{digest}` that nothing is missing. Requests carry the
//! user's Kubernetes bearer token (from the kubeconfig, or `--token`) and name the namespace
//! (`?namespace=`) where RBAC must allow `create` and `get` on `releases.fleet.lekiwi.io`.

pub mod agent;
mod files;
mod gateway;
mod list;
mod push;
mod upload;

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use clap::{Args, Subcommand};
use lekiwi_protocol::release::{ReleaseManifest, digest_hex};

use crate::Output;

pub use files::{HashedFile, LocalFile, hash_file, walk};
pub use gateway::ReleaseInfo;
pub(crate) use gateway::{Gateway, message, refused};
use push::PushOptions;
pub use push::{Pushed, human};

/// Where the gateway is and which Kubernetes token to present to it.
#[derive(Debug, Args)]
pub struct ServerArgs {
    /// Base URL of the gateway (the agents' address, over HTTP). Default: the chart's gateway
    /// in --gateway-namespace, reached through the API server (a port-forward the plugin opens
    /// to a Pod of its Service) and trusted by the CA in the chart's ConfigMap.
    #[arg(long, global = true, env = "LEKIWI_SERVER")]
    pub server: Option<String>,
    /// Kubernetes bearer token to present to the gateway (e.g. from `kubectl create token SA`);
    /// default: the kubeconfig user's token. The gateway checks it with the API server and
    /// asks RBAC whether its user may do what the command does.
    #[arg(long, global = true, env = "LEKIWI_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// PEM file of a CA to trust for an https:// gateway, besides the public roots.
    #[arg(long, global = true)]
    pub certificate_authority: Option<PathBuf>,
    /// Send the Kubernetes token over plain http:// to a host other than this machine (anyone
    /// on the path can read it and act as you in the cluster); refused without this flag.
    #[arg(long, global = true)]
    pub insecure_allow_plaintext: bool,
}

impl ServerArgs {
    /// Refuses a plain `http://` server on another host unless `--insecure-allow-plaintext`:
    /// the token would cross the network readable by anyone on the path.
    pub fn check_transport(&self) -> anyhow::Result<()> {
        let Some(server) = &self.server else {
            // Through the API server's port-forward: the tunnel is the API server's TLS.
            return Ok(());
        };
        match lekiwi_protocol::transport::plaintext_remote_host(server) {
            Some(host) if !self.insecure_allow_plaintext => anyhow::bail!(
                "refusing to send your Kubernetes token over plain http:// to {host} (--server {server}): \
                 anyone on the path could read it and act as you in the cluster. Use https:// (with \
                 --certificate-authority for the gateway's CA), or on a network you trust pass \
                 --insecure-allow-plaintext"
            ),
            Some(host) => {
                eprintln!(
                    "WARNING: sending your Kubernetes token over plain http:// to {host} (--insecure-allow-plaintext)"
                );
                Ok(())
            }
            None => Ok(()),
        }
    }
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
    /// List the releases pushed to the namespace, newest first, with their size and how many
    /// robots and deployments use them (`-o table|wide|json|yaml`).
    ///
    /// DESIRED: robots whose spec.release it is; CURRENT: robots running it; PREVIOUS: robots a
    /// RobotDeployment would roll back to it; DEPLOYMENTS: RobotDeployments rolling it out. The
    /// gateway removes a release nothing uses once it is older than the newest
    /// --release-retention (default 10) of the namespace.
    List,
    /// Delete a release nothing uses, with the files no other release shares; refused while a
    /// Robot or RobotDeployment references it.
    Delete {
        /// The release's version (when only one release of the namespace has it) or its
        /// manifest digest.
        release: String,
    },
}

/// Runs a release subcommand.
pub async fn run(
    kube: &crate::KubeContext,
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
            let options = PushOptions {
                parallel: parallel.max(1),
                chunk_bytes: chunk_bytes.max(1),
            };
            push_dir(kube, server, &dir, &version, options).await
        }
        ReleaseCommand::List => {
            let gateway = Gateway::connect_api(kube, server).await?;
            let items = gateway.releases(&kube.namespace).await?;
            let items: Vec<list::ReleaseItem> = items
                .into_iter()
                .map(serde_json::from_value)
                .collect::<Result<_, _>>()
                .context("reading the release list")?;
            print!("{}", list::render(&items, output, jiff::Timestamp::now())?);
            Ok(())
        }
        ReleaseCommand::Delete { release } => {
            let gateway = Gateway::connect_api(kube, server).await?;
            let deleted = gateway.delete_release(&kube.namespace, &release).await?;
            println!(
                "release {} ({}) deleted: {} blobs, {} freed",
                deleted["version"].as_str().unwrap_or_default(),
                deleted["digest"].as_str().unwrap_or_default(),
                deleted["blobs"].as_u64().unwrap_or_default(),
                human(deleted["bytes"].as_u64().unwrap_or_default())
            );
            Ok(())
        }
        ReleaseCommand::Inspect { digest } => {
            digest_hex(&digest)?;
            let gateway = Gateway::connect(kube, server, Some(&kube.namespace)).await?;
            let info = gateway.release(&digest).await?;
            print!("{}", render(&info, output)?);
            Ok(())
        }
    }
}

/// Pushes `dir` as release `version` and prints its digest (on stdout, for scripts) and how to
/// use it (on stderr).
async fn push_dir(
    kube: &crate::KubeContext,
    server: &ServerArgs,
    dir: &Path,
    version: &str,
    options: PushOptions,
) -> anyhow::Result<()> {
    // Everything local is checked before the gateway is asked.
    let files = walk(dir)?;
    let hashed = files::hash_all(files).await?;
    let manifest = ReleaseManifest::new(
        version.to_owned(),
        hashed.iter().map(|f| f.manifest.clone()).collect(),
    );
    manifest
        .validate()
        .with_context(|| format!("cannot make a release of {}", dir.display()))?;
    let gateway = Gateway::connect(kube, server, Some(&kube.namespace)).await?;
    let pushed = push::push(&gateway, &manifest, &hashed, options).await?;
    eprintln!("{}", pushed.summary(version));
    eprintln!(
        "add to the RobotDeployment's spec:\n  release: {{version: {version}, digest: {}}}",
        pushed.digest
    );
    println!("{}", pushed.digest);
    Ok(())
}

/// Renders a release in the chosen format.
pub fn render(info: &ReleaseInfo, output: Output) -> anyhow::Result<String> {
    Ok(match output.structured(info)? {
        Some(text) => text,
        None => table(info, output == Output::Wide),
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
    out.push_str(&crate::output::aligned(&rows));
    out
}

#[cfg(test)]
mod tests;
