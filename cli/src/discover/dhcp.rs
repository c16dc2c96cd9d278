//! DHCP as a discovery method: the addresses in a DHCP server's lease file (see `leases`), and
//! the addresses seen in DHCP traffic (UDP ports 67/68) on an interface during the discovery
//! window, read passively from an AF_PACKET socket (CAP_NET_RAW). Both give candidates that the
//! agent's status endpoint confirms.

use std::net::{IpAddr, Ipv4Addr};

use tokio::sync::mpsc::UnboundedSender;
use tokio::time::Instant;

use super::raw::{self, Interface};

/// BOOTP's magic cookie, which starts the DHCP options.
const MAGIC_COOKIE: [u8; 4] = [99, 130, 83, 99];
/// DHCP option: the address a client asks for.
const OPT_REQUESTED_IP: u8 = 50;
/// DHCP option: padding.
const OPT_PAD: u8 = 0;
/// DHCP option: end of options.
const OPT_END: u8 = 255;

/// The client addresses a DHCP frame names: the client's current address (`ciaddr`), the address
/// given to it (`yiaddr`), the one it asks for (option 50), and the IPv4 source of a frame a
/// client sent. Empty for any other frame. Ethernet II with IPv4 and UDP only.
pub fn client_addresses(frame: &[u8]) -> Vec<Ipv4Addr> {
    let mut out = Vec::new();
    if frame.len() < 14 || frame[12..14] != [0x08, 0x00] {
        return out;
    }
    let ip = &frame[14..];
    if ip.len() < 20 || ip[0] >> 4 != 4 || ip[9] != 17 {
        return out;
    }
    let ihl = usize::from(ip[0] & 0x0f) * 4;
    let Some(udp) = ip.get(ihl..).filter(|u| u.len() >= 8) else {
        return out;
    };
    let src_port = u16::from_be_bytes([udp[0], udp[1]]);
    let dst_port = u16::from_be_bytes([udp[2], udp[3]]);
    if !matches!((src_port, dst_port), (68, 67) | (67, 68)) {
        return out;
    }
    let bootp = &udp[8..];
    if bootp.len() < 240 || bootp[236..240] != MAGIC_COOKIE {
        return out;
    }
    let addr = |at: usize| Ipv4Addr::new(bootp[at], bootp[at + 1], bootp[at + 2], bootp[at + 3]);
    out.push(addr(12));
    out.push(addr(16));
    if src_port == 68 {
        out.push(Ipv4Addr::new(ip[12], ip[13], ip[14], ip[15]));
    }
    out.extend(requested_ip(&bootp[240..]));
    out.retain(|a| !a.is_unspecified() && !a.is_broadcast() && !a.is_multicast());
    out.sort();
    out.dedup();
    out
}

/// Option 50 of DHCP options, if present and well formed.
fn requested_ip(mut options: &[u8]) -> Option<Ipv4Addr> {
    loop {
        match options {
            [OPT_END, ..] | [] => return None,
            [OPT_PAD, rest @ ..] => options = rest,
            [code, len, rest @ ..] => {
                let len = usize::from(*len);
                let value = rest.get(..len)?;
                if *code == OPT_REQUESTED_IP && len == 4 {
                    return Some(Ipv4Addr::new(value[0], value[1], value[2], value[3]));
                }
                options = &rest[len..];
            }
            [_] => return None,
        }
    }
}

/// Listens on `iface` until `deadline` and sends each new client address seen in DHCP traffic to
/// `found`. An error when the socket cannot be opened (no CAP_NET_RAW) or fails.
pub fn listen(
    iface: &Interface,
    deadline: Instant,
    found: &UnboundedSender<IpAddr>,
) -> std::io::Result<()> {
    let mut link = raw::Link::open(iface, true)?;
    let mut seen = std::collections::BTreeSet::new();
    while Instant::now() < deadline {
        let Some(frame) = link.next()? else {
            continue;
        };
        for ip in client_addresses(frame) {
            if seen.insert(ip) && found.send(IpAddr::V4(ip)).is_err() {
                return Ok(());
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A DHCPREQUEST from 0.0.0.0 asking for `requested`, as a client broadcasts it.
    fn request(requested: [u8; 4], ciaddr: [u8; 4]) -> Vec<u8> {
        let mut f = vec![0xff; 6];
        f.extend([0x52, 0x54, 0, 0, 0, 0x11, 0x08, 0x00]);
        let mut bootp = vec![0u8; 240];
        bootp[0] = 1;
        bootp[12..16].copy_from_slice(&ciaddr);
        bootp[236..240].copy_from_slice(&MAGIC_COOKIE);
        bootp.extend([53, 1, 3, OPT_PAD, OPT_REQUESTED_IP, 4]);
        bootp.extend(requested);
        bootp.push(OPT_END);
        let udp_len = 8 + bootp.len();
        let mut ip = vec![
            0x45, 0, 0, 0, 0, 0, 0, 0, 64, 17, 0, 0, 0, 0, 0, 0, 255, 255, 255, 255,
        ];
        ip[2..4].copy_from_slice(&((20 + udp_len) as u16).to_be_bytes());
        f.extend(ip);
        f.extend([0, 68, 0, 67]);
        f.extend((udp_len as u16).to_be_bytes());
        f.extend([0, 0]);
        f.extend(bootp);
        f
    }

    #[test]
    fn addresses_from_dhcp_frames() {
        assert_eq!(
            client_addresses(&request([10, 78, 0, 31], [0; 4])),
            [Ipv4Addr::new(10, 78, 0, 31)]
        );
        assert_eq!(
            client_addresses(&request([10, 78, 0, 31], [10, 78, 0, 30])),
            [Ipv4Addr::new(10, 78, 0, 30), Ipv4Addr::new(10, 78, 0, 31)]
        );
        // Not DHCP: other ports, not UDP, truncated, no cookie.
        let mut other = request([10, 78, 0, 31], [0; 4]);
        other[14 + 20 + 3] = 53;
        assert!(client_addresses(&other).is_empty());
        let mut tcp = request([10, 78, 0, 31], [0; 4]);
        tcp[14 + 9] = 6;
        assert!(client_addresses(&tcp).is_empty());
        assert!(client_addresses(&request([10, 78, 0, 31], [0; 4])[..100]).is_empty());
        let mut cookie = request([10, 78, 0, 31], [0; 4]);
        cookie[14 + 28 + 236] = 0;
        assert!(client_addresses(&cookie).is_empty());
        // A malformed option list ends the search, without a panic.
        let mut bad = request([10, 78, 0, 31], [0; 4]);
        let n = bad.len();
        bad[n - 6] = 200;
        assert!(client_addresses(&bad).is_empty());
    }
}
