//! A cap on the download rate of release blobs, shared by the parallel downloads of a client
//! (`releaseDownloadRateLimit`): each chunk books its share of time, and a chunk that arrives
//! ahead of its time waits. The reads pause, so TCP flow control slows the gateway down too.

use std::sync::Mutex;
use std::time::Duration;

use tokio::time::Instant;

/// Bytes per second over all downloads of one client, and when the next byte may arrive.
#[derive(Debug)]
pub(in crate::release) struct Pace {
    bytes_per_second: u64,
    next: Mutex<Option<Instant>>,
}

impl Pace {
    /// A cap of `bytes_per_second`; none for 0.
    pub(in crate::release) fn new(bytes_per_second: u64) -> Option<Self> {
        (bytes_per_second > 0).then(|| Self {
            bytes_per_second,
            next: Mutex::new(None),
        })
    }

    /// Books `bytes` that just arrived and waits until the cap allows them.
    pub(in crate::release) async fn spend(&self, bytes: usize) {
        let cost = Duration::from_secs_f64(bytes as f64 / self.bytes_per_second as f64);
        let now = Instant::now();
        let until = {
            let Ok(mut next) = self.next.lock() else {
                return;
            };
            // Time left unused (an idle gap) is not saved up: no burst after a pause.
            let start = next.filter(|n| *n > now).unwrap_or(now);
            *next = Some(start + cost);
            start + cost
        };
        tokio::time::sleep_until(until).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn chunks_of_all_downloads_share_the_cap() {
        let pace = Pace::new(1000).unwrap();
        let started = Instant::now();
        tokio::join!(pace.spend(500), pace.spend(500), pace.spend(1000));
        let took = started.elapsed();
        assert!(took >= Duration::from_millis(1900), "{took:?}");
        assert!(Pace::new(0).is_none());
    }
}
