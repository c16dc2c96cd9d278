//! Batched event inserts: events the sessions hand in while the database is busy are written
//! together, one transaction of two multi-row `INSERT ... ON CONFLICT (namespace, robot, seq)
//! DO NOTHING RETURNING` per flush (the seqs' claims, then the events that got theirs; SQLite
//! and PostgreSQL alike), instead of statements and a pooled connection for each. A session
//! still waits for its own event: it learns "stored" or "already stored" only once the
//! transaction has committed, so an ack still means durable, and `(robot, seq)` is still stored
//! once. A batch the database refuses is retried row by row, so one bad row fails only its own
//! insert.

use std::collections::HashSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use sqlx::QueryBuilder;
use sqlx::types::Json;
use tokio::sync::{Mutex, mpsc, oneshot};

use super::drain::next_batch;
use super::{Error, Result, RobotKey, Store, StoredEvent, storable_ms};

const CLAIM_SEQS: &str = "INSERT INTO seqs (namespace, robot, seq, received_ms) ";
const INSERT_EVENTS: &str = "INSERT INTO events \
     (namespace, robot, seq, ts_ms, kind, severity, message, data, received_ms, bytes) ";
/// Rows already there are skipped; those written now are returned.
const RETURN_STORED: &str =
    " ON CONFLICT (namespace, robot, seq) DO NOTHING RETURNING namespace, robot, seq";

/// A stored row's `(namespace, robot, seq)`.
type RowKey = (String, String, i64);

/// Rows per statement: ten parameters each keeps it under SQLite's 32,766 parameters.
const EVENTS_PER_STATEMENT: usize = 500;
/// Events waiting for a flush before a session's insert waits for room.
const QUEUE: usize = 4096;
/// Flushes at once on PostgreSQL (each holds one pooled connection while it runs); SQLite
/// serialises writers anyway, so it gets one.
const POSTGRES_FLUSHERS: usize = 4;

/// One event waiting for its flush, and who waits for the outcome.
pub(super) struct Pending {
    pub(super) robot: RobotKey,
    pub(super) seq: i64,
    pub(super) event: StoredEvent,
    pub(super) bytes: u64,
    pub(super) received_ms: i64,
    reply: oneshot::Sender<Result<bool>>,
}

/// Hands events to the flushers (counting their multi-row statements), and session opens and
/// connection closes to theirs.
#[derive(Clone)]
pub(super) struct Batcher {
    tx: mpsc::Sender<Pending>,
    /// Connection records to close (see [`super::closes`]).
    pub(super) closes: mpsc::Sender<super::closes::Close>,
    pub(super) close_statements: Arc<AtomicU64>,
    /// Sessions to open (see [`super::opens`]).
    pub(super) opens: mpsc::Sender<super::opens::Open>,
    pub(super) open_statements: Arc<AtomicU64>,
    statements: Arc<AtomicU64>,
}

impl Store {
    /// This store with its event inserts batched by flusher tasks (none outside a Tokio
    /// runtime: inserts then go one by one).
    pub(super) fn batched(mut self) -> Store {
        if tokio::runtime::Handle::try_current().is_err() {
            return self;
        }
        let (tx, rx) = mpsc::channel(QUEUE);
        let rx = Arc::new(Mutex::new(rx));
        let flushers = match self.backend() {
            "postgres" => POSTGRES_FLUSHERS,
            _ => 1,
        };
        // The flushers' store has no batcher: the channel closes when the last user clone goes.
        let unbatched = Store {
            batcher: None,
            ..self.clone()
        };
        let statements = Arc::new(AtomicU64::new(0));
        for _ in 0..flushers {
            tokio::spawn(flush_loop(
                unbatched.clone(),
                rx.clone(),
                statements.clone(),
            ));
        }
        let (closes, closes_rx) = mpsc::channel(super::closes::QUEUE);
        let close_statements = Arc::new(AtomicU64::new(0));
        tokio::spawn(super::closes::close_loop(
            unbatched.clone(),
            closes_rx,
            close_statements.clone(),
        ));
        let (opens, opens_rx) = mpsc::channel(super::opens::QUEUE);
        let open_statements = Arc::new(AtomicU64::new(0));
        tokio::spawn(super::opens::open_loop(
            unbatched,
            opens_rx,
            open_statements.clone(),
        ));
        self.batcher = Some(Batcher {
            tx,
            closes,
            close_statements,
            opens,
            open_statements,
            statements,
        });
        self
    }

