//! An emulated Raspberry Pi 5 (`scripts/testbed/pi.sh`): QEMU's `virt` machine with a Cortex-A76 booting
//! the arm64 agent from an initramfs. The guest reaches the host's loopback as 10.0.2.2; its
//! serial console is a file the test reads, where the guest's `/init` prints markers
//! (`LEKIWI-CPU`, `LEKIWI-RSS`, `LEKIWI-EXIT`).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde_json::Value;

use crate::http::http_get;
use crate::{log_dir, repo_root, wait_for};

/// The host's loopback as the guest sees it (QEMU's user network).
pub const HOST_FROM_GUEST: &str = "10.0.2.2";

/// The guest port of the agent's status endpoint (`--status-listen 0.0.0.0:9477`).
pub const GUEST_STATUS_PORT: u16 = 9477;

/// The emulated Pi's script, by its path in the repository.
const PI_SH: &str = "scripts/testbed/pi.sh";

/// `scripts/testbed/pi.sh` with `args`, with none of the calling `cargo test`'s variables (the
/// script builds with Debian's cargo in its own target directory).
fn pi_sh(args: &[&str]) -> Command {
    let mut cmd = Command::new("bash");
    cmd.arg(repo_root().join(PI_SH))
        .args(args)
        .env("LEKIWI_PI_RUN", log_dir().join("pi"));
    cmd
}

/// Runs `scripts/testbed/pi.sh build` once per test process: the arm64 agent, its unit-test binary, the
/// kernel and the initramfs (cached; `scripts/setup.sh` ran it cold already).
pub fn build() -> Result<()> {
    static BUILT: OnceLock<Result<String, String>> = OnceLock::new();
    once(&BUILT, PI_SH, &["build"]).map(drop)
}

/// Runs `scripts/testbed/pi.sh` (or another script, by its path in the repository) once per
/// test process and returns its stdout; the error carries its stderr.
fn once(
    cell: &'static OnceLock<Result<String, String>>,
    script: &str,
    args: &[&str],
) -> Result<String> {
    cell.get_or_init(|| {
        let mut cmd = pi_sh(args);
        if script != PI_SH {
            cmd = Command::new("bash");
            cmd.arg(repo_root().join(script)).args(args);
        }
        let out = cmd.output().map_err(|e| e.to_string())?;
        if out.status.success() {
            Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
        } else {
            Err(format!(
                "{script} {} failed:\n{}",
                args.join(" "),
                String::from_utf8_lossy(&out.stderr)
            ))
        }
    })
    .clone()
    .map_err(anyhow::Error::msg)
}

/// The arm64 `.deb` (`scripts/deb.sh --arch arm64`), built once per test process under
/// `target/test-logs/deb/`.
pub fn deb() -> Result<PathBuf> {
    static DEB: OnceLock<Result<String, String>> = OnceLock::new();
    let out = log_dir().join("deb");
    let path = once(
        &DEB,
        "scripts/deb.sh",
        &["--arch", "arm64", "--out", out.to_str().context("log dir")?],
    )?;
    Ok(PathBuf::from(path.lines().last().unwrap_or_default()))
}

/// The Debian bookworm arm64 root filesystem (`scripts/testbed/pi.sh rootfs`: cached; the first build
/// runs debootstrap's second stage in the emulated Pi).
pub fn rootfs() -> Result<()> {
    static ROOTFS: OnceLock<Result<String, String>> = OnceLock::new();
    build()?;
    once(&ROOTFS, PI_SH, &["rootfs"]).map(drop)
}

/// What the guest's `/init` runs (`lekiwi.run=` on the kernel command line).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Run {
    /// `/bin/lekiwi-agent` with the given arguments.
    Agent,
    /// The agent crate's unit-test binaries.
    UnitTests,
    /// `/lekiwi/run.sh` from the payload (busybox sh).
    Script,
}

/// One emulated Pi 5: the QEMU process (killed when dropped) and its console log.
pub struct PiGuest {
    child: Child,
    /// Its directory under `target/test-logs/pi/` (the console log is kept after the test).
    pub dir: PathBuf,
    /// Host port forwarded to the guest's [`GUEST_STATUS_PORT`].
    pub status_port: u16,
    /// When QEMU was started.
    pub booted: Instant,
}

impl PiGuest {
    /// Boots guest `name` running `run`; `payload`'s files appear in the guest under `/lekiwi`;
    /// `agent_args` are the agent's arguments (one each, spaces kept).
    pub fn boot(name: &str, run: Run, payload: Option<&Path>, agent_args: &[&str]) -> Result<Self> {
        build()?;
        let status_port = crate::free_port();
        let port = status_port.to_string();
        let what = match run {
            Run::Agent => "agent",
            Run::UnitTests => "unit-tests",
            Run::Script => "script",
        };
        let mut args = vec!["boot", "--foreground", "--name", name, "--run", what];
        args.extend(["--status-port", &port]);
        if let Some(p) = payload {
            args.extend(["--payload", p.to_str().context("payload path")?]);
        }
        args.push("--");
        args.extend(agent_args);
        Self::spawn(name, status_port, &args)
    }

