//! DHCP server lease files as discovery candidates: dnsmasq's `dnsmasq.leases` and ISC dhcpd's
//! `dhcpd.leases`, told apart by their content. A line that cannot be read is reported and
//! skipped; the rest of the file still counts.

use std::collections::BTreeMap;
use std::net::IpAddr;
use std::path::Path;

use anyhow::Context as _;

/// Largest lease file read, so a wrong path (a disk image, a log) cannot hold the command.
const MAX_LEASE_FILE_BYTES: u64 = 16 * 1024 * 1024;

/// One lease: the address a DHCP server handed out and to whom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Lease {
    /// The leased address.
    pub ip: IpAddr,
    /// The client's hardware address (dnsmasq: for IPv6, its IAID), if the file names it.
    pub mac: Option<String>,
    /// The host name the client sent, if any.
    pub hostname: Option<String>,
}

/// The format of a lease file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// dnsmasq: `expiry mac ip hostname client-id`, one lease a line.
    Dnsmasq,
    /// ISC dhcpd: `lease ip { ... }` blocks; a later block for an address replaces earlier ones.
    Isc,
}

/// What a lease file holds: the leases that are in force, and one message per line that could
/// not be read (`line N: ...`).
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Parsed {
    /// Leases in force, in file order of their last mention.
    pub leases: Vec<Lease>,
    /// Lines that could not be read.
    pub errors: Vec<String>,
}

/// Reads the lease file at `path`; an error only when the file itself cannot be read.
pub fn read(path: &Path) -> anyhow::Result<Parsed> {
    let meta =
        std::fs::metadata(path).with_context(|| format!("cannot read {}", path.display()))?;
    anyhow::ensure!(
        meta.len() <= MAX_LEASE_FILE_BYTES,
        "{} is larger than {MAX_LEASE_FILE_BYTES} bytes: not a lease file",
        path.display()
    );
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    Ok(parse(&String::from_utf8_lossy(&bytes)))
}

/// Parses a lease file of either format.
pub fn parse(text: &str) -> Parsed {
    match detect(text) {
        Format::Dnsmasq => parse_dnsmasq(text),
        Format::Isc => parse_isc(text),
    }
}

/// Tells the format from the first line that says something: ISC files start with comments,
/// `authoring-byte-order`, `server-duid` or `lease`; dnsmasq lines start with an expiry time
/// or `duid`.
pub fn detect(text: &str) -> Format {
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'));
    match first {
        Some(l) if l.starts_with(|c: char| c.is_ascii_digit()) || l.starts_with("duid ") => {
            Format::Dnsmasq
        }
        Some(_) => Format::Isc,
        None if text.contains("dhcpd") => Format::Isc,
        None => Format::Dnsmasq,
    }
}

/// Parses dnsmasq's format. Its `duid` line (the server's IPv6 identity) is not a lease.
pub fn parse_dnsmasq(text: &str) -> Parsed {
    let mut out = Parsed::default();
    for (n, line) in text.lines().enumerate() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        match fields.as_slice() {
            [] | ["duid", ..] => {}
            [expiry, mac, ip, hostname, ..] if expiry.parse::<u64>().is_ok() => {
                match ip.parse::<IpAddr>() {
                    Ok(ip) => out.leases.push(Lease {
                        ip,
                        mac: Some((*mac).to_owned()),
                        hostname: (*hostname != "*").then(|| (*hostname).to_owned()),
                    }),
                    Err(_) => out
                        .errors
                        .push(format!("line {}: {ip:?} is not an IP address", n + 1)),
                }
            }
            _ => out.errors.push(format!(
                "line {}: not `expiry mac ip hostname client-id`",
                n + 1
            )),
        }
    }
    out
}

/// Parses ISC dhcpd's format: `lease` blocks (IPv4); `lease6` and other blocks are skipped.
/// Leases whose `binding state` is not `active` (free, expired, released, abandoned, backup)
/// are not in force.
pub fn parse_isc(text: &str) -> Parsed {
    let mut out = Parsed::default();
    let mut leases: BTreeMap<IpAddr, (usize, Lease)> = BTreeMap::new();
    // The lease block being read (None inside a block that is not a lease), and its state.
    let mut current: Option<(Option<Lease>, bool, usize)> = None;
    let mut depth = 0usize;
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or_default().trim();
        if line.is_empty() {
            continue;
        }
        let opens = line.ends_with('{');
        let closes = line == "}" || line.ends_with('}');
        if depth == 0 && opens {
            let words: Vec<&str> = line.trim_end_matches('{').split_whitespace().collect();
            let lease = match words.as_slice() {
                ["lease", ip] => match ip.parse::<IpAddr>() {
                    Ok(ip) => Some(Lease {
                        ip,
                        mac: None,
                        hostname: None,
                    }),
                    Err(_) => {
                        out.errors
                            .push(format!("line {}: {ip:?} is not an IP address", n + 1));
                        None
                    }
                },
                _ => None,
            };
            current = Some((lease, true, n + 1));
            depth = 1;
            continue;
        }
        if depth == 0 {
            if !line.ends_with(';') {
                out.errors
                    .push(format!("line {}: not a statement or block", n + 1));
            }
            continue;
        }
        if opens {
            depth += 1;
        }
        if closes {
            depth -= 1;
            if depth == 0 {
                match current.take() {
                    Some((Some(lease), true, _)) => {
                        leases.insert(lease.ip, (n, lease));
                    }
                    Some((Some(lease), false, _)) => {
                        leases.remove(&lease.ip);
                    }
                    _ => {}
                }
            }
            continue;
        }
        if depth == 1
            && let Some((Some(lease), active, _)) = current.as_mut()
        {
            read_isc_statement(line, lease, active);
        }
    }
    if let Some((_, _, start)) = current {
        out.errors.push(format!(
            "line {start}: block not closed before the end of the file"
        ));
    }
    let mut in_force: Vec<(usize, Lease)> = leases.into_values().collect();
    in_force.sort_by_key(|(n, _)| *n);
    out.leases = in_force.into_iter().map(|(_, l)| l).collect();
    out
}

