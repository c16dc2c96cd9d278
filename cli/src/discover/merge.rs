//! What `discover` prints: the findings of every method (mDNS, probe, ARP, DHCP) merged into one entry per robot, and their
//! table, JSON or YAML.

use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;

use lekiwi_discovery::Found;

use super::{Discovered, Probed};
use crate::Output;

/// Splits an agent's robot name into namespace and name; a bare name is in `namespace`.
fn split_robot(robot: &str, namespace: &str) -> (String, String) {
    match robot.split_once('/') {
        Some((ns, name)) => (ns.to_owned(), name.to_owned()),
        None => (namespace.to_owned(), robot.to_owned()),
    }
}

/// Merges the methods' findings by robot (mDNS, and the status endpoints that answered,
/// each marked with the method that found it), without duplicates, sorted by namespace and name.
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
        d.via.push(p.via.into());
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
pub fn render(found: &[Discovered], output: &Output) -> anyhow::Result<String> {
    Ok(
        match output.rows(found, |d| format!("{}/{}", d.namespace, d.name))? {
            Some(text) => text,
            None => {
                if found.is_empty() {
                    return Ok("No agents found.\n".into());
                }
                let wide = output.wide();
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
        },
    )
}

/// The address to show first: IPv4 before IPv6, as people type them.
fn preferred(addresses: &[String]) -> String {
    addresses
        .iter()
        .find(|a| a.parse::<SocketAddr>().is_ok_and(|s| s.is_ipv4()))
        .unwrap_or(&addresses[0])
        .clone()
}
