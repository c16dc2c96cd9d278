//! Batched connection closes: when many sessions end at once (a fleet leaving a gateway that
//! shuts down, a network cut), their connection records are closed by one multi-row `UPDATE`
//! per flush instead of one statement, and one pooled connection, each; a pool of a few
//! connections then never has thousands of sessions queued for it. Each session still learns
//! its own outcome, and a record already closed keeps its first time and reason.

use std::collections::HashSet;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use sqlx::QueryBuilder;
use tokio::sync::{mpsc, oneshot};

use super::{Error, Result, Store};

// The first disconnect wins: a late duplicate must not rewrite when or why it closed.
const CLOSE_CONNECTION: &str = "UPDATE connections SET disconnected_at_ms = $2, reason = $3 \
     WHERE id = $1 AND disconnected_at_ms IS NULL";

/// Rows per statement (three parameters each).
const CLOSES_PER_STATEMENT: usize = 500;
/// Closes waiting for a flush before a session's close waits for room.
pub(super) const QUEUE: usize = 4096;

/// One connection record to close, and who waits for the outcome.
pub(super) struct Close {
    id: i64,
    at_ms: i64,
    reason: String,
    reply: oneshot::Sender<Result<()>>,
}

impl Store {
    /// Marks connection `id` closed at `at_ms` (batched with other sessions' closes). A
    /// connection already closed keeps its first time and reason; an unknown id changes nothing.
    pub async fn record_disconnect(&self, id: i64, at_ms: i64, reason: &str) -> Result<()> {
        self.unless_down(self.close_connection(id, at_ms, reason))
            .await
    }

    /// [`Store::record_disconnect`] in a statement of its own.
    pub(super) async fn close_connection_row(
        &self,
        id: i64,
        at_ms: i64,
        reason: &str,
    ) -> Result<()> {
        with_pool!(self, pool => {
            sqlx::query(CLOSE_CONNECTION)
                .bind(id)
                .bind(at_ms)
                .bind(reason)
                .execute(pool)
                .await
                .map(|_| ())
        })
        .map_err(|source| Error::Update {
            what: "connection",
            source,
        })?;
        Ok(())
    }

    /// Closes connection record `id` through the batcher if there is one.
    pub(super) async fn close_connection(&self, id: i64, at_ms: i64, reason: &str) -> Result<()> {
        let Some(batcher) = &self.batcher else {
            return self.close_connection_row(id, at_ms, reason).await;
        };
        let (reply, answer) = oneshot::channel();
        let close = Close {
            id,
            at_ms,
            reason: reason.to_owned(),
            reply,
        };
        if batcher.closes.send(close).await.is_err() {
            return Err(Error::Closed);
        }
        answer.await.unwrap_or(Err(Error::Closed))
    }

    /// Multi-row connection closes this store's flusher has made (`None`: closes are not
    /// batched); with many sessions ending at once, far fewer than the closes.
    pub fn close_statements(&self) -> Option<u64> {
        let batcher = self.batcher.as_ref()?;
        Some(batcher.close_statements.load(Ordering::Relaxed))
    }

    /// Closes `batch` in one statement per chunk; row by row if a statement fails, so one bad
    /// row fails only its own close. The first close of a record in a batch wins, as it would
    /// one by one.
    async fn flush_closes(&self, batch: Vec<Close>, statements: &AtomicU64) {
        let mut seen = HashSet::new();
        let (first, repeats): (Vec<Close>, Vec<Close>) =
            batch.into_iter().partition(|c| seen.insert(c.id));
        for chunk in first.chunks(CLOSES_PER_STATEMENT) {
            statements.fetch_add(1, Ordering::Relaxed);
            // Skipped at once while the database is out of reach (the records stay open until
            // the gateway's next start closes them), one by one too.
            if let Err(e) = self.unless_down(self.close_rows(chunk)).await {
                if e.is_unavailable() {
                    continue;
                }
                tracing::warn!(error = %e, closes = chunk.len(), "batched connection close failed; closing one by one");
                for c in chunk {
                    let closed =
                        self.unless_down(self.close_connection_row(c.id, c.at_ms, &c.reason));
                    if let Err(e) = closed.await
                        && !e.is_unavailable()
                    {
                        tracing::warn!(error = %e, id = c.id, "cannot close a connection record");
                    }
                }
            }
        }
        for c in first.into_iter().chain(repeats) {
            let _ = c.reply.send(Ok(()));
        }
    }

    /// One `UPDATE ... FROM (VALUES ...)` closing `rows` that are still open. The values are
    /// cast so that PostgreSQL knows their types; SQLite names the columns as PostgreSQL does.
    async fn close_rows(&self, rows: &[Close]) -> Result<()> {
        with_pool!(self, pool => {
            let mut update = QueryBuilder::new(
                "UPDATE connections SET disconnected_at_ms = closes.column2, \
                 reason = closes.column3 FROM (VALUES ",
            );
            for (i, c) in rows.iter().enumerate() {
                if i > 0 {
                    update.push(", ");
                }
                update
                    .push("(CAST(")
                    .push_bind(c.id)
                    .push(" AS BIGINT), CAST(")
                    .push_bind(c.at_ms)
                    .push(" AS BIGINT), CAST(")
                    .push_bind(&c.reason)
                    .push(" AS TEXT))");
            }
            update.push(
                ") AS closes WHERE connections.id = closes.column1 \
                 AND connections.disconnected_at_ms IS NULL",
            );
            update.build().execute(pool).await.map(|_| ())
        })
        .map_err(|source| Error::Update {
            what: "connections",
            source,
        })
    }
}

/// Takes whatever closes wait (at least one, at most a statement's worth) and flushes them,
/// until every sender is gone.
pub(super) async fn close_loop(
    store: Store,
    mut rx: mpsc::Receiver<Close>,
    statements: Arc<AtomicU64>,
) {
    while let Some(batch) = super::drain::next_batch(&mut rx, CLOSES_PER_STATEMENT).await {
        store.flush_closes(batch, &statements).await;
    }
}