    /// Multi-row event inserts this store's flushers have made (`None`: inserts are not
    /// batched); with many sessions storing at once, far fewer than the events.
    pub fn event_statements(&self) -> Option<u64> {
        let batcher = self.batcher.as_ref()?;
        Some(batcher.statements.load(Ordering::Relaxed))
    }

    /// Stores one event through the batcher if there is one; `Ok(true)` if newly stored.
    pub(super) async fn store_event(
        &self,
        robot: &RobotKey,
        seq: i64,
        event: &StoredEvent,
        bytes: u64,
        received_ms: i64,
    ) -> Result<bool> {
        let Some(Batcher { tx, .. }) = &self.batcher else {
            return self
                .insert_event_row(robot, seq, event, bytes, received_ms)
                .await;
        };
        let (reply, answer) = oneshot::channel();
        let pending = Pending {
            robot: robot.clone(),
            seq,
            event: event.clone(),
            bytes,
            received_ms,
            reply,
        };
        if tx.send(pending).await.is_err() {
            return Err(Error::Closed);
        }
        answer.await.unwrap_or(Err(Error::Closed))
    }

    /// Inserts `batch` in one statement and tells each waiter whether its row is new (the
    /// second of two equal `(robot, seq)` in one batch is a replay); row by row if it fails.
    async fn flush(&self, batch: Vec<Pending>) {
        let mut seen = HashSet::new();
        let (mut first, repeats): (Vec<Pending>, Vec<Pending>) = batch
            .into_iter()
            .partition(|p| seen.insert((p.robot.clone(), p.seq)));
        // Every flusher claims seqs in the same order: two claiming some of the same (each
        // waits for the other's transaction) wait in a line, never in a circle (a deadlock).
        first.sort_unstable_by(|a, b| (&a.robot, a.seq).cmp(&(&b.robot, b.seq)));
        // The first copies this flush could not store (none when the batch went in whole).
        let mut failed = HashSet::new();
        // Events that waited for a flusher while the database went out of reach are refused
        // at once, not after another connect deadline.
        match self.unless_down(self.insert_event_rows(&first)).await {
            Ok(inserted) => {
                for p in first {
                    let new = inserted.contains(&row_key(&p));
                    let _ = p.reply.send(Ok(new));
                }
            }
            Err(e) => {
                // One by one finds the bad row of a refused batch; with the database out of
                // reach it would wait out the connect deadline once per row: those are refused.
                if !e.is_unavailable() {
                    tracing::warn!(error = %e, events = first.len(), "batched event insert failed; inserting one by one");
                }
                for p in first {
                    let single = self
                        .unless_down(self.insert_event_row(
                            &p.robot,
                            p.seq,
                            &p.event,
                            p.bytes,
                            p.received_ms,
                        ))
                        .await;
                    if single.is_err() {
                        failed.insert(row_key(&p));
                    }
                    let _ = p.reply.send(single);
                }
            }
        }
        // A copy is a replay only if its first copy is stored: when that insert failed, the
        // copy fails with it, as acknowledging it would lose the message.
        for p in repeats {
            let answer = if failed.contains(&row_key(&p)) {
                Err(Error::NotStored {
                    robot: p.robot.to_string(),
                    seq: p.seq,
                })
            } else {
                Ok(false)
            };
            let _ = p.reply.send(answer);
        }
    }

