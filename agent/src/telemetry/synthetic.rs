//! Synthetic readings for simulated robots (`lekiwi-fleet`, `lekiwi-sim`), where many robots
//! share one machine whose own readings say nothing about any of them: each robot gets a small
//! world of its own, seeded by its name, that moves like a robot's Raspberry Pi (an idle load
//! with now and then a busy spell, memory and temperature following it, a disk filling slowly).
//! The collector treats these readings exactly as a real probe's: same samplers, intervals and
//! delta compression, so a simulated robot sends the frames a real agent would.

use std::time::Instant;

use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};

use super::probe::{MemoryReading, NetworkReading, Probe};

/// Memory of the simulated computer (a Raspberry Pi 5 with 8 GiB).
const MEMORY_BYTES: f64 = (8u64 << 30) as f64;
/// Its CPU count, for the load average.
const CPUS: f64 = 4.0;

/// One simulated robot's world.
pub(super) struct SyntheticProbe {
    rng: SmallRng,
    started: Instant,
    /// Uptime before the simulation started, seconds.
    booted_s: u64,
    idle_cpu: f64,
    idle_memory: f64,
    cpu: f64,
    memory: f64,
    temperature: f64,
    disk: f64,
    /// CPU readings left in the current busy spell (a teleoperation session, a recording).
    busy_for: u32,
}

impl SyntheticProbe {
    /// The world of the robot named `name`: the same name starts from the same state.
    pub(super) fn new(name: &str) -> Self {
        let mut rng = SmallRng::seed_from_u64(seed(name));
        let idle_cpu = rng.random_range(6.0..22.0);
        let idle_memory = rng.random_range(24.0..42.0);
        Self {
            booted_s: rng.random_range(600..86_400),
            cpu: idle_cpu,
            memory: idle_memory,
            temperature: 45.0 + idle_cpu * 0.3,
            disk: rng.random_range(28.0..62.0),
            idle_cpu,
            idle_memory,
            busy_for: 0,
            started: Instant::now(),
            rng,
        }
    }

    fn busy(&self) -> bool {
        self.busy_for > 0
    }
}

/// A stable seed from a robot's name (FNV-1a: the same on every run and platform).
fn seed(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

impl Probe for SyntheticProbe {
    fn cpu_percent(&mut self) -> Option<f64> {
        if self.busy_for > 0 {
            self.busy_for -= 1;
        } else if self.rng.random_bool(0.04) {
            self.busy_for = self.rng.random_range(6..30);
        }
        let target = if self.busy() {
            self.rng.random_range(55.0..90.0)
        } else {
            self.idle_cpu
        };
        let noise = self.rng.random_range(-4.0..4.0);
        self.cpu = (self.cpu + 0.5 * (target - self.cpu) + noise).clamp(0.5, 100.0);
        Some(self.cpu)
    }

    fn memory(&mut self) -> Option<MemoryReading> {
        let target = self.idle_memory + if self.busy() { 14.0 } else { 0.0 };
        let noise = self.rng.random_range(-0.8..0.8);
        self.memory = (self.memory + 0.3 * (target - self.memory) + noise).clamp(5.0, 98.0);
        Some(MemoryReading {
            percent: self.memory,
            used_bytes: (MEMORY_BYTES * self.memory / 100.0) as u64,
        })
    }

    fn network(&mut self) -> Option<NetworkReading> {
        // Camera streams while busy, control traffic and logs otherwise.
        let (rx, tx) = if self.busy() {
            (
                self.rng.random_range(150e3..400e3),
                self.rng.random_range(1.5e6..4e6),
            )
        } else {
            (
                self.rng.random_range(8e3..40e3),
                self.rng.random_range(4e3..20e3),
            )
        };
        Some(NetworkReading {
            rx_bytes_per_s: rx,
            tx_bytes_per_s: tx,
        })
    }

    fn temperature_c(&mut self) -> Option<f64> {
        // The SoC warms with its load, slowly (a heat sink and a fan).
        let target = 42.0 + 0.3 * self.cpu;
        let noise = self.rng.random_range(-0.4..0.4);
        self.temperature += 0.4 * (target - self.temperature) + noise;
        Some(self.temperature)
    }

    fn disk_percent(&mut self) -> Option<f64> {
        // Logs and recordings fill the card slowly.
        self.disk = (self.disk + self.rng.random_range(0.0..0.05)).min(99.0);
        Some(self.disk)
    }

    fn uptime_s(&self) -> Option<u64> {
        Some(self.booted_s + self.started.elapsed().as_secs())
    }

    fn load1(&self) -> Option<f64> {
        Some((self.cpu / 100.0 * CPUS * 100.0).round() / 100.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each robot's world is its own and the same on every run; its readings stay in range and
    /// move, with busy spells now and then.
    #[test]
    fn a_robots_world_is_its_own_plausible_and_moving() {
        let mut a = SyntheticProbe::new("kiwi-000");
        let mut again = SyntheticProbe::new("kiwi-000");
        let mut b = SyntheticProbe::new("kiwi-001");
        let cpu = |p: &mut SyntheticProbe| (0..500).map(|_| p.cpu_percent().unwrap()).collect();
        let (ca, cb): (Vec<f64>, Vec<f64>) = (cpu(&mut a), cpu(&mut b));
        assert_eq!(ca, cpu(&mut again), "the same name, the same world");
        assert_ne!(ca, cb, "another name, another world");
        assert!(ca.iter().all(|c| (0.5..=100.0).contains(c)));
        assert!(ca.iter().any(|&c| c > 50.0), "busy spells happen");
        assert!(
            ca.iter().filter(|&&c| c < 30.0).count() > 250,
            "mostly idle"
        );
        for _ in 0..200 {
            let m = a.memory().unwrap();
            assert!((5.0..=98.0).contains(&m.percent));
            assert!(m.used_bytes > 0 && (m.used_bytes as f64) < MEMORY_BYTES);
            let t = a.temperature_c().unwrap();
            assert!((35.0..=80.0).contains(&t), "{t}");
            let n = a.network().unwrap();
            assert!(n.rx_bytes_per_s > 0.0 && n.tx_bytes_per_s > 0.0);
        }
        let d0 = a.disk_percent().unwrap();
        assert!(
            (0..100)
                .map(|_| a.disk_percent().unwrap())
                .all(|d| d >= d0 && d <= 99.0)
        );
        assert!(a.uptime_s().unwrap() >= 600);
    }
}
