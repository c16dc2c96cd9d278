//! Paged reads of a robot's history for the Fleet API: events by sequence number within a range
//! of times the gateway received them, telemetry samples by the time they were taken within a
//! range of those, resumed from a cursor the previous page ended on.

use sqlx_macros::FromRow;

use super::{Error, Result, RobotKey, Store, StoredEvent, StoredSample, from_db_seq};

/// A time range in Unix milliseconds: from `since` (included) to `until` (excluded).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TimeRange {
    /// First millisecond in the range.
    pub since_ms: i64,
    /// First millisecond after the range.
    pub until_ms: i64,
}

/// Where a page of samples resumes: after the sample taken at `ts_ms` with row `id`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SampleCursor {
    /// When the last sample of the previous page was taken.
    pub ts_ms: i64,
    /// Its row id (ties of `ts_ms` are ordered by it).
    pub id: i64,
}

/// A stored sample with the cursor that resumes after it.
#[derive(Clone, Debug, PartialEq)]
pub struct PagedSample {
    /// The sample.
    pub sample: StoredSample,
    /// Resumes after it.
    pub cursor: SampleCursor,
}

#[derive(FromRow)]
struct EventRow {
    seq: i64,
    ts_ms: i64,
    kind: String,
    severity: String,
    message: String,
    data: sqlx::types::Json<serde_json::Value>,
}

#[derive(FromRow)]
struct SampleRow {
    id: i64,
    seq: i64,
    metric: String,
    ts_ms: i64,
    value: f64,
}

// By receive time, the gateway's clock: a robot whose clock is wrong (or sends extreme times)
// still has its fresh events in "the last hour".
const EVENTS_IN_RANGE: &str = "SELECT seq, ts_ms, kind, severity, message, data FROM events \
     WHERE namespace = $1 AND robot = $2 AND seq > $3 AND received_ms >= $4 AND received_ms < $5 \
     ORDER BY seq LIMIT $6";
// `$7` is the metric or NULL for all: one statement for both, the same text in each backend.
const SAMPLES_IN_RANGE: &str = "SELECT id, seq, metric, ts_ms, value FROM samples \
     WHERE namespace = $1 AND robot = $2 AND ts_ms >= $3 AND ts_ms < $4 \
     AND (ts_ms > $5 OR (ts_ms = $5 AND id > $6)) AND ($7 IS NULL OR metric = $7) \
     ORDER BY ts_ms, id LIMIT $8";