    /// Multi-row inserts of `rows`, a statement's worth at a time: their seqs' claims, then the
    /// events whose seq no message of any kind held yet, in one transaction. The
    /// `(namespace, robot, seq)` it stored (not those already there).
    async fn insert_event_rows(&self, rows: &[Pending]) -> Result<HashSet<RowKey>> {
        let mut stored = HashSet::new();
        for chunk in rows.chunks(EVENTS_PER_STATEMENT) {
            // Built per backend: a query builder is typed by its database.
            let new: Vec<RowKey> = with_pool!(self, pool, begin => async {
                let mut tx = pool.begin_with(begin).await?;
                let mut claim = QueryBuilder::new(CLAIM_SEQS);
                claim.push_values(chunk, |mut row, p| {
                    row.push_bind(&p.robot.namespace)
                        .push_bind(&p.robot.name)
                        .push_bind(p.seq)
                        .push_bind(p.received_ms);
                });
                claim.push(RETURN_STORED);
                let claimed: HashSet<RowKey> =
                    claim.build_query_as().fetch_all(&mut *tx).await?.into_iter().collect();
                let fresh: Vec<&Pending> = chunk
                    .iter()
                    .filter(|p| claimed.contains(&row_key(p)))
                    .collect();
                if fresh.is_empty() {
                    return Ok(Vec::new());
                }
                let mut insert = QueryBuilder::new(INSERT_EVENTS);
                insert.push_values(fresh, |mut row, p| {
                    row.push_bind(&p.robot.namespace)
                        .push_bind(&p.robot.name)
                        .push_bind(p.seq)
                        .push_bind(storable_ms(p.event.ts_ms))
                        .push_bind(&p.event.kind)
                        .push_bind(&p.event.severity)
                        .push_bind(&p.event.message)
                        .push_bind(Json(&p.event.data))
                        .push_bind(p.received_ms)
                        .push_bind(i64::try_from(p.bytes).unwrap_or(i64::MAX));
                });
                insert.push(RETURN_STORED);
                let new = insert.build_query_as().fetch_all(&mut *tx).await?;
                tx.commit().await?;
                Ok::<_, sqlx::Error>(new)
            }
            .await)
            .map_err(|source| Error::Insert {
                what: "events",
                robot: format!("{} robots", rows.len()),
                source,
            })?;
            stored.extend(new);
        }
        Ok(stored)
    }
}

fn row_key(p: &Pending) -> RowKey {
    (p.robot.namespace.clone(), p.robot.name.clone(), p.seq)
}

/// Takes whatever events wait (at least one, at most a statement's worth) and flushes them,
/// until every sender is gone.
async fn flush_loop(
    store: Store,
    rx: Arc<Mutex<mpsc::Receiver<Pending>>>,
    statements: Arc<AtomicU64>,
) {
    loop {
        let Some(batch) = next_batch(&mut *rx.lock().await, EVENTS_PER_STATEMENT).await else {
            return;
        };
        let rows = batch.len() as u64;
        store.flush(batch).await;
        statements.fetch_add(
            rows.div_ceil(EVENTS_PER_STATEMENT as u64),
            Ordering::Relaxed,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An event of `robot` under `seq` for [`Store::flush`], and where its answer arrives.
    fn pending(robot: &RobotKey, seq: i64) -> (Pending, oneshot::Receiver<Result<bool>>) {
        let (reply, answer) = oneshot::channel();
        let event = StoredEvent {
            seq: seq as u64,
            ts_ms: 1_000,
            kind: "note".into(),
            severity: "info".into(),
            message: "hello".into(),
            data: serde_json::Value::Null,
        };
        let pending = Pending {
            robot: robot.clone(),
            seq,
            event,
            bytes: 10,
            received_ms: 1_000,
            reply,
        };
        (pending, answer)
    }

    /// A robot resends a message whose ack is late, so both copies can wait in one batch.
    /// The copy is a replay once the first is stored...
    #[tokio::test]
    async fn a_second_copy_in_a_batch_is_a_replay_of_the_stored_first() {
        let store = Store::connect("sqlite::memory:").await.unwrap();
        let robot = RobotKey::new("lab", "kiwi-1");
        let (first, first_answer) = pending(&robot, 7);
        let (copy, copy_answer) = pending(&robot, 7);
        store.flush(vec![first, copy]).await;
        assert!(first_answer.await.unwrap().unwrap());
        assert!(!copy_answer.await.unwrap().unwrap());
        assert_eq!(store.last_seq(&robot).await.unwrap(), Some(7));
    }

    /// ...but when the first copy could not be stored (the database restarting), the copy is
    /// refused too: an ack for it would make the robot drop a message the store lacks.
    #[tokio::test]
    async fn a_second_copy_of_a_message_that_failed_is_not_acknowledged() {
        let store = Store::connect("sqlite::memory:").await.unwrap();
        store.close().await;
        let robot = RobotKey::new("lab", "kiwi-1");
        let (first, first_answer) = pending(&robot, 7);
        let (copy, copy_answer) = pending(&robot, 7);
        store.flush(vec![first, copy]).await;
        assert!(first_answer.await.unwrap().is_err());
        let copy = copy_answer.await.unwrap();
        assert!(
            matches!(copy, Err(Error::NotStored { seq: 7, .. })),
            "{copy:?}"
        );
        assert!(
            copy.unwrap_err()
                .to_string()
                .contains("message 7 of robot lab/kiwi-1 was not stored")
        );
    }
}
