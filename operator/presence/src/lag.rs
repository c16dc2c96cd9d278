//! How late this gateway's status writes run. When the API server takes fewer writes than the
//! fleet's refreshes need, robots wait in the queues and their `lastHeartbeatTime` ages past the
//! refresh period although their sessions are live. The gateway says so on its Lease
//! ([`lekiwi_crds::contract::STATUS_LAG_ANNOTATION`]), and the Robot controller extends the
//! heartbeat grace of the robots it holds by as much, instead of showing them `Offline`.

use std::time::{Duration, Instant};

use super::Presence;

impl Presence {
    /// How long the robot next in line for a status write has waited (the longest over the
    /// three queues, held while it decays; see `State::oldest_wait`); also exported as
    /// `lekiwi_gateway_status_lag_seconds`.
    pub fn status_lag(&self) -> Duration {
        let lag = self.with_state(|s| s.oldest_wait(Instant::now()));
        self.metrics.gateway.status_lag.set(lag.as_secs_f64());
        lag
    }
}

/// The [`lekiwi_crds::contract::STATUS_LAG_ANNOTATION`] value of a lag: whole seconds, rounded
/// up; `None` under a second (writes keep up).
pub fn status_lag_annotation(lag: Duration) -> Option<String> {
    let seconds = lag.as_secs() + u64::from(lag.subsec_nanos() > 0);
    (lag >= Duration::from_secs(1)).then(|| seconds.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whole seconds rounded up, and nothing while writes keep up.
    #[test]
    fn the_annotation_is_whole_seconds_rounded_up() {
        let ms = Duration::from_millis;
        assert_eq!(status_lag_annotation(ms(0)), None);
        assert_eq!(status_lag_annotation(ms(999)), None);
        assert_eq!(status_lag_annotation(ms(1000)).as_deref(), Some("1"));
        assert_eq!(status_lag_annotation(ms(1200)).as_deref(), Some("2"));
        assert_eq!(status_lag_annotation(ms(269_000)).as_deref(), Some("269"));
    }
}
