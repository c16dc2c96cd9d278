//! Resource use of the LeKiwi host process, read from `/proc`: its resident memory and its
//! share of all cores since the previous reading (sent in heartbeat vitals, PROTOCOL.md §5.1).

use std::path::{Path, PathBuf};

/// One reading of the host process.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HostStats {
    /// Resident memory, bytes (`VmRSS`).
    pub rss_bytes: u64,
    /// CPU use since the previous reading of the same process, percent of all cores; `None` at
    /// its first reading.
    pub cpu_percent: Option<f64>,
}

/// Reads [`HostStats`], keeping the previous CPU counters for the next share.
#[derive(Debug)]
pub(super) struct Sampler {
    proc_root: PathBuf,
    /// The pid, its CPU ticks and the machine's total ticks at the previous reading.
    last: Option<(u32, u64, u64)>,
}

impl Sampler {
    pub(super) fn new(proc_root: &Path) -> Self {
        Self {
            proc_root: proc_root.to_owned(),
            last: None,
        }
    }

    /// A reading of `pid`; `None` (and the counters forgotten) when it cannot be read.
    pub(super) fn sample(&mut self, pid: u32) -> Option<HostStats> {
        let dir = self.proc_root.join(pid.to_string());
        let reading = (|| {
            let rss_kib = vm_rss_kib(&std::fs::read_to_string(dir.join("status")).ok()?)?;
            let ticks = process_ticks(&std::fs::read_to_string(dir.join("stat")).ok()?)?;
            let total = total_ticks(&std::fs::read_to_string(self.proc_root.join("stat")).ok()?)?;
            Some((rss_kib * 1024, ticks, total))
        })();
        let Some((rss_bytes, ticks, total)) = reading else {
            self.last = None;
            return None;
        };
        let cpu_percent = match self.last {
            Some((last_pid, last_ticks, last_total)) if last_pid == pid && total > last_total => {
                Some(ticks.saturating_sub(last_ticks) as f64 * 100.0 / (total - last_total) as f64)
            }
            _ => None,
        };
        self.last = Some((pid, ticks, total));
        Some(HostStats {
            rss_bytes,
            cpu_percent,
        })
    }
}

/// `VmRSS` of a `/proc/PID/status`, KiB.
fn vm_rss_kib(status: &str) -> Option<u64> {
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// `utime + stime` of a `/proc/PID/stat`, clock ticks (the command name, in parentheses, may
/// hold spaces: fields are counted after its closing parenthesis).
fn process_ticks(stat: &str) -> Option<u64> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace().skip(11);
    let utime: u64 = fields.next()?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    Some(utime + stime)
}

/// The sum of the `cpu` line of `/proc/stat`: every core's ticks, in the same unit.
fn total_ticks(stat: &str) -> Option<u64> {
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    Some(
        line.split_whitespace()
            .skip(1)
            .filter_map(|v| v.parse::<u64>().ok())
            .sum(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_proc_files() {
        assert_eq!(
            vm_rss_kib("Name:\tpython3\nVmRSS:\t  51200 kB\n"),
            Some(51200)
        );
        let stat = "42 (lekiwi host (x)) S 1 42 42 0 -1 4194560 100 0 0 0 250 50 0 0 20 0 1 0";
        assert_eq!(process_ticks(stat), Some(300));
        assert_eq!(
            total_ticks("cpu  10 20 30 40\ncpu0 5 10 15 20\n"),
            Some(100)
        );
    }

    /// A process that spins shows a CPU share at its second reading, and its memory.
    #[test]
    fn reads_a_live_process() {
        let mut child = std::process::Command::new("sh")
            .args(["-c", "while :; do :; done"])
            .spawn()
            .unwrap();
        let mut sampler = Sampler::new(Path::new("/proc"));
        let first = sampler.sample(child.id()).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(500));
        let second = sampler.sample(child.id()).unwrap();
        child.kill().unwrap();
        child.wait().unwrap();
        assert!(
            first.rss_bytes > 0 && first.cpu_percent.is_none(),
            "{first:?}"
        );
        assert!(second.cpu_percent.is_some_and(|c| c > 0.0), "{second:?}");
        assert_eq!(sampler.sample(u32::MAX), None);
    }
}
