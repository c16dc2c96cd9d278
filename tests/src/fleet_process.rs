//! `lekiwi-fleet`: N real agents (the agent's own run loop, one state directory each) in one
//! process, for tests that need a fleet that installs releases; and `lekiwi-sim`, N simulated
//! robots (the agent's connection code, no releases) in one process.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Result;

use crate::log_dir;
use crate::process::{ChildProcess, Launch};

/// What a test chooses for a `lekiwi-fleet` run; quick settings (health timeout 2 s, backoff at
/// most 2 s) are filled in.
pub struct FleetSpec<'a> {
    /// The gateway's WebSocket URL.
    pub gateway: &'a str,
    /// File holding the fleet enrollment token.
    pub token_file: &'a Path,
    /// Namespace the robots enroll into.
    pub namespace: &'a str,
    /// How many robots (named `kiwi-000` on).
    pub robots: usize,
    /// Where each robot's state directory goes.
    pub state_root: &'a Path,
    /// Each robot's health command after a switch.
    pub health_command: &'a str,
    /// Seconds between the fleet's summary log lines.
    pub report_every: &'a str,
    /// `RUST_LOG` of the process.
    pub rust_log: &'static str,
    /// Flags appended as they are.
    pub extra: &'a [&'a str],
}

/// A running `lekiwi-fleet` process; SIGKILLed when dropped. Its log is
/// `fleet-<namespace>.log` in the test log directory.
pub struct FleetProcess {
    process: ChildProcess,
    state_root: PathBuf,
}

impl FleetProcess {
    /// Starts the fleet (a fresh log).
    pub fn start(spec: FleetSpec<'_>) -> Result<Self> {
        let log = log_dir().join(format!("fleet-{}.log", spec.namespace));
        std::fs::File::create(&log)?;
        let mut args: Vec<String> = [
            "--gateway",
            spec.gateway,
            "--enrollment-token-file",
            spec.token_file.to_str().unwrap(),
            "--namespace",
            spec.namespace,
            "--robots",
            &spec.robots.to_string(),
            "--state-root",
            spec.state_root.to_str().unwrap(),
            "--health-command",
            spec.health_command,
            "--health-timeout-s",
            "2",
            "--backoff-max-ms",
            "2000",
            "--report-every",
            spec.report_every,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(spec.extra.iter().map(|s| s.to_string()));
        let process = ChildProcess::spawn(Launch {
            binary: "lekiwi-fleet",
            what: "fleet",
            rust_log: spec.rust_log,
            args,
            env: Vec::new(),
            log,
            term_deadline: Duration::from_secs(10),
            term_poll: Duration::from_millis(20),
        })?;
        Ok(Self {
            process,
            state_root: spec.state_root.to_owned(),
        })
    }

    /// SIGKILL: every robot of the fleet crashes at once.
    pub fn kill(&mut self) {
        self.process.kill();
    }

    /// Starts it again with the same flags and state (log appended).
    pub fn restart(&mut self) -> Result<()> {
        self.process.restart()
    }

    /// A robot's state directory, e.g. for `state("kiwi-003")`.
    pub fn state(&self, robot: &str) -> PathBuf {
        self.state_root.join(robot)
    }
}

/// A running `lekiwi-sim` process; SIGKILLed when dropped. Its log is `sim-<namespace>.log` in
/// the test log directory.
pub struct SimProcess {
    process: ChildProcess,
}

impl SimProcess {
    /// Starts `robots` simulated robots (`sim-00001` on) of `namespace` against the gateway
    /// WebSocket URL `gateway`, enrolling with the fleet enrollment token `token`; `extra` flags
    /// are appended as they are.
    pub fn start(
        gateway: &str,
        token: &str,
        namespace: &str,
        robots: usize,
        extra: &[&str],
    ) -> Result<Self> {
        let log = log_dir().join(format!("sim-{namespace}.log"));
        std::fs::File::create(&log)?;
        let mut args: Vec<String> = [
            "--gateway",
            gateway,
            "--namespace",
            namespace,
            "--robots",
            &robots.to_string(),
            "--report-every",
            "10",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(extra.iter().map(|s| s.to_string()));
        let process = ChildProcess::spawn(Launch {
            binary: "lekiwi-sim",
            what: "sim",
            rust_log: "warn",
            args,
            // Not a flag: the process list shows flags.
            env: vec![("LEKIWI_ENROLLMENT_TOKEN".into(), token.into())],
            log,
            term_deadline: Duration::from_secs(10),
            term_poll: Duration::from_millis(20),
        })?;
        Ok(Self { process })
    }

    /// SIGKILL: every simulated robot drops its connection at once.
    pub fn kill(&mut self) {
        self.process.kill();
    }
}
