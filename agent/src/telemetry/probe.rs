//! Where telemetry readings come from: the [`Probe`] interface and its `sysinfo` implementation
//! for this machine, which refreshes only what each sampler reads.

use lekiwi_protocol::SystemFacts;
use std::path::Path;

use sysinfo::{Components, CpuRefreshKind, MemoryRefreshKind, Networks, System};
use tracing::info;

use super::thermal::ThermalZones;

/// A reading of the memory sampler.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct MemoryReading {
    pub(super) percent: f64,
    pub(super) used_bytes: u64,
}

/// A reading of the network sampler.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct NetworkReading {
    pub(super) rx_bytes_per_s: f64,
    pub(super) tx_bytes_per_s: f64,
}

/// Where readings come from: the machine ([`SystemProbe`]) or, in tests, a synthetic world.
/// `None` means "no reading" (no sensor, no root file system, a read failed).
pub(super) trait Probe: Send + Sync {
    fn cpu_percent(&mut self) -> Option<f64>;
    fn memory(&mut self) -> Option<MemoryReading>;
    /// Rates since the previous call.
    fn network(&mut self) -> Option<NetworkReading>;
    fn temperature_c(&mut self) -> Option<f64>;
    fn disk_percent(&mut self) -> Option<f64>;
    fn uptime_s(&self) -> Option<u64>;
    fn load1(&self) -> Option<f64>;
}

/// Facts about this computer for `hello`.
pub fn system_facts() -> SystemFacts {
    let mut system = System::new();
    system.refresh_memory_specifics(MemoryRefreshKind::nothing().with_ram());
    system.refresh_cpu_list(CpuRefreshKind::nothing());
    let arch = System::cpu_arch();
    SystemFacts {
        hostname: System::host_name(),
        os: System::long_os_version(),
        kernel: System::kernel_version(),
        arch: (!arch.is_empty()).then_some(arch),
        cpus: u32::try_from(system.cpus().len()).ok().filter(|&n| n > 0),
        memory_bytes: Some(system.total_memory()).filter(|&b| b > 0),
    }
}

/// Reads this machine through `sysinfo`, refreshing only what each sampler needs.
pub(super) struct SystemProbe {
    /// CPU usage and memory only; never processes.
    system: System,
    networks: Networks,
    networks_at: std::time::Instant,
    /// The CPU/SoC thermal zones (a Raspberry Pi's `cpu-thermal`): read first, when there are.
    zones: ThermalZones,
    /// Else the hwmon sensors.
    components: Components,
    /// Indices into `components` of the sensors that count (see [`pick_sensors`]).
    sensors: Vec<usize>,
}

impl SystemProbe {
    pub(super) fn new() -> Self {
        let mut system = System::new();
        // CPU use is a difference of counters: take the first snapshot now.
        system.refresh_cpu_usage();
        let networks = Networks::new_with_refreshed_list();
        let zones = ThermalZones::discover(std::path::Path::new("/sys"));
        let components = if zones.is_empty() {
            Components::new_with_refreshed_list()
        } else {
            Components::new()
        };
        let sensors = pick_sensors(components.list().iter().map(sysinfo::Component::label));
        info!(
            thermal_zones = ?zones.names(),
            sensors = ?sensors
                .iter()
                .map(|&i| components.list()[i].label())
                .collect::<Vec<_>>(),
            "telemetry samplers ready"
        );
        Self {
            system,
            networks,
            networks_at: std::time::Instant::now(),
            zones,
            components,
            sensors,
        }
    }
}

impl Probe for SystemProbe {
    fn cpu_percent(&mut self) -> Option<f64> {
        self.system.refresh_cpu_usage();
        if self.system.cpus().is_empty() {
            return None;
        }
        Some(f64::from(self.system.global_cpu_usage()))
    }

    fn memory(&mut self) -> Option<MemoryReading> {
        self.system
            .refresh_memory_specifics(MemoryRefreshKind::nothing().with_ram());
        let total = self.system.total_memory();
        let used = self.system.used_memory();
        (total > 0).then(|| MemoryReading {
            percent: used as f64 * 100.0 / total as f64,
            used_bytes: used,
        })
    }

