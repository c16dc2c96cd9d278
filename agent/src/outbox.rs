//! The durable outbox: every event, telemetry batch and progress report is written to an on-disk
//! SQLite queue (WAL, `synchronous=FULL`) before it is sent, and removed only when the gateway
//! acknowledges it.
//!
//! - **Sequence numbers** are allocated in the same transaction as the insert and kept in a
//!   `meta` row, so they never repeat, also across crashes and when the queue is empty.
//! - **Lanes**: [`Lane::Critical`] (deployment progress and results, teleoperation changes) is
//!   sent before [`Lane::Event`], which is sent before [`Lane::Telemetry`]; within a lane, in
//!   sequence order. A backlog of telemetry never delays a critical message.
//! - **Bound**: when the queued bytes exceed the bound, the oldest telemetry goes first, then the
//!   oldest ordinary events; critical messages are never dropped (they are small and rare; the
//!   bound may be exceeded by them alone). Drops are counted and reported once reconnected.
//! - Other processes (e.g. `lekiwi-agent event`) may append at the same time: SQLite's locking
//!   and a busy timeout serialise them.

use std::path::{Path, PathBuf};
use std::time::Duration;

use lekiwi_protocol::{AgentMessage, MAX_SEQ, encode};
use rusqlite::{Connection, OptionalExtension, Transaction, TransactionBehavior, params};

/// Outbox errors.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// SQLite failed (disk full, corrupt file, permissions).
    #[error("outbox {path}: {source}")]
    Sqlite {
        /// The database file.
        path: PathBuf,
        /// What SQLite reported.
        source: rusqlite::Error,
    },
}

/// Outbox result.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Priority lanes, most urgent first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Lane {
    /// Deployment progress and results, teleoperation changes: never dropped, sent first.
    Critical = 0,
    /// Other events: dropped after telemetry when over the bound.
    Event = 1,
    /// Telemetry batches: dropped first, oldest first.
    Telemetry = 2,
}

impl Lane {
    /// All lanes in sending order.
    pub const ALL: [Lane; 3] = [Lane::Critical, Lane::Event, Lane::Telemetry];

    fn from_db(v: i64) -> Lane {
        match v {
            0 => Lane::Critical,
            1 => Lane::Event,
            _ => Lane::Telemetry,
        }
    }
}

/// One queued message.
#[derive(Clone, Debug, PartialEq)]
pub struct Entry {
    /// Its sequence number, also inside `frame`; the gateway acknowledges it.
    pub seq: u64,
    /// Its lane, which decides when it is sent and whether it may be dropped.
    pub lane: Lane,
    /// The encoded frame, ready to send.
    pub frame: String,
}

/// What was dropped to honour the bound, since it was last reported.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Dropped {
    /// Telemetry batches dropped.
    pub telemetry: u64,
    /// Ordinary events dropped.
    pub events: u64,
}

/// Queue depth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Depth {
    /// Messages not yet acknowledged.
    pub messages: u64,
    /// Their encoded size, which the bound limits.
    pub bytes: u64,
}