    /// Boots guest `name` from the Debian root filesystem with systemd as PID 1 (`pi.sh boot
    /// --rootfs`): `payload` is its second disk, whose `run.sh` runs at every boot. The guest's
    /// `systemctl reboot` reboots it in the same QEMU process.
    pub fn boot_rootfs(name: &str, payload: &Path) -> Result<Self> {
        rootfs()?;
        let status_port = crate::free_port();
        let port = status_port.to_string();
        let payload = payload.to_str().context("payload path")?;
        let args = [
            "boot",
            "--rootfs",
            "--foreground",
            "--name",
            name,
            "--memory",
            "768",
            "--status-port",
            &port,
            "--payload",
            payload,
        ];
        Self::spawn(name, status_port, &args)
    }

    /// Runs `pi.sh ARGS` for guest `name` in the foreground of a child process.
    fn spawn(name: &str, status_port: u16, args: &[&str]) -> Result<Self> {
        let child = pi_sh(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .spawn()?;
        Ok(Self {
            child,
            dir: log_dir().join("pi").join(name),
            status_port,
            booted: Instant::now(),
        })
    }

    /// The serial console so far.
    pub fn console(&self) -> String {
        std::fs::read_to_string(self.dir.join("console.log")).unwrap_or_default()
    }

    /// The console's last `lines` lines, for failure messages.
    pub fn console_tail(&self, lines: usize) -> String {
        let text = self.console();
        let all: Vec<&str> = text.lines().collect();
        all[all.len().saturating_sub(lines)..].join("\n")
    }

    /// The value after `marker ` on the console's first line that starts with it.
    pub fn marker(&self, marker: &str) -> Option<String> {
        self.console()
            .lines()
            .find_map(|l| l.strip_prefix(marker)?.strip_prefix(' ').map(str::to_owned))
    }

    /// The agent's `VmRSS` in kB, each 10 s reading so far.
    pub fn rss_kb(&self) -> Vec<u64> {
        self.console()
            .lines()
            .filter_map(|l| l.strip_prefix("LEKIWI-RSS VmRSS:"))
            .filter_map(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .collect()
    }

    /// Waits for `/init`'s `LEKIWI-EXIT` marker and returns the exit status it reports; the error
    /// carries the console's tail.
    pub async fn wait_exit(&mut self, within: Duration) -> Result<i32> {
        let line = wait_for("the guest's exit marker", within, || async {
            self.marker("LEKIWI-EXIT")
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", self.console_tail(60)))?;
        let status = line
            .rsplit("status=")
            .next()
            .and_then(|s| s.trim().parse().ok());
        match status {
            Some(s) => Ok(s),
            None => bail!("malformed exit marker {line:?}"),
        }
    }

    /// `GET /status` of the agent in the guest, through the forwarded port.
    pub async fn status(&self) -> Result<Value> {
        let (code, body) = http_get(self.status_port, "/status").await?;
        if code != 200 {
            bail!("/status answered {code}: {body}");
        }
        Ok(serde_json::from_str(&body)?)
    }
}

impl Drop for PiGuest {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        // The initrd and the disk are tens of MB; the console log stays for debugging.
        let _ = std::fs::remove_file(self.dir.join("initrd"));
        let _ = std::fs::remove_file(self.dir.join("disk.img"));
        let _ = std::fs::remove_file(self.dir.join("disk.qcow2"));
        let _ = std::fs::remove_file(self.dir.join("payload.img"));
    }
}

/// Makes, with openssl, a CA (`ca.crt`) and a gateway certificate it signed (`tls.crt`,
/// `tls.key`) in `dir`, valid for 127.0.0.1 (the host's tools) and 10.0.2.2 (the guest's view of
/// the host).
pub fn gateway_ca(dir: &Path) -> Result<()> {
    let d = dir.display();
    std::fs::write(
        dir.join("ext"),
        format!("subjectAltName=IP:127.0.0.1,IP:{HOST_FROM_GUEST}\nbasicConstraints=CA:FALSE\n"),
    )?;
    let script = format!(
        "set -e; cd {d}
openssl req -x509 -newkey rsa:2048 -nodes -days 1 -subj /CN=lekiwi-pi-ca -keyout ca.key -out ca.crt
openssl req -newkey rsa:2048 -nodes -subj /CN=lekiwi-gateway -keyout tls.key -out tls.csr
openssl x509 -req -in tls.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 1 -extfile ext -out tls.crt"
    );
    let out = Command::new("bash").arg("-c").arg(&script).output()?;
    if !out.status.success() {
        bail!("making the CA: {}", String::from_utf8_lossy(&out.stderr));
    }
    Ok(())
}
