//! Command-line flags of `lekiwi-operator`; every flag can also be set by an environment variable.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};

/// Log output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line, for log shippers.
    Json,
}

/// The LeKiwi fleet operator: reconciles Robot and RobotDeployment resources.
#[derive(Clone, Debug, Parser)]
#[command(name = "lekiwi-operator", version, about, long_about = None)]
pub struct Config {
    /// Kubeconfig file; without it, $KUBECONFIG, ~/.kube/config or the in-cluster service account.
    #[arg(long, env = "LEKIWI_KUBECONFIG")]
    pub kubeconfig: Option<PathBuf>,

    /// Kubeconfig context to use.
    #[arg(long, env = "LEKIWI_CONTEXT")]
    pub context: Option<String>,

    /// Namespace of the operator itself: its leader Lease and the gateways' Leases live here.
    #[arg(long, env = "POD_NAMESPACE", default_value = "lekiwi-system")]
    pub namespace: String,

    /// Only watch robots in this namespace (default: all namespaces).
    #[arg(long, env = "LEKIWI_WATCH_NAMESPACE")]
    pub watch_namespace: Option<String>,

    /// This replica's identity in leader election (default: host name and process id).
    #[arg(long, env = "POD_NAME")]
    pub identity: Option<String>,

    /// Install or upgrade the CRDs at start instead of refusing to start without them.
    #[arg(long, env = "LEKIWI_INSTALL_CRDS")]
    pub install_crds: bool,

    /// Address of the HTTP server for /metrics, /healthz and /readyz.
    #[arg(long, env = "LEKIWI_HTTP_ADDR", default_value = "0.0.0.0:8080")]
    pub http_addr: SocketAddr,

    /// Log format.
    #[arg(long, env = "LEKIWI_LOG_FORMAT", value_enum, default_value = "text")]
    pub log_format: LogFormat,

    /// Log filter in `RUST_LOG` syntax.
    #[arg(long, env = "RUST_LOG", default_value = "info,kube=warn")]
    pub log_level: String,

    /// Name of the Lease used for leader election.
    #[arg(long, env = "LEKIWI_LEADER_LEASE", default_value = "lekiwi-operator")]
    pub leader_lease: String,

    /// How long a leader's Lease stays valid without renewal; a standby takes over after it.
    #[arg(long, env = "LEKIWI_LEASE_DURATION_SECONDS", default_value_t = 15)]
    pub lease_duration_seconds: u64,

    /// How often candidates retry and the leader renews.
    #[arg(long, env = "LEKIWI_LEASE_RETRY_SECONDS", default_value_t = 2)]
    pub lease_retry_seconds: u64,

    /// A robot whose last recorded heartbeat is older than this is Offline. Must exceed the
    /// gateway's status refresh period (300 s by default).
    #[arg(long, env = "LEKIWI_HEARTBEAT_GRACE_SECONDS", default_value_t = 360)]
    pub heartbeat_grace_seconds: u64,

    /// Most reconciles running at once.
    #[arg(long, env = "LEKIWI_CONCURRENCY", default_value_t = 16)]
    pub concurrency: u16,
}

impl Config {
    /// Leader lease validity.
    pub fn lease_duration(&self) -> Duration {
        Duration::from_secs(self.lease_duration_seconds.max(1))
    }

    /// Leader retry and renew period.
    pub fn lease_retry(&self) -> Duration {
        Duration::from_secs(self.lease_retry_seconds.max(1))
    }

    /// The identity to hold the leader Lease with.
    pub fn identity(&self) -> String {
        self.identity.clone().unwrap_or_else(|| {
            let host = std::fs::read_to_string("/etc/hostname").unwrap_or_else(|_| "lekiwi".into());
            format!("{}-{}", host.trim(), std::process::id())
        })
    }
}
