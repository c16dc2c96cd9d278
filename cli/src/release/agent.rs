//! `kubectl lekiwi agent push --version V --arch amd64|arm64 BINARY`: uploads one build of
//! `lekiwi-agent` to the gateway's blob store (the release blob store, with the same RBAC as
//! `release push`: `create` and `get` on `releases.fleet.lekiwi.io` in the namespace) and prints
//! its digest, to put in `Robot.spec.agent.builds`.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use clap::Subcommand;
use lekiwi_protocol::rules;

use super::upload::{Blob, Progress, Source, Upload};
use super::{Gateway, ServerArgs, files, human};

/// Agent subcommands.
#[derive(Debug, Subcommand)]
pub enum AgentCommand {
    /// Upload a `lekiwi-agent` binary for one architecture; prints its digest for
    /// `Robot.spec.agent.builds`.
    ///
    /// The binary is stored once by its SHA-256, like a release file; pushing it again uploads
    /// nothing. Robots download it when a Robot of their namespace names its digest.
    Push {
        /// The `lekiwi-agent` binary (e.g. from the .deb, `/usr/bin/lekiwi-agent`).
        binary: PathBuf,
        /// The version the binary reports (`lekiwi-agent --version` prints it); robots count as
        /// updated when their agent says this in `hello`.
        #[arg(long)]
        version: String,
        /// The CPU architecture the binary is for.
        #[arg(long, value_parser = ["amd64", "arm64"])]
        arch: String,
        /// Bytes per upload request.
        #[arg(long, default_value_t = 8 * 1024 * 1024)]
        chunk_bytes: u64,
    },
}

/// Runs an agent subcommand.
pub async fn run(
    kube: &crate::KubeContext,
    server: &ServerArgs,
    cmd: AgentCommand,
) -> anyhow::Result<()> {
    let AgentCommand::Push {
        binary,
        version,
        arch,
        chunk_bytes,
    } = cmd;
    if version.is_empty()
        || version.chars().count() > rules::MAX_VERSION_CHARS as usize
        || !version
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '+' | '-'))
    {
        bail!("--version {version:?}: use 1 to 128 letters, digits, `.`, `_`, `+` or `-`");
    }
    let (digest, size) = hash(&binary)?;
    let gateway = Gateway::connect(kube, server, Some(&kube.namespace)).await?;
    let blob = Blob {
        digest: digest.clone(),
        size,
        name: binary.display().to_string(),
        source: Source::File(binary.clone()),
    };
    let upload = Upload {
        gateway: &gateway,
        blob: &blob,
    };
    let (sent, _) = upload.run(chunk_bytes.max(1), &Progress::default()).await?;
    eprintln!(
        "agent {version} ({arch}): {} uploaded of {}",
        human(sent),
        human(size)
    );
    eprintln!(
        "add to the Robot's spec:\n  agent: {{version: {version}, builds: [{{arch: {arch}, digest: {digest}}}]}}"
    );
    println!("{digest}");
    Ok(())
}

/// Digest and size of a regular file.
fn hash(binary: &Path) -> anyhow::Result<(String, u64)> {
    let meta =
        std::fs::metadata(binary).with_context(|| format!("cannot read {}", binary.display()))?;
    if !meta.is_file() {
        bail!("{} is not a regular file", binary.display());
    }
    files::hash_file(binary)
}
