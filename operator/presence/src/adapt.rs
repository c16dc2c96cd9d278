//! The status writer's rate, adapted to what the API server answers (AIMD): it rises while
//! writes are answered fast and more wait, halves on a 429, a 5xx or a timeout, and drops by a
//! quarter after a second in which more than a quarter of the answers were slow, within
//! `[min, max]`. So a survivor writes its moved robots as fast as the API server allows, and
//! backs off before it overloads it. A rate the API server has not objected to for
//! [`CALM`] rises fast (half a write per second more per answer) and, once nothing waits, is
//! back at the starting rate at least: a cut during a busy minute does not leave the next
//! storm to start from the minimum.

use std::time::{Duration, Instant};

/// Bounds of the adaptive status rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RateBounds {
    /// Never below this many writes per second.
    pub min: f64,
    /// Never above this many writes per second.
    pub max: f64,
    /// An answer slower than this counts as slow; many slow answers mean an overloaded API
    /// server.
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
/// (at 50 writes/s: +5/s each second, i.e. +10 % per second) when the rate was cut less than
/// [`CALM`] ago: it probes gently near a limit the API server showed lately.
const INCREASE_PER_ANSWER: f64 = 0.1;
/// The same with no cut for [`CALM`]: +50 % per second, from 50 to 200 writes/s in about 3 s.
/// A survivor's storm of moved robots begins at once, and the writes in flight (at most
/// `--status-concurrency`) bound what the API server gets meanwhile.
const CALM_INCREASE_PER_ANSWER: f64 = 0.5;
/// How long after its last cut the rate counts as calm. The kill benchmark found a survivor
/// starting its recovery at the minimum: its rate had been cut while the fleet came up, and
/// without a backlog it never rose again (`bench/README.md`, session 34).
const CALM: Duration = Duration::from_secs(30);
/// A 429, a 5xx or no answer halves the rate.
const THROTTLED_FACTOR: f64 = 0.5;
/// A second with too many slow answers cuts it by a quarter: latency also grows with the
/// gateway's own load.
const SLOW_FACTOR: f64 = 0.75;
/// Slow answers are judged per window of this length, and answers to writes sent before a cut
/// say nothing new: at most one cut per this long.
const WINDOW: Duration = Duration::from_secs(1);
/// A window in which more than this share of the answers were slow cuts the rate. One slow
/// answer is not enough: on a busy API server a tenth of the answers take about a second
/// (garbage collection, an etcd sync) while the median stays at tens of milliseconds, and
/// cutting on each of them held a survivor at a sixth of what the API server sustains
/// (`bench/README.md`, session 27).
const SLOW_SHARE: f64 = 0.25;

/// Answers counted in the current window.
#[derive(Debug, Default)]
struct Window {
    started: Option<Instant>,
    answers: u32,
    slow: u32,
}

/// The current rate, when it was last cut, and the window being counted.
#[derive(Debug)]
pub(super) struct AdaptiveRate {
    rate: f64,
    start: f64,
    bounds: RateBounds,
    last_cut: Option<Instant>,
    window: Window,
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
        let start = start.clamp(bounds.min, bounds.max);
        Self {
            rate: start,
            start,
            bounds,
            last_cut: None,
            window: Window::default(),
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
        self.close_window(now);
        self.window.answers += 1;
        let calm = self.last_cut.is_none_or(|t| now.duration_since(t) >= CALM);
        match answer {
            Answer::Fast if backlog => {
                let step = if calm {
                    CALM_INCREASE_PER_ANSWER
                } else {
                    INCREASE_PER_ANSWER
                };
                self.rate = (self.rate + step).min(self.bounds.max);
            }
            Answer::Fast if calm => self.rate = self.rate.max(self.start),
            Answer::Fast => {}
            Answer::Slow => self.window.slow += 1,
            Answer::Throttled => self.cut(THROTTLED_FACTOR, now),
        }
        self.rate
    }

    /// Judges the window once it has lasted [`WINDOW`] (cutting the rate if too many of its
    /// answers were slow) and starts the next one.
    fn close_window(&mut self, now: Instant) {
        let started = *self.window.started.get_or_insert(now);
        if now.duration_since(started) < WINDOW {
            return;
        }
        let w = std::mem::take(&mut self.window);
        if w.answers > 0 && f64::from(w.slow) > SLOW_SHARE * f64::from(w.answers) {
            self.cut(SLOW_FACTOR, now);
        }
        self.window.started = Some(now);
    }

