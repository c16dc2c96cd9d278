//! Metrics of the agent gateway (`lekiwi_gateway_*`): sessions, frames, status writes, polls,
//! blobs, and the opt-in per-robot series (`lekiwi_robot_*`).

use std::collections::HashMap;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};

use lekiwi_protocol::{Release, Vitals};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};

use super::{KindLabels, Registrar, Registry};

/// Labels of gateway status-queue series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct PriorityLabels {
    /// `gone`, `move`, `high` or `low`.
    pub priority: &'static str,
}

/// Labels of gateway status writes.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct WriteLabels {
    /// `gone`, `move`, `high` or `low`.
    pub priority: &'static str,
    /// `ok`, `error` (retried), `conflict` (the Robot kept changing while writing; retried),
    /// `gone`, `superseded` (a later session of another gateway holds the robot; not retried)
    /// or `refused` (invalid even as presence alone; not retried).
    pub result: &'static str,
}

/// Labels of the API server reviews the gateway makes for its HTTP API.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReviewLabels {
    /// `token_review` or `access_review`.
    pub kind: &'static str,
    /// `accepted`, `refused`, `throttled` (tokens), `allowed`, `denied` (access) or `error`.
    pub result: &'static str,
}

/// Labels of refused durable messages.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ReasonLabels {
    /// Why it was not stored: `quota_rows` or `quota_bytes`.
    pub reason: &'static str,
}

/// What the gateway exports.
/// Labels of `lekiwi_gateway_agent_updates_total`: the step and the agent version. The version
/// is one an administrator named in a Robot's `spec.agent` (the session's desired one), or
/// `other`: a robot's events cannot create series.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct AgentUpdateLabels {
    /// `sent`, `unavailable`, `unsupported`, `started`, `succeeded`, `failed`, `fallen_back`.
    pub kind: &'static str,
    /// The agent version of the step.
    pub version: String,
}

#[derive(Clone)]
pub struct GatewayMetrics {
    /// Agent connections open now.
    pub connections: Gauge,
    /// Sessions ended, by how (`closed`, `replaced`, `moved`, `heartbeat_timeout`, `error`, ...).
    pub sessions_ended: Family<KindLabels, Counter>,
    /// Upgrade requests refused, by reason.
    pub refused: Family<KindLabels, Counter>,
    /// API reads for requests the Secret cache could not authenticate, by kind
    /// (`robot_secret`, `enrollment_list`) and reads skipped (`remembered`, `throttled`).
    pub auth_lookups: Family<KindLabels, Counter>,
    /// Frames received, by message type.
    pub frames: Family<KindLabels, Counter>,
    /// Error frames sent, by code.
    pub errors: Family<KindLabels, Counter>,
    /// Durable messages acknowledged, `stored` or `replay`.
    pub durable: Family<KindLabels, Counter>,
    /// Durable messages refused and never stored, by reason (`quota_rows`, `quota_bytes`).
    pub events_refused: Family<ReasonLabels, Counter>,
    /// Agent update steps (`spec.agent`), by kind: `sent`, `unavailable`, `unsupported` (what
    /// the gateway did) and `started`, `succeeded`, `failed`, `fallen_back` (what agents
    /// reported).
    pub agent_updates: Family<AgentUpdateLabels, Counter>,
    /// Heartbeat round-trip time the agents report.
    pub heartbeat_rtt: Histogram,
    /// Robots waiting for a status write, by priority.
    pub status_queue: Family<PriorityLabels, Gauge>,
    /// Robots listed in the gateway Lease's claims annotation at its last renewal.
    pub claimed_robots: Gauge,
    /// How long the robot next in line for a status write has waited, seconds (held while it
    /// decays): what the gateway's Lease declares as its status lag.
    pub status_lag: Gauge<f64, AtomicU64>,
    /// Status writes per second the writer allows now (it adapts to the API server's answers).
    pub status_rate: Gauge<f64, AtomicU64>,
    /// Status writes, by priority and result.
    pub status_writes: Family<WriteLabels, Counter>,
    /// Status writes the API server refused because the Robot changed since the version they
    /// were fenced on (each is followed by a read of the Robot and a new try).
    pub status_write_conflicts: Counter,
    /// Legacy polls answered, `200` or `304`.
    pub polls: Family<KindLabels, Counter>,
    /// Blob bytes sent to robots and clients (no per-robot label: robots are unbounded).
    pub blob_bytes_served: Counter,
    /// Blob bytes received in uploads.
    pub blob_bytes_received: Counter,
    /// Blob upload requests, by outcome (`created`, `partial`, `exists`, `conflict`, ...).
    pub blob_uploads: Family<KindLabels, Counter>,
    /// Connections the gateway closed before any authenticated request, by why
    /// (`per_address_limit`, `unauthenticated_limit`, `tls_handshake`, `header_timeout`,
    /// `header_too_large`).
    pub connections_dropped: Family<KindLabels, Counter>,
    /// Reloads of the TLS certificate files, `reloaded` or `failed` (the old one kept).
    pub tls_reloads: Family<KindLabels, Counter>,
    /// The notAfter of the TLS certificate the gateway serves now, in Unix seconds.
    pub tls_certificate_expiry: Gauge,
    /// TokenReviews and SubjectAccessReviews made for the HTTP API, by kind and result.
    pub kube_reviews: Family<ReviewLabels, Counter>,
    /// Reviews answered from the gateway's cache instead, by kind.
    pub kube_review_cache_hits: Family<KindLabels, Counter>,
    /// Event store operations that failed, by operation (`write`, `open_session`,
    /// `close_session`).
    pub event_store_errors: Family<KindLabels, Counter>,
    /// Bytes of the blobs in the release blob store.
    pub blob_store_bytes: Gauge,
    /// Blobs in the release blob store.
    pub blob_store_blobs: Gauge,
    /// Releases recorded in the blob store, all namespaces together.
    pub blob_store_releases: Gauge,
    /// Free bytes of the blob store's volume.
    pub blob_volume_free_bytes: Gauge,
    /// Size of the blob store's volume in bytes.
    pub blob_volume_size_bytes: Gauge,
    /// Releases removed from the blob store, by how (`gc`, `delete`).
    pub releases_removed: Family<KindLabels, Counter>,
    /// Blob bytes garbage collection and deletions freed.
    pub blob_bytes_removed: Counter,
}

