//! The event store against SQLite files in temporary directories.

use std::time::Duration;

use lekiwi_protocol::Sample;
use serde_json::json;
use tokio_util::sync::CancellationToken;

use super::*;

fn robot(name: &str) -> RobotKey {
    RobotKey::new("fleet-a", name)
}

fn event(seq: u64, ts_ms: i64) -> StoredEvent {
    StoredEvent {
        seq,
        ts_ms,
        kind: "teleoperation_started".into(),
        severity: "info".into(),
        message: format!("event {seq}"),
        data: json!({ "port": 5555, "seq": seq }),
    }
}

fn sample(metric: &str, ts_ms: i64, value: f64) -> Sample {
    Sample {
        metric: metric.into(),
        ts_ms,
        value,
    }
}

fn connection(at_ms: i64) -> ConnectionRecord {
    ConnectionRecord {
        gateway: "gw-0".into(),
        protocol: "websocket".into(),
        address: Some("10.0.0.7:40112".into()),
        connected_at_ms: at_ms,
        disconnected_at_ms: None,
        reason: None,
    }
}

async fn open(dir: &tempfile::TempDir) -> Store {
    let url = format!("sqlite://{}", dir.path().join("events.db").display());
    Store::connect(&url).await.expect("open store")
}

async fn count(store: &Store, table: &str) -> i64 {
    let Backend::Sqlite(pool) = &store.backend else {
        panic!("not sqlite")
    };
    sqlx::query_scalar(&format!("SELECT COUNT(*) FROM {table}"))
        .fetch_one(pool)
        .await
        .expect("count")
}

#[tokio::test]
async fn replayed_event_is_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    assert_eq!(store.backend(), "sqlite");
    let r = robot("kiwi-1");
    assert!(store.insert_event(&r, &event(1, 1_000)).await.unwrap());
    // A replay with other content changes nothing: the first copy wins.
    let mut replay = event(1, 2_000);
    replay.message = "changed".into();
    assert!(!store.insert_event(&r, &replay).await.unwrap());
    assert_eq!(count(&store, "events").await, 1);
    assert_eq!(
        store.events(&r, None, 10).await.unwrap(),
        vec![event(1, 1_000)]
    );
    // The same seq of another robot is another event.
    assert!(
        store
            .insert_event(&robot("kiwi-2"), &event(1, 1_000))
            .await
            .unwrap()
    );
    assert_eq!(count(&store, "events").await, 2);
}

#[tokio::test]
async fn replayed_telemetry_is_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    let r = robot("kiwi-1");
    let batch = [
        sample("cpu_percent", 1_000, 12.5),
        sample("memory_percent", 1_000, 40.0),
    ];
    assert!(store.insert_telemetry(&r, 7, &batch).await.unwrap());
    assert!(!store.insert_telemetry(&r, 7, &batch).await.unwrap());
    assert_eq!(count(&store, "samples").await, 2);
    // A telemetry seq is taken for events too: both share the robot's sequence.
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(7));
}

/// One sequence per robot (PROTOCOL.md §6 rule 1): a seq stored by one kind of durable message
/// is a replay for every other, through the batched inserts and the row-by-row ones alike, and
/// counts as stored for as long as its record is kept.
#[tokio::test]
async fn a_seq_is_stored_once_whatever_its_kind() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    let r = robot("kiwi-1");
    let cpu = [sample("cpu_percent", 1_000, 12.5)];
    assert!(store.insert_event(&r, &event(1, 1_000)).await.unwrap());
    assert!(!store.insert_telemetry(&r, 1, &cpu).await.unwrap());
    assert!(store.insert_telemetry(&r, 2, &cpu).await.unwrap());
    assert!(!store.insert_event(&r, &event(2, 1_000)).await.unwrap());
    let bytes = records::event_bytes(&event(2, 1_000));
    assert!(
        !store
            .insert_event_row(&r, 2, &event(2, 1_000), bytes, 1_000)
            .await
            .unwrap()
    );
    assert_eq!(count(&store, "events").await, 1);
    assert_eq!(count(&store, "samples").await, 1);
    // Another robot's seqs are its own.
    assert!(
        store
            .insert_telemetry(&robot("kiwi-2"), 1, &cpu)
            .await
            .unwrap()
    );
    // Once retention deleted a record, its seq is free again, as it was for its own kind.
    store.insert_event_at(&r, &event(3, 0), 10).await.unwrap();
    store.prune(100).await.unwrap();
    assert!(store.insert_telemetry(&r, 3, &cpu).await.unwrap());
}

