//! Robots on other hosts, made of network namespaces: each namespace is linked by a veth pair
//! to a bridge in the root namespace (`10.<net>.0.1/24`), has the address `10.<net>.0.<10 + i>`
//! and can run a real `lekiwi-agent` serving `/status` there. Used by the `discover` tests and
//! the discovery benchmark; everything is removed when the [`Lab`] is dropped. Needs root. Also
//! [`NetView`]: what a network namespace holds (addresses, routes, bridges, iptables chains).

use std::net::IpAddr;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{Context as _, Result, bail};
use ipnet::IpNet;
use serde_json::Value;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

use crate::{bin, log_dir};

/// Runs `ip` with `args`; an error carries its stderr.
pub fn ip(args: &[&str]) -> Result<()> {
    let out = Command::new("ip")
        .args(args)
        .output()
        .context("run ip (iproute2)")?;
    if !out.status.success() {
        bail!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

/// Whether `ip` (iproute2) is installed.
pub fn have_ip() -> bool {
    Command::new("ip").arg("-V").output().is_ok()
}

/// The namespaces, links and agent processes of a test; all removed when dropped.
pub struct Lab {
    /// The bridge in the root namespace.
    pub bridge: String,
    /// The second octet of the lab's subnet `10.<net>.0.0/24`.
    pub net: u8,
    namespaces: Vec<String>,
    host_links: Vec<String>,
    /// Agents and other processes started in the namespaces.
    agents: Vec<Child>,
    states: Vec<tempfile::TempDir>,
}

impl Drop for Lab {
    fn drop(&mut self) {
        for agent in &mut self.agents {
            let _ = agent.kill();
            let _ = agent.wait();
        }
        // Deleting a namespace deletes the veth end inside it and so its peer.
        for ns in &self.namespaces {
            let _ = ip(&["netns", "del", ns]);
        }
        for link in &self.host_links {
            let _ = ip(&["link", "del", link]);
        }
        let _ = ip(&["link", "del", &self.bridge]);
    }
}

impl Lab {
    /// A bridge on `10.<net>.0.0/24` with `n` (at most 200) namespaces on it, or why it cannot
    /// be made. Labs of one process need different `net`s.
    pub fn build(n: usize, net: u8) -> Result<Lab> {
        anyhow::ensure!(n <= 200, "at most 200 namespaces in a lab");
        let id = std::process::id() % 10_000;
        let mut lab = Lab {
            bridge: format!("lkb{net}-{id}"),
            net,
            namespaces: Vec::new(),
            host_links: Vec::new(),
            agents: Vec::new(),
            states: Vec::new(),
        };
        // The first namespace tells whether we may make them at all.
        let first = format!("lkd{net}-{id}-1");
        ip(&["netns", "add", &first])?;
        lab.namespaces.push(first);
        // Snooping off: without an IGMP querier on this bridge, mDNS multicast is flooded.
        let bridge = lab.bridge.clone();
        ip(&[
            "link",
            "add",
            "name",
            &bridge,
            "type",
            "bridge",
            "mcast_snooping",
            "0",
        ])?;
        ip(&["addr", "add", &format!("10.{net}.0.1/24"), "dev", &bridge])?;
        ip(&["link", "set", &bridge, "up"])?;
        for i in 1..=n {
            let ns = format!("lkd{net}-{id}-{i}");
            if i > 1 {
                ip(&["netns", "add", &ns])?;
                lab.namespaces.push(ns.clone());
            }
            let host = format!("lk{net}-{id}h{i}");
            let inner = format!("lk{net}-{id}n{i}");
            ip(&["link", "add", &host, "type", "veth", "peer", "name", &inner])?;
            lab.host_links.push(host.clone());
            ip(&["link", "set", &inner, "netns", &ns])?;
            ip(&["link", "set", &host, "master", &bridge])?;
            ip(&["link", "set", &host, "up"])?;
            let addr = format!("{}/24", lab.address(i));
            ip(&["-n", &ns, "addr", "add", &addr, "dev", &inner])?;
            ip(&["-n", &ns, "link", "set", &inner, "up"])?;
            ip(&["-n", &ns, "link", "set", "lo", "up"])?;
        }
        Ok(lab)
    }

    /// The subnet, `10.<net>.0.0/24`.
    pub fn subnet(&self) -> String {
        format!("10.{}.0.0/24", self.net)
    }

    /// The address of namespace `i` (1-based).
    pub fn address(&self, i: usize) -> String {
        format!("10.{}.0.{}", self.net, 10 + i)
    }

    /// Runs `program` with `args` in namespace `i` (1-based), its output in the test logs;
    /// the lab kills it when dropped.
    pub fn spawn_in(&mut self, i: usize, name: &str, program: &str, args: &[&str]) -> Result<()> {
        let ns = self.namespaces[i - 1].clone();
        let log = log_dir().join(format!("netns-{name}-{ns}.log"));
        let file = std::fs::File::create(&log)?;
        let child = Command::new("ip")
            .args(["netns", "exec", &ns, program])
            .args(args)
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .with_context(|| format!("spawn {program} in a network namespace"))?;
        self.agents.push(child);
        Ok(())
    }

    /// Starts a real agent for `robot` in namespace `i` (1-based), serving `/status` on all
    /// its addresses, advertising over mDNS if `mdns`. Its gateway is unreachable from there.
    pub fn start_agent(&mut self, i: usize, robot: &str, mdns: bool) -> Result<()> {
        let ns = self.namespaces[i - 1].clone();
        let state = tempfile::tempdir()?;
        let log = log_dir().join(format!("netns-agent-{ns}.log"));
        let file = std::fs::File::create(&log)?;
        let child = Command::new("ip")
            .args(["netns", "exec", &ns])
            .arg(bin("lekiwi-agent"))
            .args(["--config", "/nonexistent/lekiwi-agent.yaml"])
            .args(["--gateway", &format!("ws://10.{}.0.1:9/v1/agent", self.net)])
            // Not loopback, and never reached: plain text must be allowed explicitly.
            .arg("--insecure-allow-plaintext")
            .args(["--robot-name", robot])
            .args(["--enrollment-token", "lke_unused-gateway-unreachable"])
            .arg("--state-dir")
            .arg(state.path())
            .args(["--status-listen", "0.0.0.0:9477"])
            .args(["--mdns", if mdns { "true" } else { "false" }])
            .args(["--backoff-initial-ms", "200", "--backoff-max-ms", "2000"])
            .args(["--log-format", "json"])
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .context("spawn lekiwi-agent in a network namespace")?;
        self.agents.push(child);
        self.states.push(state);
        Ok(())
    }

    /// Waits until the status endpoint of each of the first `n` namespaces answers.
    pub async fn wait_status(&self, n: usize, timeout: Duration) -> Result<()> {
        for i in 1..=n {
            let addr = format!("{}:9477", self.address(i));
            crate::wait_for(&format!("the status endpoint at {addr}"), timeout, || {
                let addr = addr.clone();
                async move { status(&addr).await }
            })
            .await?;
        }
        Ok(())
    }
}

/// `GET /status` of an address in a lab, from the root namespace.
pub async fn status(addr: &str) -> Option<Value> {
    let connect = tokio::net::TcpStream::connect(addr);
    let mut stream = tokio::time::timeout(Duration::from_millis(500), connect)
        .await
        .ok()?
        .ok()?;
    stream
        .write_all(b"GET /status HTTP/1.0\r\nHost: lab\r\n\r\n")
        .await
        .ok()?;
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await.ok()?;
    let text = String::from_utf8_lossy(&buf);
    serde_json::from_str(text.split_once("\r\n\r\n")?.1).ok()
}

/// What a network namespace holds, as `ip` and `iptables-save` list it.
#[derive(Debug)]
pub struct NetView {
    /// Every address with its prefix, and its link.
    pub addresses: Vec<(IpNet, String)>,
    /// Every route in every table, IPv4 and IPv6, but `default` (it says nothing of where a
    /// range is).
    pub routes: Vec<Route>,
    /// The bridges' names.
    pub bridges: Vec<String>,
    /// The names of the iptables and ip6tables chains, in every table.
    pub chains: Vec<String>,
}

/// A route of a [`NetView`].
#[derive(Debug)]
pub struct Route {
    /// Where it leads.
    pub dst: IpNet,
    /// Its link.
    pub dev: String,
    /// Its gateway, if any.
    pub via: Option<IpAddr>,
}

impl NetView {
    /// The view of the network namespace `netns` (an `ip netns` name), or of the caller's own
    /// with `None`.
    pub fn of(netns: Option<&str>) -> Result<NetView> {
        let run = |program: &str, args: &[&str]| -> Result<String> {
            let mut cmd = match netns {
                Some(ns) => {
                    let mut cmd = Command::new("ip");
                    cmd.args(["netns", "exec", ns, program]);
                    cmd
                }
                None => Command::new(program),
            };
            let out = cmd
                .args(args)
                .output()
                .with_context(|| format!("run {program}"))?;
            if !out.status.success() {
                bail!(
                    "{program} {}: {}",
                    args.join(" "),
                    String::from_utf8_lossy(&out.stderr).trim()
                );
            }
            Ok(String::from_utf8_lossy(&out.stdout).into_owned())
        };
        let json =
            |args: &[&str]| -> Result<Vec<Value>> { Ok(serde_json::from_str(&run("ip", args)?)?) };
        let mut addresses = Vec::new();
        for link in json(&["-j", "addr", "show"])? {
            let name = link["ifname"].as_str().unwrap_or_default();
            for info in link["addr_info"].as_array().into_iter().flatten() {
                let addr: IpAddr = info["local"].as_str().unwrap_or_default().parse()?;
                let prefix = info["prefixlen"].as_u64().unwrap_or_default();
                addresses.push((IpNet::new(addr, u8::try_from(prefix)?)?, name.to_owned()));
            }
        }
        let mut routes = Vec::new();
        for family in ["-4", "-6"] {
            for route in json(&["-j", family, "route", "show", "table", "all"])? {
                let dst = route["dst"].as_str().unwrap_or_default();
                let dst = match dst.parse::<IpNet>() {
                    Ok(net) => net,
                    Err(_) => match dst.parse::<IpAddr>() {
                        Ok(addr) => IpNet::from(addr),
                        Err(_) => continue,
                    },
                };
                routes.push(Route {
                    dst,
                    dev: route["dev"].as_str().unwrap_or_default().to_owned(),
                    via: route["gateway"].as_str().and_then(|g| g.parse().ok()),
                });
            }
        }
        let bridges = json(&["-j", "link", "show", "type", "bridge"])?
            .iter()
            .filter_map(|link| Some(link["ifname"].as_str()?.to_owned()))
            .collect();
        let mut chains = Vec::new();
        for save in ["iptables-save", "ip6tables-save"] {
            let rules = run(save, &[])?;
            let names = rules.lines().filter_map(|l| l.strip_prefix(':'));
            chains.extend(names.filter_map(|l| Some(l.split_whitespace().next()?.to_owned())));
        }
        Ok(NetView {
            addresses,
            routes,
            bridges,
            chains,
        })
    }
}
