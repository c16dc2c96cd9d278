//! `kubectl lekiwi discover`: finds agents on the network by mDNS (`_lekiwi._tcp.local.`) and,
//! at the same time, by probing given addresses and CIDRs for the agent's `GET /status`; merges
//! what both find by robot name and marks which robots are registered in the cluster.
//!
//! mDNS, the probes and the connection to the cluster run concurrently against one deadline,
//! then each robot found is looked up (one GET each, bounded in time); none waits for another: a method that fails or hangs costs a warning on
//! stderr, never the others' results.

use std::collections::{BTreeMap, BTreeSet};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::time::Duration;

use anyhow::{Context as _, bail};
use clap::Args;
use futures::StreamExt;
use kube::Api;
use kube::api::ListParams;
use lekiwi_crds::Robot;
use lekiwi_discovery::{Found, StatusSnapshot};
use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use crate::Output;

/// Most addresses one `discover` probes, so a typo like `/8` does not scan a network for hours.
pub const MAX_PROBE_ADDRESSES: usize = 4096;
/// Probes in flight at once.
const PROBE_CONCURRENCY: usize = 256;
/// Time to establish a probe's TCP connection; a LAN host answers in well under this.
const PROBE_CONNECT_TIMEOUT: Duration = Duration::from_millis(300);
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
    /// Do not browse mDNS (probe only).
    #[arg(long)]
    pub no_mdns: bool,
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
    /// How it was found: `mdns`, `probe`.
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

/// What a probe of one status endpoint found.
#[derive(Clone, Debug)]
pub struct Probed {
    /// Where.
    pub address: SocketAddr,
    /// What it said.
    pub status: StatusSnapshot,
}

