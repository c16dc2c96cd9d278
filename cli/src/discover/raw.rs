//! Network interfaces and raw Ethernet frames (AF_PACKET, through `pnet_datalink`) for the ARP
//! sweep and DHCP listening. Opening a link needs CAP_NET_RAW; [`is_permission`] tells that
//! failure apart so the caller can say so and fall back.

use std::io;
use std::net::{IpAddr, Ipv4Addr};
use std::time::Duration;

/// How long one read waits for a frame before the caller looks at its deadline again.
const READ_POLL: Duration = Duration::from_millis(50);

/// A network interface as discovery uses it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Interface {
    /// Its name (`eth0`).
    pub name: String,
    /// Its hardware address.
    pub mac: [u8; 6],
    /// Its IPv4 addresses with their prefix lengths.
    pub ipv4: Vec<(Ipv4Addr, u8)>,
}

/// Whether `e` is the refusal of a raw socket to a process without CAP_NET_RAW.
pub fn is_permission(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::PermissionDenied
}

/// The message for a raw socket refused for want of privileges.
pub fn permission_hint(what: &str) -> String {
    format!("{what} needs CAP_NET_RAW (run as root, or `setcap cap_net_raw+ep` on kubectl-lekiwi)")
}

/// The named interfaces (an error names one that does not exist), or when `names` is empty
/// every interface that is up, not loopback, has a hardware address and an IPv4 address.
pub fn interfaces(names: &[String]) -> anyhow::Result<Vec<Interface>> {
    let all = pnet_datalink::interfaces();
    let convert = |i: &pnet_datalink::NetworkInterface| Interface {
        name: i.name.clone(),
        mac: i.mac.map(|m| m.octets()).unwrap_or_default(),
        ipv4: i
            .ips
            .iter()
            .filter_map(|n| match n.ip() {
                IpAddr::V4(ip) => Some((ip, n.prefix())),
                IpAddr::V6(_) => None,
            })
            .collect(),
    };
    if names.is_empty() {
        return Ok(all
            .iter()
            .filter(|i| {
                i.is_up() && !i.is_loopback() && i.mac.is_some_and(|m| m.octets() != [0; 6])
            })
            .map(convert)
            .filter(|i| !i.ipv4.is_empty())
            .collect());
    }
    names
        .iter()
        .map(|name| {
            all.iter()
                .find(|i| &i.name == name)
                .map(convert)
                .ok_or_else(|| anyhow::anyhow!("no network interface named {name:?}"))
        })
        .collect()
}

/// An open AF_PACKET link on one interface.
pub struct Link {
    tx: Box<dyn pnet_datalink::DataLinkSender>,
    rx: Box<dyn pnet_datalink::DataLinkReceiver>,
}

impl Link {
    /// Opens a link on `iface`, in promiscuous mode if asked (to see frames to other hosts).
    pub fn open(iface: &Interface, promiscuous: bool) -> io::Result<Link> {
        let wanted = pnet_datalink::interfaces()
            .into_iter()
            .find(|i| i.name == iface.name)
            .ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, "interface gone"))?;
        let config = pnet_datalink::Config {
            read_timeout: Some(READ_POLL),
            write_timeout: Some(READ_POLL),
            promiscuous,
            ..pnet_datalink::Config::default()
        };
        match pnet_datalink::channel(&wanted, config)? {
            pnet_datalink::Channel::Ethernet(tx, rx) => Ok(Link { tx, rx }),
            _ => Err(io::Error::other("not an Ethernet interface")),
        }
    }

    /// Sends one Ethernet frame.
    pub fn send(&mut self, frame: &[u8]) -> io::Result<()> {
        self.tx
            .send_to(frame, None)
            .unwrap_or_else(|| Err(io::Error::other("frame too large")))
    }

    /// The next frame, or `None` when none came within a short poll.
    pub fn next(&mut self) -> io::Result<Option<&[u8]>> {
        match self.rx.next() {
            Ok(frame) => Ok(Some(frame)),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
                ) =>
            {
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }
}
