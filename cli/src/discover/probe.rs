//! Probing status endpoints: `GET /status` of each target, many at once, until the deadline;
//! the targets given up front (`--probe`), or candidates as other methods (ARP, DHCP) find them.

use std::collections::BTreeSet;
use std::net::{IpAddr, SocketAddr};
use std::time::Duration;

use anyhow::{Context as _, bail};
use futures::StreamExt;
use futures::stream::FuturesUnordered;
use lekiwi_discovery::StatusSnapshot;
use tokio::sync::mpsc::UnboundedReceiver;
use tokio::time::Instant;

/// Probes in flight at once.
const PROBE_CONCURRENCY: usize = 256;
/// Time to establish a probe's TCP connection; a LAN host answers in well under this.
const PROBE_CONNECT_TIMEOUT: Duration = Duration::from_millis(300);
/// Most candidates one method may have probed, so a flood of addresses cannot run away.
const MAX_CANDIDATES: usize = 4096;

/// What a probe of one status endpoint found.
#[derive(Clone, Debug)]
pub struct Probed {
    /// The status endpoint that answered (`ip:port`).
    pub address: SocketAddr,
    /// Its `/status` document, which names the robot.
    pub status: StatusSnapshot,
    /// The method that found the address: `probe` (given), `arp`, `dhcp`.
    pub via: &'static str,
}

/// The HTTP client of the probes.
fn http_client(timeout: Duration) -> reqwest::Result<reqwest::Client> {
    reqwest::Client::builder()
        .no_proxy()
        .connect_timeout(PROBE_CONNECT_TIMEOUT)
        .timeout(timeout.min(Duration::from_secs(1)))
        .pool_max_idle_per_host(0)
        .build()
}

/// Probes every target until `deadline`; returns the agents that answered and warnings about
/// targets that were named one by one and did not (silence from most of a CIDR is normal).
pub(super) async fn probe_all(
    targets: &[SocketAddr],
    timeout: Duration,
    deadline: Instant,
) -> (Vec<Probed>, Vec<String>) {
    let mut warnings = Vec::new();
    if targets.is_empty() {
        return (Vec::new(), warnings);
    }
    let http = match http_client(timeout) {
        Ok(c) => c,
        Err(e) => {
            warnings.push(format!("probes unavailable: {e}"));
            return (Vec::new(), warnings);
        }
    };
    let single = targets.len() == 1;
    let mut results = futures::stream::iter(targets.iter().copied())
        .map(|addr| {
            let http = http.clone();
            async move { (addr, probe(&http, addr).await) }
        })
        .buffer_unordered(PROBE_CONCURRENCY);
    let mut found = Vec::new();
    let mut answered = 0usize;
    loop {
        match tokio::time::timeout_at(deadline, results.next()).await {
            Ok(Some((address, Ok(status)))) => {
                answered += 1;
                found.push(Probed {
                    address,
                    status,
                    via: "probe",
                });
            }
            Ok(Some((address, Err(e)))) => {
                answered += 1;
                if single {
                    warnings.push(format!("probe of {address}: {e:#}"));
                }
            }
            Ok(None) => break,
            Err(_) => {
                warnings.push(format!(
                    "probing stopped at the deadline: {answered} of {} addresses answered or failed",
                    targets.len()
                ));
                break;
            }
        }
    }
    (found, warnings)
}

/// Probes the status endpoint (`port`) of each candidate address as it comes, once each, until
/// `deadline` or until the candidates end and every probe is done; what answers was found
/// `via` the method that sent the candidates. Silence from a candidate is normal (not every
/// neighbour is a robot), so it is not reported.
pub(super) async fn confirm(
    mut candidates: UnboundedReceiver<IpAddr>,
    port: u16,
    via: &'static str,
    timeout: Duration,
    deadline: Instant,
) -> anyhow::Result<Vec<Probed>> {
    let http = http_client(timeout).context("probes unavailable")?;
    let mut seen = BTreeSet::new();
    let mut probes = FuturesUnordered::new();
    let mut open = true;
    let mut found = Vec::new();
    let stop = tokio::time::sleep_until(deadline);
    tokio::pin!(stop);
    loop {
        tokio::select! {
            () = &mut stop => break,
            ip = candidates.recv(), if open => match ip {
                Some(ip) if seen.len() < MAX_CANDIDATES && seen.insert(ip) => {
                    let address = SocketAddr::new(ip, port);
                    let http = &http;
                    probes.push(async move { (address, probe(http, address).await) });
                }
                Some(_) => {}
                None => open = false,
            },
            Some((address, answer)) = probes.next(), if !probes.is_empty() => {
                if let Ok(status) = answer {
                    found.push(Probed { address, status, via });
                }
            }
            else => break,
        }
    }
    Ok(found)
}

async fn probe(http: &reqwest::Client, addr: SocketAddr) -> anyhow::Result<StatusSnapshot> {
    let resp = http
        .get(format!("http://{addr}/status"))
        .send()
        .await
        .map_err(|e| anyhow::anyhow!("{}", crate::http_error(&e)))?;
    if !resp.status().is_success() {
        bail!("answered {}", resp.status());
    }
    let status: StatusSnapshot = resp
        .json()
        .await
        .context("not a LeKiwi agent status endpoint")?;
    if status.robot.is_empty() {
        bail!("not a LeKiwi agent status endpoint (no robot)");
    }
    Ok(status)
}
