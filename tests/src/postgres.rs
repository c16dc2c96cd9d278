//! A private PostgreSQL 15 server per test: `initdb` in a temporary directory, `postgres` on a
//! free loopback port, stopped and deleted on drop.

use std::os::unix::fs::MetadataExt as _;
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail};

use crate::{free_port, log_dir};

/// Where Debian's `postgresql-15` puts the server binaries.
pub const PG_BIN: &str = "/usr/lib/postgresql/15/bin";
const SUPERUSER: &str = "postgres";
const READY_TIMEOUT: Duration = Duration::from_secs(30);
const STOP_TIMEOUT: Duration = Duration::from_secs(30);

/// A running PostgreSQL server of one test's own. Trust authentication over TCP on 127.0.0.1,
/// fsync off: fast, and a crash of the server process alone still loses nothing committed.
pub struct Postgres {
    dir: tempfile::TempDir,
    port: u16,
    /// User and group to run as: `postgres` refuses to run as root.
    run_as: Option<(u32, u32)>,
    child: Option<Child>,
    /// Log of the server process, kept after the test.
    pub log: PathBuf,
    /// How long `initdb` took.
    pub init_time: Duration,
    /// How long the last start took until the server accepted connections.
    pub start_time: Duration,
}

impl Postgres {
    /// Initialises a cluster in a new temporary directory and starts the server on a free port.
    /// Fails, rather than skips, when PostgreSQL is not installed.
    pub fn start() -> Result<Postgres> {
        for bin in ["initdb", "postgres", "pg_isready", "psql"] {
            if !Path::new(PG_BIN).join(bin).exists() {
                bail!(
                    "PostgreSQL 15 is not installed ({PG_BIN}/{bin} is missing): run scripts/setup.sh"
                );
            }
        }
        let run_as = if running_as_root()? {
            Some(postgres_user().context(
                "we run as root and PostgreSQL must not: the `postgres` user is missing; run scripts/setup.sh",
            )?)
        } else {
            None
        };
        let dir = tempfile::Builder::new().prefix("lekiwi-pg-").tempdir()?;
        if let Some((uid, gid)) = run_as {
            std::os::unix::fs::chown(dir.path(), Some(uid), Some(gid))
                .context("hand the temporary directory to the postgres user")?;
        }
        let mut pg = Postgres {
            port: 0,
            log: PathBuf::new(),
            dir,
            run_as,
            child: None,
            init_time: Duration::ZERO,
            start_time: Duration::ZERO,
        };

        let started = Instant::now();
        let out = pg
            .as_postgres(PG_BIN.to_owned() + "/initdb")
            .arg("-D")
            .arg(pg.data_dir())
            .args(["-U", SUPERUSER, "-A", "trust", "-E", "UTF8", "--locale=C"])
            .args(["--no-sync", "--no-instructions"])
            .output()
            .context("run initdb")?;
        check("initdb", &out)?;
        pg.init_time = started.elapsed();

        // Another test may take a port between our probe and the server's bind: try others.
        let mut last_err = None;
        for _ in 0..3 {
            pg.port = free_port();
            pg.log = log_dir().join(format!("postgres-{}.log", pg.port));
            match pg.spawn() {
                Ok(()) => return Ok(pg),
                Err(e) => last_err = Some(e),
            }
        }
        Err(last_err.unwrap_or_else(|| anyhow::anyhow!("postgres did not start")))
    }

