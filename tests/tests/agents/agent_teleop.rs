//! Teleoperation detection against this machine's real `/proc`: a real stand-in for the LeKiwi
//! host (a Python process that listens on a command port and holds a "serial device" open),
//! driven by a real TCP client.

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result, bail, ensure};
use lekiwi_agent::config::Config;
use lekiwi_agent::teleop::{Detector, Verdict};

/// How long a socket may take to leave ESTABLISHED after the client closes.
const SETTLE: Duration = Duration::from_secs(5);

/// Opens the device, listens on a free port, prints it, then serves one client at a time
/// until the client closes. The marker and device come as arguments, so the marker is in
/// the command line but not in this script.
const HOST: &str = r#"
import socket, sys
device = open(sys.argv[2], "rb")
server = socket.socket()
server.bind(("127.0.0.1", 0))
server.listen(8)
print(server.getsockname()[1], flush=True)
while True:
    conn, _ = server.accept()
    while conn.recv(4096):
        pass
    conn.close()
"#;

/// The stand-in host; killed on drop.
struct Host {
    child: Child,
    port: u16,
    pattern: String,
    device: PathBuf,
    _dir: tempfile::TempDir,
}

impl Host {
    fn start() -> Result<Host> {
        let dir = tempfile::Builder::new()
            .prefix("lekiwi-teleop-")
            .tempdir()?;
        let device = dir.path().join("ttyACM0");
        std::fs::write(&device, "")?;
        let nanos = SystemTime::now().duration_since(UNIX_EPOCH)?.as_nanos();
        let pattern = format!("lekiwi-teleop-test-{}-{nanos}", std::process::id());
        let mut child = Command::new("python3")
            .args(["-c", HOST, &pattern])
            .arg(&device)
            .stdout(Stdio::piped())
            .spawn()
            .context("spawn python3")?;
        let stdout = child.stdout.take().context("child stdout")?;
        let mut host = Host {
            child,
            port: 0,
            pattern,
            device,
            _dir: dir,
        };
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line)?;
        host.port = line
            .trim()
            .parse()
            .with_context(|| format!("host printed {line:?}, not its port"))?;
        Ok(host)
    }

    /// The agent's configuration for this host: its pattern, its port as the only command
    /// port, its device; no video or stream ports, so that other sockets of this machine
    /// cannot interfere.
    fn config(&self) -> Config {
        Config {
            teleop_process_pattern: self.pattern.clone(),
            teleop_command_ports: vec![self.port],
            teleop_video_ports: vec![],
            teleop_stream_ports: vec![],
            teleop_serial_device: self.device.clone(),
            ..Config::default()
        }
    }

    fn connect(&self) -> Result<TcpStream> {
        Ok(TcpStream::connect(("127.0.0.1", self.port))?)
    }
}

