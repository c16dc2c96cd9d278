//! The mDNS browser: collects the agents that answer for [`SERVICE_TYPE`] within a time limit.

use std::collections::BTreeMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

use mdns_sd::{ServiceDaemon, ServiceEvent, ServiceInfo};
use serde::{Deserialize, Serialize};

use crate::{DAEMON_REPLY_TIMEOUT, Error, Result, SERVICE_TYPE, txt};

/// An agent found on the network by [`browse`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Found {
    /// Instance label, e.g. `kiwi-01-lab`.
    pub instance: String,
    /// Robot, `namespace/name` or `name` (TXT `robot`).
    pub robot: String,
    /// Agent version (TXT `agent_version`).
    pub agent_version: String,
    /// Release version, if the robot runs one (TXT `release`).
    pub release: Option<String>,
    /// Gateway URL (TXT `gateway`).
    pub gateway: String,
    /// The robot's addresses, sorted.
    pub addresses: Vec<IpAddr>,
    /// Port of its status endpoint (the SRV port).
    pub port: u16,
}

impl Found {
    fn from_info(info: &ServiceInfo) -> Found {
        let value = |key: &str| {
            info.get_property_val_str(key)
                .unwrap_or_default()
                .to_owned()
        };
        let mut addresses: Vec<IpAddr> = info.get_addresses().iter().copied().collect();
        addresses.sort();
        let release = value(txt::RELEASE);
        Found {
            instance: instance_of(info.get_fullname()).to_owned(),
            robot: value(txt::ROBOT),
            agent_version: value(txt::AGENT_VERSION),
            release: (!release.is_empty()).then_some(release),
            gateway: value(txt::GATEWAY),
            addresses,
            port: info.get_port(),
        }
    }
}

/// The instance part of a full service name.
fn instance_of(fullname: &str) -> &str {
    fullname
        .strip_suffix(SERVICE_TYPE)
        .and_then(|s| s.strip_suffix('.'))
        .unwrap_or(fullname)
}

/// Browses for `_lekiwi._tcp.local.` until `timeout` has passed (blocking) and returns the
/// agents resolved in that time, one per instance with its latest records, sorted by instance.
pub fn browse(timeout: Duration) -> Result<Vec<Found>> {
    let daemon = ServiceDaemon::new().map_err(Error::StartDaemon)?;
    let found = collect(&daemon, timeout);
    let _ = daemon.stop_browse(SERVICE_TYPE);
    if let Ok(done) = daemon.shutdown() {
        let _ = done.recv_timeout(DAEMON_REPLY_TIMEOUT);
    }
    Ok(found?.into_values().collect())
}

fn collect(daemon: &ServiceDaemon, timeout: Duration) -> Result<BTreeMap<String, Found>> {
    let events = daemon.browse(SERVICE_TYPE).map_err(Error::Browse)?;
    let deadline = Instant::now() + timeout;
    let mut found = BTreeMap::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break;
        }
        match events.recv_timeout(left) {
            Ok(ServiceEvent::ServiceResolved(info)) => {
                let agent = Found::from_info(&info);
                found.insert(agent.instance.clone(), agent);
            }
            Ok(ServiceEvent::ServiceRemoved(_, fullname)) => {
                found.remove(instance_of(&fullname));
            }
            Ok(_) => {}
            // Timed out, or the daemon is gone: either way nothing more will come.
            Err(_) => break,
        }
    }
    Ok(found)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_of_strips_the_service_type() {
        assert_eq!(instance_of("kiwi-lab._lekiwi._tcp.local."), "kiwi-lab");
        assert_eq!(instance_of("odd"), "odd");
    }
}
