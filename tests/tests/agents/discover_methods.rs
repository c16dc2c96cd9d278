//! `kubectl lekiwi discover` by ARP and DHCP: real `lekiwi-agent` processes with mDNS off, each
//! in a network namespace on a bridge, found by an ARP sweep (and, without CAP_NET_RAW, by the
//! kernel's neighbour table), from dnsmasq and ISC dhcpd lease files and by listening to DHCP
//! traffic on the bridge, each confirmed by its status endpoint; all methods at once find each robot exactly once, listing every method that
//! found it, and a method that fails (an unreadable lease file, a missing interface) costs a
//! warning, never the others' results. Skipped where network namespaces cannot be made.
//!
//! `discover_time_to_find_per_method` (ignored; `bench/discover.sh` runs it) prints how long each
//! method needs to find `LEKIWI_DISCOVER_ROBOTS` (default 50) robots.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Result, ensure};
use lekiwi_tests::netns::{Lab, have_ip};
use lekiwi_tests::{ControlPlane, bin, create_robot, namespace};
use serde_json::{Value, json};

/// The test lab's subnet is 10.78.0.0/24, the benchmark's 10.79.0.0/24.
const NET: u8 = 78;
const BENCH_NET: u8 = 79;
/// Time the benchmark's agents get to start up before it measures.
const BENCH_SETTLE: Duration = Duration::from_secs(15);

/// A DHCP client renewing its lease: a DHCPREQUEST from port 68 to the server `argv[2]`:67
/// naming its address `argv[1]` (`ciaddr` and option 50), every 100 ms for 20 s.
const DHCP_CLIENT: &str = r#"
import socket, struct, sys, time
ip = socket.inet_aton(sys.argv[1])
bootp = struct.pack("!BBBBIHH4s4s4s4s16s64s128s", 1, 1, 6, 0, 0x1234, 0, 0, ip, b"\0" * 4,
                    b"\0" * 4, b"\0" * 4, b"\x52\x54\x00\x00\x00\x03" + b"\0" * 10, b"", b"")
bootp += bytes([99, 130, 83, 99, 53, 1, 3, 50, 4]) + ip + bytes([255])
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("", 68))
end = time.time() + 20
while time.time() < end:
    s.sendto(bootp, (sys.argv[2], 67))
    time.sleep(0.1)
"#;

/// One `discover -o json` run: what it found, its stderr and how long it took.
struct Run {
    found: Vec<Value>,
    stderr: String,
    took: Duration,
}

impl Run {
    /// The entries for `robot`.
    fn of(&self, robot: &str) -> Vec<&Value> {
        self.found.iter().filter(|f| f["robot"] == robot).collect()
    }
}

/// Runs `discover -o json` with `args`, under `wrapper` (e.g. `capsh ... --`) if any.
fn discover(kubeconfig: &Path, wrapper: &[&str], args: &[&str]) -> Result<Run> {
    let start = Instant::now();
    let mut cmd = match wrapper.split_first() {
        Some((program, rest)) => {
            let mut c = Command::new(program);
            c.args(rest).arg(bin("kubectl-lekiwi"));
            c
        }
        None => Command::new(bin("kubectl-lekiwi")),
    };
    let out = cmd
        .arg("--kubeconfig")
        .arg(kubeconfig)
        .args(["discover", "-o", "json"])
        .args(args)
        .output()?;
    let took = start.elapsed();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    ensure!(out.status.success(), "discover failed: {stderr}");
    eprintln!("discover {args:?} took {took:?}; stderr: {stderr}");
    Ok(Run {
        found: lekiwi_tests::list_items(&out.stdout)?,
        stderr,
        took,
    })
}

/// A lab of `n` agents advertising over mDNS or not, robots `<ns>/kiwi-<i>`; `None` (and why, printed) where
/// network namespaces cannot be made.
async fn lab(n: usize, net: u8, ns: &str, mdns: bool) -> Result<Option<(Lab, Vec<String>)>> {
    if !have_ip() {
        eprintln!("skipped: `ip` (iproute2) is not installed");
        return Ok(None);
    }
    let mut lab = match Lab::build(n, net) {
        Ok(lab) => lab,
        Err(e) => {
            eprintln!("skipped: cannot create network namespaces here ({e:#})");
            return Ok(None);
        }
    };
    let robots: Vec<String> = (1..=n).map(|i| format!("{ns}/kiwi-{i}")).collect();
    for (i, robot) in robots.iter().enumerate() {
        lab.start_agent(i + 1, robot, mdns)?;
    }
    lab.wait_status(n, Duration::from_secs(60)).await?;
    Ok(Some((lab, robots)))
}

