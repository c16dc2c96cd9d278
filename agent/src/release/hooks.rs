//! The configured shell commands of a deployment: pre-switch, restart and health check, run
//! with `sh -c` in the release directory, output kept for failure messages.

use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

use lekiwi_protocol::Release;
use tokio::time::Instant;

use crate::config::Config;

/// Output kept for a failure message, bytes.
const OUTPUT_TAIL: u64 = 2048;
/// Pause between two runs of the health command.
const HEALTH_INTERVAL: Duration = Duration::from_secs(1);

/// The release a hook runs for.
pub(super) struct HookEnv {
    /// `releases/<version>`, the working directory.
    pub dir: PathBuf,
    /// The release the hook is about (the target, or the one switched back to).
    pub release: Release,
    /// The version that ran before (or, when switching back, the one that failed).
    pub previous: Option<String>,
}

/// The configured commands; empty ones are skipped.
pub(super) struct Hooks {
    pub pre_switch: String,
    pub restart: String,
    pub health: String,
    pub health_timeout: Duration,
    pub health_interval: Duration,
    /// Longest run of the pre-switch or restart command.
    pub hook_timeout: Duration,
    /// Where a command's output goes (a file rather than a pipe, so that a daemon the command
    /// leaves behind cannot keep the agent waiting for the end of its output).
    log: PathBuf,
}

impl Hooks {
    pub(super) fn from_config(config: &Config) -> Self {
        Self {
            pre_switch: config.release_pre_switch_command.trim().to_owned(),
            restart: config.release_restart_command.trim().to_owned(),
            health: config.release_health_command.trim().to_owned(),
            health_timeout: Duration::from_secs(config.release_health_timeout_s),
            health_interval: HEALTH_INTERVAL,
            hook_timeout: Duration::from_secs(config.release_hook_timeout_s),
            log: config.state_dir.join("release-hook.log"),
        }
    }

    /// Runs `command` to its end (at most the hook timeout); `Err` says why it failed.
    pub(super) async fn run(&self, command: &str, env: &HookEnv) -> Result<(), String> {
        self.run_for(command, env, self.hook_timeout).await
    }

    /// Runs the health command until it passes or the health timeout ends.
    pub(super) async fn health_check(&self, env: &HookEnv) -> Result<(), String> {
        let deadline = Instant::now() + self.health_timeout;
        let mut attempts = 0;
        loop {
            attempts += 1;
            let left = deadline
                .saturating_duration_since(Instant::now())
                .max(Duration::from_millis(100));
            match self.run_for(&self.health, env, left).await {
                Ok(()) => return Ok(()),
                Err(why) => {
                    // The last attempt runs at the deadline, not an interval before it.
                    let now = Instant::now();
                    if now >= deadline {
                        return Err(format!(
                            "not healthy within {}s ({attempts} attempts); last: {why}",
                            self.health_timeout.as_secs_f64()
                        ));
                    }
                    tokio::time::sleep(self.health_interval.min(deadline - now)).await;
                }
            }
        }
    }

    async fn run_for(&self, command: &str, env: &HookEnv, timeout: Duration) -> Result<(), String> {
        let out = std::fs::File::create(&self.log)
            .map_err(|e| format!("cannot create {}: {e}", self.log.display()))?;
        let err = out
            .try_clone()
            .map_err(|e| format!("cannot open {}: {e}", self.log.display()))?;
        let mut child = tokio::process::Command::new("sh")
            .arg("-c")
            .arg(command)
            .current_dir(&env.dir)
            .env("LEKIWI_RELEASE_DIR", &env.dir)
            .env("LEKIWI_RELEASE_VERSION", &env.release.version)
            .env("LEKIWI_RELEASE_DIGEST", &env.release.digest)
            .env(
                "LEKIWI_PREVIOUS_VERSION",
                env.previous.as_deref().unwrap_or_default(),
            )
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err)
            .kill_on_drop(true)
            // Its own process group, so that a timeout ends what the command started too.
            .process_group(0)
            .spawn()
            .map_err(|e| format!("cannot start `sh -c {command}`: {e}"))?;
        let status = match tokio::time::timeout(timeout, child.wait()).await {
            Ok(Ok(status)) => status,
            Ok(Err(e)) => return Err(format!("waiting for `{command}`: {e}")),
            Err(_) => {
                if let Some(pid) = child.id() {
                    kill_group(pid);
                }
                let _ = child.kill().await;
                return Err(format!(
                    "`{command}` timed out after {}s{}",
                    timeout.as_secs_f64(),
                    self.output()
                ));
            }
        };
        if status.success() {
            Ok(())
        } else {
            Err(format!("`{command}` {status}{}", self.output()))
        }
    }

    /// The end of the last command's output, as `: <text>`, or nothing.
    fn output(&self) -> String {
        use std::io::{Read, Seek, SeekFrom};
        let Ok(mut file) = std::fs::File::open(&self.log) else {
            return String::new();
        };
        let len = file.metadata().map(|m| m.len()).unwrap_or_default();
        let start = len.saturating_sub(OUTPUT_TAIL);
        let mut bytes = Vec::new();
        if file.seek(SeekFrom::Start(start)).is_err() || file.read_to_end(&mut bytes).is_err() {
            return String::new();
        }
        let text = String::from_utf8_lossy(&bytes);
        let text = text.trim();
        match (text.is_empty(), start > 0) {
            (true, _) => String::new(),
            (false, false) => format!(": {text}"),
            (false, true) => format!(": …{text}"),
        }
    }
}

