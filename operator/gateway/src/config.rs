//! The gateway's section of `lekiwi-operator`'s flags ([`GatewayConfig`], flattened into the
//! binary's), and what a gateway runs with ([`Config`]): that section and the operator-wide
//! settings it shares.

use std::net::SocketAddr;
use std::path::PathBuf;

use clap::Args;
use lekiwi_fleet_api::config::FleetApiConfig;

/// The agent gateway's flags: its listeners, TLS, sessions, status writes and release blobs.
#[derive(Clone, Debug, Args)]
pub struct GatewayConfig {
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

/// What a gateway runs with.
#[derive(Clone, Debug)]
pub struct Config {
    /// Its own flags.
    pub flags: GatewayConfig,
    /// The operator's namespace, where the gateways' Leases live.
    pub namespace: String,
    /// The only namespace whose robots it serves, if set.
    pub watch_namespace: Option<String>,
    /// Its name (`--gateway-name`, else the replica's identity): written to
    /// `Robot.status.gateway` and the name of its Lease.
    pub name: String,
    /// A robot whose last recorded heartbeat is older than this many seconds is Offline.
    pub heartbeat_grace_seconds: u64,
    /// Days stored agent events are kept.
    pub retention_days: u64,
    /// The Fleet API's section, for the routes it serves.
    pub fleet_api: FleetApiConfig,
}
