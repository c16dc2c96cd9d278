//! Batched session opens: each new session records its connection and reads the robot's last
//! stored seq (for its `welcome`). When a fleet arrives at once (a gateway restart, the robots of
//! a dead replica moving over), those are one multi-row `INSERT ... RETURNING` and one multi-row
//! `SELECT` per flush, not two statements, a pooled connection and (on PostgreSQL) a commit per
//! session. Each session still gets its own record id and its own robot's seq.

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use sqlx::QueryBuilder;
use sqlx_macros::FromRow;
use tokio::sync::{mpsc, oneshot};

use super::{ConnectionRecord, Error, Result, RobotKey, Store, from_db_seq};

/// Sessions per flush: eight parameters a row keeps the insert under SQLite's 32,766.
const OPENS_PER_STATEMENT: usize = 500;
/// Opens waiting for a flush before a new session waits for room.
pub(super) const QUEUE: usize = 4096;

/// What a new session learns from the store: its connection record's id (for
/// [`Store::record_disconnect`]) and its robot's last stored seq; each may fail on its own.
#[derive(Debug)]
pub struct SessionStart {
    /// The connection record's id.
    pub record_id: Result<i64>,
    /// Highest seq stored for the robot (see [`Store::last_seq`]).
    pub last_seq: Result<Option<u64>>,
}

/// One session to open, and who waits for the outcome.
pub(super) struct Open {
    robot: RobotKey,
    record: ConnectionRecord,
    reply: oneshot::Sender<SessionStart>,
}

/// The columns a connection record is told apart by within one flush: two equal ones are the
/// same record for all anyone can see, so either may take either id.
type RecordKey = (
    String,
    String,
    String,
    String,
    Option<String>,
    i64,
    Option<i64>,
    Option<String>,
);

#[derive(FromRow)]
struct Inserted {
    id: i64,
    namespace: String,
    robot: String,
    gateway: String,
    protocol: String,
    address: Option<String>,
    connected_at_ms: i64,
    disconnected_at_ms: Option<i64>,
    reason: Option<String>,
}

impl Inserted {
    fn key(self) -> (RecordKey, i64) {
        let key = (
            self.namespace,
            self.robot,
            self.gateway,
            self.protocol,
            self.address,
            self.connected_at_ms,
            self.disconnected_at_ms,
            self.reason,
        );
        (key, self.id)
    }
}

fn record_key(robot: &RobotKey, rec: &ConnectionRecord) -> RecordKey {
    (
        robot.namespace.clone(),
        robot.name.clone(),
        rec.gateway.clone(),
        rec.protocol.clone(),
        rec.address.clone(),
        rec.connected_at_ms,
        rec.disconnected_at_ms,
        rec.reason.clone(),
    )
}

#[derive(FromRow)]
struct LastSeqRow {
    namespace: String,
    robot: String,
    events: Option<i64>,
    batches: Option<i64>,
}

impl Store {
    /// Records a new session's connection and reads its robot's last stored seq, batched with
    /// other sessions opening at the same time (one by one without a batcher).
    pub async fn open_session(&self, robot: &RobotKey, record: &ConnectionRecord) -> SessionStart {
        // Both answers refused, or neither: a last seq of `Ok(None)` beside a refused record
        // would tell the agent that nothing is stored.
        if let (Err(record), Err(seq)) = (self.refuse_while_down(), self.refuse_while_down()) {
            return SessionStart {
                record_id: Err(record),
                last_seq: Err(seq),
            };
        }
        let Some(batcher) = &self.batcher else {
            return self.open_session_alone(robot, record).await;
        };
        let (reply, answer) = oneshot::channel();
        let open = Open {
            robot: robot.clone(),
            record: record.clone(),
            reply,
        };
        if batcher.opens.send(open).await.is_err() {
            return closed();
        }
        answer.await.unwrap_or_else(|_| closed())
    }

    /// Multi-row statements this store's open flusher has made, inserts and reads together
    /// (`None`: opens are not batched); with many sessions opening at once, far fewer than two
    /// per session.
    pub fn open_statements(&self) -> Option<u64> {
        let batcher = self.batcher.as_ref()?;
        Some(batcher.open_statements.load(Ordering::Relaxed))
    }

    /// [`Store::open_session`] in statements of its own.
    async fn open_session_alone(
        &self,
        robot: &RobotKey,
        record: &ConnectionRecord,
    ) -> SessionStart {
        SessionStart {
            record_id: self.record_connect(robot, record).await,
            last_seq: self.last_seq(robot).await,
        }
    }

