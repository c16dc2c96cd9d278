//! The budget of API-server reads the gateway makes for callers its caches cannot answer (a
//! token its Secret cache does not hold, a robot's blob read its Robot cache does not show
//! yet): misses are remembered for a short time and the reads share a small token bucket of
//! their own, so guesses cost the API server a bounded number of requests and never the budget
//! of status writes or Lease renewals.

use std::collections::HashSet;
use std::sync::Mutex;
use std::time::Duration;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use tokio::time::Instant;

use crate::config::Config;
use lekiwi_core::rate::SharedBucket;
use lekiwi_metrics::KindLabels;

/// Most misses remembered at once (each a short string); beyond it the older half is forgotten.
const MAX_MISSES: usize = 10_000;

/// What a live read is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Subject<'a> {
    /// The token Secret of robot `(namespace, name)`.
    Robot(&'a str, &'a str),
    /// The enrollment token Secrets of a namespace.
    Enrollment(&'a str),
    /// The Robot `(namespace, name)` itself, for its read of blob `digest`: whether its
    /// `spec.release` or `spec.agent` names the blob when the read reached this replica before
    /// its watch showed them.
    Spec(&'a str, &'a str, &'a str),
}

impl Subject<'_> {
    fn key(self) -> String {
        match self {
            Subject::Robot(ns, name) => format!("r/{ns}/{name}"),
            Subject::Enrollment(ns) => format!("e/{ns}"),
            Subject::Spec(ns, name, digest) => format!("s/{ns}/{name}/{digest}"),
        }
    }
}

/// Why a live read was not made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Skip {
    /// The same read found nothing a moment ago.
    Remembered,
    /// The budget of reads is spent for now.
    Throttled,
}

/// Settings of [`Lookups`].
#[derive(Clone, Copy, Debug)]
pub struct LookupConfig {
    /// Live reads per second, sustained.
    pub qps: f64,
    /// Live reads at once.
    pub burst: u32,
    /// How long a miss is remembered (between this and twice this).
    pub miss_ttl: Duration,
}

impl LookupConfig {
    /// The settings the operator's flags give (`--auth-lookup-qps`, `--auth-lookup-burst`,
    /// `--auth-miss-seconds`).
    pub fn of(config: &Config) -> Self {
        Self {
            qps: config.flags.auth_lookup_qps,
            burst: config.flags.auth_lookup_burst,
            miss_ttl: Duration::from_secs(config.flags.auth_miss_seconds.max(1)),
        }
    }
}

impl Default for LookupConfig {
    fn default() -> Self {
        Self {
            qps: 1.0,
            burst: 10,
            miss_ttl: Duration::from_secs(5),
        }
    }
}

/// Misses in two generations: a miss lives until the generation after its own is dropped, so
/// between one and two TTLs, with no per-entry timer.
struct Misses {
    current: HashSet<String>,
    previous: HashSet<String>,
    since: Instant,
}

impl Misses {
    fn age(&mut self, ttl: Duration) {
        let elapsed = self.since.elapsed();
        if elapsed >= ttl * 2 {
            self.current.clear();
            self.previous.clear();
            self.since = Instant::now();
        } else if elapsed >= ttl || self.current.len() >= MAX_MISSES / 2 {
            self.previous = std::mem::take(&mut self.current);
            self.since = Instant::now();
        }
    }
}

/// Guards the gateway's live reads on behalf of unauthenticated requests.
pub struct Lookups {
    budget: SharedBucket,
    misses: Mutex<Misses>,
    ttl: Duration,
    /// Live reads made and skipped, by kind (`robot_secret`, `enrollment_list`, `robot_spec`,
    /// `remembered`, `throttled`).
    counted: Family<KindLabels, Counter>,
}

impl Lookups {
    /// Lookups with `config`, counted in `counted`.
    pub fn new(config: LookupConfig, counted: Family<KindLabels, Counter>) -> Self {
        Self {
            budget: SharedBucket::new(config.qps, config.burst),
            misses: Mutex::new(Misses {
                current: HashSet::new(),
                previous: HashSet::new(),
                since: Instant::now(),
            }),
            ttl: config.miss_ttl,
            counted,
        }
    }

