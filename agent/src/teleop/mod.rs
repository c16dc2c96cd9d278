//! Teleoperation detection: a weighted score from indicators read in `/proc` (the LeKiwi host
//! process, ESTABLISHED connections on its ports, the motor serial device held open).
//!
//! A check reads `/proc/net/tcp` and `/proc/net/tcp6` once each (the kernel's walk of its TCP
//! hash table behind each is most of the cost) and makes one pass over `/proc/[pid]`, shared by
//! the process and serial indicators and skipped when the processes found last time still
//! match. An indicator with a weight of 0 costs nothing; an absent serial device costs no fd
//! scan.

use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use crate::config::Config;

mod procfs;

use procfs::{READ_CHUNK, canonical_if_different, join, join_pid, read_proc, read_table};
pub use procfs::{
    TCP_ESTABLISHED, TCP_LISTEN, TcpSocket, cmdline_contains, parse_hex_socket_addr, parse_tcp_line,
};

/// Indicator: a process whose command line contains the configured pattern runs.
pub const PROCESS: &str = "process";
/// Indicator: an ESTABLISHED connection whose local port is a command port.
pub const COMMAND_CONNECTION: &str = "command_connection";
/// Indicator: an ESTABLISHED connection whose local port is a video port.
pub const VIDEO_CONNECTION: &str = "video_connection";
/// Indicator: an ESTABLISHED connection whose local port is a stream port.
pub const STREAM_CONNECTION: &str = "stream_connection";
/// Indicator: a process other than the agent holds the serial device open.
pub const SERIAL_DEVICE: &str = "serial_device";

/// Scores are rounded to this many parts so that `0.1 + 0.2` reads `0.3` and sums that are
/// meant to equal the threshold do not miss it by one ulp.
const SCORE_SCALE: f64 = 1e9;

/// The outcome of one check.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Verdict {
    /// Whether the score reached the threshold.
    pub active: bool,
    /// Sum of the weights of the indicators that fired.
    pub score: f64,
    /// Names of the indicators that fired, in a fixed order: `process`, `command_connection`,
    /// `video_connection`, `stream_connection`, `serial_device`.
    pub indicators: Vec<String>,
}

impl Verdict {
    /// The verdict as heartbeats carry it; the score is clamped to the protocol's 0 to 1.
    pub fn to_wire(&self) -> lekiwi_protocol::Teleoperation {
        lekiwi_protocol::Teleoperation {
            active: self.active,
            score: Some(self.score.clamp(0.0, 1.0)),
        }
    }
}

/// Which process indicators a scan of `/proc` looks for.
#[derive(Clone, Copy, Debug)]
struct Wanted {
    process: bool,
    serial: bool,
}

impl Wanted {
    /// Whether every indicator looked for has fired, so the scan can stop.
    fn satisfied(self, process_hit: bool, serial_hit: bool) -> bool {
        (!self.process || process_hit) && (!self.serial || serial_hit)
    }
}

/// "A connection on one of these local ports is ESTABLISHED".
#[derive(Debug)]
struct PortIndicator {
    name: &'static str,
    ports: Vec<u16>,
    weight: f64,
}

/// "A process whose command line contains the pattern runs".
#[derive(Debug)]
struct ProcessIndicator {
    pattern: Vec<u8>,
    weight: f64,
    /// The pid that matched last time, checked first.
    last_match: Option<u32>,
}

/// "A process other than the agent holds the serial device open".
#[derive(Debug)]
struct SerialIndicator {
    configured: PathBuf,
    /// The device's canonical path (resolved once, as soon as the device exists).
    canonical: Option<PathBuf>,
    weight: f64,
    /// The pid that held the device last time, checked first.
    last_holder: Option<u32>,
}

impl SerialIndicator {
    fn is(&self, target: &Path) -> bool {
        target == self.configured || self.canonical.as_deref() == Some(target)
    }
}

/// What a look at one process's command line found.
enum Cmdline {
    /// It contains the pattern.
    Matches,
    /// It does not.
    Other,
    /// There is none: a kernel thread or a zombie.
    Empty,
}

/// What a look at one process's open files found.
enum Holding {
    /// The device is among its open files.
    Yes,
    /// It is not (or the process is gone).
    No,
    /// Its fds cannot be read (another user's process).
    Denied,
}

/// Teleoperation detector; keeps its buffers and last hits between checks.
#[derive(Debug)]
pub struct Detector {
    proc_root: PathBuf,
    own_pid: u32,
    threshold: f64,
    process: Option<ProcessIndicator>,
    /// Only the enabled ones (weight > 0, at least one port); at most three.
    connections: Vec<PortIndicator>,
    serial: Option<SerialIndicator>,
    /// Scratch path, reused for every file read.
    path: PathBuf,
    /// Scratch buffer for `cmdline` files.
    bytes: Vec<u8>,
    /// Scratch buffer for `net/tcp` files.
    table: Vec<u8>,
    /// Whether unreadable fd directories were logged already.
    denied_logged: bool,
}

