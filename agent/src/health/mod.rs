//! The robot's own health: the checks behind the `health` that the agent sends in `hello` and
//! every heartbeat (PROTOCOL.md §5.1).
//!
//! Every `healthIntervalS` a task runs each configured check: the health command
//! (`healthCommand`, killed after `healthTimeoutS`), a process whose command line
//! contains `hostProcessPattern`, the device `healthSerialDevice`, and the use of the state
//! directory's file system against `healthDiskMaxPercent`. A check that is not configured is
//! skipped; with none configured the robot is healthy. The verdict names every failed check in
//! its message and the first in its `reason`; the run loop hears a changed verdict at once and
//! sends it in a heartbeat. The same task reads the host process's memory and CPU ([`host`]),
//! which heartbeats carry in their vitals.

mod host;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use lekiwi_protocol::Health;
use tokio::sync::watch;
use tracing::{info, warn};

use crate::config::Config;
pub use host::HostStats;

/// Output of the health command kept for the message, characters.
const OUTPUT_CHARS: usize = 200;

/// One failed check.
#[derive(Clone, Debug, PartialEq)]
struct Failure {
    /// CamelCase, the `reason` sent when this check fails first.
    reason: &'static str,
    /// What failed, for people.
    message: String,
}

/// The configured checks.
#[derive(Clone, Debug)]
pub struct Checks {
    command: String,
    timeout: Duration,
    /// Where the command runs: the current release if there is one, else the state directory.
    state_dir: PathBuf,
    pattern: Vec<u8>,
    serial: Option<PathBuf>,
    disk_max_percent: f64,
    /// The agent itself, whose command line may hold the pattern (as a flag).
    own_pid: u32,
    proc_root: PathBuf,
}

impl Checks {
    /// The checks `config` asks for.
    pub fn from_config(config: &Config) -> Self {
        Self {
            command: config.health_command.trim().to_owned(),
            timeout: Duration::from_secs_f64(config.health_timeout_s),
            state_dir: config.state_dir.clone(),
            pattern: config.host_process_pattern.as_bytes().to_vec(),
            serial: config.health_serial_device.clone(),
            disk_max_percent: config.health_disk_max_percent,
            own_pid: std::process::id(),
            proc_root: PathBuf::from("/proc"),
        }
    }

    /// The verdict of the checks that start no process (host process, device, disk): what
    /// `hello` says before the first full check has run.
    pub fn quick(&self) -> Health {
        verdict(self.quick_failures(self.host_pid()))
    }

    /// The verdict of every check, the health command included.
    pub async fn run(&self) -> Health {
        self.run_with(self.host_pid()).await
    }

    /// [`Checks::run`] with the host process already looked for (`host_pid`).
    async fn run_with(&self, host_pid: Option<u32>) -> Health {
        let mut failures = Vec::new();
        if !self.command.is_empty()
            && let Err(message) = self.run_command().await
        {
            failures.push(Failure {
                reason: "HealthCommandFailed",
                message,
            });
        }
        failures.extend(self.quick_failures(host_pid));
        verdict(failures)
    }

    fn quick_failures(&self, host_pid: Option<u32>) -> Vec<Failure> {
        let mut failures = Vec::new();
        if !self.pattern.is_empty() && host_pid.is_none() {
            failures.push(Failure {
                reason: "HostProcessNotRunning",
                message: format!(
                    "no process matching {:?} runs",
                    String::from_utf8_lossy(&self.pattern)
                ),
            });
        }
        if let Some(device) = &self.serial
            && !device.exists()
        {
            failures.push(Failure {
                reason: "SerialDeviceMissing",
                message: format!("{} does not exist", device.display()),
            });
        }
        if self.disk_max_percent > 0.0
            && let Some(used) = crate::telemetry::fs_use_percent(&self.state_dir)
            && used >= self.disk_max_percent
        {
            failures.push(Failure {
                reason: "DiskFull",
                message: format!(
                    "the file system of {} is {used:.1} % full (limit {} %)",
                    self.state_dir.display(),
                    self.disk_max_percent
                ),
            });
        }
        failures
    }

