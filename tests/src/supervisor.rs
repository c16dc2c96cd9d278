//! A small service manager for the agent self-update tests: it plays systemd's part exactly as
//! `manifests/systemd/lekiwi-agent.service` and `lekiwi-agent-guard.{service,timer}` say, with
//! shorter timers:
//!
//! - before every start, `lekiwi-agent guard` from the package binary (`ExecStartPre=-`; its
//!   failure does not stop the start);
//! - start `<state>/agent/current/lekiwi-agent` when it is executable, else the package binary
//!   (`ExecStart`);
//! - restart after every exit, after `restart_delay` (`Restart=on-failure` with
//!   `RestartForceExitStatus=75`; the agent exits 0 only when stopped);
//! - every `check_every`, `lekiwi-agent guard --check`; on exit status 3 stop the agent
//!   (SIGTERM), which restarts it (`systemctl restart lekiwi-agent.service`).
//!
//! "The package binary" is the workspace's `lekiwi-agent` (the test's agent A).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::bin;

/// One start of the agent: when, which binary, and how it ended (`None` while it runs or when
/// it was killed by a signal).
#[derive(Clone, Debug)]
pub struct Start {
    /// When it was started.
    pub at: Instant,
    /// The binary started.
    pub binary: PathBuf,
    /// Its exit code.
    pub exit: Option<i32>,
}

/// What the supervisor did, for assertions and the report.
#[derive(Debug, Default)]
pub struct History {
    /// Every start, in order.
    pub starts: Vec<Start>,
    /// Guard runs that switched back (their output).
    pub fallbacks: Vec<(Instant, String)>,
}

/// A supervised `lekiwi-agent`: stopped (SIGKILL) when dropped.
pub struct Supervised {
    /// The agent's state directory.
    pub state_dir: PathBuf,
    /// Where the agent's and the guard's output goes.
    pub log: PathBuf,
    /// What happened so far.
    pub history: Arc<Mutex<History>>,
    stop: Arc<AtomicBool>,
    child: Arc<Mutex<Option<Child>>>,
    threads: Vec<JoinHandle<()>>,
}

/// How to supervise.
#[derive(Clone, Debug)]
pub struct SuperviseSpec {
    /// The agent's flags (`--config`, `--state-dir` first: the guard gets those two).
    pub args: Vec<String>,
    /// The state directory (also in `args`).
    pub state_dir: PathBuf,
    /// The log file.
    pub log: PathBuf,
    /// `RestartSec=`.
    pub restart_delay: Duration,
    /// The guard timer's period.
    pub check_every: Duration,
}