    fn network(&mut self) -> Option<NetworkReading> {
        // `true`: forget interfaces that are gone; a new one starts from its current counters.
        self.networks.refresh(true);
        let now = std::time::Instant::now();
        let elapsed = now.duration_since(self.networks_at).as_secs_f64();
        self.networks_at = now;
        if elapsed < 0.001 {
            return None;
        }
        let (rx, tx) = self
            .networks
            .iter()
            .filter(|(name, data)| !is_loopback(name, data))
            .fold((0u64, 0u64), |(rx, tx), (_, data)| {
                (
                    rx.saturating_add(data.received()),
                    tx.saturating_add(data.transmitted()),
                )
            });
        Some(NetworkReading {
            rx_bytes_per_s: rx as f64 / elapsed,
            tx_bytes_per_s: tx as f64 / elapsed,
        })
    }

    fn temperature_c(&mut self) -> Option<f64> {
        if !self.zones.is_empty() {
            return self.zones.hottest_c();
        }
        if self.sensors.is_empty() {
            // Sensors may appear late (a driver loading after the agent started): look again,
            // which costs one directory listing when there are none.
            self.components.refresh(true);
            self.sensors =
                pick_sensors(self.components.list().iter().map(sysinfo::Component::label));
            if !self.sensors.is_empty() {
                info!("temperature sensors found");
            }
        } else {
            let list = self.components.list_mut();
            for &i in &self.sensors {
                if let Some(component) = list.get_mut(i) {
                    component.refresh();
                }
            }
        }
        let list = self.components.list();
        let hottest = self
            .sensors
            .iter()
            .filter_map(|&i| list.get(i)?.temperature())
            .map(f64::from)
            .filter(|t| t.is_finite())
            .reduce(f64::max);
        if hottest.is_none() {
            // Every chosen sensor failed: list them afresh next time.
            self.sensors.clear();
        }
        hottest
    }

    fn disk_percent(&mut self) -> Option<f64> {
        fs_use_percent(Path::new("/"))
    }

    fn uptime_s(&self) -> Option<u64> {
        Some(System::uptime()).filter(|&s| s > 0)
    }

    fn load1(&self) -> Option<f64> {
        let load = System::load_average().one;
        load.is_finite().then_some(load)
    }
}

fn is_loopback(name: &str, data: &sysinfo::NetworkData) -> bool {
    name == "lo"
        || (!data.ip_networks().is_empty()
            && data.ip_networks().iter().all(|n| n.addr.is_loopback()))
}

/// Indices of the sensors whose maximum is "the temperature": the CPU/SoC ones if any
/// (`cpu_thermal` on a Raspberry Pi, `k10temp`/`coretemp` on x86), else all of them (a disk or
/// Wi-Fi sensor is still better than nothing).
pub(super) fn pick_sensors<'a>(labels: impl Iterator<Item = &'a str>) -> Vec<usize> {
    const CPU_LIKE: [&str; 6] = ["cpu", "soc", "k10temp", "coretemp", "thermal", "tctl"];
    let labels: Vec<String> = labels.map(str::to_ascii_lowercase).collect();
    let cpu_like: Vec<usize> = labels
        .iter()
        .enumerate()
        .filter(|(_, label)| CPU_LIKE.iter().any(|key| label.contains(key)))
        .map(|(i, _)| i)
        .collect();
    if cpu_like.is_empty() {
        (0..labels.len()).collect()
    } else {
        cpu_like
    }
}

/// Percent in use of the file system holding `path`, as `df` reports it; `None` when it cannot
/// be read or has no size (ramfs). Asked of the file system itself (`statvfs`), so it also
/// works where no mount table lists the path, as on an initramfs root.
pub fn fs_use_percent(path: &Path) -> Option<f64> {
    let st = rustix::fs::statvfs(path).ok()?;
    use_percent(st.f_blocks, st.f_bfree, st.f_bavail)
}

/// Percent in use of a file system of `blocks` blocks, `free` of them free and `available` of
/// those usable without root, as `df` computes it: used over used plus available, so the blocks
/// only root may use count on neither side. A shared or quota-bound file system thus reads as
/// full as it is for the agent, not as full as its reservation makes it look.
pub(super) fn use_percent(blocks: u64, free: u64, available: u64) -> Option<f64> {
    let used = blocks.saturating_sub(free);
    let usable = used.saturating_add(available);
    (usable > 0).then(|| used as f64 * 100.0 / usable as f64)
}
