//! Command-line flags of `lekiwi-operator`; every flag can also be set by an environment variable.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};

pub use lekiwi_fleet_api::config::{FleetApiConfig, GraphQlConfig};

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

    /// Address of the agent gateway: the robots' WebSocket `/v1/agent`, the release blob API,
    /// the events API and legacy `/v1/poll`; also the Fleet API and dashboard unless
    /// --api-addr serves them apart.
    #[arg(long, env = "LEKIWI_GATEWAY_ADDR", default_value = "0.0.0.0:8081")]
    pub gateway_addr: SocketAddr,

    /// Address of a listener of its own for the Fleet API (`/api/v1`, GraphQL) and the
    /// dashboard, with the same TLS as the gateway; the gateway address then serves neither,
    /// so the robots' port can be exposed without them. It also serves the release blob and
    /// events APIs, so people's tools need only this address. Unset: the gateway address
    /// serves everything.
    #[arg(long, env = "LEKIWI_API_ADDR")]
    pub api_addr: Option<SocketAddr>,

    /// This gateway's name: written to `Robot.status.gateway` and the name of its Lease
    /// (default: the identity).
    #[arg(long, env = "LEKIWI_GATEWAY_NAME")]
    pub gateway_name: Option<String>,

    /// PEM certificate chain for TLS on the gateway; with --tls-key, agents connect over wss://.
    #[arg(long, env = "LEKIWI_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,

    /// PEM private key for --tls-cert.
    #[arg(long, env = "LEKIWI_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,

    /// Seconds between checks of the --tls-cert and --tls-key files: when they change (a
    /// Secret volume updated, a certificate renewed) new connections get the new certificate
    /// and open ones stay; files that do not load keep the old one. 0: never reload.
    #[arg(long, env = "LEKIWI_TLS_RELOAD_SECONDS", default_value_t = 10)]
    pub tls_reload_seconds: u64,

    /// PEM certificate of the CA that signs --tls-cert, sent after it in every handshake:
    /// `lekiwi-agent join` takes the CA from there and checks it against its pin.
    #[arg(long, env = "LEKIWI_TLS_CA", requires = "tls_cert")]
    pub tls_ca: Option<PathBuf>,

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

    /// Heartbeat interval the gateway asks agents for.
    #[arg(long, env = "LEKIWI_HEARTBEAT_INTERVAL_SECONDS", default_value_t = 30)]
    pub heartbeat_interval_seconds: u64,

    /// Silent heartbeat intervals after which the gateway closes a session (robot Offline).
    #[arg(long, env = "LEKIWI_MISSED_HEARTBEATS", default_value_t = 3)]
    pub missed_heartbeats: u32,

    /// Refresh `lastHeartbeatTime` in Robot status at most this often when nothing changes: N
    /// robots cost N / period status writes a second. A robot switched by a rollout with
    /// `spec.analysis` is written once more, when its analysis window ends.
    #[arg(long, env = "LEKIWI_STATUS_REFRESH_SECONDS", default_value_t = 300)]
    pub status_refresh_seconds: u64,

    /// A legacy polling robot that has not polled for this long is Offline.
    #[arg(long, env = "LEKIWI_POLL_GRACE_SECONDS", default_value_t = 180)]
    pub poll_grace_seconds: u64,

    /// Most agent connections this gateway holds at once.
    #[arg(long, env = "LEKIWI_MAX_CONNECTIONS", default_value_t = 20_000)]
    pub max_connections: usize,

    /// Largest frame accepted from an agent, in bytes.
    #[arg(long, env = "LEKIWI_MAX_FRAME_BYTES", default_value_t = 256 * 1024)]
    pub max_frame_bytes: usize,

    /// Messages per second one agent may send, sustained.
    #[arg(long, env = "LEKIWI_AGENT_RATE", default_value_t = 20)]
    pub agent_rate: u32,

    /// Messages one agent may send at once.
    #[arg(long, env = "LEKIWI_AGENT_BURST", default_value_t = 40)]
    pub agent_burst: u32,

    /// Sessions one robot may open per minute, sustained (0: no limit). A robot's token that
    /// reconnects faster (a stolen token in a loop) gets 429 with `Retry-After` before the
    /// upgrade, so it cannot turn connects into status writes, controller work and Events.
    #[arg(long, env = "LEKIWI_SESSION_OPENS_PER_MINUTE", default_value_t = 6.0)]
    pub session_opens_per_minute: f64,

    /// Sessions one robot may open at once before that rate applies.
    #[arg(long, env = "LEKIWI_SESSION_OPEN_BURST", default_value_t = 10)]
    pub session_open_burst: u32,

    /// Enrollments (first connects with an enrollment token, a handful of API writes each) this
    /// gateway admits per second, sustained; beyond, an enrolling agent gets 503 with a
    /// `Retry-After` that spreads the refused ones over time at this rate (0: no limit).
    #[arg(long, env = "LEKIWI_ENROLL_RATE", default_value_t = 20.0)]
    pub enroll_rate: f64,

    /// Enrollments admitted at once before that rate applies.
    #[arg(long, env = "LEKIWI_ENROLL_BURST", default_value_t = 40)]
    pub enroll_burst: u32,

    /// Seconds an agent has to send `hello` after connecting.
    #[arg(long, env = "LEKIWI_HANDSHAKE_TIMEOUT_SECONDS", default_value_t = 10)]
    pub handshake_timeout_seconds: u64,

    /// Seconds one frame to an agent may take to be written; an agent that stops reading has
    /// its session closed after it and its connection slot freed.
    #[arg(long, env = "LEKIWI_SEND_TIMEOUT_SECONDS", default_value_t = 10)]
    pub send_timeout_seconds: u64,

    /// Seconds a client has to send a request's complete headers, counted from connecting (after
    /// TLS) or from the end of the previous response on a kept-alive connection: bounds slow
    /// headers and idle keep-alive connections alike (WebSocket sessions, once upgraded, keep
    /// their own handshake and heartbeat deadlines).
    #[arg(long, env = "LEKIWI_HEADER_TIMEOUT_SECONDS", default_value_t = 10)]
    pub header_timeout_seconds: u64,

    /// Seconds a client has to complete the TLS handshake.
    #[arg(
        long,
        env = "LEKIWI_TLS_HANDSHAKE_TIMEOUT_SECONDS",
        default_value_t = 10
    )]
    pub tls_handshake_timeout_seconds: u64,

    /// Largest request head (request line and headers) the gateway reads, in bytes (at least
    /// 8192); a longer one is answered 431 and the connection closed.
    #[arg(long, env = "LEKIWI_MAX_HEADER_BYTES", default_value_t = 16 * 1024)]
    pub max_header_bytes: usize,

    /// Connections one client address may hold before any of their requests is authenticated;
    /// more are closed at once (counted in `lekiwi_gateway_connections_dropped_total`).
    /// Authenticated connections do not count, so many robots behind one NAT address are
    /// limited only by --max-connections. 0: no limit.
    #[arg(
        long,
        env = "LEKIWI_MAX_UNAUTHENTICATED_PER_ADDRESS",
        default_value_t = 64
    )]
    pub max_unauthenticated_per_address: usize,

    /// Connections the gateway holds, in all, before any of their requests is authenticated;
    /// more are closed at once.
    #[arg(
        long,
        env = "LEKIWI_MAX_UNAUTHENTICATED_CONNECTIONS",
        default_value_t = 1024
    )]
    pub max_unauthenticated_connections: usize,

    /// Robot status writes per second from this gateway at start; the rate then adapts to the
    /// API server's answers within `--status-qps-min`..`--status-qps-max`, and returns to at
    /// least this once the API server has not slowed it for 30 s and nothing waits.
    #[arg(long, env = "LEKIWI_STATUS_QPS", default_value_t = 50.0)]
    pub status_qps: f64,

    /// Lowest rate of status writes the adaptive limit cuts to (writes per second).
    #[arg(long, env = "LEKIWI_STATUS_QPS_MIN", default_value_t = 20.0)]
    pub status_qps_min: f64,

    /// Highest rate of status writes the adaptive limit raises to (writes per second); set it
    /// to `--status-qps` for a fixed rate.
    #[arg(long, env = "LEKIWI_STATUS_QPS_MAX", default_value_t = 200.0)]
    pub status_qps_max: f64,

    /// A status write answered slower than this (milliseconds) is slow: a second in which more
    /// than a quarter of the answers were slow cuts the rate by a quarter (a 429, a 5xx or a
    /// timeout halves it).
    #[arg(long, env = "LEKIWI_STATUS_SLOW_MS", default_value_t = 1000)]
    pub status_slow_ms: u64,

    /// Robot status writes at once.
    #[arg(long, env = "LEKIWI_STATUS_BURST", default_value_t = 100)]
    pub status_burst: u32,

    /// Robot status writes in flight at most. A rate needs rate x latency writes in flight:
    /// 32 keeps 200 writes/s going up to 160 ms per answer; raise it for a large API server
    /// whose answers take longer, within its own limit on mutating requests in flight (200
    /// by default).
    #[arg(long, env = "LEKIWI_STATUS_CONCURRENCY", default_value_t = 32,
          value_parser = clap::value_parser!(u16).range(1..=1000))]
    pub status_concurrency: u16,

    /// API-server reads per second, sustained, that the gateway may make for requests its
    /// token cache cannot authenticate (a token minted a moment ago, or a guess); beyond it they
    /// are refused with 503. The HTTP API's TokenReviews of uncached tokens, and the reads of a
    /// robot's Robot when its blob download reaches a replica whose watch has not shown the
    /// release yet, have budgets of the same size. Status writes and Lease renewals have
    /// budgets of their own.
    #[arg(long, env = "LEKIWI_AUTH_LOOKUP_QPS", default_value_t = 1.0)]
    pub auth_lookup_qps: f64,

    /// Such reads at once.
    #[arg(long, env = "LEKIWI_AUTH_LOOKUP_BURST", default_value_t = 10)]
    pub auth_lookup_burst: u32,

    /// Seconds a read that found no matching token (or no release naming a robot's blob) is
    /// remembered (between this and twice this): the same robot or namespace costs no further
    /// read meanwhile.
    #[arg(long, env = "LEKIWI_AUTH_MISS_SECONDS", default_value_t = 5)]
    pub auth_miss_seconds: u64,

    /// The Fleet API's per-user budgets and GraphQL limits.
    #[command(flatten)]
    pub fleet_api: FleetApiConfig,

    /// Validity of the gateway's own Lease (renewed every third of it).
    #[arg(long, env = "LEKIWI_GATEWAY_LEASE_SECONDS", default_value_t = 15)]
    pub gateway_lease_seconds: u64,

    /// Directory of the release blob store (`sha256/<hex>` blobs, `uploads/` in progress); a
    /// PersistentVolume shared by the gateways in a cluster.
    #[arg(long, env = "LEKIWI_BLOB_DIR", default_value = "/var/lib/lekiwi/blobs")]
    pub blob_dir: PathBuf,

    /// Hours an interrupted blob upload is kept for resuming before it is deleted (checked at
    /// start and every hour).
    #[arg(long, env = "LEKIWI_STALE_UPLOAD_HOURS", default_value_t = 24)]
    pub stale_upload_hours: u64,

    /// Largest release blob the gateway accepts, in bytes.
    #[arg(long, env = "LEKIWI_MAX_BLOB_BYTES", default_value_t = 4 * 1024 * 1024 * 1024)]
    pub max_blob_bytes: u64,

    /// Releases of each namespace kept by garbage collection besides those in use: the newest
    /// this many pushed there. A release no Robot (desired, current, previous) and no
    /// RobotDeployment (release, rollback target) references, older than these, is removed
    /// with the blobs no other release lists.
    #[arg(long, env = "LEKIWI_RELEASE_RETENTION", default_value_t = 10)]
    pub release_retention: usize,

    /// Seconds between two garbage collections of the release blob store (one also follows
    /// each push); 0 turns collection off. With several replicas only the one holding the
    /// leader Lease collects.
    #[arg(long, env = "LEKIWI_RELEASE_GC_SECONDS", default_value_t = 300)]
    pub release_gc_seconds: u64,

    /// Seconds a release stays safe from garbage collection after a download of one of its
    /// blobs ended (a robot resuming a download or fetching its next file); one being read now
    /// always is.
    #[arg(long, env = "LEKIWI_BLOB_READ_GRACE_SECONDS", default_value_t = 300)]
    pub blob_read_grace_seconds: u64,

    /// Free space of the blob store's volume, in percent of its size, under which the gateway
    /// publishes a Warning Event (`BlobStoreNearlyFull`, on its own Lease).
    #[arg(long, env = "LEKIWI_BLOB_FREE_WARN_PERCENT", default_value_t = 10)]
    pub blob_free_warn_percent: u8,
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
            blob_dir: self.blob_dir.clone(),
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
        self.gateway_name.clone().unwrap_or_else(|| self.identity())
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
