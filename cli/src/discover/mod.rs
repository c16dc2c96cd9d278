//! `kubectl lekiwi discover`: finds agents on the network by mDNS (`_lekiwi._tcp.local.`) and,
//! at the same time, by probing given addresses and CIDRs for the agent's `GET /status`, by ARP
//! (the neighbour table and a sweep of the local subnets) and by DHCP (lease files, listening
//! to DHCP traffic), the addresses of the last two confirmed by their `GET /status`; merges what
//! all find by robot name and marks which robots are registered in the cluster.
//!
//! The methods and the connection to the cluster run concurrently against one deadline,
//! then each robot found is looked up (one GET each, bounded in time); none waits for another: a method that fails or hangs costs a warning on
//! stderr, never the others' results.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;
use futures::StreamExt;
use kube::Api;
use kube::api::ListParams;
use lekiwi_crds::Robot;
use lekiwi_discovery::Found;
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use crate::Output;

mod arp;
mod dhcp;
mod leases;
mod merge;
mod methods;
mod probe;
mod raw;
mod targets;

pub use merge::{merge, render};
pub use probe::Probed;
use probe::probe_all;
pub use targets::{MAX_PROBE_ADDRESSES, parse_targets};

/// Time the Robot lookups of the found agents may take after the deadline.
const LOOKUP_BUDGET: Duration = Duration::from_millis(300);
/// Robot lookups in flight at once.
const LOOKUP_CONCURRENCY: usize = 16;
/// Time after the deadline the mDNS browser may take to shut its daemon down.
const MDNS_GRACE: Duration = Duration::from_millis(300);

/// Arguments of `discover`.
#[derive(Debug, Args)]
pub struct DiscoverArgs {
    /// Also probe these for the agent's status endpoint: an address (`10.0.0.7`,
    /// `10.0.0.7:9000`, `[fe80::1]:9477`) or a CIDR (`10.0.0.0/24`); repeatable.
    #[arg(long, value_name = "ADDR|CIDR")]
    pub probe: Vec<String>,
    /// How long to look (e.g. 1.5s, 800ms).
    #[arg(long, default_value = "1.5s", value_parser = crate::duration::parse)]
    pub timeout: Duration,
    /// Port of the status endpoint for probes that name none.
    #[arg(long, default_value_t = 9477)]
    pub port: u16,
    /// Do not browse mDNS.
    #[arg(long)]
    pub no_mdns: bool,
    /// Also find agents by ARP: the kernel's neighbour table, and a sweep of the local IPv4
    /// subnets (at most 4096 addresses; needs CAP_NET_RAW, without it only the table is read);
    /// each address found is confirmed by its status endpoint.
    #[arg(long)]
    pub arp: bool,
    /// Interface whose neighbours and subnets ARP reads and sweeps (implies --arp; default:
    /// every interface that is up, not loopback, with an IPv4 address); repeatable.
    #[arg(long, value_name = "IFACE")]
    pub arp_interface: Vec<String>,
    /// Also probe the addresses leased in this DHCP server lease file (dnsmasq or ISC dhcpd
    /// format, told apart by content; unreadable lines are reported and skipped); repeatable.
    #[arg(long, value_name = "PATH")]
    pub dhcp_leases: Vec<PathBuf>,
    /// Also listen for DHCP traffic (UDP 67/68) on this interface for the whole window and
    /// probe the client addresses seen (needs CAP_NET_RAW); repeatable.
    #[arg(long, value_name = "IFACE")]
    pub dhcp_listen: Vec<String>,
}

/// An agent found on the network.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Discovered {
    /// The robot as the agent names it: `namespace/name` or `name`.
    pub robot: String,
    /// Namespace of its Robot (the given namespace for a bare name).
    pub namespace: String,
    /// Name of its Robot.
    pub name: String,
    /// Whether the Robot exists; `None` when the cluster could not be asked.
    pub registered: Option<bool>,
    /// Status endpoints (`ip:port`) it was found at, sorted.
    pub addresses: Vec<String>,
    /// How it was found: `arp`, `dhcp`, `mdns`, `probe`.
    pub via: Vec<String>,
    /// Agent version.
    pub agent_version: String,
    /// Release it runs, if any.
    pub release: Option<String>,
    /// Gateway URL it connects to.
    pub gateway: String,
    /// Whether its gateway connection is up (known from a probe only).
    pub connected: Option<bool>,
}