impl GatewayMetrics {
    /// Counts a failed event store operation.
    pub fn event_store_error(&self, operation: &'static str) {
        self.event_store_errors
            .get_or_create(&KindLabels { kind: operation })
            .inc();
    }

    // shape: a flat list, one entry per metric, read as the gateway's metrics catalogue.
    pub(crate) fn register(registry: &mut Registry) -> Self {
        let mut r = Registrar(registry);
        Self {
            connections: r.add("lekiwi_gateway_connections", "Agent connections open now"),
            sessions_ended: r.add(
                "lekiwi_gateway_sessions_ended",
                "Agent sessions ended, by how (moved: another gateway's later session took over)",
            ),
            refused: r.add(
                "lekiwi_gateway_refused",
                "Agent upgrade requests refused, by reason",
            ),
            auth_lookups: r.add(
                "lekiwi_gateway_auth_lookups",
                "API reads for requests the token cache could not authenticate, made or skipped, by kind",
            ),
            frames: r.add(
                "lekiwi_gateway_frames",
                "Frames received from agents, by message type",
            ),
            errors: r.add(
                "lekiwi_gateway_error_frames",
                "Error frames sent to agents, by code",
            ),
            durable: r.add(
                "lekiwi_gateway_durable_messages",
                "Durable agent messages acknowledged, stored or replay",
            ),
            agent_updates: r.add(
                "lekiwi_gateway_agent_updates",
                "Agent self-update steps, by kind (sent, unavailable, unsupported, started, succeeded, failed, fallen_back) and agent version (one that a Robot's spec.agent names, else other)",
            ),
            events_refused: r.add(
                "lekiwi_gateway_events_refused",
                "Durable agent messages refused and not stored, by reason (per-robot quota)",
            ),
            heartbeat_rtt: r.with(
                "lekiwi_gateway_heartbeat_rtt_seconds",
                "Heartbeat round-trip time as reported by agents",
                Histogram::new(exponential_buckets(0.0005, 2.0, 14)),
            ),
            status_queue: r.add(
                "lekiwi_gateway_status_queue",
                "Robots waiting for a status write, by priority",
            ),
            claimed_robots: r.add("lekiwi_gateway_claimed_robots", "Robots the Lease claims"),
            status_lag: r.add(
                "lekiwi_gateway_status_lag_seconds",
                "Wait of the robot next in line for a status write, as the Lease declares it",
            ),
            status_rate: r.add("lekiwi_gateway_status_rate", "Status writes/s allowed now"),
            status_writes: r.add(
                "lekiwi_gateway_status_writes",
                "Robot status writes, by priority and result",
            ),
            status_write_conflicts: r.add(
                "lekiwi_gateway_status_write_conflicts",
                "Status writes refused as the Robot changed since their version (each then reads it)",
            ),
            polls: r.add("lekiwi_gateway_polls", "Legacy polls answered, by code"),
            blob_bytes_served: r.add(
                "lekiwi_gateway_blob_bytes_served",
                "Release blob bytes sent to robots and clients",
            ),
            blob_bytes_received: r.add(
                "lekiwi_gateway_blob_bytes_received",
                "Release blob bytes received in uploads",
            ),
            blob_uploads: r.add(
                "lekiwi_gateway_blob_uploads",
                "Release blob upload requests, by outcome",
            ),
            connections_dropped: r.add(
                "lekiwi_gateway_connections_dropped",
                "Gateway connections closed before or without an authenticated request, by why",
            ),
            tls_reloads: r.add(
                "lekiwi_gateway_tls_reloads",
                "Reloads of the gateway's TLS certificate and key after their files changed, by result (reloaded, failed: the certificate loaded before is kept)",
            ),
            tls_certificate_expiry: r.add(
                "lekiwi_gateway_tls_certificate_expiry_timestamp_seconds",
                "Expiry (notAfter) of the TLS certificate the gateway serves to new connections, in Unix seconds, set at each load and reload",
            ),
            kube_reviews: r.add(
                "lekiwi_gateway_kube_reviews",
                "TokenReviews and SubjectAccessReviews made for the HTTP API, by kind and result",
            ),
            kube_review_cache_hits: r.add(
                "lekiwi_gateway_kube_review_cache_hits",
                "API server reviews answered from the gateway's cache, by kind",
            ),
            event_store_errors: r.add(
                "lekiwi_gateway_event_store_errors",
                "Event store operations that failed, by operation (write, open_session, close_session)",
            ),
            blob_store_bytes: r.add(
                "lekiwi_gateway_blob_store_bytes",
                "Bytes of the blobs in the release blob store",
            ),
            blob_store_blobs: r.add(
                "lekiwi_gateway_blob_store_blobs",
                "Blobs in the release blob store",
            ),
            blob_store_releases: r.add(
                "lekiwi_gateway_blob_store_releases",
                "Releases recorded in the blob store, all namespaces together",
            ),
            blob_volume_free_bytes: r.add(
                "lekiwi_gateway_blob_volume_free_bytes",
                "Free bytes of the blob store's volume",
            ),
            blob_volume_size_bytes: r.add(
                "lekiwi_gateway_blob_volume_size_bytes",
                "Size of the blob store's volume in bytes",
            ),
            releases_removed: r.add(
                "lekiwi_gateway_releases_removed",
                "Releases removed from the blob store, by how (gc, delete)",
            ),
            blob_bytes_removed: r.add(
                "lekiwi_gateway_blob_bytes_removed",
                "Blob bytes removed by garbage collection and release deletions",
            ),
        }
    }
}

