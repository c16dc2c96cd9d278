//! `--probe` values (addresses, `address:port`, CIDRs) as the status endpoints to probe.

use std::collections::BTreeSet;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};

use anyhow::{Context as _, bail};

/// Most addresses one `discover` probes, so a typo like `/8` does not scan a network for hours.
pub const MAX_PROBE_ADDRESSES: usize = 4096;
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
        let hosts = cidr_hosts(value, ip, prefix)?;
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

/// The host addresses of the CIDR `value`, i.e. `ip/prefix`: an IPv4 network without its
/// network and broadcast addresses (for prefixes up to /30), an IPv6 network whole.
fn cidr_hosts(value: &str, ip: &str, prefix: &str) -> anyhow::Result<Vec<IpAddr>> {
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
    Ok(hosts)
}