/// Sends SIGKILL to the process group `pgid` (by the system call: some `kill(1)`s misread a
/// negative pid after a signal, procps-ng 4.0's turning `-KILL -12345` into every process); a
/// failure leaves only the group leader to kill, which the caller does anyway. Group 0 (ours) and
/// 1 (every process) are never signalled.
pub(crate) fn kill_group(pgid: u32) {
    let group = i32::try_from(pgid)
        .ok()
        .and_then(rustix::process::Pid::from_raw)
        .filter(|g| *g != rustix::process::Pid::INIT);
    let Some(group) = group else {
        tracing::warn!(pgid, "not a process group to kill");
        return;
    };
    if let Err(e) = rustix::process::kill_process_group(group, rustix::process::Signal::KILL) {
        tracing::warn!(pgid, error = %e, "could not kill the hook's process group");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Release 1 in `dir`, with nothing before it.
    fn env_in(dir: &std::path::Path) -> HookEnv {
        HookEnv {
            dir: dir.to_owned(),
            release: Release {
                version: "1".into(),
                digest: format!("sha256:{}", "0".repeat(64)),
            },
            previous: None,
        }
    }

    /// A service that turns healthy 1.5 s after the switch passes a 2 s health timeout: the last
    /// attempt runs at the deadline, not an interval before it.
    #[tokio::test]
    async fn the_last_health_attempt_runs_at_the_deadline() {
        let dir = tempfile::tempdir().unwrap();
        let config = Config {
            state_dir: dir.path().to_owned(),
            release_health_command: format!("test -e {}", dir.path().join("healthy").display()),
            release_health_timeout_s: 2,
            ..Config::default()
        };
        let hooks = Hooks::from_config(&config);
        let env = env_in(dir.path());
        let healthy = dir.path().join("healthy");
        let started = Instant::now();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(1500)).await;
            std::fs::write(healthy, "").unwrap();
        });
        hooks.health_check(&env).await.unwrap();
        assert!(started.elapsed() >= Duration::from_millis(1500));

        // Never healthy: refused after the whole timeout.
        std::fs::remove_file(dir.path().join("healthy")).unwrap();
        let started = Instant::now();
        let err = hooks.health_check(&env).await.unwrap_err();
        assert!(err.contains("not healthy within 2s"), "{err}");
        assert!(
            started.elapsed() >= Duration::from_secs(2),
            "{:?}",
            started.elapsed()
        );
    }

    /// A restart command that hangs is stopped at the hook timeout, with what it started.
    #[tokio::test]
    async fn a_hanging_hook_times_out_with_its_children() {
        let dir = tempfile::tempdir().unwrap();
        let config = Config {
            state_dir: dir.path().to_owned(),
            release_hook_timeout_s: 1,
            ..Config::default()
        };
        let hooks = Hooks::from_config(&config);
        let env = env_in(dir.path());
        let pid_file = dir.path().join("child.pid");
        let command = format!(
            "sleep 60 & echo $! > {}; echo started; wait",
            pid_file.display()
        );
        let started = Instant::now();
        let err = hooks.run(&command, &env).await.unwrap_err();
        assert!(err.contains("timed out after 1s: started"), "{err}");
        assert!(started.elapsed() < Duration::from_secs(10));
        let child = std::fs::read_to_string(&pid_file).unwrap();
        let stat = format!("/proc/{}/stat", child.trim());
        let gone = || {
            std::fs::read_to_string(&stat)
                .map(|s| {
                    s.split(") ")
                        .nth(1)
                        .is_some_and(|rest| rest.starts_with('Z'))
                })
                .unwrap_or(true)
        };
        let deadline = Instant::now() + Duration::from_secs(5);
        while !gone() && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(gone(), "the command's child {} still runs", child.trim());
    }
}
