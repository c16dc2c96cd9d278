//! `mdns-browse`: prints the DNS-SD services it resolves as JSON lines, as they arrive.
//!
//! It uses mdns-sd directly rather than `lekiwi_discovery`, so the tests check the
//! agent's advertisement with code that shares nothing with the advertiser but the protocol.
//!
//! ```text
//! mdns-browse [--timeout-ms 3000] [--type _lekiwi._tcp.local.]
//! {"event":"resolved","instance":"kiwi-lab","fullname":"kiwi-lab._lekiwi._tcp.local.",
//!  "host":"kiwi-lab.local.","port":9477,"addresses":["192.0.2.2"],"txt":{"robot":"lab/kiwi",...}}
//! {"event":"removed","instance":"kiwi-lab","fullname":"kiwi-lab._lekiwi._tcp.local."}
//! ```
//!
//! Every resolution is printed, also a repeated one with changed records, so a caller watching
//! the output sees updates; the program exits when the timeout has passed.

use std::collections::BTreeMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail};
use mdns_sd::{ServiceDaemon, ServiceEvent};
use serde_json::json;

const USAGE: &str = "usage: mdns-browse [--timeout-ms MS] [--type SERVICE_TYPE]";

fn main() -> Result<()> {
    let mut timeout = Duration::from_millis(3000);
    let mut service_type = "_lekiwi._tcp.local.".to_owned();
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--timeout-ms" => {
                let value = args.next().context(USAGE)?;
                timeout = Duration::from_millis(
                    value
                        .parse()
                        .with_context(|| format!("--timeout-ms {value}"))?,
                );
            }
            "--type" => service_type = args.next().context(USAGE)?,
            "-h" | "--help" => {
                println!("{USAGE}");
                return Ok(());
            }
            other => bail!("unknown argument {other}\n{USAGE}"),
        }
    }

    let daemon = ServiceDaemon::new().context("start the mDNS daemon")?;
    let events = daemon
        .browse(&service_type)
        .with_context(|| format!("browse {service_type}"))?;
    let instance = |fullname: &str| {
        fullname
            .strip_suffix(service_type.as_str())
            .and_then(|s| s.strip_suffix('.'))
            .unwrap_or(fullname)
            .to_owned()
    };
    let deadline = Instant::now() + timeout;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break;
        }
        let Ok(event) = events.recv_timeout(left) else {
            break;
        };
        match event {
            ServiceEvent::ServiceResolved(info) => {
                let mut addresses: Vec<IpAddr> = info.get_addresses().iter().copied().collect();
                addresses.sort();
                let txt: BTreeMap<String, String> = info
                    .get_properties()
                    .iter()
                    .map(|p| (p.key().to_owned(), p.val_str().to_owned()))
                    .collect();
                println!(
                    "{}",
                    json!({
                        "event": "resolved",
                        "instance": instance(info.get_fullname()),
                        "fullname": info.get_fullname(),
                        "host": info.get_hostname(),
                        "port": info.get_port(),
                        "addresses": addresses,
                        "txt": txt,
                    })
                );
            }
            ServiceEvent::ServiceRemoved(_, fullname) => {
                println!(
                    "{}",
                    json!({ "event": "removed", "instance": instance(&fullname), "fullname": fullname })
                );
            }
            _ => {}
        }
    }
    let _ = daemon.stop_browse(&service_type);
    if let Ok(done) = daemon.shutdown() {
        let _ = done.recv_timeout(Duration::from_secs(1));
    }
    Ok(())
}