    /// Multiplies the rate by `factor`, unless it was cut less than [`WINDOW`] ago.
    fn cut(&mut self, factor: f64, now: Instant) {
        if self
            .last_cut
            .is_none_or(|t| now.duration_since(t) >= WINDOW)
        {
            self.rate = (self.rate * factor).max(self.bounds.min);
            self.last_cut = Some(now);
        }
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

    /// Feeds `answers` fast answers at `at` while writes wait.
    fn busy(r: &mut AdaptiveRate, answers: u32, at: Instant) {
        for _ in 0..answers {
            r.observe(Answer::Fast, true, at);
        }
    }

    /// The rate is `want`, but for the rounding of many small steps.
    #[track_caller]
    fn assert_rate(r: &AdaptiveRate, want: f64, why: &str) {
        assert!((r.rate() - want).abs() < 1e-9, "{why}: {}", r.rate());
    }

    #[test]
    fn rises_while_fast_and_busy_halves_on_trouble_within_bounds() {
        let mut r = AdaptiveRate::new(50.0, bounds());
        let t0 = Instant::now();
        assert_eq!(r.observe(Answer::Fast, false, t0), 50.0, "idle: no rise");
        busy(&mut r, 20, t0);
        assert_rate(&r, 60.0, "calm: +0.5 each");
        r.observe(Answer::Throttled, true, t0);
        assert_eq!(r.rate(), 30.0);
        busy(&mut r, 300, t0);
        assert_rate(&r, 60.0, "cut lately: +0.1 each");
        busy(&mut r, 1000, t0);
        assert_eq!(r.rate(), 100.0, "capped at max");
        let t1 = t0 + WINDOW;
        assert_eq!(r.observe(Answer::Throttled, true, t1), 50.0);
        assert_eq!(
            r.observe(Answer::Throttled, true, t1),
            50.0,
            "one cut per second"
        );
        assert_eq!(r.observe(Answer::Throttled, true, t1 + WINDOW), 25.0);
        for i in 2..10 {
            r.observe(Answer::Throttled, true, t1 + WINDOW * i);
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
    fn a_calm_rate_is_back_at_the_start_once_nothing_waits() {
        let mut r = AdaptiveRate::new(50.0, bounds());
        let t0 = Instant::now();
        for i in 0..3 {
            r.observe(Answer::Throttled, true, t0 + WINDOW * i);
        }
        assert_eq!(r.rate(), 6.25, "cut three times");
        let calm = t0 + WINDOW * 2 + CALM;
        r.observe(Answer::Fast, false, calm - WINDOW);
        assert_eq!(r.rate(), 6.25, "not calm yet: stays");
        r.observe(Answer::Fast, false, calm);
        assert_eq!(r.rate(), 50.0, "calm and idle: the starting rate again");
        busy(&mut r, 40, calm);
        assert_eq!(r.rate(), 70.0, "and a backlog rises fast from there");
        r.observe(Answer::Fast, false, calm);
        assert_eq!(r.rate(), 70.0, "idle keeps a rate above the start");
    }

    /// Feeds one window's answers at `at`: `slow` slow ones among `answers`.
    fn window(r: &mut AdaptiveRate, at: Instant, answers: u32, slow: u32) {
        for i in 0..answers {
            let answer = if i < slow { Answer::Slow } else { Answer::Fast };
            r.observe(answer, false, at);
        }
    }

    #[test]
    fn cuts_by_a_quarter_after_a_second_with_more_than_a_quarter_slow() {
        let mut r = AdaptiveRate::new(80.0, bounds());
        let t0 = Instant::now();
        window(&mut r, t0, 40, 1);
        assert_eq!(r.rate(), 80.0, "one slow answer alone: no cut");
        window(&mut r, t0 + WINDOW, 40, 10);
        assert_eq!(
            r.rate(),
            80.0,
            "a quarter slow is tolerated, judged a window later"
        );
        window(&mut r, t0 + WINDOW * 2, 40, 11);
        assert_eq!(r.rate(), 80.0, "the window of 11 slow is judged at its end");
        window(&mut r, t0 + WINDOW * 3, 1, 0);
        assert_eq!(r.rate(), 60.0, "over a quarter slow: cut by a quarter");
        let mut r = AdaptiveRate::new(80.0, bounds());
        window(&mut r, t0, 4, 4);
        r.observe(Answer::Throttled, false, t0 + WINDOW);
        assert_eq!(
            r.rate(),
            60.0,
            "a throttle just after a cut does not cut again"
        );
        r.observe(Answer::Throttled, false, t0 + WINDOW * 2);
        assert_eq!(r.rate(), 30.0);
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