#[tokio::test]
async fn last_seq_spans_events_and_telemetry() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    let r = robot("kiwi-1");
    assert_eq!(store.last_seq(&r).await.unwrap(), None);
    store.insert_event(&r, &event(3, 1_000)).await.unwrap();
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(3));
    store
        .insert_telemetry(&r, 9, &[sample("cpu_percent", 1_000, 1.0)])
        .await
        .unwrap();
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(9));
    store.insert_event(&r, &event(5, 1_000)).await.unwrap();
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(9));
    // An empty batch still claims its seq.
    store.insert_telemetry(&r, 11, &[]).await.unwrap();
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(11));
    assert_eq!(store.last_seq(&robot("other")).await.unwrap(), None);
}

#[tokio::test]
async fn queries_are_ordered_and_limited() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    let r = robot("kiwi-1");
    for seq in [5, 1, 3, 2, 4] {
        store
            .insert_event(&r, &event(seq, 1_000 + seq as i64))
            .await
            .unwrap();
    }
    let seqs = |evs: Vec<StoredEvent>| evs.into_iter().map(|e| e.seq).collect::<Vec<_>>();
    assert_eq!(
        seqs(store.events(&r, None, 100).await.unwrap()),
        [1, 2, 3, 4, 5]
    );
    assert_eq!(seqs(store.events(&r, Some(2), 2).await.unwrap()), [3, 4]);
    assert_eq!(
        seqs(store.events(&r, Some(u64::MAX), 10).await.unwrap()),
        [] as [u64; 0]
    );

    store
        .insert_telemetry(
            &r,
            10,
            &[
                sample("cpu_percent", 2_000, 1.0),
                sample("temp_c", 2_000, 40.0),
            ],
        )
        .await
        .unwrap();
    store
        .insert_telemetry(
            &r,
            11,
            &[
                sample("cpu_percent", 3_000, 2.0),
                sample("temp_c", 3_000, 41.0),
            ],
        )
        .await
        .unwrap();
    let cpu = store.samples(&r, Some("cpu_percent"), 0, 10).await.unwrap();
    assert_eq!(
        cpu,
        vec![
            StoredSample {
                seq: 10,
                metric: "cpu_percent".into(),
                ts_ms: 2_000,
                value: 1.0
            },
            StoredSample {
                seq: 11,
                metric: "cpu_percent".into(),
                ts_ms: 3_000,
                value: 2.0
            },
        ]
    );
    let since = store.samples(&r, None, 2_500, 10).await.unwrap();
    assert_eq!(since.len(), 2);
    assert!(since.iter().all(|s| s.ts_ms == 3_000 && s.seq == 11));
    assert_eq!(store.samples(&r, None, 0, 3).await.unwrap().len(), 3);

    let first = store.record_connect(&r, &connection(1_000)).await.unwrap();
    store
        .record_disconnect(first, 1_500, "heartbeat_timeout")
        .await
        .unwrap();
    // A second disconnect of the same connection keeps the first.
    store.record_disconnect(first, 9_999, "late").await.unwrap();
    let second = store.record_connect(&r, &connection(2_000)).await.unwrap();
    assert_ne!(first, second);
    let conns = store.connections(&r, 10).await.unwrap();
    assert_eq!(conns.len(), 2);
    assert_eq!(conns[0], connection(2_000));
    assert_eq!(
        conns[1],
        ConnectionRecord {
            disconnected_at_ms: Some(1_500),
            reason: Some("heartbeat_timeout".into()),
            ..connection(1_000)
        }
    );
    assert_eq!(
        store.connections(&r, 1).await.unwrap(),
        vec![connection(2_000)]
    );
    assert_eq!(
        store
            .close_open_connections("gw-0", 3_000, "gateway restarted")
            .await
            .unwrap(),
        1
    );
    assert_eq!(
        store.connections(&r, 1).await.unwrap()[0].disconnected_at_ms,
        Some(3_000)
    );
}