/// Applies one statement inside a `lease` block.
fn read_isc_statement(line: &str, lease: &mut Lease, active: &mut bool) {
    let statement = line.trim_end_matches(';').trim();
    if let Some(state) = statement.strip_prefix("binding state ") {
        *active = state.trim() == "active";
    } else if let Some(mac) = statement.strip_prefix("hardware ethernet ") {
        lease.mac = Some(mac.trim().to_owned());
    } else if let Some(name) = statement.strip_prefix("client-hostname ") {
        lease.hostname = Some(name.trim().trim_matches('"').to_owned());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DNSMASQ: &str = "\
duid 00:01:00:01:2c:5f:1a:2b:52:54:00:aa:bb:cc
1764000000 52:54:00:00:00:11 10.78.0.11 kiwi-1 01:52:54:00:00:00:11
0 52:54:00:00:00:12 10.78.0.12 * *
1764000000 52:54:00:00:00:13 10.78.0.999 kiwi-3 *
garbage
1764000000 1234 fd00::5 kiwi-6 00:01:00:01
";

    #[test]
    fn dnsmasq_leases_and_bad_lines() {
        assert_eq!(detect(DNSMASQ), Format::Dnsmasq);
        let p = parse(DNSMASQ);
        let ips: Vec<String> = p.leases.iter().map(|l| l.ip.to_string()).collect();
        assert_eq!(ips, ["10.78.0.11", "10.78.0.12", "fd00::5"]);
        assert_eq!(p.leases[0].hostname.as_deref(), Some("kiwi-1"));
        assert_eq!(p.leases[0].mac.as_deref(), Some("52:54:00:00:00:11"));
        assert_eq!(p.leases[1].hostname, None);
        assert_eq!(p.errors.len(), 2, "{:?}", p.errors);
        assert!(
            p.errors[0].starts_with("line 4: \"10.78.0.999\""),
            "{:?}",
            p.errors
        );
        assert!(p.errors[1].starts_with("line 5:"), "{:?}", p.errors);
    }

    const ISC: &str = r#"# The format of this file is documented in the dhcpd.leases(5) manual page.
# This lease file was written by isc-dhcp-4.4.3
authoring-byte-order little-endian;
server-duid "\000\001";

lease 10.78.0.21 {
  starts 2 2026/11/24 12:00:00;
  ends 2 2026/11/24 13:00:00;
  binding state active;
  next binding state free;
  hardware ethernet 52:54:00:00:00:21;
  uid "\001RT\000\000\000!";
  client-hostname "kiwi-21";
}
lease 10.78.0.22 {
  binding state free;
  hardware ethernet 52:54:00:00:00:22;
}
lease 10.78.0.23 {
  binding state active;
}
lease 10.78.0.23 {
  binding state released;
}
lease 10.78.0.300 {
  binding state active;
}
failover peer "x" state {
  my state normal at 2 2026/11/24 12:00:00;
}
stray words
lease 10.78.0.24 {
  binding state active;
"#;

    #[test]
    fn isc_leases_last_block_wins_and_bad_lines() {
        assert_eq!(detect(ISC), Format::Isc);
        let p = parse(ISC);
        assert_eq!(
            p.leases,
            [Lease {
                ip: "10.78.0.21".parse().unwrap(),
                mac: Some("52:54:00:00:00:21".into()),
                hostname: Some("kiwi-21".into()),
            }]
        );
        assert_eq!(p.errors.len(), 3, "{:?}", p.errors);
        assert!(
            p.errors[0].starts_with("line 25: \"10.78.0.300\""),
            "{:?}",
            p.errors
        );
        assert!(p.errors[1].starts_with("line 31:"), "{:?}", p.errors);
        assert!(
            p.errors[2].starts_with("line 32: block not closed"),
            "{:?}",
            p.errors
        );
    }

    #[test]
    fn format_detection() {
        assert_eq!(detect(""), Format::Dnsmasq);
        assert_eq!(detect("lease 10.0.0.1 {\n}\n"), Format::Isc);
        assert_eq!(detect("\n1764000000 aa 10.0.0.1 * *\n"), Format::Dnsmasq);
    }
}