    fn count(&self, kind: &'static str) {
        self.counted.get_or_create(&KindLabels { kind }).inc();
    }

    /// Whether a live read about `subject` may be made now; a yes takes one from the budget.
    pub fn admit(&self, subject: Subject<'_>) -> Result<(), Skip> {
        let key = subject.key();
        let remembered = {
            let mut misses = self.misses.lock().unwrap_or_else(|p| p.into_inner());
            misses.age(self.ttl);
            misses.current.contains(&key) || misses.previous.contains(&key)
        };
        if remembered {
            self.count("remembered");
            return Err(Skip::Remembered);
        }
        if !self.budget.try_take() {
            self.count("throttled");
            return Err(Skip::Throttled);
        }
        self.count(match subject {
            Subject::Robot(..) => "robot_secret",
            Subject::Enrollment(_) => "enrollment_list",
            Subject::Spec(..) => "robot_spec",
        });
        Ok(())
    }

    /// Remembers that a live read about `subject` found nothing that matched.
    pub fn missed(&self, subject: Subject<'_>) {
        let mut misses = self.misses.lock().unwrap_or_else(|p| p.into_inner());
        misses.age(self.ttl);
        misses.current.insert(subject.key());
    }

    /// Forgets a miss about `subject` (this gateway just made its token).
    pub fn forget(&self, subject: Subject<'_>) {
        let key = subject.key();
        let mut misses = self.misses.lock().unwrap_or_else(|p| p.into_inner());
        misses.current.remove(&key);
        misses.previous.remove(&key);
    }
}

impl Default for Lookups {
    fn default() -> Self {
        Self::new(LookupConfig::default(), Family::default())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lookups(qps: f64, burst: u32) -> Lookups {
        Lookups::new(
            LookupConfig {
                qps,
                burst,
                miss_ttl: Duration::from_secs(5),
            },
            Family::default(),
        )
    }

    #[tokio::test(start_paused = true)]
    async fn a_miss_is_remembered_for_one_to_two_ttls() {
        let l = lookups(100.0, 100);
        let robot = Subject::Robot("lab", "kiwi-1");
        assert_eq!(l.admit(robot), Ok(()));
        l.missed(robot);
        assert_eq!(l.admit(robot), Err(Skip::Remembered));
        assert_eq!(l.admit(Subject::Robot("lab", "kiwi-2")), Ok(()));
        assert_eq!(l.admit(Subject::Enrollment("lab")), Ok(()));
        tokio::time::advance(Duration::from_secs(6)).await;
        assert_eq!(l.admit(robot), Err(Skip::Remembered));
        tokio::time::advance(Duration::from_secs(5)).await;
        assert_eq!(l.admit(robot), Ok(()));
        l.missed(robot);
        l.forget(robot);
        assert_eq!(l.admit(robot), Ok(()));
    }

    #[tokio::test(start_paused = true)]
    async fn reads_beyond_the_budget_are_throttled() {
        let l = lookups(2.0, 3);
        let admitted = (0..10)
            .filter(|i| l.admit(Subject::Robot("lab", &format!("r{i}"))).is_ok())
            .count();
        assert_eq!(admitted, 3);
        assert_eq!(l.admit(Subject::Enrollment("x")), Err(Skip::Throttled));
        tokio::time::advance(Duration::from_millis(500)).await;
        assert_eq!(l.admit(Subject::Enrollment("x")), Ok(()));
    }

    #[tokio::test(start_paused = true)]
    async fn misses_are_bounded() {
        let l = lookups(1e9, u32::MAX);
        for i in 0..3 * MAX_MISSES {
            l.missed(Subject::Robot("lab", &format!("r{i}")));
        }
        let m = l.misses.lock().unwrap();
        assert!(m.current.len() + m.previous.len() <= MAX_MISSES);
    }
}