impl Detector {
    /// A detector reading the real `/proc`.
    pub fn new(config: &Config) -> Detector {
        Detector::with_proc_root(config, "/proc")
    }

    /// A detector reading another `/proc` tree (tests use a fake one in a temporary directory).
    ///
    /// An indicator is off when its weight is not above 0, when its port list is empty, or
    /// (the process indicator) when its pattern is empty.
    pub fn with_proc_root(config: &Config, proc_root: impl Into<PathBuf>) -> Detector {
        let on = |weight: f64| weight > 0.0;
        let process = (on(config.teleop_process_weight)
            && !config.teleop_process_pattern.is_empty())
        .then(|| ProcessIndicator {
            pattern: config.teleop_process_pattern.as_bytes().to_vec(),
            weight: config.teleop_process_weight,
            last_match: None,
        });
        let connections = [
            (
                COMMAND_CONNECTION,
                &config.teleop_command_ports,
                config.teleop_command_weight,
            ),
            (
                VIDEO_CONNECTION,
                &config.teleop_video_ports,
                config.teleop_video_weight,
            ),
            (
                STREAM_CONNECTION,
                &config.teleop_stream_ports,
                config.teleop_stream_weight,
            ),
        ]
        .into_iter()
        .filter(|(_, ports, weight)| on(*weight) && !ports.is_empty())
        .map(|(name, ports, weight)| PortIndicator {
            name,
            ports: ports.clone(),
            weight,
        })
        .collect();
        let serial = on(config.teleop_serial_weight).then(|| {
            let configured = config.teleop_serial_device.clone();
            SerialIndicator {
                canonical: canonical_if_different(&configured),
                configured,
                weight: config.teleop_serial_weight,
                last_holder: None,
            }
        });
        Detector {
            proc_root: proc_root.into(),
            own_pid: std::process::id(),
            threshold: config.teleop_threshold,
            process,
            connections,
            serial,
            path: PathBuf::new(),
            bytes: Vec::new(),
            table: Vec::new(),
            denied_logged: false,
        }
    }

    /// Reads the indicators once and scores them.
    pub fn check(&mut self) -> Verdict {
        let connections = self.scan_connections();
        let (process, serial) = self.scan_processes();

        let mut score = 0.0;
        let mut indicators = Vec::new();
        let mut fire = |name: &str, weight: f64| {
            score += weight;
            indicators.push(name.to_owned());
        };
        if let Some(p) = self.process.as_ref().filter(|_| process) {
            fire(PROCESS, p.weight);
        }
        for (i, c) in self.connections.iter().enumerate() {
            if connections & (1 << i) != 0 {
                fire(c.name, c.weight);
            }
        }
        if let Some(s) = self.serial.as_ref().filter(|_| serial) {
            fire(SERIAL_DEVICE, s.weight);
        }
        let score = (score * SCORE_SCALE).round() / SCORE_SCALE;
        let verdict = Verdict {
            active: score >= self.threshold,
            score,
            indicators,
        };
        tracing::debug!(
            active = verdict.active,
            score = verdict.score,
            indicators = %verdict.indicators.join(","),
            "teleoperation check"
        );
        verdict
    }

    /// Which connection indicators fired, as a bit per index of `self.connections`.
    fn scan_connections(&mut self) -> u32 {
        let all = (1u32 << self.connections.len()) - 1;
        let mut fired = 0u32;
        for file in ["net/tcp", "net/tcp6"] {
            if fired == all {
                break;
            }
            let path = join(&mut self.path, &self.proc_root, &[file]);
            let table = match read_table(path, &mut self.table) {
                Ok(table) => table,
                // No IPv6 in this kernel.
                Err(e) if e.kind() == io::ErrorKind::NotFound => continue,
                Err(e) => {
                    tracing::debug!(path = %path.display(), error = %e, "cannot read sockets");
                    continue;
                }
            };
            for socket in table.lines().skip(1).filter_map(parse_tcp_line) {
                if socket.state != TCP_ESTABLISHED {
                    continue;
                }
                let port = socket.local.port();
                for (i, c) in self.connections.iter().enumerate() {
                    if c.ports.contains(&port) {
                        fired |= 1 << i;
                    }
                }
            }
        }
        fired
    }

    /// Whether the process and the serial indicators fired, from one pass over `/proc`.
    fn scan_processes(&mut self) -> (bool, bool) {
        let want = Wanted {
            process: self.process.is_some(),
            serial: self.serial_wanted(),
        };
        let (mut process_hit, mut serial_hit) = self.recheck_last(want);
        if !want.satisfied(process_hit, serial_hit) {
            (process_hit, serial_hit) = self.scan_all(want, process_hit, serial_hit);
        }
        self.remember(process_hit, serial_hit);
        (process_hit, serial_hit)
    }