#[tokio::test]
async fn prune_deletes_by_receive_time_and_keeps_open_connections() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    let r = robot("kiwi-1");
    // The robot's clock says nothing about when a record arrived: a 1970 clock received late
    // is kept, a far-future clock received early goes.
    let future = 4_000_000_000_000;
    store
        .insert_event_at(&r, &event(1, future), 1_000)
        .await
        .unwrap();
    store
        .insert_event_at(&r, &event(2, 0), 5_000)
        .await
        .unwrap();
    store
        .insert_telemetry_at(
            &r,
            3,
            &[
                sample("cpu_percent", future, 1.0),
                sample("cpu_percent", future + 1, 2.0),
            ],
            1_000,
        )
        .await
        .unwrap();
    store
        .insert_telemetry_at(&r, 4, &[sample("cpu_percent", 0, 3.0)], 5_000)
        .await
        .unwrap();
    let old_closed = store.record_connect(&r, &connection(500)).await.unwrap();
    store
        .record_disconnect(old_closed, 1_000, "closed")
        .await
        .unwrap();
    let new_closed = store.record_connect(&r, &connection(2_000)).await.unwrap();
    store
        .record_disconnect(new_closed, 4_000, "closed")
        .await
        .unwrap();
    // Opened long ago and still open: kept however old.
    store.record_connect(&r, &connection(100)).await.unwrap();

    let counts = store.prune(3_000).await.unwrap();
    assert_eq!(
        counts,
        PruneCounts {
            events: 1,
            samples: 2,
            connections: 1
        }
    );
    // What is kept still shows the robot's own claim.
    assert_eq!(store.events(&r, None, 10).await.unwrap(), vec![event(2, 0)]);
    let samples = store.samples(&r, None, 0, 10).await.unwrap();
    assert_eq!(samples.len(), 1);
    assert_eq!((samples[0].seq, samples[0].ts_ms), (4, 0));
    let conns = store.connections(&r, 10).await.unwrap();
    let started: Vec<i64> = conns.iter().map(|c| c.connected_at_ms).collect();
    assert_eq!(started, [2_000, 100]);
    assert_eq!(count(&store, "telemetry_batches").await, 1);
    assert_eq!(store.prune(3_000).await.unwrap(), PruneCounts::default());
}

#[tokio::test]
async fn quota_refuses_rows_and_bytes_beyond_it() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await.with_quota(Quota {
        rows: 3,
        bytes: 10_000,
    });
    let r = robot("kiwi-1");
    for seq in 1..=2 {
        assert!(
            store
                .insert_event_at(&r, &event(seq, 0), 1_000)
                .await
                .unwrap()
        );
    }
    // One event and one sample fit; a batch of two samples does not.
    let two = [sample("cpu_percent", 0, 1.0), sample("cpu_percent", 1, 2.0)];
    let err = store
        .insert_telemetry_at(&r, 3, &two, 1_000)
        .await
        .unwrap_err();
    assert!(
        matches!(
            err,
            Error::QuotaExceeded {
                limit: QuotaLimit::Rows,
                ..
            }
        ),
        "{err:?}"
    );
    assert!(err.to_string().contains("quota of 3 rows"), "{err}");
    assert!(
        store
            .insert_event_at(&r, &event(4, 0), 1_000)
            .await
            .unwrap()
    );
    let err = store
        .insert_event_at(&r, &event(5, 0), 1_000)
        .await
        .unwrap_err();
    assert!(matches!(err, Error::QuotaExceeded { .. }), "{err:?}");
    assert_eq!(count(&store, "events").await, 3);
    // A replay of a stored event is still acknowledged, and another robot has its own quota.
    assert!(
        !store
            .insert_event_at(&r, &event(4, 0), 1_000)
            .await
            .unwrap()
    );
    assert!(
        store
            .insert_event(&robot("kiwi-2"), &event(1, 0))
            .await
            .unwrap()
    );
    // Retention frees room: the counts are read again after a prune.
    store.prune(2_000).await.unwrap();
    assert!(
        store
            .insert_event_at(&r, &event(5, 0), 3_000)
            .await
            .unwrap()
    );

    // Bytes: a store opened later counts what is already there.
    let small = open(&dir).await.with_quota(Quota {
        rows: 100,
        bytes: 200,
    });
    let mut big = event(6, 0);
    big.message = "x".repeat(150);
    let err = small.insert_event(&r, &big).await.unwrap_err();
    assert!(
        matches!(
            err,
            Error::QuotaExceeded {
                limit: QuotaLimit::Bytes,
                ..
            }
        ),
        "{err:?}"
    );
    big.message = "x".repeat(50);
    assert!(small.insert_event(&r, &big).await.unwrap());
}

