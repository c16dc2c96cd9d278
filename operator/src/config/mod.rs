//! Command-line flags of `lekiwi-operator`; every flag can also be set by an environment variable.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};

pub use lekiwi_fleet_api::config::{FleetApiConfig, GraphQlConfig};
pub use lekiwi_gateway::config::GatewayConfig;

/// Log output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LogFormat {
    /// Human-readable lines.
    Text,
    /// One JSON object per line, for log shippers.
    Json,
}

/// Which parts of the operator this process runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Role {
    /// Controllers (leader-elected) and the gateway.
    All,
    /// Only the controllers.
    Controller,
    /// Only the agent gateway (scales apart from the controllers; no leader election).
    Gateway,
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

    /// This replica's identity in leader election (default: host name and process id); also in
    /// its API requests' User-Agent: lekiwi-operator/<version> (<role>; <identity>).
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

    /// A gateway whose status writes run late (the API server takes fewer writes than its
    /// robots' refreshes need) declares by how much on its Lease; the heartbeat grace of the
    /// robots it holds grows by that much, but by at most this many seconds, so a gateway that
    /// cannot write at all does not keep its robots Online for ever.
    #[arg(long, env = "LEKIWI_MAX_STATUS_LAG_SECONDS", default_value_t = 900)]
    pub max_status_lag_seconds: u64,

    /// Most reconciles running at once.
    #[arg(long, env = "LEKIWI_CONCURRENCY", default_value_t = 16)]
    pub concurrency: u16,

    /// What this process runs.
    #[arg(long, env = "LEKIWI_ROLE", value_enum, default_value = "all")]
    pub role: Role,

    /// The agent gateway's flags: its listeners, TLS, sessions, status writes and release blobs.
    #[command(flatten)]
    pub gateway: GatewayConfig,

    /// Event store: `sqlite://FILE` (embedded default) or `postgres://...`.
    #[arg(
        long,
        env = "LEKIWI_STORE_URL",
        default_value = "sqlite://lekiwi-events.db"
    )]
    pub store_url: String,

    /// Agent events, telemetry and connection history older than this are deleted.
    #[arg(long, env = "LEKIWI_RETENTION_DAYS", default_value_t = 30)]
    pub retention_days: u64,

    /// Most rows (events plus telemetry samples) one robot may keep in the event store within
    /// the retention window; past it, its durable messages are refused with `quota_exceeded`
    /// and not stored. The default holds the reference agent's worst case at its default
    /// telemetry intervals (about 0.85 samples/s) for the default 30 days. 0: no limit.
    #[arg(long, env = "LEKIWI_ROBOT_QUOTA_ROWS", default_value_t = 2_500_000)]
    pub robot_quota_rows: u64,

    /// Most bytes (event kind, severity, message and data; 16 bytes plus the metric name per
    /// sample) one robot may keep in the event store within the retention window. 0: no limit.
    #[arg(long, env = "LEKIWI_ROBOT_QUOTA_BYTES", default_value_t = 256 * 1024 * 1024)]
    pub robot_quota_bytes: u64,

    /// Export per-robot gauges from heartbeats (`lekiwi_robot_cpu_percent`, `_memory_percent`,
    /// `_temperature_celsius`, `_release_info`, labelled by namespace and robot): about five
    /// series per connected robot, dropped on disconnect. For fleets whose Prometheus can afford
    /// that.
    #[arg(long, env = "LEKIWI_PER_ROBOT_METRICS")]
    pub per_robot_metrics: bool,

    /// The Fleet API's per-user budgets and GraphQL limits.
    #[command(flatten)]
    pub fleet_api: FleetApiConfig,
}

impl Config {
    /// The per-robot event store quota of `--robot-quota-rows` and `--robot-quota-bytes`.
    pub fn robot_quota(&self) -> lekiwi_event_store::Quota {
        let limit = |n: u64| if n == 0 { u64::MAX } else { n };
        lekiwi_event_store::Quota {
            rows: limit(self.robot_quota_rows),
            bytes: limit(self.robot_quota_bytes),
        }
    }

    /// The controllers' section of these flags.
    pub fn controller_settings(&self) -> lekiwi_controllers::Settings {
        lekiwi_controllers::Settings {
            namespace: self.namespace.clone(),
            watch_namespace: self.watch_namespace.clone(),
            leader_lease: self.leader_lease.clone(),
            heartbeat_grace_seconds: self.heartbeat_grace_seconds,
            max_status_lag_seconds: self.max_status_lag_seconds,
            concurrency: self.concurrency,
            blob_dir: self.gateway.blob_dir.clone(),
        }
    }

    /// Leader lease validity.
    pub fn lease_duration(&self) -> Duration {
        Duration::from_secs(self.lease_duration_seconds.max(1))
    }

    /// Leader retry and renew period.
    pub fn lease_retry(&self) -> Duration {
        Duration::from_secs(self.lease_retry_seconds.max(1))
    }

    /// The gateway's name.
    pub fn gateway_name(&self) -> String {
        self.gateway
            .gateway_name
            .clone()
            .unwrap_or_else(|| self.identity())
    }

    /// What the gateway runs with: its section of these flags and the settings it shares.
    pub fn gateway_settings(&self) -> lekiwi_gateway::config::Config {
        lekiwi_gateway::config::Config {
            flags: self.gateway.clone(),
            namespace: self.namespace.clone(),
            watch_namespace: self.watch_namespace.clone(),
            name: self.gateway_name(),
            heartbeat_grace_seconds: self.heartbeat_grace_seconds,
            retention_days: self.retention_days,
            fleet_api: self.fleet_api.clone(),
        }
    }

    /// Whether this process runs the controllers.
    pub fn runs_controllers(&self) -> bool {
        matches!(self.role, Role::All | Role::Controller)
    }

    /// Whether this process runs the gateway.
    pub fn runs_gateway(&self) -> bool {
        matches!(self.role, Role::All | Role::Gateway)
    }

    /// The identity to hold the leader Lease with.
    pub fn identity(&self) -> String {
        self.identity.clone().unwrap_or_else(|| {
            let host = std::fs::read_to_string("/etc/hostname").unwrap_or_else(|_| "lekiwi".into());
            format!("{}-{}", host.trim(), std::process::id())
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every flag can also be set by an environment variable (the book's generated reference
    /// lists both).
    #[test]
    fn every_flag_has_an_environment_variable() {
        use clap::CommandFactory;
        for arg in Config::command().get_arguments() {
            if let Some(long) = arg.get_long() {
                assert!(
                    arg.get_env().is_some(),
                    "--{long} has no environment variable"
                );
            }
        }
    }
}
