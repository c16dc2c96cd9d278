//! The status writer's rate, adapted to what the API server answers (AIMD): it rises while
//! writes are answered fast and more wait, halves on a 429, a 5xx or a timeout and drops by a
//! quarter on a slow answer, within `[min, max]`. So a survivor writes its moved robots as fast as the API server
//! allows, and backs off before it overloads it.

use std::time::{Duration, Instant};

/// Bounds of the adaptive status rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RateBounds {
    /// Never below this many writes per second.
    pub min: f64,
    /// Never above this many writes per second.
    pub max: f64,
    /// An answer slower than this counts as the API server being overloaded.
    pub slow: Duration,
}

/// How the API server answered one status write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Answer {
    /// Answered (whatever the outcome) within [`RateBounds::slow`].
    Fast,
    /// Answered, but slower than [`RateBounds::slow`].
    Slow,
    /// 429, a 5xx, or no answer (timeout, connection error).
    Throttled,
}

/// Each fast answer while writes wait raises the rate by this fraction of a write per second
/// (at 50 writes/s: +5/s each second, i.e. +10 % per second).
const INCREASE_PER_ANSWER: f64 = 0.1;
/// A 429, a 5xx or no answer halves the rate.
const THROTTLED_FACTOR: f64 = 0.5;
/// A slow answer cuts it by a quarter: latency also grows with the gateway's own load.
const SLOW_FACTOR: f64 = 0.75;
/// Answers to writes sent before a cut say nothing new: at most one cut per this long.
const CUT_GAP: Duration = Duration::from_secs(1);

/// The current rate and when it was last cut.
#[derive(Debug)]
pub(super) struct AdaptiveRate {
    rate: f64,
    bounds: RateBounds,
    last_cut: Option<Instant>,
}

impl AdaptiveRate {
    /// Starts at `start`, brought within `bounds`.
    pub(super) fn new(start: f64, bounds: RateBounds) -> Self {
        // A maximum below the minimum wins: it is how a fixed rate is asked for.
        let max = bounds.max.max(0.001);
        let bounds = RateBounds {
            min: bounds.min.clamp(0.001, max),
            max,
            ..bounds
        };
        Self {
            rate: start.clamp(bounds.min, bounds.max),
            bounds,
            last_cut: None,
        }
    }

    /// Writes per second allowed now.
    pub(super) fn rate(&self) -> f64 {
        self.rate
    }

    /// Classifies an answer that took `took`; `throttled` for a 429, 5xx or no answer.
    pub(super) fn classify(&self, took: Duration, throttled: bool) -> Answer {
        if throttled {
            Answer::Throttled
        } else if took > self.bounds.slow {
            Answer::Slow
        } else {
            Answer::Fast
        }
    }

    /// Takes `answer` into account (`backlog`: robots still wait for a write) and returns the
    /// new rate.
    pub(super) fn observe(&mut self, answer: Answer, backlog: bool, now: Instant) -> f64 {
        match answer {
            Answer::Fast if backlog => {
                self.rate = (self.rate + INCREASE_PER_ANSWER).min(self.bounds.max);
            }
            Answer::Fast => {}
            Answer::Slow | Answer::Throttled => {
                if self
                    .last_cut
                    .is_none_or(|t| now.duration_since(t) >= CUT_GAP)
                {
                    let factor = match answer {
                        Answer::Slow => SLOW_FACTOR,
                        _ => THROTTLED_FACTOR,
                    };
                    self.rate = (self.rate * factor).max(self.bounds.min);
                    self.last_cut = Some(now);
                }
            }
        }
        self.rate
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bounds() -> RateBounds {
        RateBounds {
            min: 5.0,
            max: 100.0,
            slow: Duration::from_millis(500),
        }
    }

    #[test]
    fn rises_while_fast_and_busy_halves_on_trouble_within_bounds() {
        let mut r = AdaptiveRate::new(50.0, bounds());
        let t0 = Instant::now();
        assert_eq!(r.observe(Answer::Fast, false, t0), 50.0, "idle: no rise");
        for _ in 0..100 {
            r.observe(Answer::Fast, true, t0);
        }
        assert!((r.rate() - 60.0).abs() < 1e-9, "{}", r.rate());
        for _ in 0..1000 {
            r.observe(Answer::Fast, true, t0);
        }
        assert_eq!(r.rate(), 100.0, "capped at max");
        assert_eq!(r.observe(Answer::Throttled, true, t0), 50.0);
        assert_eq!(
            r.observe(Answer::Slow, true, t0),
            50.0,
            "one cut per second"
        );
        let later = t0 + CUT_GAP;
        assert_eq!(r.observe(Answer::Slow, true, later), 37.5);
        for i in 2..10 {
            r.observe(Answer::Throttled, true, t0 + CUT_GAP * i);
        }
        assert_eq!(r.rate(), 5.0, "floored at min");
        assert_eq!(AdaptiveRate::new(500.0, bounds()).rate(), 100.0);
        let fixed = RateBounds {
            max: 3.0,
            ..bounds()
        };
        let mut r = AdaptiveRate::new(3.0, fixed);
        r.observe(Answer::Throttled, true, t0);
        assert_eq!(r.rate(), 3.0, "a maximum below the minimum fixes the rate");
    }

    #[test]
    fn classifies_by_latency_and_status() {
        let r = AdaptiveRate::new(50.0, bounds());
        assert_eq!(r.classify(Duration::from_millis(20), false), Answer::Fast);
        assert_eq!(r.classify(Duration::from_millis(800), false), Answer::Slow);
        assert_eq!(
            r.classify(Duration::from_millis(5), true),
            Answer::Throttled
        );
    }
}