#[tokio::test]
async fn retention_task_prunes_until_cancelled() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&dir).await;
    let r = robot("kiwi-1");
    let now = jiff::Timestamp::now().as_millisecond();
    // Received two hours ago although the robot's clock says now: pruned.
    store
        .insert_event_at(&r, &event(1, now), now - 2 * 3_600_000)
        .await
        .unwrap();
    // Received now although the robot's clock says 1970: kept.
    store.insert_event(&r, &event(2, 0)).await.unwrap();
    let cancel = CancellationToken::new();
    let task = store.spawn_retention(
        Duration::from_secs(3_600),
        Duration::from_millis(20),
        cancel.clone(),
    );
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while store.events(&r, None, 10).await.unwrap().len() != 1 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "retention did not prune"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(store.events(&r, None, 10).await.unwrap()[0].seq, 2);
    cancel.cancel();
    tokio::time::timeout(Duration::from_secs(5), task)
        .await
        .expect("retention stops when cancelled")
        .unwrap();
}

#[tokio::test]
async fn data_survives_reopening_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let r = robot("kiwi-1");
    {
        let store = open(&dir).await;
        store.insert_event(&r, &event(1, 1_000)).await.unwrap();
        store
            .insert_telemetry(&r, 2, &[sample("cpu_percent", 1_000, 1.0)])
            .await
            .unwrap();
        store.record_connect(&r, &connection(1_000)).await.unwrap();
        store.close().await;
    }
    let store = open(&dir).await;
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(2));
    assert_eq!(
        store.events(&r, None, 10).await.unwrap(),
        vec![event(1, 1_000)]
    );
    assert_eq!(store.samples(&r, None, 0, 10).await.unwrap().len(), 1);
    assert_eq!(store.connections(&r, 10).await.unwrap().len(), 1);
    // Replays after a restart are still recognised.
    assert!(!store.insert_event(&r, &event(1, 1_000)).await.unwrap());
}

#[tokio::test]
async fn file_is_durable_wal_and_created_with_its_directory() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nested/deeper/events.db");
    let store = Store::connect(&format!("sqlite://{}", path.display()))
        .await
        .unwrap();
    assert!(path.exists());
    let Backend::Sqlite(pool) = &store.backend else {
        panic!("not sqlite")
    };
    let mode: String = sqlx::query_scalar("PRAGMA journal_mode")
        .fetch_one(pool)
        .await
        .unwrap();
    assert_eq!(mode, "wal");
    let sync: i64 = sqlx::query_scalar("PRAGMA synchronous")
        .fetch_one(pool)
        .await
        .unwrap();
    assert_eq!(sync, 2, "synchronous=FULL");
    let busy: i64 = sqlx::query_scalar("PRAGMA busy_timeout")
        .fetch_one(pool)
        .await
        .unwrap();
    assert!(busy > 0);
}

#[tokio::test]
async fn memory_url_works() {
    let store = Store::connect("sqlite::memory:").await.unwrap();
    let r = robot("kiwi-1");
    assert!(store.insert_event(&r, &event(1, 1_000)).await.unwrap());
    assert!(!store.insert_event(&r, &event(1, 1_000)).await.unwrap());
    assert_eq!(store.last_seq(&r).await.unwrap(), Some(1));
}