/// The outbox, one SQLite file in the state directory.
pub struct Outbox {
    conn: Connection,
    path: PathBuf,
    max_bytes: u64,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS outbox (
    seq INTEGER PRIMARY KEY,
    lane INTEGER NOT NULL,
    frame TEXT NOT NULL,
    bytes INTEGER NOT NULL,
    created_ms INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS outbox_lane_seq ON outbox (lane, seq);
INSERT OR IGNORE INTO meta (key, value) VALUES
    ('next_seq', 1), ('last_acked_seq', 0), ('dropped_telemetry', 0), ('dropped_events', 0);
";

impl Outbox {
    /// Opens (creating if needed) `outbox.db` in `dir`, bounded to `max_bytes` of messages.
    pub fn open(dir: &Path, max_bytes: u64) -> Result<Self> {
        let path = dir.join("outbox.db");
        let err = |source| Error::Sqlite {
            path: path.clone(),
            source,
        };
        let conn = Connection::open(&path).map_err(err)?;
        conn.busy_timeout(Duration::from_secs(10)).map_err(err)?;
        // auto_vacuum must precede the first table; it is a no-op on an existing file.
        conn.execute_batch(
            "PRAGMA auto_vacuum = INCREMENTAL;
             PRAGMA journal_mode = WAL;
             PRAGMA synchronous = FULL;
             PRAGMA cache_size = -256;",
        )
        .map_err(err)?;
        conn.execute_batch(SCHEMA).map_err(err)?;
        Ok(Self {
            conn,
            path,
            max_bytes,
        })
    }

    fn err(&self) -> impl Fn(rusqlite::Error) -> Error + '_ {
        |source| Error::Sqlite {
            path: self.path.clone(),
            source,
        }
    }

    /// Runs `work` in one immediate (write-locking) transaction and commits it; an error rolls
    /// everything back.
    fn write<T>(
        &mut self,
        work: impl FnOnce(&Transaction<'_>) -> rusqlite::Result<T>,
    ) -> Result<T> {
        let err = |source| Error::Sqlite {
            path: self.path.clone(),
            source,
        };
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(err)?;
        let out = work(&tx).map_err(err)?;
        tx.commit().map_err(err)?;
        Ok(out)
    }

    /// Appends a message built by `build` from its newly allocated sequence number, durably
    /// (fsync'd) before returning; then enforces the bound. Returns the sequence number.
    pub fn push(
        &mut self,
        lane: Lane,
        ts_ms: i64,
        build: impl FnOnce(u64) -> AgentMessage,
    ) -> Result<u64> {
        let max_bytes = self.max_bytes;
        self.write(|tx| {
            let seq = read_meta(tx, "next_seq")?;
            let frame = encode(&build(seq as u64));
            tx.execute(
                "INSERT INTO outbox (seq, lane, frame, bytes, created_ms) VALUES (?1, ?2, ?3, ?4, ?5)",
                params![seq, lane as i64, frame, frame.len() as i64, ts_ms],
            )?;
            set_next_seq(tx, seq + 1)?;
            enforce_bound(tx, max_bytes)?;
            Ok(seq as u64)
        })
    }

    /// Up to `limit` messages of `lane` with a sequence number above `after`, in order.
    pub fn next_in_lane(&self, lane: Lane, after: u64, limit: usize) -> Result<Vec<Entry>> {
        let mut stmt = self
            .conn
            .prepare_cached(
                "SELECT seq, frame FROM outbox WHERE lane = ?1 AND seq > ?2 ORDER BY seq LIMIT ?3",
            )
            .map_err(self.err())?;
        let rows = stmt
            .query_map(params![lane as i64, after as i64, limit as i64], |r| {
                Ok(Entry {
                    seq: r.get::<_, i64>(0)? as u64,
                    lane,
                    frame: r.get(1)?,
                })
            })
            .map_err(self.err())?;
        rows.collect::<Result<Vec<_>, _>>().map_err(self.err())
    }

    /// Everything queued, in sending order (lane, then sequence). For tests and diagnostics.
    pub fn all(&self) -> Result<Vec<Entry>> {
        let mut stmt = self
            .conn
            .prepare("SELECT seq, lane, frame FROM outbox ORDER BY lane, seq")
            .map_err(self.err())?;
        let rows = stmt
            .query_map([], |r| {
                Ok(Entry {
                    seq: r.get::<_, i64>(0)? as u64,
                    lane: Lane::from_db(r.get(1)?),
                    frame: r.get(2)?,
                })
            })
            .map_err(self.err())?;
        rows.collect::<Result<Vec<_>, _>>().map_err(self.err())
    }

    /// Removes acknowledged messages (one transaction) and records the highest acknowledged
    /// sequence number. Unknown numbers are ignored (acknowledged twice, or dropped).
    pub fn ack(&mut self, seqs: &[u64]) -> Result<()> {
        if seqs.is_empty() {
            return Ok(());
        }
        self.write(|tx| {
            let mut del = tx.prepare_cached("DELETE FROM outbox WHERE seq = ?1")?;
            for seq in seqs {
                del.execute(params![*seq as i64])?;
            }
            let max = seqs.iter().copied().max().unwrap_or_default() as i64;
            tx.execute(
                "UPDATE meta SET value = max(value, ?1) WHERE key = 'last_acked_seq'",
                params![max],
            )?;
            Ok(())
        })?;
        // Give freed pages back a little at a time, so the file shrinks after a backlog.
        let _ = self.conn.execute_batch("PRAGMA incremental_vacuum(64);");
        Ok(())
    }

    /// Removes a message the gateway refused for good (`malformed` naming its `seq`, or a frame
    /// larger than the gateway accepts): it is never sent again, and, unlike [`Outbox::ack`],
    /// not recorded as acknowledged. Returns whether it was queued.
    pub fn discard(&mut self, seq: u64) -> Result<bool> {
        let Ok(seq) = i64::try_from(seq) else {
            return Ok(false);
        };
        let n = self.write(|tx| tx.execute("DELETE FROM outbox WHERE seq = ?1", params![seq]))?;
        Ok(n > 0)
    }

    /// The highest sequence number the gateway acknowledged (0 when none).
    pub fn last_acked_seq(&self) -> Result<u64> {
        self.meta("last_acked_seq")
    }

    /// The sequence number the next message will get.
    pub fn next_seq(&self) -> Result<u64> {
        self.meta("next_seq")
    }

    /// Applies the gateway's `stored_seq` (PROTOCOL.md §6 rule 5): when it is at or above
    /// every number this outbox ever assigned, the state directory was lost or restored from an
    /// old copy, and queued messages would be taken for replays and never stored. They are
    /// renumbered consecutively from `stored + 1`, in order, and numbering continues after them.
    /// Returns how many messages were renumbered, or `None` when nothing had to change or
    /// could: a `stored` so high that the renumbered messages, or the next one after them,
    /// would pass [`MAX_SEQ`] is not a number the protocol allows, and changes nothing.
    pub fn renumber_after(&mut self, stored: u64) -> Result<Option<u64>> {
        self.write(|tx| {
            if stored > MAX_SEQ || (stored as i64) < read_meta(tx, "next_seq")? {
                return Ok(None);
            }
            let queued: i64 = tx.query_row("SELECT count(*) FROM outbox", [], |r| r.get(0))?;
            if stored + queued as u64 >= MAX_SEQ {
                return Ok(None);
            }
            let rows: Vec<(i64, String)> = tx
                .prepare("SELECT seq, frame FROM outbox ORDER BY seq")?
                .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                .collect::<Result<_, _>>()?;
            let mut seq = stored as i64 + 1;
            for (old, frame) in &rows {
                let frame = with_seq(frame, seq);
                tx.execute(
                    "UPDATE outbox SET seq = ?1, frame = ?2, bytes = ?3 WHERE seq = ?4",
                    params![seq, frame, frame.len() as i64, old],
                )?;
                seq += 1;
            }
            set_next_seq(tx, seq)?;
            Ok(Some(rows.len() as u64))
        })
    }

    /// Messages and bytes queued.
    pub fn depth(&self) -> Result<Depth> {
        self.conn
            .query_row(
                "SELECT count(*), coalesce(sum(bytes), 0) FROM outbox",
                [],
                |r| {
                    Ok(Depth {
                        messages: r.get::<_, i64>(0)? as u64,
                        bytes: r.get::<_, i64>(1)? as u64,
                    })
                },
            )
            .map_err(self.err())
    }

    /// Drops counted since the last call, and resets the counters.
    pub fn take_dropped(&mut self) -> Result<Dropped> {
        self.write(|tx| {
            let dropped = Dropped {
                telemetry: read_meta(tx, "dropped_telemetry")? as u64,
                events: read_meta(tx, "dropped_events")? as u64,
            };
            tx.execute(
                "UPDATE meta SET value = 0 WHERE key IN ('dropped_telemetry', 'dropped_events')",
                [],
            )?;
            Ok(dropped)
        })
    }

    fn meta(&self, key: &str) -> Result<u64> {
        self.conn
            .query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| {
                r.get::<_, i64>(0)
            })
            .optional()
            .map(|v| v.unwrap_or_default() as u64)
            .map_err(self.err())
    }
}

/// A counter of the `meta` table.
fn read_meta(tx: &Transaction<'_>, key: &str) -> rusqlite::Result<i64> {
    tx.query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get(0))
}