/// Labels of per-robot series: one set per robot connected to this gateway.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RobotLabels {
    /// Namespace of the Robot.
    pub namespace: String,
    /// Robot name.
    pub robot: String,
}

/// Labels of the per-robot release series: one version per robot at a time.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RobotReleaseLabels {
    /// Namespace of the Robot.
    pub namespace: String,
    /// Robot name.
    pub robot: String,
    /// Release version the robot runs.
    pub version: String,
}

/// Per-robot gauges from heartbeats, behind `--per-robot-metrics`. Cost: about five series per
/// connected robot (a 10 000-robot fleet adds 50 000 series to every gateway's scrape), removed
/// when the robot disconnects; off by default.
#[derive(Clone)]
pub struct RobotMetrics {
    enabled: bool,
    /// CPU use, percent of all cores.
    pub cpu: Family<RobotLabels, Gauge<f64, AtomicU64>>,
    /// Memory in use, percent.
    pub memory: Family<RobotLabels, Gauge<f64, AtomicU64>>,
    /// SoC temperature.
    pub temperature: Family<RobotLabels, Gauge<f64, AtomicU64>>,
    /// 1 for the release version each robot runs.
    pub release: Family<RobotReleaseLabels, Gauge>,
    /// The version each robot's release series carries, to drop it when the version changes.
    versions: Arc<Mutex<HashMap<RobotLabels, String>>>,
}

