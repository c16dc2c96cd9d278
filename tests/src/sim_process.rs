//! `lekiwi-sim`: simulated robots (N connections in one process) that carry out commands, for
//! tests that compare them with real agents or need a fleet larger than real agents allow.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Result;
use serde_json::Value;

use crate::log_dir;
use crate::process::{ChildProcess, Launch};

/// What a test chooses for a `lekiwi-sim` run.
pub struct SimSpec<'a> {
    /// The gateway's WebSocket URL.
    pub gateway: &'a str,
    /// File holding the fleet enrollment token.
    pub token_file: &'a Path,
    /// Namespace the robots enroll into.
    pub namespace: &'a str,
    /// How many robots (named `<prefix>-00001` on).
    pub robots: usize,
    /// Their name prefix.
    pub prefix: &'a str,
    /// Flags appended as they are (`--fail-health-share`, hooks, ...).
    pub extra: &'a [&'a str],
}

/// A running `lekiwi-sim` process; SIGKILLed when dropped. Its log is
/// `sim-<namespace>-<prefix>.log` in the test log directory, its summary (written when it
/// ends on SIGTERM) `summary.json` in its own directory.
pub struct SimProcess {
    process: ChildProcess,
    summary: PathBuf,
}

impl SimProcess {
    /// Starts the simulator (a fresh log), reporting every 2 s.
    pub fn start(spec: SimSpec<'_>, dir: &Path) -> Result<Self> {
        let log = log_dir().join(format!("sim-{}-{}.log", spec.namespace, spec.prefix));
        std::fs::File::create(&log)?;
        let summary = dir.join(format!("sim-{}-summary.json", spec.prefix));
        let token = std::fs::read_to_string(spec.token_file)?;
        let mut args: Vec<String> = [
            "--gateway",
            spec.gateway,
            "--namespace",
            spec.namespace,
            "--robots",
            &spec.robots.to_string(),
            "--prefix",
            spec.prefix,
            "--report-every",
            "2",
            "--json",
            summary.to_str().expect("a UTF-8 path"),
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(spec.extra.iter().map(|s| s.to_string()));
        let process = ChildProcess::spawn(Launch {
            binary: "lekiwi-sim",
            what: "sim",
            rust_log: "warn",
            args,
            env: vec![("LEKIWI_ENROLLMENT_TOKEN".into(), token.trim().to_owned())],
            log,
            term_deadline: Duration::from_secs(10),
            term_poll: Duration::from_millis(20),
        })?;
        Ok(Self { process, summary })
    }

    /// SIGTERM: the simulator writes its summary and exits; the summary.
    pub fn stop(&mut self) -> Result<Value> {
        self.process.terminate()?;
        Ok(serde_json::from_str(&std::fs::read_to_string(
            &self.summary,
        )?)?)
    }

    /// The process id (to stop and continue it, as a cut-off does).
    pub fn pid(&self) -> u32 {
        self.process.pid()
    }

    /// The log as text, for failure messages.
    pub fn log_text(&self) -> String {
        self.process.log_text()
    }
}
