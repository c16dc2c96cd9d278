//! The agent's mDNS advertisement: one DNS-SD service per robot, re-announced when its
//! identity changes and withdrawn with goodbye packets when dropped.

use lekiwi_discovery::{DAEMON_REPLY_TIMEOUT, SERVICE_TYPE, StatusSnapshot, instance_name, txt};
use mdns_sd::{ServiceDaemon, ServiceInfo};
use tracing::{debug, info};

/// Errors of the mDNS advertisement.
#[derive(Debug, thiserror::Error)]
pub enum AdvertiseError {
    /// The mDNS daemon (its thread and sockets) could not start.
    #[error("cannot start the mDNS daemon: {0}")]
    StartDaemon(#[source] mdns_sd::Error),
    /// The service description was rejected, e.g. a TXT key is invalid.
    #[error("invalid mDNS service {instance}: {source}")]
    ServiceInfo {
        instance: String,
        source: mdns_sd::Error,
    },
    /// The daemon did not take the registration.
    #[error("cannot register mDNS service {instance}: {source}")]
    Register {
        instance: String,
        source: mdns_sd::Error,
    },
}

type Result<T, E = AdvertiseError> = std::result::Result<T, E>;

/// The TXT records of a snapshot, in the order they are advertised.
fn txt_records(snapshot: &StatusSnapshot, port: u16) -> Vec<(&'static str, String)> {
    vec![
        (txt::ROBOT, snapshot.robot.clone()),
        (txt::AGENT_VERSION, snapshot.agent_version.clone()),
        (
            txt::RELEASE,
            snapshot
                .release
                .as_ref()
                .map(|r| r.version.clone())
                .unwrap_or_default(),
        ),
        (txt::GATEWAY, snapshot.gateway.clone()),
        (txt::STATUS_PORT, port.to_string()),
    ]
}

/// An mDNS advertisement of this agent, withdrawn (with goodbye packets) when dropped.
pub struct Advertiser {
    daemon: ServiceDaemon,
    port: u16,
    instance: String,
    fullname: String,
    txt: Vec<(&'static str, String)>,
}

impl Advertiser {
    /// Starts an mDNS daemon and advertises the robot of `snapshot` with the status `port`.
    ///
    /// The addresses are those of the machine's interfaces, kept current by mdns-sd; `port`
    /// is only reachable from the LAN if the status endpoint listens beyond loopback.
    pub fn start(snapshot: &StatusSnapshot, port: u16) -> Result<Advertiser> {
        let daemon = ServiceDaemon::new().map_err(AdvertiseError::StartDaemon)?;
        let instance = instance_name(&snapshot.robot);
        let advertiser = Advertiser {
            daemon,
            port,
            fullname: format!("{instance}.{SERVICE_TYPE}"),
            instance,
            txt: txt_records(snapshot, port),
        };
        // On failure the advertiser drops here, which shuts the daemon down again.
        advertiser.register()?;
        info!(
            instance = %advertiser.instance,
            robot = %snapshot.robot,
            port,
            "advertising over mDNS"
        );
        Ok(advertiser)
    }

    /// Re-announces the service if a TXT-relevant field (robot, agent version, release,
    /// gateway) changed; otherwise does nothing, so it can be called on every status change.
    pub fn update(&mut self, snapshot: &StatusSnapshot) -> Result<()> {
        let txt = txt_records(snapshot, self.port);
        if txt == self.txt {
            return Ok(());
        }
        let instance = instance_name(&snapshot.robot);
        if instance != self.instance {
            // A new name is a new service: withdraw the old one instead of leaving it to expire.
            self.unregister();
            self.fullname = format!("{instance}.{SERVICE_TYPE}");
            self.instance = instance;
        }
        self.txt = txt;
        // Registering the same name again makes mdns-sd announce the new records; receivers
        // replace the cached TXT because mDNS answers carry the cache-flush bit.
        self.register()?;
        debug!(instance = %self.instance, release = %self.txt[2].1, "mDNS advertisement updated");
        Ok(())
    }

    /// The instance label, e.g. `kiwi-01-lab`.
    pub fn instance(&self) -> &str {
        &self.instance
    }

    /// The full service name, e.g. `kiwi-01-lab._lekiwi._tcp.local.`.
    pub fn fullname(&self) -> &str {
        &self.fullname
    }

    fn register(&self) -> Result<()> {
        let host = format!("{}.local.", self.instance);
        let info = ServiceInfo::new(
            SERVICE_TYPE,
            &self.instance,
            &host,
            (),
            self.port,
            &self.txt[..],
        )
        .map_err(|source| AdvertiseError::ServiceInfo {
            instance: self.instance.clone(),
            source,
        })?
        .enable_addr_auto();
        self.daemon
            .register(info)
            .map_err(|source| AdvertiseError::Register {
                instance: self.instance.clone(),
                source,
            })
    }

    /// Sends the goodbye for the current name and waits briefly for the daemon to confirm.
    fn unregister(&self) {
        match self.daemon.unregister(&self.fullname) {
            Ok(done) => {
                if done.recv_timeout(DAEMON_REPLY_TIMEOUT).is_err() {
                    debug!(instance = %self.instance, "mDNS daemon did not confirm the unregistration");
                }
            }
            Err(error) => debug!(instance = %self.instance, %error, "mDNS unregistration failed"),
        }
    }
}

impl Drop for Advertiser {
    fn drop(&mut self) {
        self.unregister();
        match self.daemon.shutdown() {
            Ok(done) => {
                let _ = done.recv_timeout(DAEMON_REPLY_TIMEOUT);
            }
            Err(error) => debug!(%error, "mDNS daemon shutdown failed"),
        }
        info!(instance = %self.instance, "mDNS advertisement withdrawn");
    }
}

impl std::fmt::Debug for Advertiser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Advertiser")
            .field("fullname", &self.fullname)
            .field("port", &self.port)
            .field("txt", &self.txt)
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use lekiwi_protocol::Release;

    use super::*;

    #[test]
    fn txt_records_carry_identity_only() {
        let mut snapshot = StatusSnapshot {
            robot: "lab/kiwi".into(),
            agent_version: "1.2.3".into(),
            gateway: "wss://gw/v1/agent".into(),
            ..StatusSnapshot::default()
        };
        let txt = txt_records(&snapshot, 9477);
        assert_eq!(txt[2], ("release", String::new()));
        assert_eq!(txt[4], ("status_port", "9477".into()));
        snapshot.connected = true;
        snapshot.bytes_sent = 42;
        assert_eq!(
            txt_records(&snapshot, 9477),
            txt,
            "live state does not re-announce"
        );
        snapshot.release = Some(Release {
            version: "v2".into(),
            digest: "sha256:00".into(),
        });
        assert_eq!(txt_records(&snapshot, 9477)[2], ("release", "v2".into()));
    }
}