/// Runs `discover`. `client` is an error when no cluster configuration was found; the robots
/// are listed anyway.
pub async fn run(
    client: anyhow::Result<kube::Client>,
    namespace: &str,
    only_namespace: Option<&str>,
    output: Output,
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
    // Connecting early means the per-robot lookups afterwards cost one round trip each.
    let cluster = async {
        let client = client?;
        match tokio::time::timeout_at(deadline, reachable(&client, namespace)).await {
            Ok(Ok(())) => Ok(client),
            Ok(Err(e)) => Err(e),
            Err(_) => bail!("the cluster did not answer within {:?}", args.timeout),
        }
    };
    let (mdns, (probed, probe_warnings), cluster) = tokio::join!(mdns, probes, cluster);

    let mdns = mdns.unwrap_or_else(|e| {
        eprintln!("warning: mDNS browse failed: {e:#}");
        Vec::new()
    });
    for w in probe_warnings {
        eprintln!("warning: {w}");
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
    print!("{}", render(&found, output)?);
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

/// Parses `--probe` values into status endpoints, in order and without repeats.
pub fn parse_targets(values: &[String], default_port: u16) -> anyhow::Result<Vec<SocketAddr>> {
    let mut out = Vec::new();
    let mut seen = BTreeSet::new();
    for value in values {
        for addr in parse_target(value.trim(), default_port)? {
            if seen.insert(addr) {
                out.push(addr);
            }
            if out.len() > MAX_PROBE_ADDRESSES {
                bail!(
                    "--probe covers more than {MAX_PROBE_ADDRESSES} addresses; probe smaller networks"
                );
            }
        }
    }
    Ok(out)
}

fn parse_target(value: &str, port: u16) -> anyhow::Result<Vec<SocketAddr>> {
    if let Some((ip, prefix)) = value.split_once('/') {
        let ip: IpAddr = ip
            .parse()
            .with_context(|| format!("--probe {value}: {ip:?} is not an IP address"))?;
        let prefix: u32 = prefix
            .parse()
            .with_context(|| format!("--probe {value}: {prefix:?} is not a prefix length"))?;
        let bits = if ip.is_ipv4() { 32 } else { 128 };
        if prefix > bits {
            bail!("--probe {value}: prefix longer than {bits} bits");
        }
        let host_bits = bits - prefix;
        if host_bits > 12 {
            bail!(
                "--probe {value} covers {} addresses, more than {MAX_PROBE_ADDRESSES}; probe smaller networks",
                if host_bits >= 64 {
                    "too many".to_owned()
                } else {
                    (1u64 << host_bits).to_string()
                }
            );
        }
        let count = 1u128 << host_bits;
        let hosts: Vec<IpAddr> = match ip {
            IpAddr::V4(v4) => {
                let base = u32::from(v4) & !((count - 1) as u32);
                let (first, last) = if host_bits >= 2 {
                    // Skip the network and broadcast addresses.
                    (1, count - 2)
                } else {
                    (0, count - 1)
                };
                (first..=last)
                    .map(|i| IpAddr::V4(Ipv4Addr::from(base + i as u32)))
                    .collect()
            }
            IpAddr::V6(v6) => {
                let base = u128::from(v6) & !(count - 1);
                (0..count)
                    .map(|i| IpAddr::V6(Ipv6Addr::from(base + i)))
                    .collect()
            }
        };
        return Ok(hosts
            .into_iter()
            .map(|ip| SocketAddr::new(ip, port))
            .collect());
    }
    if let Ok(addr) = value.parse::<SocketAddr>() {
        return Ok(vec![addr]);
    }
    let ip: IpAddr = value
        .trim_start_matches('[')
        .trim_end_matches(']')
        .parse()
        .with_context(|| {
            format!("--probe {value}: not an address, address:port or CIDR (e.g. 10.0.0.0/24)")
        })?;
    Ok(vec![SocketAddr::new(ip, port)])
}

/// Probes every target until `deadline`; returns the agents that answered and warnings about
/// targets that were named one by one and did not (silence from most of a CIDR is normal).
async fn probe_all(
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

/// Splits an agent's robot name into namespace and name; a bare name is in `namespace`.
fn split_robot(robot: &str, namespace: &str) -> (String, String) {
    match robot.split_once('/') {
        Some((ns, name)) => (ns.to_owned(), name.to_owned()),
        None => (namespace.to_owned(), robot.to_owned()),
    }
}

/// Merges both methods' findings by robot, without duplicates, sorted by namespace and name.
pub fn merge(
    namespace: &str,
    mdns: &[Found],
    probed: &[Probed],
    registered: Option<&BTreeSet<(String, String)>>,
) -> Vec<Discovered> {
    let entry = |robot: &str| {
        let key = split_robot(robot, namespace);
        Discovered {
            robot: robot.to_owned(),
            registered: registered.map(|r| r.contains(&key)),
            namespace: key.0,
            name: key.1,
            ..Discovered::default()
        }
    };
    let mut merged: BTreeMap<(String, String), Discovered> = BTreeMap::new();
    for f in mdns.iter().filter(|f| !f.robot.is_empty()) {
        let d = merged
            .entry(split_robot(&f.robot, namespace))
            .or_insert_with(|| entry(&f.robot));
        d.addresses.extend(
            f.addresses
                .iter()
                .map(|ip| SocketAddr::new(*ip, f.port).to_string()),
        );
        d.via.push("mdns".into());
        d.agent_version.clone_from(&f.agent_version);
        d.release.clone_from(&f.release);
        d.gateway.clone_from(&f.gateway);
    }
    for p in probed {
        let d = merged
            .entry(split_robot(&p.status.robot, namespace))
            .or_insert_with(|| entry(&p.status.robot));
        d.addresses.push(p.address.to_string());
        d.via.push("probe".into());
        d.agent_version.clone_from(&p.status.agent_version);
        d.release = p.status.release.as_ref().map(|r| r.version.clone());
        d.gateway.clone_from(&p.status.gateway);
        d.connected = Some(p.status.connected);
    }
    merged
        .into_values()
        .map(|mut d| {
            d.addresses.sort();
            d.addresses.dedup();
            d.via.sort();
            d.via.dedup();
            d
        })
        .collect()
}

/// Renders the found agents in the given format.
pub fn render(found: &[Discovered], output: Output) -> anyhow::Result<String> {
    Ok(match output {
        Output::Json => serde_json::to_string_pretty(found)? + "\n",
        Output::Yaml => serde_yaml::to_string(found)?,
        Output::Table | Output::Wide => {
            if found.is_empty() {
                return Ok("No agents found.\n".into());
            }
            let wide = output == Output::Wide;
            let mut header = vec!["NAMESPACE", "NAME", "REGISTERED", "ADDRESS", "VIA"];
            if wide {
                header.extend(["AGENT", "RELEASE", "CONNECTED", "GATEWAY"]);
            }
            let mut rows = vec![header.iter().map(|s| s.to_string()).collect::<Vec<_>>()];
            for d in found {
                let address = if wide {
                    d.addresses.join(",")
                } else {
                    match d.addresses.len() {
                        0 => "-".to_owned(),
                        1 => d.addresses[0].clone(),
                        n => format!("{} (+{})", preferred(&d.addresses), n - 1),
                    }
                };
                let mut row = vec![
                    d.namespace.clone(),
                    d.name.clone(),
                    match d.registered {
                        Some(true) => "yes".into(),
                        Some(false) => "no".into(),
                        None => "unknown".into(),
                    },
                    address,
                    d.via.join(","),
                ];
                if wide {
                    let dash = |s: &str| {
                        if s.is_empty() {
                            "-".into()
                        } else {
                            s.to_owned()
                        }
                    };
                    row.push(dash(&d.agent_version));
                    row.push(dash(d.release.as_deref().unwrap_or_default()));
                    row.push(match d.connected {
                        Some(true) => "yes".into(),
                        Some(false) => "no".into(),
                        None => "-".into(),
                    });
                    row.push(dash(&d.gateway));
                }
                rows.push(row);
            }
            crate::robots::format_table(rows)
        }
    })
}

/// The address to show first: IPv4 before IPv6, as people type them.
fn preferred(addresses: &[String]) -> String {
    addresses
        .iter()
        .find(|a| a.parse::<SocketAddr>().is_ok_and(|s| s.is_ipv4()))
        .unwrap_or(&addresses[0])
        .clone()
}

#[cfg(test)]
mod tests {
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

    fn probed(robot: &str, addr: &str) -> Probed {
        Probed {
            address: addr.parse().unwrap(),
            status: StatusSnapshot {
                robot: robot.into(),
                connected: true,
                ..StatusSnapshot::default()
            },
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
        let table = render(&unknown, Output::Table).unwrap();
        assert!(table.lines().nth(1).unwrap().contains("unknown"));
    }
}