fn set_next_seq(tx: &Transaction<'_>, seq: i64) -> rusqlite::Result<usize> {
    tx.execute(
        "UPDATE meta SET value = ?1 WHERE key = 'next_seq'",
        params![seq],
    )
}

/// `frame` with its `seq` field set to `seq` (a frame that is not JSON stays as it is).
fn with_seq(frame: &str, seq: i64) -> String {
    match serde_json::from_str::<serde_json::Value>(frame) {
        Ok(mut v) => {
            v["seq"] = serde_json::Value::from(seq);
            v.to_string()
        }
        Err(_) => frame.to_owned(),
    }
}

/// Deletes the oldest telemetry, then the oldest ordinary events, until the queue fits.
fn enforce_bound(tx: &Transaction<'_>, max_bytes: u64) -> rusqlite::Result<()> {
    let total: i64 = tx.query_row("SELECT coalesce(sum(bytes), 0) FROM outbox", [], |r| {
        r.get(0)
    })?;
    let mut excess = total - max_bytes as i64;
    if excess <= 0 {
        return Ok(());
    }
    for (lane, counter) in [
        (Lane::Telemetry, "dropped_telemetry"),
        (Lane::Event, "dropped_events"),
    ] {
        let victims: Vec<(i64, i64)> = {
            let mut stmt =
                tx.prepare_cached("SELECT seq, bytes FROM outbox WHERE lane = ?1 ORDER BY seq")?;
            let mut rows = stmt.query([lane as i64])?;
            let mut victims = Vec::new();
            while excess > 0 {
                let Some(row) = rows.next()? else { break };
                let (seq, bytes): (i64, i64) = (row.get(0)?, row.get(1)?);
                excess -= bytes;
                victims.push((seq, bytes));
            }
            victims
        };
        if victims.is_empty() {
            continue;
        }
        let last = victims.last().map(|v| v.0).unwrap_or_default();
        let n = tx.execute(
            "DELETE FROM outbox WHERE lane = ?1 AND seq <= ?2",
            params![lane as i64, last],
        )?;
        tx.execute(
            "UPDATE meta SET value = value + ?1 WHERE key = ?2",
            params![n as i64, counter],
        )?;
        tracing::warn!(
            lane = ?lane,
            dropped = n,
            max_bytes,
            "outbox over its bound: dropped the oldest messages of this lane"
        );
        if excess <= 0 {
            break;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use lekiwi_protocol::{Sample, Severity};

    fn event(seq: u64, kind: &str, pad: usize) -> AgentMessage {
        AgentMessage::Event {
            seq,
            ts_ms: 1,
            kind: kind.into(),
            severity: Severity::Info,
            message: "x".repeat(pad),
            data: serde_json::Value::Null,
        }
    }

    fn telemetry(seq: u64, n: usize) -> AgentMessage {
        AgentMessage::Telemetry {
            seq,
            samples: (0..n)
                .map(|i| Sample {
                    metric: "cpu_percent".into(),
                    ts_ms: i as i64,
                    value: 1.5,
                })
                .collect(),
        }
    }

    #[test]
    fn sequence_numbers_survive_reopen_and_an_empty_queue() {
        let dir = tempfile::tempdir().unwrap();
        let mut ob = Outbox::open(dir.path(), 1 << 20).unwrap();
        assert_eq!(ob.push(Lane::Event, 1, |s| event(s, "a", 1)).unwrap(), 1);
        assert_eq!(ob.push(Lane::Event, 1, |s| event(s, "b", 1)).unwrap(), 2);
        ob.ack(&[1, 2]).unwrap();
        assert_eq!(ob.depth().unwrap().messages, 0);
        drop(ob);
        let mut ob = Outbox::open(dir.path(), 1 << 20).unwrap();
        assert_eq!(ob.last_acked_seq().unwrap(), 2);
        assert_eq!(ob.push(Lane::Event, 1, |s| event(s, "c", 1)).unwrap(), 3);
        // The gateway has more than we remember: queued messages move past it, in order.
        ob.push(Lane::Event, 1, |s| event(s, "d", 1)).unwrap(); // 4
        assert_eq!(ob.renumber_after(10).unwrap(), Some(2));
        assert_eq!(ob.renumber_after(5).unwrap(), None);
        let all = ob.all().unwrap();
        assert_eq!(all.iter().map(|e| e.seq).collect::<Vec<_>>(), vec![11, 12]);
        assert!(all[0].frame.contains(r#""seq":11"#) && all[0].frame.contains(r#""kind":"c""#));
        assert!(all[1].frame.contains(r#""seq":12"#) && all[1].frame.contains(r#""kind":"d""#));
        assert_eq!(ob.push(Lane::Event, 1, |s| event(s, "e", 1)).unwrap(), 13);
    }

    #[test]
    fn a_stored_seq_beyond_the_protocol_maximum_changes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut ob = Outbox::open(dir.path(), 1 << 20).unwrap();
        ob.push(Lane::Event, 1, |s| event(s, "a", 1)).unwrap();
        ob.push(Lane::Event, 1, |s| event(s, "b", 1)).unwrap();
        for forged in [u64::MAX, i64::MAX as u64, MAX_SEQ + 1, MAX_SEQ, MAX_SEQ - 2] {
            assert_eq!(ob.renumber_after(forged).unwrap(), None, "{forged}");
        }
        assert_eq!(ob.next_seq().unwrap(), 3);
        assert_eq!(ob.renumber_after(MAX_SEQ - 3).unwrap(), Some(2));
        assert_eq!(ob.next_seq().unwrap(), MAX_SEQ);
        assert!(ob.discard(MAX_SEQ - 1).unwrap());
        assert!(!ob.discard(MAX_SEQ - 1).unwrap());
        assert!(!ob.discard(u64::MAX).unwrap());
        assert_eq!(ob.last_acked_seq().unwrap(), 0, "a discard is no ack");
        assert_eq!(ob.all().unwrap().len(), 1);
    }

    #[test]
    fn lanes_come_out_in_priority_then_sequence_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut ob = Outbox::open(dir.path(), 1 << 20).unwrap();
        ob.push(Lane::Telemetry, 1, |s| telemetry(s, 2)).unwrap(); // 1
        ob.push(Lane::Event, 1, |s| event(s, "e", 1)).unwrap(); // 2
        ob.push(Lane::Telemetry, 1, |s| telemetry(s, 2)).unwrap(); // 3
        ob.push(Lane::Critical, 1, |s| event(s, "teleop", 1))
            .unwrap(); // 4
        let order: Vec<u64> = ob.all().unwrap().iter().map(|e| e.seq).collect();
        assert_eq!(order, vec![4, 2, 1, 3]);
        let t = ob.next_in_lane(Lane::Telemetry, 1, 10).unwrap();
        assert_eq!(t.iter().map(|e| e.seq).collect::<Vec<_>>(), vec![3]);
        assert!(t[0].frame.contains(r#""seq":3"#));
    }

    #[test]
    fn the_bound_drops_oldest_telemetry_then_events_never_critical() {
        let dir = tempfile::tempdir().unwrap();
        let max = 64 * 1024;
        let mut ob = Outbox::open(dir.path(), max).unwrap();
        let crit = ob
            .push(Lane::Critical, 1, |s| event(s, "deploy_done", 30_000))
            .unwrap();
        let ev = ob
            .push(Lane::Event, 1, |s| event(s, "note", 10_000))
            .unwrap();
        let mut tele = Vec::new();
        for _ in 0..40 {
            tele.push(ob.push(Lane::Telemetry, 1, |s| telemetry(s, 20)).unwrap());
        }
        let d = ob.depth().unwrap();
        assert!(d.bytes <= max, "{d:?}");
        let left: Vec<u64> = ob.all().unwrap().iter().map(|e| e.seq).collect();
        assert!(left.contains(&crit) && left.contains(&ev), "{left:?}");
        // The survivors are the newest telemetry batches, contiguous up to the last one.
        let kept: Vec<u64> = left.iter().copied().filter(|s| tele.contains(s)).collect();
        assert!(!kept.is_empty() && kept.len() < tele.len());
        assert_eq!(kept, tele[tele.len() - kept.len()..].to_vec());
        let dropped = ob.take_dropped().unwrap();
        assert_eq!(dropped.telemetry as usize, tele.len() - kept.len());
        assert_eq!(dropped.events, 0);
        assert_eq!(ob.take_dropped().unwrap(), Dropped::default());

        // Only events and critical left to give: events go, critical stays.
        for _ in 0..4 {
            ob.push(Lane::Critical, 1, |s| event(s, "deploy_done", 20_000))
                .unwrap();
        }
        let left = ob.all().unwrap();
        assert!(left.iter().all(|e| e.lane == Lane::Critical), "{left:?}");
        assert_eq!(left.len(), 5);
        let dropped = ob.take_dropped().unwrap();
        assert_eq!(dropped.events, 1);
    }

    #[test]
    fn a_second_writer_process_shares_the_sequence() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = Outbox::open(dir.path(), 1 << 20).unwrap();
        let mut b = Outbox::open(dir.path(), 1 << 20).unwrap();
        let mut seqs = Vec::new();
        for i in 0..10 {
            let ob = if i % 2 == 0 { &mut a } else { &mut b };
            seqs.push(ob.push(Lane::Event, 1, |s| event(s, "x", 1)).unwrap());
        }
        assert_eq!(seqs, (1..=10).collect::<Vec<_>>());
    }
}