    /// Whether the serial indicator needs an fd scan: not when it is off or its device absent.
    fn serial_wanted(&mut self) -> bool {
        match &mut self.serial {
            None => false,
            // An absent device is held by nobody: skip the fd scan, the costly part.
            Some(s) if !s.configured.exists() => {
                s.last_holder = None;
                false
            }
            Some(s) => {
                if s.canonical.is_none() {
                    s.canonical = canonical_if_different(&s.configured);
                }
                true
            }
        }
    }

    /// Checks the processes that fired last time: the host found last time is most likely
    /// still there and still holds the device.
    fn recheck_last(&mut self, want: Wanted) -> (bool, bool) {
        let mut process_hit = false;
        let mut serial_hit = false;
        if let Some(pid) = self.process.as_ref().and_then(|p| p.last_match) {
            process_hit = matches!(self.cmdline_matches(pid), Some(Cmdline::Matches));
        }
        if want.serial {
            let last_holder = self.serial.as_ref().and_then(|s| s.last_holder);
            let host = self.process.as_ref().and_then(|p| p.last_match);
            for pid in [last_holder, host.filter(|_| process_hit)]
                .into_iter()
                .flatten()
            {
                if matches!(self.holds_serial(pid), Holding::Yes) {
                    serial_hit = true;
                    break;
                }
            }
        }
        (process_hit, serial_hit)
    }

    /// One pass over `/proc/[pid]` until every wanted indicator fired; both `false` when the
    /// process list cannot be read.
    fn scan_all(
        &mut self,
        want: Wanted,
        mut process_hit: bool,
        mut serial_hit: bool,
    ) -> (bool, bool) {
        let entries = match fs::read_dir(&self.proc_root) {
            Ok(entries) => entries,
            Err(e) => {
                tracing::debug!(proc = %self.proc_root.display(), error = %e, "cannot list processes");
                return (false, false);
            }
        };
        let mut denied = 0u32;
        for entry in entries.flatten() {
            let name = entry.file_name();
            let Some(pid) = name.to_str().and_then(|n| n.parse::<u32>().ok()) else {
                continue;
            };
            if pid == self.own_pid {
                continue;
            }
            let mut kernel_thread = false;
            if want.process && !process_hit {
                match self.cmdline_matches(pid) {
                    // Gone since the listing.
                    None => continue,
                    Some(Cmdline::Matches) => {
                        process_hit = true;
                        if let Some(p) = &mut self.process {
                            p.last_match = Some(pid);
                        }
                    }
                    Some(Cmdline::Empty) => kernel_thread = true,
                    Some(Cmdline::Other) => {}
                }
            }
            // Kernel threads (and zombies) have no open files.
            if want.serial && !serial_hit && !kernel_thread {
                match self.holds_serial(pid) {
                    Holding::Yes => {
                        serial_hit = true;
                        if let Some(s) = &mut self.serial {
                            s.last_holder = Some(pid);
                        }
                    }
                    Holding::No => {}
                    Holding::Denied => denied += 1,
                }
            }
            if want.satisfied(process_hit, serial_hit) {
                break;
            }
        }
        self.log_denied_once(denied);
        (process_hit, serial_hit)
    }

    /// Says once per agent that some processes' open files are unreadable (not root).
    fn log_denied_once(&mut self, denied: u32) {
        if denied > 0 && !self.denied_logged {
            self.denied_logged = true;
            tracing::debug!(
                processes = denied,
                "cannot read the open files of some processes; a serial device held by them is \
                 not seen (logged once)"
            );
        }
    }

    /// Forgets the pids of indicators that did not fire, so the next check scans afresh.
    fn remember(&mut self, process_hit: bool, serial_hit: bool) {
        if let Some(p) = self.process.as_mut().filter(|_| !process_hit) {
            p.last_match = None;
        }
        if let Some(s) = self.serial.as_mut().filter(|_| !serial_hit) {
            s.last_holder = None;
        }
    }

    /// Whether `pid`'s command line contains the pattern; `None` when it cannot be read.
    fn cmdline_matches(&mut self, pid: u32) -> Option<Cmdline> {
        let process = self.process.as_ref()?;
        let path = join_pid(&mut self.path, &self.proc_root, pid, "cmdline");
        // The kernel copies the whole argument area unless the buffer is full: a short read
        // is the end.
        let len = read_proc(path, &mut self.bytes, READ_CHUNK).ok()?;
        Some(if len == 0 {
            Cmdline::Empty
        } else if cmdline_contains(&mut self.bytes[..len], &process.pattern) {
            Cmdline::Matches
        } else {
            Cmdline::Other
        })
    }

