//! Probing status endpoints: `GET /status` of each target, many at once, until the deadline.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context as _, bail};
use futures::StreamExt;
use lekiwi_discovery::StatusSnapshot;
use tokio::time::Instant;

/// Probes in flight at once.
const PROBE_CONCURRENCY: usize = 256;
/// Time to establish a probe's TCP connection; a LAN host answers in well under this.
const PROBE_CONNECT_TIMEOUT: Duration = Duration::from_millis(300);
/// What a probe of one status endpoint found.
#[derive(Clone, Debug)]
pub struct Probed {
    /// The status endpoint that answered (`ip:port`).
    pub address: SocketAddr,
    /// Its `/status` document, which names the robot.
    pub status: StatusSnapshot,
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
    let http = match reqwest::Client::builder()
        .no_proxy()
        .connect_timeout(PROBE_CONNECT_TIMEOUT)
        .timeout(timeout.min(Duration::from_secs(1)))
        .pool_max_idle_per_host(0)
        .build()
    {
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
                found.push(Probed { address, status });
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