    /// The port it listens on, on 127.0.0.1.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The cluster's data directory.
    pub fn data_dir(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    /// A URL for `database` as the superuser.
    pub fn url(&self, database: &str) -> String {
        format!("postgres://{SUPERUSER}@127.0.0.1:{}/{database}", self.port)
    }

    /// Creates a database and returns its URL.
    pub fn create_database(&self, name: &str) -> Result<String> {
        self.psql("postgres", &format!("CREATE DATABASE \"{name}\""))?;
        Ok(self.url(name))
    }

    /// Runs SQL with `psql` and returns its unaligned, tuples-only output.
    pub fn psql(&self, database: &str, sql: &str) -> Result<String> {
        let out = Command::new(Path::new(PG_BIN).join("psql"))
            .args([
                "-h",
                "127.0.0.1",
                "-p",
                &self.port.to_string(),
                "-U",
                SUPERUSER,
            ])
            .args([
                "-d",
                database,
                "-v",
                "ON_ERROR_STOP=1",
                "-X",
                "-A",
                "-t",
                "-q",
                "-c",
                sql,
            ])
            .stdin(Stdio::null())
            .output()
            .context("run psql")?;
        check(&format!("psql {sql:?}"), &out)?;
        Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
    }

    /// Stops the server cleanly (fast shutdown: sessions are cut, a checkpoint written) and
    /// starts it again on the same port and data.
    pub fn restart(&mut self) -> Result<()> {
        self.stop("INT")?;
        self.spawn()
    }

    /// Stops the server cleanly and leaves it down (an outage) until [`Postgres::start_again`].
    pub fn shut_down(&mut self) -> Result<()> {
        self.stop("INT")
    }

    /// Starts a server stopped by [`Postgres::shut_down`] on the same port and data.
    pub fn start_again(&mut self) -> Result<()> {
        self.spawn()
    }

    /// Stops the server as a crash would (immediate shutdown: no checkpoint, so the next start
    /// runs crash recovery from the WAL) and starts it again on the same port and data.
    pub fn crash_restart(&mut self) -> Result<()> {
        self.stop("QUIT")?;
        self.spawn()
    }

    /// A `Command` that runs as the postgres user when we are root.
    fn as_postgres(&self, program: impl AsRef<std::ffi::OsStr>) -> Command {
        let mut cmd = Command::new(program);
        // `runuser` would stay between us and the server as its parent, so the server's pid
        // would not be ours to signal; dropping privileges in the child itself keeps it so.
        if let Some((uid, gid)) = self.run_as {
            cmd.uid(uid).gid(gid).env("HOME", self.dir.path());
        }
        cmd.stdin(Stdio::null()).current_dir(self.dir.path());
        cmd
    }

    /// Starts the server process and waits until it accepts connections.
    fn spawn(&mut self) -> Result<()> {
        let started = Instant::now();
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .with_context(|| format!("open {}", self.log.display()))?;
        let child = self
            .as_postgres(PG_BIN.to_owned() + "/postgres")
            .arg("-D")
            .arg(self.data_dir())
            .args(["-p", &self.port.to_string(), "-h", "127.0.0.1", "-k"])
            .arg(self.dir.path())
            .args([
                "-c",
                "fsync=off",
                "-c",
                "shared_buffers=16MB",
                "-c",
                "max_connections=50",
            ])
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .context("spawn postgres")?;
        self.child = Some(child);
        loop {
            if let Some(status) = self
                .child
                .as_mut()
                .and_then(|c| c.try_wait().ok().flatten())
            {
                self.child = None;
                bail!(
                    "postgres exited with {status} before accepting connections; log {}:\n{}",
                    self.log.display(),
                    std::fs::read_to_string(&self.log).unwrap_or_default()
                );
            }
            let ready = Command::new(Path::new(PG_BIN).join("pg_isready"))
                .args(["-q", "-h", "127.0.0.1", "-p", &self.port.to_string()])
                .args(["-U", SUPERUSER, "-d", "postgres", "-t", "1"])
                .status()
                .context("run pg_isready")?;
            if ready.success() {
                self.start_time = started.elapsed();
                return Ok(());
            }
            if started.elapsed() > READY_TIMEOUT {
                self.stop("KILL")?;
                bail!(
                    "postgres did not accept connections within {READY_TIMEOUT:?}; log {}",
                    self.log.display()
                );
            }
            std::thread::sleep(Duration::from_millis(25));
        }
    }

    /// Sends `signal` to the server and waits for it to exit.
    fn stop(&mut self, signal: &str) -> Result<()> {
        let Some(mut child) = self.child.take() else {
            return Ok(());
        };
        if child.try_wait()?.is_none() {
            Command::new("kill")
                .args([&format!("-{signal}"), &child.id().to_string()])
                .status()
                .context("run kill")?;
        }
        let started = Instant::now();
        while child.try_wait()?.is_none() {
            if started.elapsed() > STOP_TIMEOUT {
                let _ = child.kill();
                let _ = child.wait();
                bail!("postgres did not stop within {STOP_TIMEOUT:?} of SIG{signal}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(())
    }
}

impl Drop for Postgres {
    fn drop(&mut self) {
        // Immediate shutdown ends the backends too; the temporary directory goes afterwards.
        if self.stop("QUIT").is_err()
            && let Some(mut child) = self.child.take()
        {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn check(what: &str, out: &Output) -> Result<()> {
    if !out.status.success() {
        bail!(
            "{what} failed with {}: {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(())
}

/// Whether this process runs as root: `/proc/self` belongs to our effective user.
fn running_as_root() -> Result<bool> {
    Ok(std::fs::metadata("/proc/self")
        .context("stat /proc/self")?
        .uid()
        == 0)
}

/// Uid and gid of the `postgres` user from `/etc/passwd`.
fn postgres_user() -> Result<(u32, u32)> {
    let passwd = std::fs::read_to_string("/etc/passwd")?;
    passwd
        .lines()
        .find_map(|line| {
            let fields: Vec<&str> = line.split(':').collect();
            match fields.as_slice() {
                [SUPERUSER, _, uid, gid, ..] => Some((uid.parse().ok()?, gid.parse().ok()?)),
                _ => None,
            }
        })
        .context("no postgres user in /etc/passwd")
}