    /// Whether one of `pid`'s open files is the serial device.
    fn holds_serial(&mut self, pid: u32) -> Holding {
        let Some(serial) = &self.serial else {
            return Holding::No;
        };
        let dir = join_pid(&mut self.path, &self.proc_root, pid, "fd");
        let fds = match fs::read_dir(dir) {
            Ok(fds) => fds,
            Err(e) if e.kind() == io::ErrorKind::PermissionDenied => return Holding::Denied,
            // Gone since the listing.
            Err(_) => return Holding::No,
        };
        for fd in fds.flatten() {
            match fs::read_link(fd.path()) {
                Ok(target) if serial.is(&target) => return Holding::Yes,
                Ok(_) => {}
                // Readable directory, unreadable links: all of its links are.
                Err(e) if e.kind() == io::ErrorKind::PermissionDenied => return Holding::Denied,
                // Closed since the listing.
                Err(_) => {}
            }
        }
        Holding::No
    }
}

#[cfg(test)]
mod tests {
    use std::os::unix::fs::symlink;

    use super::procfs::TABLE_PAGE;
    use super::*;

    // Lines captured from this kind of machine (little-endian: x86_64, aarch64).
    const TCP: &str = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode
   0: 00000000:15B3 00000000:0000 0A 00000000:00000000 00:00000000 00000000  1000        0 555 1 000000007e65e2a2 100 0 0 10 0
   1: 0100007F:BFB7 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 2086915 1 00000000282376b1 100 0 0 10 0
   2: 0100007F:8538 0100007F:BFB7 01 00000000:00000000 00:00000000 00000000     0        0 2086916 2 000000007e9113f6 20 0 0 10 -1
   3: 0100007F:BFB7 0100007F:8538 01 00000000:00000000 00:00000000 00000000     0        0 2086917 1 00000000ae4c85c7 20 0 0 10 -1
";
    const TCP6: &str = "  sl  local_address                         remote_address                        st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode
   0: 00000000000000000000000001000000:B849 00000000000000000000000000000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 2086920 1 000000008f8f3314 100 0 0 10 0
   1: 0000000000000000FFFF00000100007F:A6AF 0000000000000000FFFF00000100007F:996A 01 00000000:00000000 00:00000000 00000000     0        0 2086925 1 00000000bd8a9fca 20 0 0 10 -1
   2: 000080FE00000000B2FD1F3C2A5C44FE:15B3 000080FE0000000099F8FD5B0F9A3E11:D2F0 01 00000000:00000000 00:00000000 00000000  1000        0 2086921 2 00000000a5f615d7 20 0 0 10 -1
";
    const HEADER: &str = "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n";

    fn line(local: &str, remote: &str, state: &str) -> String {
        format!(
            "   7: {local} {remote} {state} 00000000:00000000 00:00000000 00000000  1000        0 4242 1 0000000000000000 20 0 0 10 -1\n"
        )
    }

    /// An idle host ([`FakeProc::idle_host`]) whose `/proc/net/tcp` holds `lines` (returned
    /// too), and an empty `/proc/net/tcp6`.
    fn idle_host_with(lines: &[(&str, &str, &str)]) -> (FakeProc, String) {
        let fake = FakeProc::new();
        fake.idle_host();
        let tcp = table(lines);
        fake.sockets(&tcp, HEADER);
        (fake, tcp)
    }

    /// A `/proc/net/tcp{,6}` table: the header and one [`line`] per `(local, remote, state)`.
    fn table(lines: &[(&str, &str, &str)]) -> String {
        lines
            .iter()
            .fold(HEADER.to_owned(), |t, (l, r, st)| t + &line(l, r, st))
    }

    #[test]
    fn parses_ipv4_lines() {
        let lines: Vec<_> = TCP.lines().map(parse_tcp_line).collect();
        assert_eq!(lines[0], None, "the header is not a socket");
        assert_eq!(
            lines[1],
            Some(TcpSocket {
                local: "0.0.0.0:5555".parse().unwrap(),
                remote: "0.0.0.0:0".parse().unwrap(),
                state: TCP_LISTEN,
            })
        );
        assert_eq!(
            lines[4],
            Some(TcpSocket {
                local: "127.0.0.1:49079".parse().unwrap(),
                remote: "127.0.0.1:34104".parse().unwrap(),
                state: TCP_ESTABLISHED,
            })
        );
    }

    #[test]
    fn parses_ipv6_lines() {
        let lines: Vec<_> = TCP6.lines().map(parse_tcp_line).collect();
        assert_eq!(lines[0], None);
        let listen = lines[1].unwrap();
        assert_eq!(listen.local, "[::1]:47177".parse().unwrap());
        assert_eq!(listen.state, TCP_LISTEN);
        let mapped = lines[2].unwrap();
        assert_eq!(mapped.local, "[::ffff:127.0.0.1]:42671".parse().unwrap());
        assert_eq!(mapped.remote, "[::ffff:127.0.0.1]:39274".parse().unwrap());
        assert_eq!(mapped.state, TCP_ESTABLISHED);
        let link_local = lines[3].unwrap();
        assert_eq!(
            link_local.local,
            "[fe80::3c1f:fdb2:fe44:5c2a]:5555".parse().unwrap()
        );
        assert_eq!(link_local.remote.port(), 0xD2F0);
    }

