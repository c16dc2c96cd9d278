//! ARP as a discovery method: the kernel's neighbour table (`/proc/net/arp`), plus an active
//! sweep that asks every address of the local IPv4 subnets who has it (an AF_PACKET socket,
//! which needs CAP_NET_RAW). Every address that answers is only a candidate; the agent's status
//! endpoint confirms it (see `probe::confirm`).

use std::net::{IpAddr, Ipv4Addr};
use std::time::Duration;

use tokio::sync::mpsc::UnboundedSender;
use tokio::time::Instant;

use super::raw::{self, Interface};

/// Most addresses one sweep asks, over all interfaces: a /22 and a few /24s.
pub const MAX_SWEEP_ADDRESSES: usize = 4096;
/// Widest subnet swept whole; a wider one is swept in the /22 around the interface's address.
const MAX_SWEEP_PREFIX_BITS: u32 = 10;
/// When to ask again the addresses that have not answered, after the first round.
const RESEND_AFTER: Duration = Duration::from_millis(250);
/// Where the kernel shows its IPv4 neighbour table.
const NEIGHBOUR_TABLE: &str = "/proc/net/arp";
/// `ATF_COM` in the table's flags: the entry is complete (the neighbour answered).
const ATF_COM: u32 = 0x2;

/// The complete entries of a `/proc/net/arp` text, limited to `interfaces` unless empty.
pub fn parse_neighbours(text: &str, interfaces: &[String]) -> Vec<Ipv4Addr> {
    text.lines()
        .skip(1)
        .filter_map(|line| {
            let f: Vec<&str> = line.split_whitespace().collect();
            let [ip, _hw_type, flags, _mac, _mask, device] = f.as_slice() else {
                return None;
            };
            let flags = u32::from_str_radix(flags.trim_start_matches("0x"), 16).ok()?;
            let wanted = interfaces.is_empty() || interfaces.iter().any(|i| i == device);
            (flags & ATF_COM != 0 && wanted)
                .then(|| ip.parse().ok())
                .flatten()
        })
        .collect()
}

/// The kernel's neighbour table, as candidates; an error when it cannot be read.
pub fn neighbours(interfaces: &[String]) -> anyhow::Result<Vec<Ipv4Addr>> {
    let text = std::fs::read_to_string(NEIGHBOUR_TABLE)
        .map_err(|e| anyhow::anyhow!("cannot read the neighbour table {NEIGHBOUR_TABLE}: {e}"))?;
    Ok(parse_neighbours(&text, interfaces))
}

/// One interface's part of a sweep: who asks (its MAC and address) and whom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SweepPlan {
    /// The interface to send from.
    pub interface: Interface,
    /// Its own IPv4 address, the sender of the requests.
    pub own: Ipv4Addr,
    /// The addresses to ask, the interface's own left out.
    pub targets: Vec<Ipv4Addr>,
}

/// Plans a sweep of each interface's IPv4 subnets, within [`MAX_SWEEP_ADDRESSES`] in all;
/// returns the plan and warnings about what was cut.
pub fn plan(interfaces: &[Interface]) -> (Vec<SweepPlan>, Vec<String>) {
    let mut plans = Vec::new();
    let mut warnings = Vec::new();
    let mut total = 0usize;
    for iface in interfaces {
        if iface.ipv4.is_empty() {
            warnings.push(format!(
                "arp: {} has no IPv4 address: not swept",
                iface.name
            ));
        }
        for &(own, prefix) in &iface.ipv4 {
            let mut host_bits = 32 - u32::from(prefix.min(32));
            if host_bits > MAX_SWEEP_PREFIX_BITS {
                warnings.push(format!(
                    "arp: {}: {own}/{prefix} is wider than a /22; sweeping the /22 around {own}",
                    iface.name
                ));
                host_bits = MAX_SWEEP_PREFIX_BITS;
            }
            let mut targets: Vec<Ipv4Addr> = subnet_hosts(own, host_bits)
                .into_iter()
                .filter(|ip| *ip != own)
                .collect();
            let room = MAX_SWEEP_ADDRESSES - total;
            if targets.len() > room {
                warnings.push(format!(
                    "arp: sweep capped at {MAX_SWEEP_ADDRESSES} addresses; {} of {}/{prefix} on {} not swept",
                    targets.len() - room,
                    own,
                    iface.name
                ));
                targets.truncate(room);
            }
            if targets.is_empty() {
                continue;
            }
            total += targets.len();
            plans.push(SweepPlan {
                interface: iface.clone(),
                own,
                targets,
            });
        }
    }
    (plans, warnings)
}

/// The host addresses of the subnet of `ip` with `host_bits` host bits (network and broadcast
/// addresses left out when there are any).
fn subnet_hosts(ip: Ipv4Addr, host_bits: u32) -> Vec<Ipv4Addr> {
    let count = 1u32 << host_bits;
    let base = u32::from(ip) & !(count - 1);
    let (first, last) = if host_bits >= 2 {
        (1, count - 2)
    } else {
        (0, count - 1)
    };
    (first..=last).map(|i| Ipv4Addr::from(base + i)).collect()
}