#[tokio::test]
async fn bad_urls_and_seqs_give_clear_errors() {
    for (url, want) in [
        ("mysql://root@localhost/db", "unknown scheme \"mysql\""),
        ("events.db", "no scheme"),
        ("sqlite://", "no SQLite file path"),
        ("sqlite://x.db?bogus=1", "unknown query parameter"),
        ("postgres://user@[::1/db", "unsupported event store URL"),
    ] {
        let err = Store::connect(url).await.expect_err(url);
        assert!(
            matches!(err, Error::UnsupportedUrl { .. }),
            "{url}: {err:?}"
        );
        let text = err.to_string();
        assert!(text.contains(want), "{url}: {text}");
        assert!(text.contains("expected sqlite://"), "{url}: {text}");
    }

    // A directory where a file is needed.
    let dir = tempfile::tempdir().unwrap();
    let blocker = dir.path().join("file");
    std::fs::write(&blocker, b"").unwrap();
    let err = Store::connect(&format!("sqlite://{}/sub/events.db", blocker.display()))
        .await
        .unwrap_err();
    assert!(matches!(err, Error::CreateDir { .. }), "{err:?}");

    // Nothing listens there; the error names the backend and not the password.
    let err = Store::connect("postgres://u:secret@127.0.0.1:1/db")
        .await
        .unwrap_err();
    let text = err.to_string();
    assert!(
        matches!(
            err,
            Error::Connect {
                backend: "postgres",
                ..
            }
        ),
        "{text}"
    );
    assert!(!text.contains("secret"), "{text}");

    let store = open(&dir).await;
    let err = store
        .insert_event(&robot("kiwi-1"), &event(u64::MAX, 1_000))
        .await
        .unwrap_err();
    assert!(matches!(err, Error::SeqOutOfRange(u64::MAX)), "{err:?}");
    assert!(err.to_string().contains("out of range"), "{err}");
    let top = i64::MAX as u64;
    assert!(
        store
            .insert_event(&robot("kiwi-1"), &event(top, 1_000))
            .await
            .unwrap()
    );
    assert_eq!(store.last_seq(&robot("kiwi-1")).await.unwrap(), Some(top));
}

#[tokio::test]
async fn migration_gives_old_rows_a_clamped_receive_time_and_their_size() {
    use std::borrow::Cow;
    use std::str::FromStr;

    use sqlx::migrate::Migrator;
    use sqlx::sqlite::{SqliteConnectOptions, SqlitePool};

    let dir = tempfile::tempdir().unwrap();
    let url = format!("sqlite://{}", dir.path().join("events.db").display());
    // A store as the first schema left it: one event from the past, one from the future.
    {
        let options = SqliteConnectOptions::from_str(&url)
            .unwrap()
            .create_if_missing(true);
        let pool = SqlitePool::connect_with(options).await.unwrap();
        let first = Migrator {
            migrations: Cow::Owned(connect::SQLITE_MIGRATIONS.migrations[..1].to_vec()),
            ..Migrator::DEFAULT
        };
        first.run(&pool).await.unwrap();
        for (seq, ts_ms) in [(1, 1_000), (2, 4_000_000_000_000_i64)] {
            sqlx::query(
                "INSERT INTO events (namespace, robot, seq, ts_ms, kind, severity, message, data) \
                 VALUES ('fleet-a', 'kiwi-1', $1, $2, 'k', 'info', 'héllo', '{\"a\":1}')",
            )
            .bind(seq)
            .bind(ts_ms)
            .execute(&pool)
            .await
            .unwrap();
        }
        pool.close().await;
    }
    let before = jiff::Timestamp::now().as_millisecond() - 1_000;
    let store = Store::connect(&url).await.unwrap();
    let Backend::Sqlite(pool) = &store.backend else {
        panic!("not sqlite")
    };
    let rows: Vec<(i64, i64, i64)> =
        sqlx::query_as("SELECT seq, received_ms, bytes FROM events ORDER BY seq")
            .fetch_all(pool)
            .await
            .unwrap();
    assert_eq!(
        rows[0],
        (1, 1_000, 1 + 4 + 6 + 7),
        "its own time, UTF-8 bytes"
    );
    let (seq, received, _) = rows[1];
    // The future is clamped to the migration's now.
    assert_eq!(seq, 2);
    assert!(received >= before && received <= jiff::Timestamp::now().as_millisecond());
    // The robot's claim is untouched.
    assert_eq!(
        store.events(&robot("kiwi-1"), None, 10).await.unwrap()[1].ts_ms,
        4_000_000_000_000
    );
}
