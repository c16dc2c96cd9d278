//! The ARP and DHCP methods of `discover`: each gathers candidate addresses (from the kernel,
//! a lease file, raw frames read on threads of their own) and confirms them by their status
//! endpoint as they come, until the deadline. Nothing here fails the command: what goes wrong
//! becomes a warning naming the method, and the rest of the method still runs.

use std::net::IpAddr;
use std::path::PathBuf;
use std::time::Duration;

use tokio::sync::mpsc::{UnboundedSender, unbounded_channel};
use tokio::time::Instant;

use super::probe::{Probed, confirm};
use super::raw;
use super::{arp, dhcp, leases};

/// Time before the deadline at which raw sweeps and listening stop, left to confirm the last
/// candidates (a status probe on a LAN takes a few milliseconds); at most a quarter of the
/// window, so a short window still reads replies.
const CONFIRM_MARGIN: Duration = Duration::from_millis(150);
/// Unreadable lines of a lease file reported one by one; the rest are counted.
const MAX_LINE_ERRORS: usize = 3;

/// What the ARP and DHCP methods are to do.
#[derive(Clone, Debug, Default)]
pub struct Plan {
    /// Port of the status endpoints.
    pub port: u16,
    /// Time one probe may take.
    pub timeout: Duration,
    /// Whether to run the ARP method.
    pub arp: bool,
    /// Interfaces the ARP method reads and sweeps (all suitable ones when empty).
    pub arp_interfaces: Vec<String>,
    /// Lease files to read.
    pub lease_files: Vec<PathBuf>,
    /// Interfaces to listen on for DHCP traffic.
    pub dhcp_interfaces: Vec<String>,
}

/// Runs the ARP and DHCP methods that `plan` asks for, at once, until `deadline`.
pub async fn run(plan: &Plan, deadline: Instant) -> (Vec<Probed>, Vec<String>) {
    let arp = async {
        if plan.arp {
            arp(plan, deadline).await
        } else {
            Default::default()
        }
    };
    let dhcp = async {
        if plan.lease_files.is_empty() && plan.dhcp_interfaces.is_empty() {
            Default::default()
        } else {
            dhcp(plan, deadline).await
        }
    };
    let ((mut found, mut warnings), (more, more_warnings)) = tokio::join!(arp, dhcp);
    found.extend(more);
    warnings.extend(more_warnings);
    (found, warnings)
}

/// ARP: the neighbour table, then (with CAP_NET_RAW) a sweep of each interface's subnets,
/// every address that answers confirmed by its status endpoint.
pub async fn arp(plan: &Plan, deadline: Instant) -> (Vec<Probed>, Vec<String>) {
    let (tx, rx) = unbounded_channel();
    let (errors_tx, mut errors) = unbounded_channel();
    let mut warnings = Vec::new();
    match arp::neighbours(&plan.arp_interfaces) {
        Ok(ips) => ips.into_iter().for_each(|ip| {
            let _ = tx.send(IpAddr::V4(ip));
        }),
        Err(e) => warnings.push(format!("arp: {e:#}")),
    }
    let stop = raw_stop(plan, deadline);
    match raw::interfaces(&plan.arp_interfaces) {
        Ok(interfaces) => {
            let (sweeps, cut) = arp::plan(&interfaces);
            warnings.extend(cut);
            for sweep in sweeps {
                let name = format!("sweep of {}", sweep.interface.name);
                spawn_raw(name, &tx, &errors_tx, move |tx| {
                    arp::sweep(&sweep, stop, tx)
                });
            }
        }
        Err(e) => warnings.push(format!("arp: no sweep: {e:#}")),
    }
    drop((tx, errors_tx));
    let found = confirm(rx, plan.port, "arp", plan.timeout, deadline).await;
    while let Ok(e) = errors.try_recv() {
        warnings.push(format!("arp: {e}; only the neighbour table was read"));
    }
    finish(found, warnings)
}

/// DHCP: the addresses in each lease file, and those seen in DHCP traffic on each listened
/// interface, confirmed by their status endpoints.
pub async fn dhcp(plan: &Plan, deadline: Instant) -> (Vec<Probed>, Vec<String>) {
    let (tx, rx) = unbounded_channel();
    let (errors_tx, mut errors) = unbounded_channel();
    let mut warnings = Vec::new();
    for path in &plan.lease_files {
        match leases::read(path) {
            Ok(parsed) => {
                let n = parsed.errors.len();
                for e in parsed.errors.iter().take(MAX_LINE_ERRORS) {
                    warnings.push(format!("dhcp: {}: {e}", path.display()));
                }
                if n > MAX_LINE_ERRORS {
                    warnings.push(format!(
                        "dhcp: {}: {} more unreadable line(s)",
                        path.display(),
                        n - MAX_LINE_ERRORS
                    ));
                }
                for lease in parsed.leases {
                    let _ = tx.send(lease.ip);
                }
            }
            Err(e) => warnings.push(format!("dhcp: {e:#}")),
        }
    }
    let stop = raw_stop(plan, deadline);
    if !plan.dhcp_interfaces.is_empty() {
        match raw::interfaces(&plan.dhcp_interfaces) {
            Ok(interfaces) => {
                for iface in interfaces {
                    let name = format!("listening on {}", iface.name);
                    spawn_raw(name, &tx, &errors_tx, move |tx| {
                        dhcp::listen(&iface, stop, tx)
                    });
                }
            }
            Err(e) => warnings.push(format!("dhcp: cannot listen: {e:#}")),
        }
    }
    drop((tx, errors_tx));
    let found = confirm(rx, plan.port, "dhcp", plan.timeout, deadline).await;
    while let Ok(e) = errors.try_recv() {
        warnings.push(format!("dhcp: {e}"));
    }
    finish(found, warnings)
}

/// When raw sweeps and listening stop: [`CONFIRM_MARGIN`] (at most a quarter of the window)
/// before the deadline.
fn raw_stop(plan: &Plan, deadline: Instant) -> Instant {
    let margin = CONFIRM_MARGIN.min(plan.timeout / 4);
    deadline.checked_sub(margin).unwrap_or(deadline)
}

/// The confirmed findings, or none and a warning when probing was impossible.
fn finish(
    found: anyhow::Result<Vec<Probed>>,
    mut warnings: Vec<String>,
) -> (Vec<Probed>, Vec<String>) {
    match found {
        Ok(found) => (found, warnings),
        Err(e) => {
            warnings.push(format!("{e:#}"));
            (Vec::new(), warnings)
        }
    }
}

/// Runs `work` (a raw-socket sweep or listener) on a thread of its own, which the command never
/// waits for: it stops by itself at its deadline. Its error, if any, goes to `errors`, worded
/// for the user (the missing privilege named).
fn spawn_raw(
    what: String,
    tx: &UnboundedSender<IpAddr>,
    errors: &UnboundedSender<String>,
    work: impl FnOnce(&UnboundedSender<IpAddr>) -> std::io::Result<()> + Send + 'static,
) {
    let (tx, thread_errors) = (tx.clone(), errors.clone());
    let failed = format!("cannot start a thread for the {what}");
    let spawned = std::thread::Builder::new()
        .name("discover-raw".into())
        .spawn(move || {
            if let Err(e) = work(&tx) {
                let message = if raw::is_permission(&e) {
                    raw::permission_hint(&what)
                } else {
                    format!("{what} failed: {e}")
                };
                let _ = thread_errors.send(message);
            }
        });
    if let Err(e) = spawned {
        let _ = errors.send(format!("{failed}: {e}"));
    }
}