impl Supervised {
    /// Starts supervising.
    pub fn start(spec: SuperviseSpec) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let child: Arc<Mutex<Option<Child>>> = Arc::default();
        let history: Arc<Mutex<History>> = Arc::default();
        std::fs::File::create(&spec.log).expect("supervisor log");
        let main = {
            let (spec, stop, child, history) =
                (spec.clone(), stop.clone(), child.clone(), history.clone());
            std::thread::spawn(move || run(&spec, &stop, &child, &history))
        };
        let timer = {
            let (spec, stop, child, history) =
                (spec.clone(), stop.clone(), child.clone(), history.clone());
            std::thread::spawn(move || check_periodically(&spec, &stop, &child, &history))
        };
        Self {
            state_dir: spec.state_dir,
            log: spec.log,
            history,
            stop,
            child,
            threads: vec![main, timer],
        }
    }

    /// The log so far.
    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// The slot `current` points at (`a`, `b`), or `None` for the package binary.
    pub fn current_slot(&self) -> Option<String> {
        let target = std::fs::read_link(self.state_dir.join("agent/current")).ok()?;
        Some(target.to_string_lossy().into_owned())
    }

    /// Stops the agent (SIGKILL) and the supervisor.
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(c) = lock(&self.child).as_mut() {
            let _ = c.kill();
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for Supervised {
    fn drop(&mut self) {
        self.stop();
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

fn append(log: &Path, line: &str) {
    if let Ok(mut f) = std::fs::OpenOptions::new().append(true).open(log) {
        let _ = writeln!(f, "{line}");
    }
}

/// `lekiwi-agent --config .. --state-dir .. guard [--check]` from the package binary: its exit
/// code and output.
fn guard(spec: &SuperviseSpec, check: bool) -> (Option<i32>, String) {
    let mut cmd = Command::new(bin("lekiwi-agent"));
    cmd.args(&spec.args[..4]).arg("guard");
    if check {
        cmd.arg("--check");
    }
    match cmd.output() {
        Ok(out) => (
            out.status.code(),
            format!(
                "{}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            ),
        ),
        Err(e) => (None, e.to_string()),
    }
}

fn note_fallback(spec: &SuperviseSpec, history: &Mutex<History>, out: &str) {
    if out.contains("switched back") {
        append(&spec.log, &format!("supervisor: guard: {}", out.trim()));
        lock(history)
            .fallbacks
            .push((Instant::now(), out.trim().to_owned()));
    }
}

/// The main loop: guard, start, wait, delay, again.
fn run(
    spec: &SuperviseSpec,
    stop: &AtomicBool,
    child: &Mutex<Option<Child>>,
    history: &Mutex<History>,
) {
    use std::os::unix::fs::PermissionsExt as _;
    while !stop.load(Ordering::SeqCst) {
        let (_, out) = guard(spec, false);
        note_fallback(spec, history, &out);
        let slot = spec.state_dir.join("agent/current/lekiwi-agent");
        let executable =
            std::fs::metadata(&slot).is_ok_and(|m| m.permissions().mode() & 0o111 != 0);
        let binary = if executable {
            slot
        } else {
            bin("lekiwi-agent")
        };
        append(
            &spec.log,
            &format!("supervisor: starting {}", binary.display()),
        );
        let log = std::fs::OpenOptions::new().append(true).open(&spec.log);
        let (Ok(out), Ok(err)) = (
            log.as_ref().map(|f| f.try_clone()),
            log.as_ref().map(|f| f.try_clone()),
        ) else {
            return;
        };
        let spawned = Command::new(&binary)
            .args(&spec.args)
            .env("RUST_LOG", "info,lekiwi_agent=debug")
            .stdin(Stdio::null())
            .stdout(out.map(Stdio::from).unwrap_or(Stdio::null()))
            .stderr(err.map(Stdio::from).unwrap_or(Stdio::null()))
            .spawn();
        let index = {
            let mut h = lock(history);
            h.starts.push(Start {
                at: Instant::now(),
                binary: binary.clone(),
                exit: None,
            });
            h.starts.len() - 1
        };
        match spawned {
            Ok(c) => *lock(child) = Some(c),
            Err(e) => append(&spec.log, &format!("supervisor: exec failed: {e}")),
        }
        let exit = wait(child, stop);
        append(&spec.log, &format!("supervisor: exited {exit:?}"));
        lock(history).starts[index].exit = exit;
        std::thread::sleep(spec.restart_delay);
    }
}

/// Waits for the running child to exit (or the supervisor to stop); its exit code.
fn wait(child: &Mutex<Option<Child>>, stop: &AtomicBool) -> Option<i32> {
    loop {
        {
            let mut c = lock(child);
            let running = c.as_mut()?;
            if stop.load(Ordering::SeqCst) {
                let _ = running.kill();
                let _ = running.wait();
                *c = None;
                return None;
            }
            if let Ok(Some(status)) = running.try_wait() {
                *c = None;
                return status.code();
            }
        }
        std::thread::sleep(Duration::from_millis(25));
    }
}

/// The guard timer: `guard --check`; on 3, SIGTERM the agent (the main loop restarts it).
fn check_periodically(
    spec: &SuperviseSpec,
    stop: &AtomicBool,
    child: &Mutex<Option<Child>>,
    history: &Mutex<History>,
) {
    let mut next = Instant::now() + spec.check_every;
    while !stop.load(Ordering::SeqCst) {
        if Instant::now() < next {
            std::thread::sleep(Duration::from_millis(50));
            continue;
        }
        next = Instant::now() + spec.check_every;
        let (code, out) = guard(spec, true);
        if code == Some(3) {
            note_fallback(spec, history, &out);
            if let Some(c) = lock(child).as_ref() {
                let _ = Command::new("kill")
                    .args(["-TERM", &c.id().to_string()])
                    .status();
            }
        }
    }
}