#[tokio::test]
async fn discover_by_arp_and_dhcp_without_mdns() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "methods").await?;
    let Some((mut lab, robots)) = lab(3, NET, &ns, false).await? else {
        return Ok(());
    };
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let kubeconfig = cp.kubeconfig();
    let bridge = lab.bridge.clone();

    // ARP sweep of the bridge's subnet, confirmed by the status endpoints: all three, once each.
    let run = discover(&kubeconfig, &[], &["--no-mdns", "--arp-interface", &bridge])?;
    for (i, robot) in robots.iter().enumerate() {
        let mine = run.of(robot);
        ensure!(
            mine.len() == 1,
            "{robot} not found once by ARP: {:?}",
            run.found
        );
        assert_eq!(mine[0]["via"], json!(["arp"]), "{robot}");
        assert_eq!(
            mine[0]["addresses"],
            json!([format!("{}:9477", lab.address(i + 1))])
        );
        assert_eq!(mine[0]["registered"], i == 0, "{robot}");
    }
    assert!(run.took < Duration::from_secs(2), "took {:?}", run.took);

    // Without CAP_NET_RAW the sweep is refused, said so, and the neighbour table (which knows
    // the three since the status checks above) still finds them.
    if Command::new("capsh").arg("--help").output().is_ok() {
        let run = discover(
            &kubeconfig,
            &[
                "capsh",
                "--drop=cap_net_raw",
                "--",
                "-c",
                "exec \"$0\" \"$@\"",
            ],
            &["--no-mdns", "--arp-interface", &bridge],
        )?;
        assert!(run.stderr.contains("needs CAP_NET_RAW"), "{}", run.stderr);
        for robot in &robots {
            ensure!(
                run.of(robot).len() == 1,
                "{robot} not in the table: {:?}",
                run.found
            );
        }
    } else {
        eprintln!(
            "capsh (libcap2-bin) not installed: the fallback without CAP_NET_RAW is not tested"
        );
    }

    // Lease files of both formats, with an unreadable line and an unreadable file.
    let dir = tempfile::tempdir()?;
    let dnsmasq = dir.path().join("dnsmasq.leases");
    let isc = dir.path().join("dhcpd.leases");
    std::fs::write(
        &dnsmasq,
        format!(
            "1764000000 52:54:00:00:00:11 {} kiwi-1 *\n1764000000 52:54:00:00:00:12 {} kiwi-2 *\nnot a lease\n",
            lab.address(1),
            lab.address(2)
        ),
    )?;
    std::fs::write(
        &isc,
        format!(
            "# isc-dhcp-4.4.3\nlease {} {{\n  binding state active;\n  hardware ethernet 52:54:00:00:00:13;\n}}\n",
            lab.address(3)
        ),
    )?;
    let (dnsmasq, isc) = (dnsmasq.to_string_lossy(), isc.to_string_lossy());
    let run = discover(
        &kubeconfig,
        &[],
        &[
            "--no-mdns",
            "--dhcp-leases",
            &dnsmasq,
            "--dhcp-leases",
            &isc,
            "--dhcp-leases",
            "/nonexistent/dhcpd.leases",
        ],
    )?;
    for robot in &robots {
        let mine = run.of(robot);
        ensure!(
            mine.len() == 1,
            "{robot} not found once by DHCP: {:?}",
            run.found
        );
        assert_eq!(mine[0]["via"], json!(["dhcp"]), "{robot}");
    }
    assert!(run.stderr.contains("line 3: not"), "{}", run.stderr);
    assert!(
        run.stderr
            .contains("dhcp: cannot read /nonexistent/dhcpd.leases"),
        "{}",
        run.stderr
    );

    // Listening on the bridge: robot 3 renews its lease (a DHCPREQUEST to the server, the
    // bridge's address, every 100 ms while discover listens) and is found by the address it
    // names.
    let server = format!("10.{NET}.0.1");
    let client = lab.address(3);
    lab.spawn_in(
        3,
        "dhcp-client",
        "python3",
        &["-c", DHCP_CLIENT, &client, &server],
    )?;
    let run = discover(&kubeconfig, &[], &["--no-mdns", "--dhcp-listen", &bridge])?;
    let mine = run.of(&robots[2]);
    ensure!(
        mine.len() == 1,
        "kiwi-3 not found by listening: {:?}",
        run.found
    );
    assert_eq!(mine[0]["via"], json!(["dhcp"]));
    for robot in &robots[..2] {
        ensure!(
            run.of(robot).is_empty(),
            "{robot} sent no DHCP: {:?}",
            run.found
        );
    }

    // Every method at once, two of them failing: each robot once, with all that found it.
    let subnet = lab.subnet();
    let run = discover(
        &kubeconfig,
        &[],
        &[
            "--probe",
            &subnet,
            "--arp-interface",
            &bridge,
            "--dhcp-leases",
            &dnsmasq,
            "--dhcp-leases",
            "/nonexistent/dhcpd.leases",
            "--dhcp-listen",
            "lk-no-such-if",
        ],
    )?;
    for (i, robot) in robots.iter().enumerate() {
        let mine = run.of(robot);
        ensure!(mine.len() == 1, "{robot} not found once: {:?}", run.found);
        let via = if i < 2 {
            json!(["arp", "dhcp", "probe"])
        } else {
            json!(["arp", "probe"])
        };
        assert_eq!(mine[0]["via"], via, "{robot}");
        assert_eq!(
            mine[0]["addresses"],
            json!([format!("{}:9477", lab.address(i + 1))])
        );
    }
    assert!(run.stderr.contains("lk-no-such-if"), "{}", run.stderr);
    assert!(run.took < Duration::from_secs(2), "took {:?}", run.took);
    Ok(())
}

