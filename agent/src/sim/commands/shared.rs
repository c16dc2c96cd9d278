//! What the simulated robots share for their commands: one blob client per gateway (with as
//! many idle connections as downloads may run), the bound on downloads in flight, the parsed
//! manifests (each robot still downloads the bytes of those it lacks), and the counters.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use lekiwi_protocol::Release;
use lekiwi_protocol::release::ReleaseManifest;
use tokio::sync::Semaphore;

use super::args::CommandArgs;
use crate::release::{BlobClient, GatewayAccess, Phase};

/// A release whose manifest some robot downloaded and verified.
#[derive(Debug)]
pub(in crate::sim) struct Known {
    /// Its version (the manifest's) and digest.
    pub(in crate::sim) release: Release,
    /// Its manifest.
    pub(in crate::sim) manifest: ReleaseManifest,
}

/// See the module docs.
pub(in crate::sim) struct Shared {
    /// The flags.
    pub(in crate::sim) args: CommandArgs,
    /// A blob client per `--gateway` URL, in the same order.
    clients: Vec<BlobClient>,
    /// Downloads in flight (`--max-downloads`).
    pub(in crate::sim) permits: Semaphore,
    /// Manifests by digest.
    manifests: Mutex<HashMap<String, Arc<Known>>>,
    /// The release every robot starts with (`--release-version`): kept "on disk", no files.
    pub(in crate::sim) factory: Option<Arc<Known>>,
    /// What the robots did.
    pub(in crate::sim) counters: Counters,
}

impl Shared {
    /// The shared parts for robots of `gateways`, trusting `ca_file` for `wss://`, starting on
    /// release `factory_version` (none when empty).
    pub(in crate::sim) fn new(
        args: CommandArgs,
        gateways: &[String],
        ca_file: Option<&std::path::Path>,
        factory_version: &str,
    ) -> anyhow::Result<Self> {
        args.validate().map_err(anyhow::Error::msg)?;
        let clients = gateways
            .iter()
            .map(|url| {
                let access = GatewayAccess::from_gateway_url(url, "", "", ca_file.map(Into::into))?;
                Ok(BlobClient::new(access)?.with_pool(args.max_downloads))
            })
            .collect::<Result<Vec<_>, crate::release::Error>>()?;
        let factory = (!factory_version.is_empty()).then(|| {
            Arc::new(Known {
                release: Release {
                    version: factory_version.to_owned(),
                    digest: format!("sha256:{}", "0".repeat(64)),
                },
                manifest: ReleaseManifest::new(factory_version, Vec::new()),
            })
        });
        Ok(Self {
            permits: Semaphore::new(args.max_downloads),
            args,
            clients,
            manifests: Mutex::default(),
            factory,
            counters: Counters::default(),
        })
    }

    /// The blob client of gateway `index`.
    pub(in crate::sim) fn client(&self, index: usize) -> &BlobClient {
        &self.clients[index % self.clients.len()]
    }

    /// The manifest `digest` if some robot fetched it already.
    pub(in crate::sim) fn cached(&self, digest: &str) -> Option<Arc<Known>> {
        lock(&self.manifests).get(digest).cloned()
    }

    /// The release of manifest `bytes`, which hash to `digest`: parsed once for the fleet.
    pub(in crate::sim) fn known(
        &self,
        digest: &str,
        bytes: &[u8],
    ) -> Result<Arc<Known>, lekiwi_protocol::release::ManifestError> {
        if let Some(k) = self.cached(digest) {
            return Ok(k);
        }
        let manifest = ReleaseManifest::parse(bytes)?;
        let known = Arc::new(Known {
            release: Release {
                version: manifest.version.clone(),
                digest: digest.to_owned(),
            },
            manifest,
        });
        lock(&self.manifests).insert(digest.to_owned(), known.clone());
        Ok(known)
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Counters of the robots' commands.
#[derive(Default)]
pub(in crate::sim) struct Counters {
    commands: AtomicU64,
    done: AtomicU64,
    failed: AtomicU64,
    rolled_back: AtomicU64,
    cancelled: AtomicU64,
    agent_updates: AtomicU64,
    agent_updates_failed: AtomicU64,
    bytes: AtomicU64,
}

impl Counters {
    /// A command arrived.
    pub(in crate::sim) fn command(&self) {
        self.commands.fetch_add(1, Ordering::Relaxed);
    }

    /// A deploy or rollback ended with `phase`.
    pub(in crate::sim) fn ended(&self, phase: Phase) {
        let counter = match phase {
            Phase::Done => &self.done,
            Phase::Failed => &self.failed,
            Phase::RolledBack => &self.rolled_back,
            Phase::Cancelled => &self.cancelled,
            _ => return,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// An agent update switched (`true`) or failed.
    pub(in crate::sim) fn agent_update(&self, switched: bool) {
        let counter = if switched {
            &self.agent_updates
        } else {
            &self.agent_updates_failed
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Blob bytes received.
    pub(in crate::sim) fn bytes(&self, n: u64) {
        self.bytes.fetch_add(n, Ordering::Relaxed);
    }

    /// The counts so far.
    pub(in crate::sim) fn summary(&self) -> CommandSummary {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        CommandSummary {
            commands: get(&self.commands),
            deploys_done: get(&self.done),
            deploys_failed: get(&self.failed),
            deploys_rolled_back: get(&self.rolled_back),
            deploys_cancelled: get(&self.cancelled),
            agent_updates: get(&self.agent_updates),
            agent_updates_failed: get(&self.agent_updates_failed),
            bytes_downloaded: get(&self.bytes),
        }
    }
}

/// What the robots did with commands, in the run's summary.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct CommandSummary {
    /// Commands received (`deploy`, `rollback`, `cancel`, `update_agent`).
    pub commands: u64,
    /// Deploys and rollbacks that ended `done`.
    pub deploys_done: u64,
    /// Deploys and rollbacks that ended `failed` (nothing switched).
    pub deploys_failed: u64,
    /// Deploys that switched, failed their health check and switched back.
    pub deploys_rolled_back: u64,
    /// Deploys a `cancel` stopped before their switch.
    pub deploys_cancelled: u64,
    /// Agent updates that switched to the new build.
    pub agent_updates: u64,
    /// Agent updates that failed (nothing switched).
    pub agent_updates_failed: u64,
    /// Blob bytes received (manifests, release files, agent builds), all discarded.
    pub bytes_downloaded: u64,
}

impl std::fmt::Display for CommandSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "deploys done {} failed {} rolled back {} cancelled {}  agent updates {}  downloaded {:.1} MB",
            self.deploys_done,
            self.deploys_failed,
            self.deploys_rolled_back,
            self.deploys_cancelled,
            self.agent_updates,
            self.bytes_downloaded as f64 / 1e6,
        )
    }
}
