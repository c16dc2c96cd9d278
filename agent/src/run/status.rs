//! What the agent publishes locally: the JSON status endpoint and the mDNS advertisement, both
//! fed from one `watch` channel of [`StatusSnapshot`]s.

use std::time::Duration;

use tokio::sync::watch;
use tracing::{info, warn};

use super::{Agent, Error};
use crate::config::Config;
use crate::discovery::{Advertiser, StatusSnapshot};

/// The status endpoint's numbers are refreshed at most this often (and on (dis)connection).
pub(super) const STATUS_EVERY: Duration = Duration::from_secs(1);

/// Starts the status endpoint (unless turned off) and the mDNS advertisement (if enabled; a
/// failure only costs the advertisement). Returns the sender that feeds both.
pub(super) async fn start(
    config: &Config,
    snapshot: StatusSnapshot,
) -> Result<(watch::Sender<StatusSnapshot>, Option<Advertiser>), Error> {
    let (status, status_rx) = watch::channel(snapshot.clone());
    let mut status_port = 0;
    if let Some(addr) = config.status_addr() {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|source| Error::StatusListen { addr, source })?;
        status_port = listener.local_addr().map(|a| a.port()).unwrap_or_default();
        info!(addr = %listener.local_addr().map(|a| a.to_string()).unwrap_or_default(), "status endpoint listening");
        tokio::spawn(crate::discovery::serve_status(listener, status_rx));
    }
    let advertiser = if config.mdns {
        match Advertiser::start(&snapshot, status_port) {
            Ok(a) => Some(a),
            Err(e) => {
                warn!(error = %e, "mDNS advertisement unavailable; going on without it");
                None
            }
        }
    } else {
        None
    };
    Ok((status, advertiser))
}

impl Agent {
    /// Refreshes the endpoint's live numbers: connection, teleoperation, outbox depth, traffic.
    pub(super) fn publish_status(&mut self, connected: bool) {
        let depth = self.outbox.depth().map(|d| d.messages).unwrap_or_default();
        let teleop = self.teleop.to_wire();
        let (bytes, rtt) = (self.bytes_sent, self.last_rtt_ms);
        self.status.send_modify(|s| {
            s.connected = connected;
            s.teleoperation = Some(teleop);
            s.outbox_pending = depth;
            s.bytes_sent = bytes;
            s.last_rtt_ms = rtt;
        });
    }

    /// Publishes the release now running, on the endpoint and in the advertisement's TXT record.
    pub(super) fn publish_release(&mut self) {
        let release = self.current_release.clone();
        self.status.send_modify(|s| s.release = release);
        if let Some(adv) = self.advertiser.as_mut() {
            let snapshot = self.status.borrow().clone();
            if let Err(e) = adv.update(&snapshot) {
                warn!(error = %e, "cannot update the mDNS advertisement");
            }
        }
    }
}
