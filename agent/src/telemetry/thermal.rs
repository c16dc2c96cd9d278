//! The SoC's temperature from the kernel's thermal zones: `class/thermal/thermal_zone*/type` under
//! `/sys` names each zone (`cpu-thermal`, the only one on a Raspberry Pi 5) and `temp` holds its
//! temperature in millidegrees Celsius: one small read per sample. Only CPU/SoC zones count; a
//! machine without one (x86 boards: `x86_pkg_temp`, `acpitz`) is read through `sysinfo`'s hwmon
//! components instead (see [`super::probe::SystemProbe`]).

use std::fs;
use std::path::{Path, PathBuf};

/// What a zone's `type` contains when it measures the CPU or the SoC (`cpu-thermal` on a
/// Raspberry Pi, `cpu0-thermal`/`soc-thermal` on other ARM boards).
const CPU_ZONE: [&str; 2] = ["cpu", "soc"];

/// The CPU/SoC thermal zones of a machine.
#[derive(Debug, Default)]
pub(super) struct ThermalZones {
    /// (`type`, path of `temp`) of each zone that counts, in zone order.
    zones: Vec<(String, PathBuf)>,
}

impl ThermalZones {
    /// The CPU/SoC zones under `sys` (`/sys` on a robot; a fixture directory in tests).
    pub(super) fn discover(sys: &Path) -> Self {
        let Ok(entries) = fs::read_dir(sys.join("class/thermal")) else {
            return Self::default();
        };
        let mut zones: Vec<(String, PathBuf)> = entries
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().starts_with("thermal_zone"))
            .filter_map(|e| {
                let kind = fs::read_to_string(e.path().join("type")).ok()?;
                let kind = kind.trim().to_owned();
                let lower = kind.to_ascii_lowercase();
                CPU_ZONE
                    .iter()
                    .any(|k| lower.contains(k))
                    .then(|| (kind, e.path().join("temp")))
            })
            .collect();
        zones.sort_by(|a, b| a.1.cmp(&b.1));
        Self { zones }
    }

    /// The zones' `type`s (for the log).
    pub(super) fn names(&self) -> Vec<&str> {
        self.zones.iter().map(|(kind, _)| kind.as_str()).collect()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.zones.is_empty()
    }

    /// The hottest zone in °C; `None` when none reads (a zone whose sensor is not ready answers
    /// its `temp` with an error).
    pub(super) fn hottest_c(&self) -> Option<f64> {
        self.zones
            .iter()
            .filter_map(|(_, temp)| millidegrees(temp))
            .reduce(f64::max)
    }
}

/// The file's millidegrees Celsius (`52350\n`) in °C.
fn millidegrees(path: &Path) -> Option<f64> {
    let text = fs::read_to_string(path).ok()?;
    let milli: i64 = text.trim().parse().ok()?;
    Some(milli as f64 / 1000.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `agent/tests/fixtures/pi5/sys` (see its README: reconstructed from public documentation).
    fn pi5_sys() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pi5/sys")
    }

    #[test]
    fn a_pi5_reads_its_cpu_thermal_zone_in_degrees() {
        let zones = ThermalZones::discover(&pi5_sys());
        assert_eq!(zones.names(), ["cpu-thermal"]);
        let t = zones.hottest_c().expect("a temperature");
        assert!((t - 52.35).abs() < 1e-9, "{t}");
    }

    /// Writes zone `n` of a fake `/sys` in `dir`.
    fn zone(dir: &Path, n: u32, kind: &str, temp: &str) {
        let z = dir.join(format!("class/thermal/thermal_zone{n}"));
        fs::create_dir_all(&z).unwrap();
        fs::write(z.join("type"), format!("{kind}\n")).unwrap();
        fs::write(z.join("temp"), temp).unwrap();
    }

    #[test]
    fn only_cpu_and_soc_zones_count_and_the_hottest_wins() {
        let dir = tempfile::tempdir().unwrap();
        zone(dir.path(), 0, "acpitz", "90000\n");
        zone(dir.path(), 1, "cpu0-thermal", "41500\n");
        zone(dir.path(), 2, "soc-thermal", "-1250\n");
        zone(dir.path(), 3, "gpu-thermal", "99000\n");
        let zones = ThermalZones::discover(dir.path());
        assert_eq!(zones.names(), ["cpu0-thermal", "soc-thermal"]);
        assert_eq!(zones.hottest_c(), Some(41.5));
    }

    #[test]
    fn an_x86_machine_has_no_zone_that_counts_and_an_unready_sensor_reads_nothing() {
        let dir = tempfile::tempdir().unwrap();
        zone(dir.path(), 0, "x86_pkg_temp", "55000\n");
        zone(dir.path(), 1, "INT3400 Thermal", "20000\n");
        assert!(ThermalZones::discover(dir.path()).is_empty());
        assert!(ThermalZones::discover(&dir.path().join("none")).is_empty());
        zone(dir.path(), 2, "cpu-thermal", "");
        let zones = ThermalZones::discover(dir.path());
        assert_eq!(zones.names(), ["cpu-thermal"]);
        assert_eq!(zones.hottest_c(), None);
    }
}
