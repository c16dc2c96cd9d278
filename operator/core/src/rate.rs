//! The gateway's one token bucket: per-session frame limits refuse excess at once
//! ([`TokenBucket::try_take`]), the status writer waits for its turn ([`TokenBucket::take`]).

use std::time::Duration;

use tokio::time::Instant;

/// Up to `burst` at once, then `rate` per second.
#[derive(Debug)]
pub struct TokenBucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    last: Instant,
}

impl TokenBucket {
    /// A full bucket; `rate` is at least 0.001 per second and `burst` at least 1.
    pub fn new(rate: f64, burst: u32) -> Self {
        let burst = f64::from(burst.max(1));
        Self {
            rate: rate.max(0.001),
            burst,
            tokens: burst,
            last: Instant::now(),
        }
    }

    fn refill(&mut self) {
        let now = Instant::now();
        self.tokens =
            (self.tokens + now.duration_since(self.last).as_secs_f64() * self.rate).min(self.burst);
        self.last = now;
    }

    /// Changes the rate from now on (tokens gathered so far stay); at least 0.001 per second.
    pub fn set_rate(&mut self, rate: f64) {
        self.refill();
        self.rate = rate.max(0.001);
    }

    /// Takes a token if there is one; never waits.
    pub fn try_take(&mut self) -> bool {
        self.refill();
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }

    /// Whether the bucket is full again (nothing taken lately).
    pub fn is_full(&mut self) -> bool {
        self.refill();
        self.tokens >= self.burst
    }

    /// Seconds until the next token, rounded up (0 when one is there).
    pub fn wait_seconds(&mut self) -> u64 {
        self.refill();
        if self.tokens >= 1.0 {
            0
        } else {
            ((1.0 - self.tokens) / self.rate).ceil() as u64
        }
    }

    /// Takes a token, sleeping until one is there.
    pub async fn take(&mut self) {
        while !self.try_take() {
            tokio::time::sleep(Duration::from_secs_f64((1.0 - self.tokens) / self.rate)).await;
        }
    }
}

/// A [`TokenBucket`] many tasks take from without waiting (budgets of API reads).
#[derive(Debug)]
pub struct SharedBucket(std::sync::Mutex<TokenBucket>);

impl SharedBucket {
    /// A full bucket, as [`TokenBucket::new`].
    pub fn new(rate: f64, burst: u32) -> Self {
        Self(std::sync::Mutex::new(TokenBucket::new(rate, burst)))
    }

    /// Takes a token if there is one; never waits.
    pub fn try_take(&self) -> bool {
        self.0.lock().unwrap_or_else(|p| p.into_inner()).try_take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn take_waits_for_the_rate() {
        let mut b = TokenBucket::new(10.0, 5);
        let start = Instant::now();
        for _ in 0..25 {
            b.take().await;
        }
        // 5 at once, then 20 at 10 per second.
        assert_eq!(start.elapsed().as_secs(), 2);
    }

    #[tokio::test(start_paused = true)]
    async fn try_take_refuses_the_excess() {
        let mut b = TokenBucket::new(2.0, 3);
        assert_eq!((0..5).filter(|_| b.try_take()).count(), 3);
        tokio::time::advance(Duration::from_millis(500)).await;
        assert!(b.try_take());
        assert!(!b.try_take());
    }
}