/// Runs `discover`. `client` is an error when no cluster configuration was found; the robots
/// are listed anyway.
pub async fn run(
    client: anyhow::Result<kube::Client>,
    namespace: &str,
    only_namespace: Option<&str>,
    output: &Output,
    no_headers: bool,
    args: DiscoverArgs,
) -> anyhow::Result<()> {
    let targets = parse_targets(&args.probe, args.port)?;
    let deadline = Instant::now() + args.timeout;

    let mdns = async {
        if args.no_mdns {
            return Ok(Vec::new());
        }
        browse(args.timeout, deadline + MDNS_GRACE).await
    };
    let probes = probe_all(&targets, args.timeout, deadline);
    let plan = methods::Plan {
        port: args.port,
        timeout: args.timeout,
        arp: args.arp || !args.arp_interface.is_empty(),
        arp_interfaces: args.arp_interface.clone(),
        lease_files: args.dhcp_leases.clone(),
        dhcp_interfaces: args.dhcp_listen.clone(),
    };
    let others = methods::run(&plan, deadline);
    // Connecting early means the per-robot lookups afterwards cost one round trip each.
    let cluster = async {
        let client = client?;
        match tokio::time::timeout_at(deadline, reachable(&client, namespace)).await {
            Ok(Ok(())) => Ok(client),
            Ok(Err(e)) => Err(e),
            Err(_) => bail!("the cluster did not answer within {:?}", args.timeout),
        }
    };
    let (mdns, (mut probed, mut warnings), (others, other_warnings), cluster) =
        tokio::join!(mdns, probes, others, cluster);
    probed.extend(others);
    warnings.extend(other_warnings);

    let mdns = mdns.unwrap_or_else(|e| {
        eprintln!("warning: mDNS browse failed: {e:#}");
        Vec::new()
    });
    for w in warnings {
        eprintln!("warning: {}", crate::sanitize::text(&w));
    }
    let mut found = merge(namespace, &mdns, &probed, None);
    if let Some(ns) = only_namespace {
        found.retain(|d| d.namespace == ns);
    }
    match cluster {
        Ok(client) => {
            let unknown = mark_registered(&client, &mut found).await;
            if unknown > 0 {
                eprintln!(
                    "warning: could not look up {unknown} robot(s) in the cluster in time, REGISTERED is unknown for them"
                );
            }
        }
        Err(e) => eprintln!("warning: cannot reach the cluster, REGISTERED is unknown: {e:#}"),
    }
    let text = render(&found, output)?;
    print!(
        "{}",
        crate::list::headers(text, no_headers && output.table())
    );
    Ok(())
}

/// Browses mDNS on a thread of its own for `timeout`; gives up waiting at `give_up` (a stuck
/// daemon must not hold the command, and a thread unlike a blocking task does not keep the
/// runtime from exiting).
async fn browse(timeout: Duration, give_up: Instant) -> anyhow::Result<Vec<Found>> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name("mdns-browse".into())
        .spawn(move || {
            let _ = tx.send(lekiwi_discovery::browse(timeout));
        })
        .context("cannot start the mDNS browser thread")?;
    match tokio::time::timeout_at(give_up, rx).await {
        Ok(Ok(found)) => Ok(found?),
        Ok(Err(_)) => bail!("the mDNS browser stopped unexpectedly"),
        Err(_) => bail!("the mDNS browser did not finish in time"),
    }
}

/// Whether the cluster answers (any answer, a refusal included, proves it is there).
async fn reachable(client: &kube::Client, namespace: &str) -> anyhow::Result<()> {
    let api: Api<Robot> = Api::namespaced(client.clone(), namespace);
    match api.list_metadata(&ListParams::default().limit(1)).await {
        Ok(_) | Err(kube::Error::Api(_)) => Ok(()),
        Err(e) => Err(e.into()),
    }
}