impl RobotMetrics {
    pub(crate) fn register(registry: &mut Registry, enabled: bool) -> Self {
        let mut r = Registrar(registry);
        Self {
            enabled,
            cpu: r.add(
                "lekiwi_robot_cpu_percent",
                "CPU use of each connected robot, percent of all cores, from its last heartbeat \
                 (only with --per-robot-metrics; one series per connected robot)",
            ),
            memory: r.add(
                "lekiwi_robot_memory_percent",
                "Memory in use on each connected robot, percent, from its last heartbeat (only with \
                 --per-robot-metrics; one series per connected robot)",
            ),
            temperature: r.add(
                "lekiwi_robot_temperature_celsius",
                "SoC temperature of each connected robot, from its last heartbeat (only with \
                 --per-robot-metrics; one series per connected robot)",
            ),
            release: r.add(
                "lekiwi_robot_release_info",
                "1 for the release version each connected robot runs (only with \
                 --per-robot-metrics; one series per connected robot, its version label changes \
                 with each update)",
            ),
            versions: Arc::default(),
        }
    }

    /// Records a heartbeat's vitals and the release the robot runs; nothing when disabled.
    pub fn record(&self, namespace: &str, robot: &str, vitals: &Vitals, release: Option<&Release>) {
        if !self.enabled {
            return;
        }
        let labels = RobotLabels {
            namespace: namespace.to_owned(),
            robot: robot.to_owned(),
        };
        for (family, value) in [
            (&self.cpu, vitals.cpu_percent),
            (&self.memory, vitals.memory_percent),
            (&self.temperature, vitals.temperature_c),
        ] {
            match value.filter(|v| v.is_finite()) {
                Some(v) => {
                    family.get_or_create(&labels).set(v);
                }
                None => {
                    family.remove(&labels);
                }
            }
        }
        let mut versions = self.versions.lock().unwrap_or_else(|p| p.into_inner());
        let new = release.map(|r| r.version.clone());
        if versions.get(&labels) == new.as_ref() {
            return;
        }
        if let Some(old) = versions.remove(&labels) {
            self.release.remove(&release_labels(&labels, old));
        }
        if let Some(version) = new {
            self.release
                .get_or_create(&release_labels(&labels, version.clone()))
                .set(1);
            versions.insert(labels, version);
        }
    }

    /// Drops every series of a robot that disconnected.
    pub fn forget(&self, namespace: &str, robot: &str) {
        if !self.enabled {
            return;
        }
        let labels = RobotLabels {
            namespace: namespace.to_owned(),
            robot: robot.to_owned(),
        };
        self.cpu.remove(&labels);
        self.memory.remove(&labels);
        self.temperature.remove(&labels);
        let old = self
            .versions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(&labels);
        if let Some(old) = old {
            self.release.remove(&release_labels(&labels, old));
        }
    }
}

fn release_labels(robot: &RobotLabels, version: String) -> RobotReleaseLabels {
    RobotReleaseLabels {
        namespace: robot.namespace.clone(),
        robot: robot.robot.clone(),
        version,
    }
}

#[cfg(test)]
mod robot_tests {
    use super::*;
    use crate::Metrics;

    #[test]
    fn per_robot_series_follow_heartbeats_and_disconnects() {
        let release = |v: &str| Release {
            version: v.into(),
            digest: "sha256:00".into(),
        };
        let vitals = Vitals {
            cpu_percent: Some(12.5),
            temperature_c: Some(51.0),
            ..Vitals::default()
        };
        let off = Metrics::default();
        off.per_robot
            .record("ns", "r2d2", &vitals, Some(&release("1.0.0")));
        assert!(!off.encode().contains("r2d2\""), "disabled by default");

        let m = Metrics::new(true);
        m.per_robot
            .record("ns", "r2d2", &vitals, Some(&release("1.0.0")));
        m.per_robot
            .record("ns", "r2d2", &vitals, Some(&release("2.0.0")));
        let text = m.encode();
        assert!(
            text.contains("lekiwi_robot_cpu_percent{namespace=\"ns\",robot=\"r2d2\"} 12.5"),
            "{text}"
        );
        assert!(
            text.contains("lekiwi_robot_temperature_celsius{namespace=\"ns\",robot=\"r2d2\"} 51.0"),
            "{text}"
        );
        assert!(
            !text.contains("lekiwi_robot_memory_percent{"),
            "no reading, no series: {text}"
        );
        assert!(
            text.contains(
                "lekiwi_robot_release_info{namespace=\"ns\",robot=\"r2d2\",version=\"2.0.0\"} 1"
            ),
            "{text}"
        );
        assert!(
            !text.contains("version=\"1.0.0\""),
            "the old version's series is gone: {text}"
        );
        m.per_robot.forget("ns", "r2d2");
        assert!(!m.encode().contains("r2d2\""), "{}", m.encode());
    }
}
