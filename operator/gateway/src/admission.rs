//! Enrollment admission: a fleet's first boot asks for more enrollments (each a handful of API
//! writes) than the API server sustains. The gateway admits them at a steady rate and tells the
//! rest, before the upgrade, when to come back: each refusal takes the next free slot of a
//! virtual queue, so 10,000 robots refused at once are told 10,000 different times spread at the
//! admission rate instead of all coming back together.

use std::sync::Mutex;
use std::time::Duration;

use tokio::time::Instant;

use lekiwi_core::rate::TokenBucket;

/// The longest `Retry-After` the gateway gives (the agent's own cap).
const MAX_RETRY_AFTER_SECS: u64 = 3600;

/// Admits enrollments at a rate; cheap to share behind an `Arc`.
#[derive(Debug)]
pub struct EnrollAdmission(Option<Mutex<Queue>>);

#[derive(Debug)]
struct Queue {
    bucket: TokenBucket,
    /// One refused enrollment's turn apart.
    spacing: Duration,
    /// The last turn handed out.
    last_turn: Instant,
}

impl EnrollAdmission {
    /// `rate` enrollments per second after `burst` at once; a `rate` of 0 admits everything.
    pub fn new(rate: f64, burst: u32) -> Self {
        if rate <= 0.0 {
            return Self(None);
        }
        Self(Some(Mutex::new(Queue {
            bucket: TokenBucket::new(rate, burst),
            spacing: Duration::from_secs_f64(1.0 / rate),
            last_turn: Instant::now(),
        })))
    }

    /// Admits one enrollment now, or returns the seconds after which it should come back: its
    /// turn behind every enrollment refused before it.
    pub fn admit(&self) -> Result<(), u64> {
        let Some(queue) = &self.0 else {
            return Ok(());
        };
        let mut q = queue.lock().unwrap_or_else(|p| p.into_inner());
        if q.bucket.try_take() {
            return Ok(());
        }
        let now = Instant::now();
        q.last_turn = q.last_turn.max(now) + q.spacing;
        let wait = q.last_turn.duration_since(now).as_secs_f64().ceil() as u64;
        Err(wait.clamp(1, MAX_RETRY_AFTER_SECS))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn refusals_are_spread_over_the_admission_rate() {
        let admission = EnrollAdmission::new(20.0, 40);
        let admitted = (0..40).filter(|_| admission.admit().is_ok()).count();
        assert_eq!(admitted, 40);
        // 1,000 more at once: told 1..=50 s, about 20 per second each.
        let waits: Vec<u64> = (0..1000).map(|_| admission.admit().unwrap_err()).collect();
        assert_eq!(waits.first(), Some(&1));
        assert_eq!(waits.last(), Some(&50));
        for second in 1..=50 {
            let n = waits.iter().filter(|&&w| w == second).count();
            assert!(
                (19..=21).contains(&n),
                "{n} told to come back after {second} s"
            );
        }
        // The queue drains as time passes: a later refusal queues behind what is left.
        tokio::time::advance(Duration::from_secs(50)).await;
        assert!(admission.admit().is_ok());
    }

    #[test]
    fn rate_zero_admits_everything() {
        let admission = EnrollAdmission::new(0.0, 0);
        assert!((0..10_000).all(|_| admission.admit().is_ok()));
    }
}
