//! Per-user request budgets of the Fleet API: a token bucket per authenticated username, so one
//! busy script is answered 429 with `Retry-After` while everybody else is served as usual.

use std::collections::HashMap;
use std::sync::Mutex;

use lekiwi_core::rate::TokenBucket;

/// Most users with a bucket at once; past this, users whose buckets are full again are
/// forgotten (they lose nothing), then, if still too many, all.
pub const MAX_USERS: usize = 10_000;

/// One token bucket per username, bounded in memory.
pub struct UserLimits {
    rate: f64,
    burst: u32,
    buckets: Mutex<HashMap<String, TokenBucket>>,
}

impl UserLimits {
    /// `rate` requests per second per user, sustained, `burst` at once.
    pub fn new(rate: f64, burst: u32) -> Self {
        Self {
            rate,
            burst,
            buckets: Mutex::default(),
        }
    }

    /// Takes one request from `user`'s budget: `Err(seconds)` until the next one is allowed.
    pub fn take(&self, user: &str) -> Result<(), u64> {
        let mut buckets = self.buckets.lock().unwrap_or_else(|p| p.into_inner());
        if !buckets.contains_key(user) && buckets.len() >= MAX_USERS {
            buckets.retain(|_, b| !b.is_full());
            if buckets.len() >= MAX_USERS {
                buckets.clear();
            }
        }
        let bucket = buckets
            .entry(user.to_owned())
            .or_insert_with(|| TokenBucket::new(self.rate, self.burst));
        if bucket.try_take() {
            Ok(())
        } else {
            Err(bucket.wait_seconds().max(1))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn one_user_over_budget_does_not_slow_another() {
        let limits = UserLimits::new(2.0, 3);
        assert_eq!((0..5).filter(|_| limits.take("alice").is_ok()).count(), 3);
        assert_eq!(limits.take("alice"), Err(1));
        assert!(limits.take("bob").is_ok());
        tokio::time::advance(std::time::Duration::from_millis(500)).await;
        assert!(limits.take("alice").is_ok());
    }

    #[tokio::test(start_paused = true)]
    async fn the_map_stays_bounded() {
        let limits = UserLimits::new(1.0, 1);
        for i in 0..(MAX_USERS + 5) {
            let _ = limits.take(&format!("user-{i}"));
        }
        assert!(limits.buckets.lock().unwrap().len() <= MAX_USERS);
    }
}