    /// A process other than the agent with the pattern in its command line; `None` also when
    /// no pattern is configured.
    fn host_pid(&self) -> Option<u32> {
        if self.pattern.is_empty() {
            return None;
        }
        find_process(&self.proc_root, &self.pattern, self.own_pid)
    }

    /// Runs the health command once, at most the timeout; `Err` says why it failed.
    async fn run_command(&self) -> Result<(), String> {
        let current = self.state_dir.join("current");
        let dir = if current.is_dir() {
            current
        } else {
            self.state_dir.clone()
        };
        let child = tokio::process::Command::new("sh")
            .arg("-c")
            .arg(&self.command)
            .current_dir(&dir)
            .env("LEKIWI_RELEASE_DIR", &dir)
            .env("LEKIWI_STATE_DIR", &self.state_dir)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .kill_on_drop(true)
            // Its own process group, so that a timeout ends what the command started too.
            .process_group(0)
            .spawn()
            .map_err(|e| format!("cannot start `sh -c {}`: {e}", self.command))?;
        let pid = child.id();
        match tokio::time::timeout(self.timeout, child.wait_with_output()).await {
            Ok(Ok(out)) if out.status.success() => Ok(()),
            Ok(Ok(out)) => Err(format!(
                "`{}` {}{}",
                self.command,
                out.status,
                tail(&out.stdout, &out.stderr)
            )),
            Ok(Err(e)) => Err(format!("waiting for `{}`: {e}", self.command)),
            Err(_) => {
                if let Some(pid) = pid {
                    crate::release::kill_group(pid);
                }
                Err(format!(
                    "`{}` timed out after {}s",
                    self.command,
                    self.timeout.as_secs_f64()
                ))
            }
        }
    }
}

/// Healthy without failures; else unhealthy, the first failure's reason, every message.
fn verdict(failures: Vec<Failure>) -> Health {
    let Some(first) = failures.first() else {
        return Health::ok();
    };
    Health {
        healthy: false,
        reason: Some(first.reason.to_owned()),
        message: Some(
            failures
                .iter()
                .map(|f| f.message.as_str())
                .collect::<Vec<_>>()
                .join("; "),
        ),
    }
}

/// The end of a command's output, as `: <text>`, or nothing.
fn tail(stdout: &[u8], stderr: &[u8]) -> String {
    let text = format!(
        "{} {}",
        String::from_utf8_lossy(stdout).trim(),
        String::from_utf8_lossy(stderr).trim()
    );
    let text = text.trim();
    let chars = text.chars().count();
    match chars {
        0 => String::new(),
        n if n <= OUTPUT_CHARS => format!(": {text}"),
        n => format!(
            ": …{}",
            text.chars().skip(n - OUTPUT_CHARS).collect::<String>()
        ),
    }
}

/// The first process (by `/proc` order) other than `own_pid` whose command line contains
/// `pattern`.
pub fn find_process(proc_root: &Path, pattern: &[u8], own_pid: u32) -> Option<u32> {
    let entries = std::fs::read_dir(proc_root).ok()?;
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&pid| pid != own_pid)
        .find(|pid| {
            std::fs::read(proc_root.join(pid.to_string()).join("cmdline"))
                .is_ok_and(|mut cmdline| crate::teleop::cmdline_contains(&mut cmdline, pattern))
        })
}

/// What the periodic checks publish: the verdict, whose changes the run loop waits for, and the
/// host process's latest reading, which it only reads.
pub struct Watch {
    /// The latest verdict (at first the quick one).
    pub health: watch::Receiver<Health>,
    /// The host process's latest reading; `None` when no host process is configured or runs.
    pub host: watch::Receiver<Option<HostStats>>,
}

/// Starts the periodic checks on the current runtime. The task ends when the health receiver
/// is gone.
pub fn spawn(config: &Config) -> Watch {
    let checks = Checks::from_config(config);
    let every = Duration::from_secs_f64(config.health_interval_s);
    let (tx, health) = watch::channel(checks.quick());
    let (host_tx, host) = watch::channel(None);
    let mut sampler = host::Sampler::new(&checks.proc_root);
    tokio::spawn(async move {
        loop {
            let pid = checks.host_pid();
            host_tx.send_replace(pid.and_then(|pid| sampler.sample(pid)));
            let verdict = checks.run_with(pid).await;
            if tx.is_closed() {
                return;
            }
            tx.send_if_modified(|old| publish(old, verdict));
            tokio::time::sleep(every).await;
        }
    });
    Watch { health, host }
}

