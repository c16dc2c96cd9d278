//! Reconnect delays: exponential backoff with full jitter, so a fleet that lost its gateway at
//! the same moment does not come back in lockstep.

use std::time::Duration;

use rand::Rng;

/// Exponential backoff with full jitter: the n-th delay is uniform in
/// `[0, min(max, initial * 2^n)]`.
#[derive(Clone, Debug)]
pub struct Backoff {
    initial: Duration,
    max: Duration,
    attempt: u32,
}

impl Backoff {
    /// A backoff whose first delay is at most `initial` and no delay exceeds `max`.
    pub fn new(initial: Duration, max: Duration) -> Self {
        Self {
            initial: initial.max(Duration::from_millis(1)),
            max: max.max(initial),
            attempt: 0,
        }
    }

    /// The upper bound of the next delay.
    pub fn ceiling(&self) -> Duration {
        let factor = 1u32.checked_shl(self.attempt.min(30)).unwrap_or(u32::MAX);
        self.initial.saturating_mul(factor).min(self.max)
    }

    /// The next delay (random up to [`Self::ceiling`]); raises the ceiling for the one after.
    pub fn next_delay(&mut self) -> Duration {
        let ceiling = self.ceiling();
        self.attempt = self.attempt.saturating_add(1);
        let ms = u64::try_from(ceiling.as_millis()).unwrap_or(u64::MAX);
        Duration::from_millis(rand::rng().random_range(0..=ms))
    }

    /// The largest delay.
    pub fn cap(&self) -> Duration {
        self.max
    }

    /// Failures since the last reset.
    pub fn attempts(&self) -> u32 {
        self.attempt
    }

    /// Jumps to the cap, for failures that retrying soon cannot fix (e.g. a refused token).
    pub fn saturate(&mut self) {
        self.attempt = 31;
    }

    /// Back to the first delay, after a connection that held.
    pub fn reset(&mut self) {
        self.attempt = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ceilings_double_up_to_the_cap() {
        let mut b = Backoff::new(Duration::from_millis(100), Duration::from_secs(2));
        let mut ceilings = Vec::new();
        for _ in 0..8 {
            ceilings.push(b.ceiling().as_millis());
            let d = b.next_delay();
            assert!(d <= Duration::from_secs(2));
        }
        assert_eq!(ceilings, vec![100, 200, 400, 800, 1600, 2000, 2000, 2000]);
        b.reset();
        assert_eq!(b.ceiling(), Duration::from_millis(100));
        b.saturate();
        assert_eq!(b.ceiling(), Duration::from_secs(2));
    }

    /// Full jitter spreads a fleet: 1,000 robots' first retries after an outage spread over
    /// the whole window rather than bunching at its end.
    #[test]
    fn full_jitter_spreads_a_fleet() {
        let delays: Vec<u128> = (0..1000)
            .map(|_| {
                let mut b = Backoff::new(Duration::from_millis(1000), Duration::from_secs(60));
                b.next_delay().as_millis()
            })
            .collect();
        let mut buckets = [0u32; 10];
        for d in &delays {
            buckets[(*d as usize / 100).min(9)] += 1;
        }
        // Uniform over [0, 1000]: every 100 ms bucket holds roughly 100 robots.
        assert!(
            buckets.iter().all(|&n| (50..=160).contains(&n)),
            "{buckets:?}"
        );
    }
}
