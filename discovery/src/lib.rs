//! How LeKiwi agents are found on a LAN, shared by the agent (which advertises and serves
//! `/status`) and `kubectl lekiwi discover` (which browses and probes): the DNS-SD service type,
//! its TXT record keys, the instance naming, the `/status` document and the mDNS browser.
//!
//! An agent advertises one DNS-SD service: instance [`instance_name`] of the robot, host
//! `<instance>.local.` with every address of the machine's multicast interfaces (mdns-sd leaves
//! out loopback), SRV port = the status port, and the TXT keys in [`txt`]. Only those identity
//! facts go into TXT: they change rarely, so the records cached on the LAN stay valid; live
//! state is what `/status` ([`StatusSnapshot`]) is for.
//!
//! mdns-sd runs its own small thread and binds `0.0.0.0:5353` / `[::]:5353` with `SO_REUSEPORT`,
//! so it coexists with avahi-daemon and with another mdns-sd process on the same host; multicast
//! loop is on, which is how a browser on the same machine sees the advertisement. Loopback is
//! left out on purpose (mdns-sd's default): a host whose only interface is `lo` advertises
//! nothing, which is right for a robot, and tests need a multicast-capable interface such as
//! the container's `eth0`.

use std::time::Duration;

use lekiwi_protocol::{Release, Teleoperation};
use serde::{Deserialize, Serialize};

mod browse;

pub use browse::{Found, browse};

/// The DNS-SD service type agents advertise and `discover` browses for.
pub const SERVICE_TYPE: &str = "_lekiwi._tcp.local.";
/// How long to wait for the mDNS daemon to confirm a goodbye or its own exit; it answers in
/// milliseconds unless its thread is stuck, and then waiting longer would not help.
pub const DAEMON_REPLY_TIMEOUT: Duration = Duration::from_secs(1);
/// A DNS label holds at most 63 bytes.
const MAX_LABEL: usize = 63;

/// The TXT record keys of an agent's advertisement, written by the agent and read by
/// [`browse`]; renaming one breaks discovery of agents that run another version.
pub mod txt {
    /// The robot, `namespace/name` or `name`: what identifies it (the instance label may not).
    pub const ROBOT: &str = "robot";
    /// The agent's version.
    pub const AGENT_VERSION: &str = "agent_version";
    /// The release version the robot runs; empty when it runs none.
    pub const RELEASE: &str = "release";
    /// The gateway URL the agent connects to.
    pub const GATEWAY: &str = "gateway";
    /// The port of the status endpoint (also the SRV port).
    pub const STATUS_PORT: &str = "status_port";
}

/// Errors of mDNS browsing.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The mDNS daemon (its thread and sockets) could not start.
    #[error("cannot start the mDNS daemon: {0}")]
    StartDaemon(#[source] mdns_sd::Error),
    /// The daemon did not take the browse request.
    #[error("cannot browse for {SERVICE_TYPE}: {0}")]
    Browse(#[source] mdns_sd::Error),
}

/// `Result` with this crate's [`Error`] as the default error.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// What an agent knows about itself right now: served as `/status`, read by `discover`'s
/// probes, and the source of the mDNS TXT records.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "camelCase", default)]
pub struct StatusSnapshot {
    /// Robot, `namespace/name` or `name`.
    pub robot: String,
    /// Version of the agent binary that serves this.
    pub agent_version: String,
    /// Release the robot runs, if any.
    pub release: Option<Release>,
    /// Gateway URL the agent connects to.
    pub gateway: String,
    /// Whether the gateway connection is up.
    pub connected: bool,
    /// Latest teleoperation verdict; `None` until the first check.
    pub teleoperation: Option<Teleoperation>,
    /// Durable messages not yet acknowledged by the gateway.
    pub outbox_pending: u64,
    /// Latest heartbeat round trip, milliseconds.
    pub last_rtt_ms: Option<f64>,
    /// Bytes sent to the gateway since the start.
    pub bytes_sent: u64,
    /// Start of the agent, Unix milliseconds.
    pub started_at_ms: i64,
}

/// The DNS-safe instance (and host) label for a robot: `name-namespace` for `namespace/name`,
/// lowercase letters, digits and `-` only, at most 63 bytes.
///
/// Dots are not allowed: mdns-sd writes every `.` as a label boundary and does not escape it,
/// so `name.namespace` would turn into a different service type for other resolvers. The
/// mapping is not injective (`a-b/c` and `b/c-a` meet), which is why the TXT record `robot`,
/// not the instance name, identifies the robot. A name longer than a label is cut and
/// suffixed with a hash of the full name to stay distinct.
pub fn instance_name(robot: &str) -> String {
    let joined = match robot.split_once('/') {
        Some((namespace, name)) => format!("{name}-{namespace}"),
        None => robot.to_owned(),
    };
    let mut label = String::with_capacity(joined.len());
    for c in joined.chars() {
        let c = if c.is_ascii_alphanumeric() {
            c.to_ascii_lowercase()
        } else {
            '-'
        };
        // Runs of separators collapse into one, which also keeps `--` out of the label.
        if !(c == '-' && (label.is_empty() || label.ends_with('-'))) {
            label.push(c);
        }
    }
    while label.ends_with('-') {
        label.pop();
    }
    if label.is_empty() {
        label.push_str("lekiwi");
    }
    if label.len() > MAX_LABEL {
        let suffix = format!("-{:08x}", fnv1a(robot.as_bytes()));
        label.truncate(MAX_LABEL - suffix.len());
        while label.ends_with('-') {
            label.pop();
        }
        label.push_str(&suffix);
    }
    label
}

/// 32-bit FNV-1a: a stable hash (unlike `DefaultHasher`) for shortened instance names.
fn fnv1a(bytes: &[u8]) -> u32 {
    bytes.iter().fold(0x811c_9dc5, |hash, b| {
        (hash ^ u32::from(*b)).wrapping_mul(0x0100_0193)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_names_are_single_dns_labels() {
        assert_eq!(instance_name("lab/kiwi-01"), "kiwi-01-lab");
        assert_eq!(instance_name("kiwi-01"), "kiwi-01");
        assert_eq!(instance_name("Lab/Kiwi_01.a"), "kiwi-01-a-lab");
        assert_eq!(instance_name("/"), "lekiwi");
        assert_eq!(instance_name(""), "lekiwi");
        assert_eq!(instance_name("ns/--x--"), "x-ns");

        let long = format!("fleet/{}", "k".repeat(80));
        let other = format!("fleet/{}x", "k".repeat(80));
        let (a, b) = (instance_name(&long), instance_name(&other));
        assert_eq!(a.len(), MAX_LABEL);
        assert_ne!(a, b, "shortened names stay distinct");
        assert!(
            a.bytes()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'-')
        );
    }

    #[test]
    fn snapshot_json_is_camel_case_and_lenient() {
        let json = serde_json::to_value(StatusSnapshot::default()).unwrap();
        for key in ["agentVersion", "outboxPending", "lastRttMs", "startedAtMs"] {
            assert!(json.get(key).is_some(), "{key} in {json}");
        }
        let parsed: StatusSnapshot = serde_json::from_str(r#"{"robot":"x","future":1}"#).unwrap();
        assert_eq!(parsed.robot, "x");
    }
}