/// Sets `registered` of each found robot by looking its Robot up, a few at once and within
/// [`LOOKUP_BUDGET`]; returns how many stayed unknown. One GET per robot found scales with
/// what is on the network, not with the size of the fleet.
async fn mark_registered(client: &kube::Client, found: &mut [Discovered]) -> usize {
    let lookups = futures::stream::iter(found.iter().enumerate())
        .map(|(i, d)| {
            let api: Api<Robot> = Api::namespaced(client.clone(), &d.namespace);
            let name = d.name.clone();
            async move { (i, api.get_metadata_opt(&name).await) }
        })
        .buffer_unordered(LOOKUP_CONCURRENCY)
        .collect::<Vec<_>>();
    let Ok(answers) = tokio::time::timeout(LOOKUP_BUDGET, lookups).await else {
        return found.len();
    };
    let mut unknown = 0;
    for (i, answer) in answers {
        match answer {
            Ok(robot) => found[i].registered = Some(robot.is_some()),
            Err(_) => unknown += 1,
        }
    }
    unknown
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;

    use lekiwi_discovery::StatusSnapshot;

    use super::*;

    #[test]
    fn targets_from_addresses_and_cidrs() {
        let t = parse_targets(&["10.77.0.0/30".into(), "10.77.0.1".into()], 9477).unwrap();
        assert_eq!(
            t,
            [
                "10.77.0.1:9477".parse().unwrap(),
                "10.77.0.2:9477".parse().unwrap()
            ]
        );
        let t = parse_targets(&["127.0.0.1/32".into(), "[::1]:9000".into()], 9477).unwrap();
        assert_eq!(
            t,
            [
                "127.0.0.1:9477".parse().unwrap(),
                "[::1]:9000".parse().unwrap()
            ]
        );
        assert_eq!(
            parse_targets(&["10.0.0.0/24".into()], 1).unwrap().len(),
            254
        );
        assert!(parse_targets(&["10.0.0.0/8".into()], 1).is_err());
        assert!(parse_targets(&["kiwi.local".into()], 1).is_err());
        assert!(parse_targets(&["10.0.0.0/33".into()], 1).is_err());
    }

    fn found(robot: &str, ip: &str) -> Found {
        Found {
            instance: lekiwi_discovery::instance_name(robot),
            robot: robot.into(),
            agent_version: "0.1.0".into(),
            release: None,
            gateway: "ws://gw".into(),
            addresses: vec![ip.parse().unwrap()],
            port: 9477,
        }
    }

    #[test]
    fn merge_lists_every_method_once() {
        let via = |p: Probed, via| Probed { via, ..p };
        let got = merge(
            "lab",
            &[found("lab/a", "10.0.0.1")],
            &[
                via(probed("lab/a", "10.0.0.1:9477"), "dhcp"),
                via(probed("lab/a", "10.0.0.1:9477"), "arp"),
                probed("lab/a", "10.0.0.1:9477"),
                via(probed("lab/a", "10.0.0.1:9477"), "arp"),
                via(probed("b", "10.0.0.2:9477"), "dhcp"),
            ],
            None,
        );
        assert_eq!(got.len(), 2);
        assert_eq!(got[0].via, ["arp", "dhcp", "mdns", "probe"]);
        assert_eq!(got[0].addresses, ["10.0.0.1:9477"]);
        assert_eq!(got[1].via, ["dhcp"]);
    }

    fn probed(robot: &str, addr: &str) -> Probed {
        Probed {
            address: addr.parse().unwrap(),
            status: StatusSnapshot {
                robot: robot.into(),
                connected: true,
                ..StatusSnapshot::default()
            },
            via: "probe",
        }
    }

    #[test]
    fn merge_dedups_by_robot_and_marks_registered() {
        let registered = BTreeSet::from([("lab".to_owned(), "a".to_owned())]);
        let got = merge(
            "lab",
            &[found("lab/a", "10.0.0.1"), found("other/b", "10.0.0.2")],
            &[
                probed("lab/a", "10.0.0.1:9477"),
                probed("c", "10.0.0.3:9477"),
            ],
            Some(&registered),
        );
        let names: Vec<_> = got
            .iter()
            .map(|d| (d.namespace.as_str(), d.name.as_str(), d.registered))
            .collect();
        assert_eq!(
            names,
            [
                ("lab", "a", Some(true)),
                ("lab", "c", Some(false)),
                ("other", "b", Some(false))
            ]
        );
        assert_eq!(got[0].addresses, ["10.0.0.1:9477"]);
        assert_eq!(got[0].via, ["mdns", "probe"]);
        assert_eq!(got[0].connected, Some(true));
        let unknown = merge("lab", &[found("lab/a", "10.0.0.1")], &[], None);
        assert_eq!(unknown[0].registered, None);
        let table = render(&unknown, &Output::Table).unwrap();
        assert!(table.lines().nth(1).unwrap().contains("unknown"));
    }
}