    #[test]
    fn rejects_malformed_lines() {
        for bad in [
            "",
            "   0:",
            "   0: 0100007F:BFB7",
            "   0: 0100007F:BFB7 0100007F:8538",
            "   0: 0100007F:BFB7 0100007F:8538 XY",
            "   0: 0100007:BFB7 0100007F:8538 01",
            "   0: 0100007F:BFB7Z 0100007F:8538 01",
            "   0: 0100007F 0100007F:8538 01",
            "   0: 0000000000000000FFFF00000100007:A6AF 00000000:0000 01",
        ] {
            assert_eq!(parse_tcp_line(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn cmdline_reads_nuls_as_spaces() {
        let raw = b"python\0-m\0lerobot.robots.lekiwi.lekiwi_host\0--robot.id=kiwi\0";
        assert!(cmdline_contains(
            &mut raw.to_vec(),
            b"lerobot.robots.lekiwi.lekiwi_host"
        ));
        assert!(cmdline_contains(
            &mut raw.to_vec(),
            b"-m lerobot.robots.lekiwi.lekiwi_host --robot"
        ));
        assert!(
            !cmdline_contains(&mut raw.to_vec(), b"kiwi "),
            "no trailing space"
        );
        assert!(!cmdline_contains(&mut raw.to_vec(), b"lekiwi_client"));
        assert!(!cmdline_contains(&mut raw.to_vec(), b""));
        assert!(!cmdline_contains(&mut Vec::new(), b"python"));
    }

    /// A fake `/proc` in a temporary directory, with a stand-in serial device beside it.
    struct FakeProc {
        dir: tempfile::TempDir,
    }

    impl FakeProc {
        fn new() -> FakeProc {
            let dir = tempfile::tempdir().unwrap();
            fs::create_dir_all(dir.path().join("proc/net")).unwrap();
            fs::write(dir.path().join("ttyACM0"), "").unwrap();
            let fake = FakeProc { dir };
            fake.sockets(HEADER, HEADER);
            fake
        }

        fn root(&self) -> PathBuf {
            self.dir.path().join("proc")
        }

        fn device(&self) -> PathBuf {
            fs::canonicalize(self.dir.path().join("ttyACM0")).unwrap()
        }

        fn sockets(&self, tcp: &str, tcp6: &str) {
            fs::write(self.root().join("net/tcp"), tcp).unwrap();
            fs::write(self.root().join("net/tcp6"), tcp6).unwrap();
        }

        /// A process with this command line and these files open.
        fn process(&self, pid: u32, argv: &[&str], open: &[&Path]) {
            let dir = self.root().join(pid.to_string());
            let _ = fs::remove_dir_all(&dir);
            fs::create_dir_all(dir.join("fd")).unwrap();
            let cmdline: Vec<u8> = argv
                .iter()
                .flat_map(|a| [a.as_bytes(), b"\0"])
                .flatten()
                .copied()
                .collect();
            fs::write(dir.join("cmdline"), cmdline).unwrap();
            symlink("/dev/null", dir.join("fd/0")).unwrap();
            symlink("socket:[4242]", dir.join("fd/1")).unwrap();
            for (i, path) in open.iter().enumerate() {
                symlink(path, dir.join(format!("fd/{}", i + 3))).unwrap();
            }
        }

        fn exit(&self, pid: u32) {
            fs::remove_dir_all(self.root().join(pid.to_string())).unwrap();
        }

        /// The idle LeKiwi host (and some bystanders): it runs and holds the motors' port.
        fn idle_host(&self) {
            self.process(1, &["/sbin/init"], &[]);
            self.process(2, &[], &[]);
            self.process(
                812,
                &[
                    "python",
                    "-m",
                    "lerobot.robots.lekiwi.lekiwi_host",
                    "--robot.id=kiwi",
                ],
                &[&self.device()],
            );
            self.process(901, &["bash"], &[Path::new("/dev/pts/0")]);
            let listening = format!(
                "{HEADER}{}{}",
                line("00000000:15B3", "00000000:0000", "0A"),
                line("00000000:15B4", "00000000:0000", "0A")
            );
            self.sockets(&listening, HEADER);
        }

        fn config(&self) -> Config {
            Config {
                teleop_serial_device: self.dir.path().join("ttyACM0"),
                ..Config::default()
            }
        }

        fn check(&self, config: &Config) -> Verdict {
            Detector::with_proc_root(config, self.root()).check()
        }
    }

    fn names(v: &Verdict) -> Vec<&str> {
        v.indicators.iter().map(String::as_str).collect()
    }

    /// `agent/tests/fixtures/pi5/proc` (a Raspberry Pi 5 whose `lekiwi_host` a laptop drives; see
    /// the fixture's README) laid out under `dir`: its files, and each process's `fd.txt` ("FD
    /// TARGET" lines) made into the `fd` symlinks the kernel shows, with `/dev/` targets moved to
    /// `dir/dev/`, where the serial device exists. `established`: keep the ESTABLISHED lines of
    /// `net/tcp` (the laptop connected), else only the listening ones (an idle host).
    fn pi5_proc(dir: &Path, established: bool) -> PathBuf {
        let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pi5/proc");
        let root = dir.join("proc");
        fs::create_dir_all(root.join("net")).unwrap();
        fs::create_dir_all(dir.join("dev")).unwrap();
        fs::write(dir.join("dev/ttyACM0"), "").unwrap();
        for table in ["net/tcp", "net/tcp6"] {
            let text = fs::read_to_string(fixture.join(table)).unwrap();
            let kept: String = text
                .lines()
                .filter(|l| established || parse_tcp_line(l).is_none_or(|s| s.state == TCP_LISTEN))
                .flat_map(|l| [l, "\n"])
                .collect();
            fs::write(root.join(table), kept).unwrap();
        }
        for entry in fs::read_dir(&fixture).unwrap().flatten() {
            if entry.file_name() == "net" {
                continue;
            }
            let pid = root.join(entry.file_name());
            fs::create_dir_all(pid.join("fd")).unwrap();
            fs::copy(entry.path().join("cmdline"), pid.join("cmdline")).unwrap();
            let fds = fs::read_to_string(entry.path().join("fd.txt")).unwrap();
            for line in fds.lines() {
                let (fd, target) = line.split_once(' ').unwrap();
                let target = match target.strip_prefix("/dev/") {
                    Some(device) => dir.join("dev").join(device),
                    None => PathBuf::from(target),
                };
                symlink(target, pid.join("fd").join(fd)).unwrap();
            }
        }
        root
    }

    #[test]
    fn a_pi5_driven_through_lekiwi_host_fires_every_indicator_and_idle_scores_0_3() {
        let dir = tempfile::tempdir().unwrap();
        let driven = Detector::with_proc_root(&config_in(&dir), pi5_proc(dir.path(), true)).check();
        assert!(driven.active, "{driven:?}");
        assert_eq!(
            names(&driven),
            [PROCESS, COMMAND_CONNECTION, VIDEO_CONNECTION, SERIAL_DEVICE]
        );
        assert!((driven.score - 1.2).abs() < 1e-9, "{driven:?}");

        let dir = tempfile::tempdir().unwrap();
        let idle = Detector::with_proc_root(&config_in(&dir), pi5_proc(dir.path(), false)).check();
        assert!(!idle.active, "{idle:?}");
        assert_eq!(names(&idle), [PROCESS, SERIAL_DEVICE]);
        assert!((idle.score - 0.3).abs() < 1e-9, "{idle:?}");
    }

    /// The default configuration with the serial device of [`pi5_proc`]'s `dir`.
    fn config_in(dir: &tempfile::TempDir) -> Config {
        Config {
            teleop_serial_device: dir.path().join("dev/ttyACM0"),
            ..Config::default()
        }
    }

    #[test]
    fn nothing_running_scores_zero() {
        let fake = FakeProc::new();
        fake.process(1, &["/sbin/init"], &[]);
        let v = fake.check(&fake.config());
        assert_eq!(
            v,
            Verdict {
                active: false,
                score: 0.0,
                indicators: vec![]
            }
        );
        assert_eq!(
            v.to_wire(),
            lekiwi_protocol::Teleoperation {
                active: false,
                score: Some(0.0)
            }
        );
    }

    #[test]
    fn an_idle_host_is_not_teleoperation() {
        let fake = FakeProc::new();
        fake.idle_host();
        let v = fake.check(&fake.config());
        assert_eq!(names(&v), [PROCESS, SERIAL_DEVICE]);
        assert_eq!(v.score, 0.3, "0.1 + 0.2, without the float residue");
        assert!(!v.active);
    }

    #[test]
    fn an_established_command_connection_is_teleoperation() {
        let (fake, tcp) = idle_host_with(&[
            ("00000000:15B3", "00000000:0000", "0A"),
            ("0A00002A:15B3", "0A000017:E1C2", "01"),
        ]);
        let v = fake.check(&fake.config());
        assert_eq!(names(&v), [PROCESS, COMMAND_CONNECTION, SERIAL_DEVICE]);
        assert_eq!(v.score, 0.9);
        assert!(v.active);

        // The same over IPv6, and the video port too: the wire score stays within 0 to 1.
        let tcp6 = format!(
            "{HEADER}{}",
            line(
                "000080FE00000000B2FD1F3C2A5C44FE:15B4",
                "000080FE0000000099F8FD5B0F9A3E11:D2F0",
                "01"
            ),
        );
        fake.sockets(&tcp, &tcp6);
        let v = fake.check(&fake.config());
        assert_eq!(
            names(&v),
            [PROCESS, COMMAND_CONNECTION, VIDEO_CONNECTION, SERIAL_DEVICE]
        );
        assert_eq!(v.score, 1.2);
        assert_eq!(v.to_wire().score, Some(1.0));
    }

    #[test]
    fn only_the_local_port_counts() {
        // This host is the client of somebody else's 5555 (and 8554): not the LeKiwi host
        // being driven. Closing states are not connections.
        let (fake, _) = idle_host_with(&[
            ("0A00002A:D2F0", "0A000017:15B3", "01"),
            ("0A00002A:D2F1", "0A000017:216A", "01"),
            ("0A00002A:15B3", "0A000017:D2F2", "06"),
            ("0A00002A:15B3", "0A000017:D2F3", "08"),
        ]);
        let v = fake.check(&fake.config());
        assert_eq!(names(&v), [PROCESS, SERIAL_DEVICE]);
    }

    #[test]
    fn long_tables_are_read_to_the_end() {
        let fake = FakeProc::new();
        let mut tcp = HEADER.to_owned();
        for port in 0..400u16 {
            tcp += &line(
                &format!("0100007F:{:04X}", 20000 + port),
                "00000000:0000",
                "0A",
            );
        }
        fake.sockets(&tcp, HEADER);
        let config = fake.config();
        let mut detector = Detector::with_proc_root(&config, fake.root());
        assert_eq!(detector.check().score, 0.0);
        tcp += &line("0A00002A:15B3", "0A000017:E1C2", "01");
        assert!(tcp.len() > 4 * TABLE_PAGE, "longer than the first read");
        fake.sockets(&tcp, HEADER);
        assert_eq!(names(&detector.check()), [COMMAND_CONNECTION]);
    }

    #[test]
    fn weights_and_threshold() {
        let (fake, _) = idle_host_with(&[
            ("0A00002A:15B3", "0A000017:E1C2", "01"),
            ("0A00002A:216A", "0A000017:E1C3", "01"),
        ]);
        let all = fake.check(&fake.config());
        assert_eq!(
            names(&all),
            [
                PROCESS,
                COMMAND_CONNECTION,
                STREAM_CONNECTION,
                SERIAL_DEVICE
            ]
        );
        assert_eq!(all.score, 1.2);

        // A zero weight turns an indicator off.
        let v = fake.check(&Config {
            teleop_command_weight: 0.0,
            ..fake.config()
        });
        assert_eq!(names(&v), [PROCESS, STREAM_CONNECTION, SERIAL_DEVICE]);
        assert_eq!(v.score, 0.6);
        assert!(v.active);
        let v = fake.check(&Config {
            teleop_command_weight: 0.0,
            teleop_stream_weight: 0.0,
            teleop_process_weight: 0.0,
            ..fake.config()
        });
        assert_eq!(names(&v), [SERIAL_DEVICE]);
        assert!(!v.active);
        let v = fake.check(&Config {
            teleop_serial_weight: 0.0,
            teleop_stream_ports: vec![],
            teleop_process_pattern: String::new(),
            ..fake.config()
        });
        assert_eq!(names(&v), [COMMAND_CONNECTION]);

        // Weights are free: here a connection alone is not enough, the host must also run.
        let config = Config {
            teleop_threshold: 0.7,
            teleop_command_weight: 0.4,
            teleop_process_weight: 0.3,
            teleop_serial_weight: 0.0,
            teleop_stream_weight: 0.0,
            ..fake.config()
        };
        let v = fake.check(&config);
        assert_eq!(
            (v.active, v.score),
            (true, 0.7),
            "the threshold itself counts"
        );
        fake.exit(812);
        let v = fake.check(&config);
        assert_eq!((v.active, v.score), (false, 0.4));
    }

    #[test]
    fn the_agent_itself_does_not_count() {
        let fake = FakeProc::new();
        fake.process(
            std::process::id(),
            &[
                "lekiwi-agent",
                "--teleop-process-pattern",
                "lerobot.robots.lekiwi.lekiwi_host",
            ],
            &[&fake.device()],
        );
        assert_eq!(fake.check(&fake.config()).score, 0.0);
    }

    #[test]
    fn the_device_is_found_under_its_canonical_name() {
        let fake = FakeProc::new();
        let by_id = fake.dir.path().join("by-id");
        fs::create_dir(&by_id).unwrap();
        symlink(fake.device(), by_id.join("usb-Feetech_kiwi")).unwrap();
        // The host opened the device by its real name, the agent is configured with the link.
        fake.process(700, &["python", "motors.py"], &[&fake.device()]);
        let config = Config {
            teleop_serial_device: by_id.join("usb-Feetech_kiwi"),
            ..fake.config()
        };
        assert_eq!(names(&fake.check(&config)), [SERIAL_DEVICE]);

        // Unplugged: nothing to hold (and no fd scan).
        fs::remove_file(by_id.join("usb-Feetech_kiwi")).unwrap();
        assert_eq!(fake.check(&config).score, 0.0);
    }

    #[test]
    fn later_checks_follow_processes_that_come_go_and_change() {
        let fake = FakeProc::new();
        let config = fake.config();
        let mut detector = Detector::with_proc_root(&config, fake.root());
        assert_eq!(detector.check().score, 0.0);

        fake.idle_host();
        assert_eq!(names(&detector.check()), [PROCESS, SERIAL_DEVICE]);
        // Found again from the remembered pids.
        assert_eq!(names(&detector.check()), [PROCESS, SERIAL_DEVICE]);

        // The host released the device; another process took it.
        fake.process(
            812,
            &["python", "-m", "lerobot.robots.lekiwi.lekiwi_host"],
            &[],
        );
        fake.process(950, &["minicom"], &[&fake.device()]);
        assert_eq!(names(&detector.check()), [PROCESS, SERIAL_DEVICE]);

        // The host's pid went to an unrelated process.
        fake.process(812, &["sleep", "60"], &[]);
        assert_eq!(names(&detector.check()), [SERIAL_DEVICE]);
        fake.exit(950);
        assert_eq!(detector.check().score, 0.0);
    }

    #[test]
    fn missing_files_score_zero() {
        let dir = tempfile::tempdir().unwrap();
        let v = Detector::with_proc_root(&Config::default(), dir.path().join("nothing")).check();
        assert_eq!((v.active, v.score), (false, 0.0));
    }

    /// Cost of one check against the real `/proc`; run with
    /// `cargo test --release -p lekiwi-agent --lib teleop::tests::cost -- --ignored --nocapture`.
    #[test]
    #[ignore = "a measurement, not a test"]
    fn cost_of_a_check() {
        let dir = tempfile::tempdir().unwrap();
        let device = dir.path().join("ttyACM0");
        fs::write(&device, "").unwrap();
        let count = |dir: &str| fs::read_dir(dir).map_or(0, |d| d.count());
        let processes = fs::read_dir("/proc")
            .unwrap()
            .flatten()
            .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
            .collect::<Vec<_>>();
        let fds: usize = processes
            .iter()
            .map(|pid| count(&format!("/proc/{pid}/fd")))
            .sum();
        let sockets = fs::read_to_string("/proc/net/tcp").unwrap().lines().count()
            + fs::read_to_string("/proc/net/tcp6")
                .unwrap()
                .lines()
                .count()
            - 2;
        println!(
            "{} processes, {fds} readable fds, {sockets} TCP sockets",
            processes.len()
        );
        let mut host = std::process::Command::new("sleep")
            .arg("59.25")
            .stdin(fs::File::open(&device).unwrap())
            .spawn()
            .unwrap();
        let off = Config {
            teleop_process_weight: 0.0,
            teleop_command_weight: 0.0,
            teleop_video_weight: 0.0,
            teleop_stream_weight: 0.0,
            teleop_serial_weight: 0.0,
            teleop_serial_device: device.clone(),
            teleop_process_pattern: "sleep 59.25".into(),
            ..Config::default()
        };
        let defaults = Config::default();
        for (what, config) in [
            (
                "connections only",
                Config {
                    teleop_command_weight: 0.6,
                    teleop_video_weight: 0.3,
                    teleop_stream_weight: 0.3,
                    ..off.clone()
                },
            ),
            (
                "process only, not running (full cmdline scan)",
                Config {
                    teleop_process_weight: 0.1,
                    teleop_process_pattern: "lerobot.robots.lekiwi.lekiwi_host".into(),
                    ..off.clone()
                },
            ),
            (
                "serial only, device present, unheld (full fd scan)",
                Config {
                    teleop_serial_weight: 0.2,
                    teleop_serial_device: dir.path().join("unheld"),
                    ..off.clone()
                },
            ),
            ("all, defaults: no host, no /dev/ttyACM0", defaults.clone()),
            (
                "all, host not running, device present, unheld",
                Config {
                    teleop_serial_device: dir.path().join("unheld"),
                    ..defaults.clone()
                },
            ),
            (
                "all, idle host running and holding the device",
                Config {
                    teleop_serial_device: device.clone(),
                    teleop_process_pattern: "sleep 59.25".into(),
                    ..defaults.clone()
                },
            ),
        ] {
            fs::write(dir.path().join("unheld"), "").unwrap();
            let mut detector = Detector::new(&config);
            let verdict = detector.check();
            let n = 300;
            let cpu = || {
                let stat = fs::read_to_string("/proc/thread-self/schedstat").unwrap();
                stat.split(' ').next().unwrap().parse::<u64>().unwrap()
            };
            let (wall, cpu0) = (std::time::Instant::now(), cpu());
            for _ in 0..n {
                std::hint::black_box(detector.check());
            }
            let cpu_us = (cpu() - cpu0) as f64 / n as f64 / 1e3;
            let wall = wall.elapsed() / n as u32;
            println!(
                "{what}: {cpu_us:.0} µs CPU, {wall:.2?} wall per check; fired {:?}",
                verdict.indicators
            );
        }
        host.kill().unwrap();
        host.wait().unwrap();
    }
}