/// Replaces `old` with `new` if they differ, logging the change; whether they differed.
fn publish(old: &mut Health, new: Health) -> bool {
    if *old == new {
        return false;
    }
    if new.healthy {
        info!("healthy again");
    } else {
        warn!(reason = ?new.reason, message = ?new.message, "unhealthy");
    }
    *old = new;
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checks(dir: &Path) -> Checks {
        let config = Config {
            state_dir: dir.to_owned(),
            health_timeout_s: 1.0,
            health_disk_max_percent: 0.0,
            ..Config::default()
        };
        Checks::from_config(&config)
    }

    /// Nothing configured: healthy.
    #[tokio::test]
    async fn no_checks_is_healthy() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(checks(dir.path()).run().await, Health::ok());
    }

    /// Each check fails with its own reason; the message names every failure, the reason the
    /// first.
    #[tokio::test]
    async fn failures_name_their_check() {
        let dir = tempfile::tempdir().unwrap();
        let mut c = checks(dir.path());
        c.command = "echo broken; exit 3".into();
        c.serial = Some(dir.path().join("ttyACM0"));
        c.pattern = b"no-such-process-4f2a".to_vec();
        let h = c.run().await;
        assert!(!h.healthy);
        assert_eq!(h.reason.as_deref(), Some("HealthCommandFailed"));
        let message = h.message.unwrap();
        for part in ["exit status: 3: broken", "no-such-process-4f2a", "ttyACM0"] {
            assert!(message.contains(part), "{message}");
        }
        c.command.clear();
        assert_eq!(c.quick().reason.as_deref(), Some("HostProcessNotRunning"));
        c.pattern.clear();
        assert_eq!(c.quick().reason.as_deref(), Some("SerialDeviceMissing"));
        std::fs::write(dir.path().join("ttyACM0"), "").unwrap();
        assert_eq!(c.quick(), Health::ok());
    }

    /// A command that hangs is killed at the timeout.
    #[tokio::test]
    async fn a_hanging_command_times_out() {
        let dir = tempfile::tempdir().unwrap();
        let mut c = checks(dir.path());
        c.command = "sleep 30".into();
        c.timeout = Duration::from_millis(200);
        let started = std::time::Instant::now();
        let h = c.run().await;
        assert!(started.elapsed() < Duration::from_secs(5));
        assert!(h.message.unwrap().contains("timed out"));
    }

    /// A process other than the agent is found by its command line; the agent itself is not.
    #[test]
    fn finds_other_processes_only() {
        let mut child = std::process::Command::new("sleep")
            .arg("31.4159")
            .spawn()
            .unwrap();
        let me = std::process::id();
        // Right after the fork the child still has this binary's command line: look until
        // its exec has happened (bounded).
        let deadline = std::time::Instant::now() + Duration::from_secs(10);
        let found = loop {
            let found = find_process(Path::new("/proc"), b"sleep 31.4159", me);
            if found.is_some() || std::time::Instant::now() > deadline {
                break found;
            }
            std::thread::sleep(Duration::from_millis(10));
        };
        let as_itself = find_process(Path::new("/proc"), b"sleep 31.4159", child.id());
        child.kill().unwrap();
        child.wait().unwrap();
        assert_eq!(found, Some(child.id()));
        assert_eq!(as_itself, None);
    }

    /// A threshold the disk already passes makes the robot unhealthy.
    #[test]
    fn a_full_disk_is_unhealthy() {
        let dir = tempfile::tempdir().unwrap();
        // Some use even on a fresh, empty file system (the emulated Pi's /tmp is one).
        std::fs::write(dir.path().join("ballast"), vec![1u8; 1 << 20]).unwrap();
        let mut c = checks(dir.path());
        c.disk_max_percent = 1e-6;
        let h = c.quick();
        assert_eq!(h.reason.as_deref(), Some("DiskFull"), "{h:?}");
    }
}