impl Store {
    /// Up to `limit` events with seq above `after_seq` (all if `None`) that the gateway received
    /// within `range` (its clock, not the robot's `ts_ms`), in ascending seq.
    pub async fn events_in_range(
        &self,
        robot: &RobotKey,
        after_seq: Option<u64>,
        range: TimeRange,
        limit: u32,
    ) -> Result<Vec<StoredEvent>> {
        let Ok(after) = after_seq.map_or(Ok(-1), i64::try_from) else {
            return Ok(Vec::new());
        };
        let rows: Vec<EventRow> = with_pool!(self, pool => {
            sqlx::query_as(EVENTS_IN_RANGE)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(after)
                .bind(range.since_ms)
                .bind(range.until_ms)
                .bind(i64::from(limit))
                .fetch_all(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "events",
            source,
        })?;
        Ok(rows
            .into_iter()
            .map(|r| StoredEvent {
                seq: from_db_seq(r.seq),
                ts_ms: r.ts_ms,
                kind: r.kind,
                severity: r.severity,
                message: r.message,
                data: r.data.0,
            })
            .collect())
    }

    /// Up to `limit` samples of `metric` (all metrics if `None`) taken within `range` after
    /// `after` (from the start if `None`), oldest first.
    pub async fn samples_in_range(
        &self,
        robot: &RobotKey,
        metric: Option<&str>,
        range: TimeRange,
        after: Option<SampleCursor>,
        limit: u32,
    ) -> Result<Vec<PagedSample>> {
        let after = after.unwrap_or(SampleCursor {
            ts_ms: i64::MIN,
            id: i64::MIN,
        });
        let rows: Vec<SampleRow> = with_pool!(self, pool => {
            sqlx::query_as(SAMPLES_IN_RANGE)
                .bind(&robot.namespace)
                .bind(&robot.name)
                .bind(range.since_ms)
                .bind(range.until_ms)
                .bind(after.ts_ms)
                .bind(after.id)
                .bind(metric)
                .bind(i64::from(limit))
                .fetch_all(pool)
                .await
        })
        .map_err(|source| Error::Query {
            what: "samples",
            source,
        })?;
        Ok(rows
            .into_iter()
            .map(|r| PagedSample {
                cursor: SampleCursor {
                    ts_ms: r.ts_ms,
                    id: r.id,
                },
                sample: StoredSample {
                    seq: from_db_seq(r.seq),
                    metric: r.metric,
                    ts_ms: r.ts_ms,
                    value: r.value,
                },
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{MAX_TIME_MS, MIN_TIME_MS, Sample};

    fn event(seq: u64, ts_ms: i64) -> StoredEvent {
        StoredEvent {
            seq,
            ts_ms,
            kind: "k".into(),
            severity: "info".into(),
            message: format!("e{seq}"),
            data: serde_json::json!({}),
        }
    }

    #[tokio::test]
    async fn pages_cover_the_range_once_in_order() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("h.db").display());
        let store = Store::connect(&url).await.unwrap();
        let r = RobotKey::new("ns", "kiwi");
        // Events go by when the gateway received them, whatever the robot's clock said:
        // here a clock running backwards, and the extremes an `i64` holds.
        let claims = [-100, 900, i64::MAX, i64::MIN, 5, 0];
        for (seq, ts_ms) in (1..=6).zip(claims) {
            store
                .insert_event_at(&r, &event(seq, ts_ms), seq as i64 * 100)
                .await
                .unwrap();
        }
        let range = TimeRange {
            since_ms: 200,
            until_ms: 600,
        };
        let first = store.events_in_range(&r, None, range, 2).await.unwrap();
        assert_eq!(first.iter().map(|e| e.seq).collect::<Vec<_>>(), [2, 3]);
        let rest = store.events_in_range(&r, Some(3), range, 9).await.unwrap();
        assert_eq!(rest.iter().map(|e| e.seq).collect::<Vec<_>>(), [4, 5]);
        // The extremes are kept as the nearest times RFC 3339 can write.
        let times: Vec<i64> = first.iter().chain(&rest).map(|e| e.ts_ms).collect();
        assert_eq!(times, [900, MAX_TIME_MS, MIN_TIME_MS, 5]);

        let at = |metric: &str, ts_ms| Sample {
            metric: metric.into(),
            ts_ms,
            value: 1.0,
        };
        let batch = [
            at("cpu", 100),
            at("mem", 100),
            at("cpu", 200),
            at("cpu", 900),
        ];
        store.insert_telemetry(&r, 10, &batch).await.unwrap();
        let range = TimeRange {
            since_ms: 0,
            until_ms: 500,
        };
        let page = store
            .samples_in_range(&r, None, range, None, 2)
            .await
            .unwrap();
        assert_eq!(page.len(), 2);
        let more = store
            .samples_in_range(&r, None, range, Some(page[1].cursor), 9)
            .await
            .unwrap();
        let ts: Vec<_> = more.iter().map(|s| s.sample.ts_ms).collect();
        assert_eq!(ts, [200]);
        let cpu = store
            .samples_in_range(&r, Some("cpu"), range, None, 9)
            .await
            .unwrap();
        assert_eq!(cpu.len(), 2);
    }

    #[tokio::test]
    async fn extreme_sample_times_are_kept_within_reach_of_a_range() {
        let store = Store::connect("sqlite::memory:").await.unwrap();
        let r = RobotKey::new("ns", "kiwi");
        let at = |ts_ms| Sample {
            metric: "cpu".into(),
            ts_ms,
            value: 1.0,
        };
        store
            .insert_telemetry(&r, 1, &[at(i64::MIN), at(i64::MAX)])
            .await
            .unwrap();
        // The widest range the Fleet API asks for: the first RFC 3339 time, no end.
        let range = TimeRange {
            since_ms: jiff::Timestamp::MIN.as_millisecond(),
            until_ms: i64::MAX,
        };
        let all = store
            .samples_in_range(&r, None, range, None, 9)
            .await
            .unwrap();
        let ts: Vec<_> = all.iter().map(|s| s.sample.ts_ms).collect();
        assert_eq!(ts, [MIN_TIME_MS, MAX_TIME_MS]);
    }

    #[test]
    fn the_time_bounds_are_those_rfc_3339_writes() {
        let text = |ms| jiff::Timestamp::from_millisecond(ms).map(|t| t.to_string());
        assert_eq!(text(MIN_TIME_MS).unwrap(), "-009999-01-02T01:59:59Z");
        assert_eq!(text(MAX_TIME_MS).unwrap(), "9999-12-30T22:00:00Z");
        assert!(text(MIN_TIME_MS - 1).is_err() && text(MAX_TIME_MS + 1).is_err());
        assert!(MAX_TIME_MS.unsigned_abs().max(MIN_TIME_MS.unsigned_abs()) < 1 << 53);
    }
}
