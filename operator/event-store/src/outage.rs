//! The database out of reach: once a write fails because no connection to it could be had,
//! every write is refused at once with [`Error::Unavailable`] (an agent keeps its message and
//! resends it) while one background probe looks for the database every second. Without this
//! each durable message waited out the pool's connect deadline, one after another, and held up
//! its session (its heartbeats, its commands) for minutes.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use tracing::{info, warn};

use super::{Error, Result, Store};

/// How often the probe asks the database whether it is back.
const PROBE_EVERY: Duration = Duration::from_secs(1);
/// How long one probe waits for its answer.
const PROBE_TIMEOUT: Duration = Duration::from_secs(5);

/// Since when the database has been out of reach; `None` while it answers.
#[derive(Debug, Default)]
pub(super) struct Outage {
    since: Mutex<Option<Instant>>,
}

impl Outage {
    fn since(&self) -> Option<Instant> {
        *self.since.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Starts an outage; `true` if none was running (so the caller starts the probe).
    fn begin(&self) -> bool {
        let mut since = self.since.lock().unwrap_or_else(|e| e.into_inner());
        let was_up = since.is_none();
        since.get_or_insert_with(Instant::now);
        was_up
    }

    /// Ends the outage; how long it lasted.
    fn end(&self) -> Option<Duration> {
        let mut since = self.since.lock().unwrap_or_else(|e| e.into_inner());
        since.take().map(|t| t.elapsed())
    }
}

impl Store {
    /// `Err(Unavailable)` at once while the database is out of reach, else `Ok`.
    pub(super) fn refuse_while_down(&self) -> Result<()> {
        match self.outage.since() {
            Some(since) => Err(Error::Unavailable {
                backend: self.backend(),
                for_s: since.elapsed().as_secs(),
            }),
            None => Ok(()),
        }
    }

    /// What a failed write says of the database: one that could not reach it starts an outage
    /// and its probe (on the current Tokio runtime; without one there is nothing to probe with,
    /// and every write keeps trying the database itself).
    pub(super) fn note_failure(&self, error: &Error) {
        if !error.unreachable() {
            return;
        }
        let Ok(runtime) = tokio::runtime::Handle::try_current() else {
            return;
        };
        if self.outage.begin() {
            warn!(backend = self.backend(), %error, "event store out of reach: durable messages are refused until it answers");
            // Not the batcher: its channel closes when the last user's clone goes.
            let probe = Store {
                batcher: None,
                ..self.clone()
            };
            runtime.spawn(probe.find_database());
        }
    }

    /// [`Store::note_failure`] of a result, passed on.
    pub(super) fn noted<T>(&self, result: Result<T>) -> Result<T> {
        if let Err(e) = &result {
            self.note_failure(e);
        }
        result
    }

    /// `op`, unless the database is out of reach (then `Err(Unavailable)` without running it);
    /// its failure noted.
    pub(super) async fn unless_down<T>(
        &self,
        op: impl std::future::Future<Output = Result<T>>,
    ) -> Result<T> {
        self.refuse_while_down()?;
        self.noted(op.await)
    }

    /// The probe: asks the database every [`PROBE_EVERY`] until it answers (ending the
    /// outage) or the store is closed.
    async fn find_database(self) {
        loop {
            tokio::time::sleep(PROBE_EVERY).await;
            if self.is_closed() {
                return;
            }
            let answered = tokio::time::timeout(PROBE_TIMEOUT, self.ping()).await;
            if let Ok(Ok(())) = answered {
                let lasted = self.outage.end().unwrap_or_default();
                info!(
                    backend = self.backend(),
                    after_s = lasted.as_secs_f64(),
                    "event store answers again"
                );
                return;
            }
        }
    }

    /// One round trip to the database.
    async fn ping(&self) -> Result<()> {
        with_pool!(self, pool => sqlx::query("SELECT 1").execute(pool).await.map(|_| ())).map_err(
            |source| Error::Query {
                what: "a probe",
                source,
            },
        )
    }

    fn is_closed(&self) -> bool {
        with_pool!(self, pool => pool.is_closed())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_outage_begins_once_and_ends_once() {
        let outage = Outage::default();
        assert!(outage.since().is_none());
        assert!(outage.begin());
        let first = outage.since();
        assert!(!outage.begin(), "a second failure is the same outage");
        assert_eq!(outage.since(), first, "which keeps its start");
        assert!(outage.end().is_some());
        assert!(outage.end().is_none());
        assert!(outage.since().is_none());
    }
}