    /// Opens `batch` (at most a statement's worth): one insert and one read; one by one for
    /// whichever of the two fails, so a bad row fails only its own session.
    async fn flush_opens(&self, batch: Vec<Open>, statements: &AtomicU64) {
        statements.fetch_add(2, Ordering::Relaxed);
        // Refused at once while the database is out of reach, and one by one then too.
        let ids = self.unless_down(self.insert_connection_rows(&batch)).await;
        let seqs = self.unless_down(self.last_seq_rows(&batch)).await;
        if let Err(e) = &ids
            && !e.is_unavailable()
        {
            tracing::warn!(error = %e, sessions = batch.len(), "batched connection insert failed; inserting one by one");
        }
        if let Err(e) = &seqs
            && !e.is_unavailable()
        {
            tracing::warn!(error = %e, sessions = batch.len(), "batched last-seq read failed; reading one by one");
        }
        let (mut ids, seqs) = (ids.ok(), seqs.ok());
        for open in batch {
            let record_id = match ids.as_mut() {
                Some(ids) => ids
                    .get_mut(&record_key(&open.robot, &open.record))
                    .and_then(Vec::pop)
                    .ok_or_else(|| missing(&open.robot)),
                None => {
                    self.unless_down(self.record_connect(&open.robot, &open.record))
                        .await
                }
            };
            let last_seq = match &seqs {
                Some(seqs) => Ok(seqs.get(&open.robot).copied().flatten()),
                None => self.unless_down(self.last_seq(&open.robot)).await,
            };
            let _ = open.reply.send(SessionStart {
                record_id,
                last_seq,
            });
        }
    }

    /// One multi-row insert of the batch's connection records; their ids by record (equal
    /// records share a list).
    async fn insert_connection_rows(&self, rows: &[Open]) -> Result<HashMap<RecordKey, Vec<i64>>> {
        let inserted: Vec<Inserted> = with_pool!(self, pool => {
            let mut insert = QueryBuilder::new(
                "INSERT INTO connections (namespace, robot, gateway, protocol, address, \
                 connected_at_ms, disconnected_at_ms, reason) ",
            );
            insert.push_values(rows, |mut row, o| {
                row.push_bind(&o.robot.namespace)
                    .push_bind(&o.robot.name)
                    .push_bind(&o.record.gateway)
                    .push_bind(&o.record.protocol)
                    .push_bind(&o.record.address)
                    .push_bind(o.record.connected_at_ms)
                    .push_bind(o.record.disconnected_at_ms)
                    .push_bind(&o.record.reason);
            });
            // The order of RETURNING rows is not promised (SQLite says so): rows are matched
            // back to their sessions by what they hold.
            insert.push(
                " RETURNING id, namespace, robot, gateway, protocol, address, connected_at_ms, \
                 disconnected_at_ms, reason",
            );
            insert.build_query_as().fetch_all(pool).await
        })
        .map_err(|source| Error::Insert {
            what: "connections",
            robot: format!("{} robots", rows.len()),
            source,
        })?;
        let mut ids: HashMap<RecordKey, Vec<i64>> = HashMap::new();
        for row in inserted {
            let (key, id) = row.key();
            ids.entry(key).or_default().push(id);
        }
        Ok(ids)
    }

    /// The last stored seq of every robot of the batch, in one statement: for each robot the
    /// same two index lookups as [`Store::last_seq`].
    async fn last_seq_rows(&self, rows: &[Open]) -> Result<HashMap<RobotKey, Option<u64>>> {
        let mut robots: Vec<&RobotKey> = rows.iter().map(|o| &o.robot).collect();
        robots.sort_unstable();
        robots.dedup();
        let found: Vec<LastSeqRow> = with_pool!(self, pool => {
            let mut select = QueryBuilder::new(
                "SELECT r.column1 AS namespace, r.column2 AS robot, \
                 (SELECT MAX(seq) FROM events e \
                  WHERE e.namespace = r.column1 AND e.robot = r.column2) AS events, \
                 (SELECT MAX(seq) FROM telemetry_batches t \
                  WHERE t.namespace = r.column1 AND t.robot = r.column2) AS batches \
                 FROM (VALUES ",
            );
            for (i, robot) in robots.iter().enumerate() {
                if i > 0 {
                    select.push(", ");
                }
                select
                    .push("(CAST(")
                    .push_bind(&robot.namespace)
                    .push(" AS TEXT), CAST(")
                    .push_bind(&robot.name)
                    .push(" AS TEXT))");
            }
            select.push(") AS r");
            select.build_query_as().fetch_all(pool).await
        })
        .map_err(|source| Error::Query {
            what: "last seqs",
            source,
        })?;
        Ok(found
            .into_iter()
            .map(|row| {
                let seq = row.events.max(row.batches).map(from_db_seq);
                (RobotKey::new(row.namespace, row.robot), seq)
            })
            .collect())
    }
}

/// What a session learns when the store shut down before its open was flushed.
fn closed() -> SessionStart {
    SessionStart {
        record_id: Err(Error::Closed),
        last_seq: Err(Error::Closed),
    }
}

/// A record the insert did not return: the database stored fewer rows than it was given.
fn missing(robot: &RobotKey) -> Error {
    Error::Insert {
        what: "connection",
        robot: robot.to_string(),
        source: sqlx::Error::RowNotFound,
    }
}

/// Takes whatever opens wait (at least one, at most a statement's worth) and flushes them,
/// until every sender is gone.
pub(super) async fn open_loop(
    store: Store,
    mut rx: mpsc::Receiver<Open>,
    statements: Arc<AtomicU64>,
) {
    while let Some(batch) = super::drain::next_batch(&mut rx, OPENS_PER_STATEMENT).await {
        store.flush_opens(batch, &statements).await;
    }
}