/// An Ethernet broadcast frame asking who has `target`, from `mac`/`own`.
pub fn request_frame(mac: [u8; 6], own: Ipv4Addr, target: Ipv4Addr) -> [u8; 42] {
    let mut f = [0u8; 42];
    f[0..6].copy_from_slice(&[0xff; 6]);
    f[6..12].copy_from_slice(&mac);
    f[12..14].copy_from_slice(&0x0806u16.to_be_bytes());
    // Ethernet, IPv4, 6-byte hardware and 4-byte protocol addresses, a request.
    f[14..22].copy_from_slice(&[0, 1, 8, 0, 6, 4, 0, 1]);
    f[22..28].copy_from_slice(&mac);
    f[28..32].copy_from_slice(&own.octets());
    f[38..42].copy_from_slice(&target.octets());
    f
}

/// The sender address of an ARP frame (a reply to us, or anyone's request: both prove the
/// sender is there); `None` for any other frame.
pub fn sender_of(frame: &[u8]) -> Option<Ipv4Addr> {
    if frame.len() < 42 || frame[12..14] != [0x08, 0x06] || frame[14..20] != [0, 1, 8, 0, 6, 4] {
        return None;
    }
    let ip = Ipv4Addr::new(frame[28], frame[29], frame[30], frame[31]);
    (!ip.is_unspecified()).then_some(ip)
}

/// Runs one interface's sweep on the calling thread until `deadline`: asks every target, asks
/// again those that have not answered after [`RESEND_AFTER`], and sends each address that
/// answers (once) to `found`. An error when the socket cannot be opened (no CAP_NET_RAW).
pub fn sweep(
    plan: &SweepPlan,
    deadline: Instant,
    found: &UnboundedSender<IpAddr>,
) -> std::io::Result<()> {
    let mut link = raw::Link::open(&plan.interface, false)?;
    let targets: std::collections::BTreeSet<Ipv4Addr> = plan.targets.iter().copied().collect();
    let mut answered = std::collections::BTreeSet::new();
    let mac = plan.interface.mac;
    for &target in &plan.targets {
        link.send(&request_frame(mac, plan.own, target))?;
    }
    let resend_at = Instant::now() + RESEND_AFTER;
    let mut resent = false;
    while Instant::now() < deadline {
        if !resent && Instant::now() >= resend_at {
            resent = true;
            for &target in targets.difference(&answered) {
                link.send(&request_frame(mac, plan.own, target))?;
            }
        }
        let Some(frame) = link.next()? else {
            continue;
        };
        if let Some(ip) = sender_of(frame)
            && targets.contains(&ip)
            && answered.insert(ip)
            && found.send(IpAddr::V4(ip)).is_err()
        {
            break;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbour_table_complete_entries() {
        let table = "\
IP address       HW type     Flags       HW address            Mask     Device
10.78.0.11       0x1         0x2         52:54:00:00:00:11     *        lkbr1
10.78.0.12       0x1         0x0         00:00:00:00:00:00     *        lkbr1
192.168.1.1      0x1         0x6         52:54:00:00:00:01     *        eth0
bad line
";
        assert_eq!(
            parse_neighbours(table, &[]),
            [Ipv4Addr::new(10, 78, 0, 11), Ipv4Addr::new(192, 168, 1, 1)]
        );
        assert_eq!(
            parse_neighbours(table, &["eth0".into()]),
            [Ipv4Addr::new(192, 168, 1, 1)]
        );
    }

    fn iface(name: &str, ipv4: &[(&str, u8)]) -> Interface {
        Interface {
            name: name.into(),
            mac: [2, 0, 0, 0, 0, 1],
            ipv4: ipv4
                .iter()
                .map(|(ip, p)| (ip.parse().unwrap(), *p))
                .collect(),
        }
    }

    #[test]
    fn sweep_plan_is_bounded() {
        let (plans, warnings) = plan(&[iface("a", &[("10.78.0.1", 24)]), iface("c", &[])]);
        assert_eq!(warnings, ["arp: c has no IPv4 address: not swept"]);
        assert_eq!(plans.len(), 1);
        assert_eq!(plans[0].targets.len(), 253);
        assert_eq!(plans[0].targets[0], Ipv4Addr::new(10, 78, 0, 2));
        let (plans, warnings) = plan(&[iface("b", &[("10.9.200.7", 8)])]);
        assert_eq!(plans[0].targets.len(), 1021);
        assert_eq!(plans[0].targets[0], Ipv4Addr::new(10, 9, 200, 1));
        assert!(warnings[0].contains("wider than a /22"), "{warnings:?}");
        let many: Vec<Interface> = (0..5)
            .map(|i| iface(&format!("i{i}"), &[(&format!("10.{i}.0.1"), 22)]))
            .collect();
        let (plans, warnings) = plan(&many);
        let total: usize = plans.iter().map(|p| p.targets.len()).sum();
        assert_eq!(total, MAX_SWEEP_ADDRESSES);
        assert!(
            warnings.iter().any(|w| w.contains("capped")),
            "{warnings:?}"
        );
    }

    #[test]
    fn request_and_reply_frames() {
        let mac = [2, 0, 0, 0, 0, 1];
        let f = request_frame(
            mac,
            Ipv4Addr::new(10, 78, 0, 1),
            Ipv4Addr::new(10, 78, 0, 11),
        );
        assert_eq!(&f[0..6], &[0xff; 6]);
        assert_eq!(sender_of(&f), Some(Ipv4Addr::new(10, 78, 0, 1)));
        let mut reply = f;
        reply[21] = 2;
        reply[28..32].copy_from_slice(&[10, 78, 0, 11]);
        assert_eq!(sender_of(&reply), Some(Ipv4Addr::new(10, 78, 0, 11)));
        reply[12] = 0x86;
        assert_eq!(sender_of(&reply), None);
        assert_eq!(sender_of(&f[..41]), None);
    }
}