impl Drop for Host {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn names(v: &Verdict) -> Vec<&str> {
    v.indicators.iter().map(String::as_str).collect()
}

/// Checks until `done` holds, for at most [`SETTLE`].
fn check_until(
    detector: &mut Detector,
    what: &str,
    done: impl Fn(&Verdict) -> bool,
) -> Result<Verdict> {
    let start = Instant::now();
    loop {
        let v = detector.check();
        if done(&v) {
            return Ok(v);
        }
        if start.elapsed() > SETTLE {
            bail!("{what}: still {v:?} after {SETTLE:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn is_idle_host(v: &Verdict) -> bool {
    names(v) == ["process", "serial_device"]
}

#[test]
fn a_connection_to_the_command_port_is_teleoperation_an_idle_host_is_not() -> Result<()> {
    let host = Host::start()?;
    let mut detector = Detector::new(&host.config());

    let idle = detector.check();
    ensure!(is_idle_host(&idle), "idle host: {idle:?}");
    ensure!(!idle.active && (idle.score - 0.3).abs() < 1e-9, "{idle:?}");

    let client = host.connect()?;
    let driven = check_until(&mut detector, "connected", |v| v.active)?;
    ensure!(
        names(&driven) == ["process", "command_connection", "serial_device"],
        "{driven:?}"
    );
    ensure!((driven.score - 0.9).abs() < 1e-9, "{driven:?}");
    ensure!(driven.to_wire().active, "{:?}", driven.to_wire());

    // Closed: the sockets go through FIN_WAIT/CLOSE_WAIT/TIME_WAIT, none of them ESTABLISHED.
    drop(client);
    let after = check_until(&mut detector, "disconnected", is_idle_host)?;
    ensure!(!after.active, "{after:?}");

    // A second session is seen again by the same detector.
    let client = host.connect()?;
    check_until(&mut detector, "reconnected", |v| v.active)?;
    drop(client);
    check_until(&mut detector, "disconnected again", |v| !v.active)?;

    drop(host);
    let gone = check_until(&mut detector, "host stopped", |v| v.indicators.is_empty())?;
    ensure!(gone.score == 0.0, "{gone:?}");
    Ok(())
}

#[test]
fn a_zero_weight_turns_an_indicator_off() -> Result<()> {
    let host = Host::start()?;
    let _client = host.connect()?;
    check_until(&mut Detector::new(&host.config()), "connected", |v| {
        v.active
    })?;

    for (config, off) in [
        (
            Config {
                teleop_command_weight: 0.0,
                ..host.config()
            },
            "command_connection",
        ),
        (
            Config {
                teleop_process_weight: 0.0,
                ..host.config()
            },
            "process",
        ),
        (
            Config {
                teleop_serial_weight: 0.0,
                ..host.config()
            },
            "serial_device",
        ),
    ] {
        let v = Detector::new(&config).check();
        let all = ["process", "command_connection", "serial_device"];
        let want: Vec<&str> = all.into_iter().filter(|n| *n != off).collect();
        ensure!(names(&v) == want, "{off} off: {v:?}");
    }
    let v = Detector::new(&Config {
        teleop_command_weight: 0.0,
        ..host.config()
    })
    .check();
    ensure!(
        !v.active,
        "without the connection the idle host remains: {v:?}"
    );
    Ok(())
}

#[test]
fn another_process_holding_the_device_counts_the_agent_itself_does_not() -> Result<()> {
    let host = Host::start()?;
    let config = Config {
        teleop_process_pattern: "lekiwi-no-such-process".into(),
        ..host.config()
    };
    let v = Detector::new(&config).check();
    ensure!(names(&v) == ["serial_device"], "{v:?}");

    // The agent (this test process) holding a device nobody else holds does not count.
    let dir = tempfile::tempdir()?;
    let own = dir.path().join("ttyUSB0");
    std::fs::write(&own, "")?;
    let _held = std::fs::File::open(&own)?;
    let v = Detector::new(&Config {
        teleop_serial_device: own,
        ..config
    })
    .check();
    ensure!(v.indicators.is_empty(), "{v:?}");
    Ok(())
}

/// The detector reads the kernel's socket tables with as few reads as it can; with more
/// sockets than fit in one read, a connection listed last is still seen.
#[test]
fn a_connection_behind_many_other_sockets_is_seen() -> Result<()> {
    let host = Host::start()?;
    let mut detector = Detector::new(&host.config());
    // Listening sockets come first in /proc/net/tcp, established ones after them.
    let others = (0..100)
        .map(|_| std::net::TcpListener::bind("127.0.0.1:0"))
        .collect::<std::io::Result<Vec<_>>>()?;
    let table = std::fs::read_to_string("/proc/net/tcp")?;
    ensure!(table.len() > 8192, "only {} bytes of sockets", table.len());
    ensure!(is_idle_host(&detector.check()));

    let _client = host.connect()?;
    let v = check_until(&mut detector, "connected", |v| v.active)?;
    ensure!(
        names(&v) == ["process", "command_connection", "serial_device"],
        "{v:?}"
    );
    drop(others);
    Ok(())
}
