//! One child process of ours (operator or agent) with its log file: spawn, restart, SIGKILL,
//! SIGTERM with a deadline.

use std::path::PathBuf;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail};

use crate::bin;

/// How to (re)start one of our binaries: its name, flags, environment and the log its output is
/// appended to.
pub(crate) struct Launch {
    /// Binary name, e.g. `lekiwi-agent`.
    pub binary: &'static str,
    /// Short name in failure messages, e.g. `agent`.
    pub what: &'static str,
    /// `RUST_LOG` for the process.
    pub rust_log: &'static str,
    /// Its flags, kept for restarts.
    pub args: Vec<String>,
    /// Extra environment variables.
    pub env: Vec<(String, String)>,
    /// The file stdout and stderr are appended to.
    pub log: PathBuf,
    /// How long [`ChildProcess::terminate`] waits after SIGTERM.
    pub term_deadline: Duration,
    /// How often [`ChildProcess::terminate`] looks whether it exited.
    pub term_poll: Duration,
}

/// A running child process that is SIGKILLed when dropped and can be started again with the same
/// flags (the log is appended to).
pub(crate) struct ChildProcess {
    child: Child,
    launch: Launch,
}

impl ChildProcess {
    pub(crate) fn spawn(launch: Launch) -> Result<Self> {
        let child = launch.spawn()?;
        Ok(Self { child, launch })
    }

    /// The process's output so far.
    pub(crate) fn log_text(&self) -> String {
        std::fs::read_to_string(&self.launch.log).unwrap_or_default()
    }

    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    /// `Some(status)` once the process has exited.
    pub(crate) fn exited(&mut self) -> Result<Option<ExitStatus>> {
        Ok(self.child.try_wait()?)
    }

    pub(crate) fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// SIGKILL: a crash, nothing is cleaned up.
    pub(crate) fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// SIGTERM, then waits for the exit within the launch's deadline.
    pub(crate) fn terminate(&mut self) -> Result<ExitStatus> {
        Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()?;
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait()? {
                return Ok(status);
            }
            if start.elapsed() > self.launch.term_deadline {
                bail!(
                    "{} did not exit within {}s of SIGTERM",
                    self.launch.what,
                    self.launch.term_deadline.as_secs()
                );
            }
            std::thread::sleep(self.launch.term_poll);
        }
    }

    /// SIGKILLs it if it runs and starts it again with the same flags.
    pub(crate) fn restart(&mut self) -> Result<()> {
        self.kill();
        self.child = self.launch.spawn()?;
        Ok(())
    }
}

impl Launch {
    fn spawn(&self) -> Result<Child> {
        let file = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .open(&self.log)?;
        Command::new(bin(self.binary))
            .args(&self.args)
            .env("RUST_LOG", self.rust_log)
            .envs(self.env.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .with_context(|| format!("spawn {}", self.binary))
    }
}

impl Drop for ChildProcess {
    fn drop(&mut self) {
        self.kill();
    }
}