/// How long each method needs to find every robot of a lab: how many it finds in each window
/// (`--timeout`) of a series, each run once, and the shortest window from which on it found
/// them all.
#[tokio::test]
#[ignore = "benchmark: bench/discover.sh runs it"]
async fn discover_time_to_find_per_method() -> Result<()> {
    let n: usize = std::env::var("LEKIWI_DISCOVER_ROBOTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(50);
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "discover-bench").await?;
    let Some((lab, robots)) = lab(n, BENCH_NET, &ns, true).await? else {
        return Ok(());
    };
    // 50 agents starting at once keep the CPUs busy for a while: measure once they idle.
    tokio::time::sleep(BENCH_SETTLE).await;
    let kubeconfig = cp.kubeconfig();
    let dir = tempfile::tempdir()?;
    let leases = dir.path().join("dnsmasq.leases");
    let lines: String = (1..=n)
        .map(|i| {
            format!(
                "1764000000 52:54:00:00:01:{i:02x} {} kiwi-{i} *\n",
                lab.address(i)
            )
        })
        .collect();
    std::fs::write(&leases, lines)?;
    let (subnet, bridge, leases) = (lab.subnet(), lab.bridge.clone(), leases.to_string_lossy());
    let methods: [(&str, Vec<&str>); 4] = [
        ("mdns", vec![]),
        ("probe", vec!["--no-mdns", "--probe", &subnet]),
        ("arp", vec!["--no-mdns", "--arp-interface", &bridge]),
        ("dhcp", vec!["--no-mdns", "--dhcp-leases", &leases]),
    ];
    const WINDOWS_MS: [u64; 7] = [100, 200, 300, 500, 750, 1000, 1500];
    let header: Vec<String> = WINDOWS_MS.iter().map(|ms| format!("{ms} ms")).collect();
    println!(
        "| method | time to find all {n} | found in a window of: {} |",
        header.join(" | ")
    );
    println!("|---|---|{}", "---|".repeat(WINDOWS_MS.len()));
    for (method, args) in methods {
        let mut counts = Vec::new();
        for ms in WINDOWS_MS {
            let timeout = format!("{ms}ms");
            let mut all_args = vec!["--timeout", timeout.as_str()];
            all_args.extend(&args);
            let run = discover(&kubeconfig, &[], &all_args)?;
            counts.push(robots.iter().filter(|r| !run.of(r).is_empty()).count());
        }
        // The shortest window from which on every longer one found all.
        let all_from = (0..WINDOWS_MS.len())
            .rev()
            .take_while(|&i| counts[i] == n)
            .last()
            .map_or("not within 1.5 s".to_owned(), |i| {
                format!("{} ms", WINDOWS_MS[i])
            });
        let counts: Vec<String> = counts.iter().map(|c| c.to_string()).collect();
        println!("| {method} | {all_from} | {} |", counts.join(" | "));
    }
    Ok(())
}
