//! The event store behaves the same on both backends: a SQLite file and a real PostgreSQL 15
//! server of the test's own (restarted and crashed where the test says so).

use std::sync::Arc;

use anyhow::{Result, ensure};
use lekiwi_core::RobotKey;
use lekiwi_event_store::{
    ConnectionRecord, Error, PruneCounts, Quota, QuotaLimit, Sample, Store, StoredEvent,
};
use lekiwi_tests::postgres::Postgres;
use serde_json::json;
use tokio::sync::Barrier;

/// One test's database.
enum Db {
    Sqlite(tempfile::TempDir),
    Postgres(Postgres),
}

impl Db {
    fn sqlite() -> Result<Db> {
        Ok(Db::Sqlite(
            tempfile::Builder::new().prefix("lekiwi-store-").tempdir()?,
        ))
    }

    fn postgres() -> Result<Db> {
        let pg = Postgres::start()?;
        eprintln!(
            "postgres on port {}: initdb {:?}, start {:?}",
            pg.port(),
            pg.init_time,
            pg.start_time
        );
        pg.create_database("lekiwi")?;
        Ok(Db::Postgres(pg))
    }

    fn url(&self) -> String {
        match self {
            Db::Sqlite(dir) => format!("sqlite://{}", dir.path().join("events.db").display()),
            Db::Postgres(pg) => pg.url("lekiwi"),
        }
    }

    async fn store(&self) -> Result<Store> {
        Ok(Store::connect(&self.url()).await?)
    }

    /// Restarts the database server cleanly, if there is one.
    fn restart(&mut self) -> Result<()> {
        match self {
            Db::Sqlite(_) => Ok(()),
            Db::Postgres(pg) => {
                pg.restart()?;
                eprintln!("postgres restarted in {:?}", pg.start_time);
                Ok(())
            }
        }
    }

    /// Stops the database server as a crash would and starts it again, if there is one.
    fn crash_restart(&mut self) -> Result<()> {
        match self {
            Db::Sqlite(_) => Ok(()),
            Db::Postgres(pg) => {
                pg.crash_restart()?;
                eprintln!("postgres recovered from a crash in {:?}", pg.start_time);
                Ok(())
            }
        }
    }
}

fn robot(name: &str) -> RobotKey {
    RobotKey::new("fleet-a", name)
}

fn event(seq: u64, ts_ms: i64) -> StoredEvent {
    StoredEvent {
        seq,
        ts_ms,
        kind: if seq.is_multiple_of(2) {
            "progress"
        } else {
            "teleoperation_started"
        }
        .into(),
        severity: "info".into(),
        message: format!("event {seq}"),
        data: json!({ "seq": seq, "nested": { "list": [1, 2.5, "x", null] } }),
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

async fn replays_are_stored_once(db: Db) -> Result<()> {
    let store = db.store().await?;
    let r = robot("kiwi-1");
    ensure!(store.insert_event(&r, &event(1, 1_000)).await?);
    let mut replay = event(1, 1_000);
    replay.message = "a different body under the same seq".into();
    ensure!(
        !store.insert_event(&r, &replay).await?,
        "replay stored again"
    );
    assert_eq!(store.events(&r, None, 100).await?, vec![event(1, 1_000)]);

    let batch = [
        sample("cpu_percent", 1_000, 12.5),
        sample("temp_c", 1_000, 48.25),
    ];
    ensure!(store.insert_telemetry(&r, 2, &batch).await?);
    ensure!(
        !store.insert_telemetry(&r, 2, &batch).await?,
        "replayed batch stored again"
    );
    assert_eq!(store.samples(&r, None, 0, 100).await?.len(), 2);
    // Another robot's seq 1 is its own.
    ensure!(
        store
            .insert_event(&robot("kiwi-2"), &event(1, 1_000))
            .await?
    );
    Ok(())
}

async fn last_seq_spans_events_and_telemetry(db: Db) -> Result<()> {
    let store = db.store().await?;
    let r = robot("kiwi-1");
    assert_eq!(store.last_seq(&r).await?, None);
    store.insert_event(&r, &event(4, 1_000)).await?;
    assert_eq!(store.last_seq(&r).await?, Some(4));
    store
        .insert_telemetry(&r, 10, &[sample("cpu_percent", 1_000, 1.0)])
        .await?;
    assert_eq!(store.last_seq(&r).await?, Some(10));
    store.insert_event(&r, &event(6, 1_000)).await?;
    assert_eq!(store.last_seq(&r).await?, Some(10));
    let top = i64::MAX as u64;
    store.insert_event(&r, &event(top, 1_000)).await?;
    assert_eq!(store.last_seq(&r).await?, Some(top));
    ensure!(
        store
            .insert_event(&r, &event(top + 1, 1_000))
            .await
            .is_err()
    );
    assert_eq!(store.last_seq(&robot("kiwi-2")).await?, None);
    Ok(())
}

async fn queries_filter_order_and_limit(db: Db) -> Result<()> {
    let store = db.store().await?;
    let r = robot("kiwi-1");
    for seq in [3, 1, 5, 2, 4] {
        store
            .insert_event(&r, &event(seq, 1_000 + seq as i64))
            .await?;
    }
    store
        .insert_event(&robot("kiwi-2"), &event(9, 1_000))
        .await?;
    let seqs = |evs: Vec<StoredEvent>| evs.iter().map(|e| e.seq).collect::<Vec<_>>();
    assert_eq!(seqs(store.events(&r, None, 100).await?), [1, 2, 3, 4, 5]);
    assert_eq!(seqs(store.events(&r, Some(1), 3).await?), [2, 3, 4]);
    assert_eq!(seqs(store.events(&r, Some(5), 3).await?), [] as [u64; 0]);
    // JSON data comes back as it went in.
    assert_eq!(store.events(&r, Some(2), 1).await?, vec![event(3, 1_003)]);

    store
        .insert_telemetry(
            &r,
            10,
            &[
                sample("cpu_percent", 2_000, 1.5),
                sample("temp_c", 2_000, 40.0),
            ],
        )
        .await?;
    store
        .insert_telemetry(
            &r,
            11,
            &[
                sample("cpu_percent", 3_000, 2.5),
                sample("temp_c", 3_000, 41.0),
            ],
        )
        .await?;
    let cpu = store.samples(&r, Some("cpu_percent"), 0, 100).await?;
    let cpu: Vec<_> = cpu.iter().map(|s| (s.seq, s.ts_ms, s.value)).collect();
    assert_eq!(cpu, [(10, 2_000, 1.5), (11, 3_000, 2.5)]);
    let recent = store.samples(&r, None, 2_500, 100).await?;
    let recent: Vec<_> = recent
        .iter()
        .map(|s| (s.metric.as_str(), s.ts_ms))
        .collect();
    assert_eq!(recent, [("cpu_percent", 3_000), ("temp_c", 3_000)]);
    assert_eq!(store.samples(&r, None, 0, 3).await?.len(), 3);
    ensure!(
        store
            .samples(&robot("kiwi-2"), None, 0, 100)
            .await?
            .is_empty()
    );

    let first = store.record_connect(&r, &connection(1_000)).await?;
    store
        .record_disconnect(first, 1_500, "heartbeat_timeout")
        .await?;
    store.record_disconnect(first, 9_000, "duplicate").await?;
    let second = store.record_connect(&r, &connection(2_000)).await?;
    ensure!(first != second);
    let conns = store.connections(&r, 100).await?;
    assert_eq!(
        conns,
        vec![
            connection(2_000),
            ConnectionRecord {
                disconnected_at_ms: Some(1_500),
                reason: Some("heartbeat_timeout".into()),
                ..connection(1_000)
            },
        ]
    );
    assert_eq!(store.connections(&r, 1).await?, vec![connection(2_000)]);
    assert_eq!(
        store
            .close_open_connections("gw-0", 5_000, "gateway restarted")
            .await?,
        1
    );
    assert_eq!(
        store.connections(&r, 1).await?[0].disconnected_at_ms,
        Some(5_000)
    );
    Ok(())
}

async fn prune_deletes_old_records_only(db: Db) -> Result<()> {
    let store = db.store().await?;
    let r = robot("kiwi-1");
    // Retention goes by when the gateway received a record, not by the robot's clock: far in
    // the future but received early goes, 1970 but received late stays.
    let future = 4_000_000_000_000;
    store.insert_event_at(&r, &event(1, future), 1_000).await?;
    store.insert_event_at(&r, &event(2, 0), 5_000).await?;
    store
        .insert_telemetry_at(
            &r,
            3,
            &[
                sample("cpu_percent", future, 1.0),
                sample("cpu_percent", 0, 2.0),
            ],
            1_000,
        )
        .await?;
    store
        .insert_telemetry_at(&r, 4, &[sample("cpu_percent", 0, 3.0)], 5_000)
        .await?;
    let old = store.record_connect(&r, &connection(500)).await?;
    store.record_disconnect(old, 1_000, "closed").await?;
    let recent = store.record_connect(&r, &connection(2_000)).await?;
    store.record_disconnect(recent, 4_000, "closed").await?;
    store.record_connect(&r, &connection(100)).await?;

    let counts = store.prune(3_000).await?;
    assert_eq!(
        counts,
        PruneCounts {
            events: 1,
            samples: 2,
            connections: 1
        }
    );
    assert_eq!(store.events(&r, None, 100).await?, vec![event(2, 0)]);
    let samples = store.samples(&r, None, 0, 100).await?;
    assert_eq!(
        samples.iter().map(|s| (s.seq, s.value)).collect::<Vec<_>>(),
        [(4, 3.0)]
    );
    let started: Vec<_> = store
        .connections(&r, 100)
        .await?
        .iter()
        .map(|c| c.connected_at_ms)
        .collect();
    // The old but still open connection stays.
    assert_eq!(started, [2_000, 100]);
    assert_eq!(store.prune(3_000).await?, PruneCounts::default());
    Ok(())
}

async fn quota_is_kept_per_robot(db: Db) -> Result<()> {
    let quota = Quota {
        rows: 4,
        bytes: 1_000,
    };
    let store = db.store().await?.with_quota(quota);
    let r = robot("kiwi-1");
    store.insert_event_at(&r, &event(1, 0), 1_000).await?;
    let two = [sample("cpu_percent", 0, 1.0), sample("temp_c", 0, 40.0)];
    store.insert_telemetry_at(&r, 2, &two, 1_000).await?;
    store.insert_event_at(&r, &event(3, 0), 5_000).await?;
    // Four rows stored: the next is refused, not stored, and says which limit.
    let err = store.insert_event(&r, &event(4, 0)).await.unwrap_err();
    ensure!(
        matches!(
            err,
            Error::QuotaExceeded {
                limit: QuotaLimit::Rows,
                ..
            }
        ),
        "{err:?}"
    );
    assert_eq!(store.events(&r, Some(3), 10).await?, vec![]);
    // A replay is still acknowledged; another robot is not affected.
    assert!(!store.insert_event(&r, &event(3, 0)).await?);
    assert!(store.insert_event(&robot("kiwi-2"), &event(1, 0)).await?);
    // A second handle (another replica) counts what the first stored.
    let other = db.store().await?.with_quota(quota);
    assert!(other.insert_event(&r, &event(4, 0)).await.is_err());
    // Retention frees the room of what it deleted.
    store.prune(2_000).await?;
    assert!(store.insert_event(&r, &event(4, 0)).await?);
    // Bytes: one event larger than the rest of the budget.
    let mut big = event(5, 0);
    big.message = "x".repeat(1_000);
    let err = store.insert_event(&r, &big).await.unwrap_err();
    ensure!(
        matches!(
            err,
            Error::QuotaExceeded {
                limit: QuotaLimit::Bytes,
                ..
            }
        ),
        "{err:?}"
    );
    Ok(())
}

async fn concurrent_inserts_store_one_row(db: Db) -> Result<()> {
    const TASKS: usize = 8;
    let store = db.store().await?;
    let r = robot("kiwi-1");
    let barrier = Arc::new(Barrier::new(TASKS));
    let mut tasks = tokio::task::JoinSet::new();
    for task in 0..TASKS {
        let (store, r, barrier) = (store.clone(), r.clone(), barrier.clone());
        tasks.spawn(async move {
            barrier.wait().await;
            let first = store.insert_event(&r, &event(1, 1_000)).await?;
            let batch = [
                sample("cpu_percent", 1_000, task as f64),
                sample("temp_c", 1_000, 40.0),
            ];
            let telemetry = store.insert_telemetry(&r, 2, &batch).await?;
            // And every task's own seqs, interleaved with the others'.
            for i in 0..10 {
                let seq = 100 + (task * 10 + i) as u64;
                ensure!(store.insert_event(&r, &event(seq, 2_000)).await?);
            }
            anyhow::Ok((first, telemetry))
        });
    }
    let (mut events, mut batches) = (0, 0);
    while let Some(joined) = tasks.join_next().await {
        let (event, telemetry) = joined??;
        events += usize::from(event);
        batches += usize::from(telemetry);
    }
    assert_eq!(
        (events, batches),
        (1, 1),
        "exactly one insert of each seq wins"
    );
    assert_eq!(store.events(&r, None, 1_000).await?.len(), 1 + TASKS * 10);
    assert_eq!(store.samples(&r, None, 0, 1_000).await?.len(), 2);
    assert_eq!(
        store.last_seq(&r).await?,
        Some(100 + (TASKS * 10 - 1) as u64)
    );
    Ok(())
}

/// Many robots' sessions storing at once (and replaying each other's first event): inserts
/// are batched into far fewer statements, every `(robot, seq)` is stored once, and exactly one
/// insert of each reports it newly stored.
async fn many_sessions_insert_in_batches(db: Db) -> Result<()> {
    const ROBOTS: usize = 40;
    const EVENTS: u64 = 25;
    let store = db.store().await?;
    let mut tasks = tokio::task::JoinSet::new();
    for i in 0..ROBOTS {
        for replay in [false, true] {
            let (store, r) = (store.clone(), robot(&format!("kiwi-{i}")));
            tasks.spawn(async move {
                let seqs = if replay { 1..=1 } else { 1..=EVENTS };
                let mut new = 0;
                for seq in seqs {
                    new += usize::from(store.insert_event(&r, &event(seq, 1_000)).await?);
                }
                anyhow::Ok(new)
            });
        }
    }
    let mut new = 0;
    while let Some(joined) = tasks.join_next().await {
        new += joined??;
    }
    assert_eq!(new, ROBOTS * EVENTS as usize, "one insert of each seq wins");
    for i in 0..ROBOTS {
        let r = robot(&format!("kiwi-{i}"));
        let seqs: Vec<u64> = store
            .events(&r, None, 1_000)
            .await?
            .iter()
            .map(|e| e.seq)
            .collect();
        assert_eq!(seqs, (1..=EVENTS).collect::<Vec<_>>(), "{r:?}");
    }
    let statements = store.event_statements().expect("inserts are batched");
    let inserts = ROBOTS * (EVENTS as usize + 1);
    println!("{inserts} event inserts in {statements} statements");
    ensure!(
        (statements as usize) < inserts / 2,
        "{statements} statements for {inserts} inserts"
    );
    Ok(())
}

async fn data_survives_reconnects_and_restarts(mut db: Db) -> Result<()> {
    let r = robot("kiwi-1");
    let store = db.store().await?;
    store.insert_event(&r, &event(1, 1_000)).await?;
    store
        .insert_telemetry(&r, 2, &[sample("cpu_percent", 1_000, 1.0)])
        .await?;
    let conn = store.record_connect(&r, &connection(1_000)).await?;
    store.close().await;

    let check = |store: Store, last: u64| {
        let r = r.clone();
        async move {
            assert_eq!(store.last_seq(&r).await?, Some(last));
            assert_eq!(store.events(&r, None, 100).await?[0], event(1, 1_000));
            assert_eq!(store.samples(&r, None, 0, 100).await?.len(), 1);
            assert_eq!(store.connections(&r, 100).await?.len(), 1);
            ensure!(
                !store.insert_event(&r, &event(1, 1_000)).await?,
                "replay after restart"
            );
            anyhow::Ok(store)
        }
    };

    // Closed pool, same database.
    let store = check(db.store().await?, 2).await?;
    store.close().await;

    // A clean server restart.
    db.restart()?;
    let store = check(db.store().await?, 2).await?;

    // A crash with the store still open: the pool replaces its dead connections, and what was
    // acknowledged before the crash is there afterwards.
    store
        .insert_event(&robot("kiwi-1"), &event(3, 2_000))
        .await?;
    store.record_disconnect(conn, 2_000, "closed").await?;
    db.crash_restart()?;
    let store = check(store, 3).await?;
    assert_eq!(
        store.connections(&robot("kiwi-1"), 1).await?[0]
            .reason
            .as_deref(),
        Some("closed")
    );
    Ok(())
}

/// PostgreSQL down for a while: each session's writes are refused at once, not after the
/// pool's 30 s connect deadline each (a session storing five messages used to be held for
/// minutes, its heartbeats and commands behind them); once the server is back the resent
/// messages go in, each once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn postgres_down_refuses_writes_at_once_and_takes_them_back_up() -> Result<()> {
    const ROBOTS: usize = 40;
    const EVENTS: u64 = 5;
    /// The pool's connect deadline: the longest a write may wait once, to learn of the outage.
    const CONNECT_DEADLINE: std::time::Duration = std::time::Duration::from_secs(30);
    let Db::Postgres(mut pg) = Db::postgres()? else {
        unreachable!()
    };
    let store = Store::connect(&pg.url("lekiwi")).await?;
    store
        .insert_event(&robot("kiwi-0"), &event(1, 1_000))
        .await?;
    pg.shut_down()?;

    // Every robot's session stores its messages one after another, as a session does.
    let started = std::time::Instant::now();
    let mut sessions = tokio::task::JoinSet::new();
    for i in 0..ROBOTS {
        let (store, r) = (store.clone(), robot(&format!("kiwi-{i}")));
        sessions.spawn(async move {
            let t0 = std::time::Instant::now();
            let mut refused = Vec::new();
            for seq in 2..2 + EVENTS {
                let answer = if seq % 2 == 0 {
                    store.insert_event(&r, &event(seq, 2_000)).await
                } else {
                    store
                        .insert_telemetry(&r, seq, &[sample("cpu_percent", 2_000, 1.0)])
                        .await
                };
                refused.push(answer.expect_err("nothing is stored while the server is down"));
            }
            (t0.elapsed(), refused)
        });
    }
    let mut unavailable = 0;
    while let Some(joined) = sessions.join_next().await {
        let (took, refused) = joined?;
        ensure!(
            took < CONNECT_DEADLINE + std::time::Duration::from_secs(10),
            "a session's {EVENTS} writes took {took:?}: more than one connect deadline"
        );
        unavailable += refused.iter().filter(|e| e.is_unavailable()).count();
    }
    println!(
        "{} writes refused in {:?}, {unavailable} of them at once",
        ROBOTS * EVENTS as usize,
        started.elapsed()
    );
    ensure!(
        unavailable >= ROBOTS * (EVENTS as usize - 1),
        "after its first, every session's writes are refused at once ({unavailable})"
    );
    // A session opening meanwhile is told at once too.
    let t0 = std::time::Instant::now();
    let start = store
        .open_session(&robot("kiwi-new"), &connection(3_000))
        .await;
    ensure!(
        matches!(start.record_id, Err(Error::Unavailable { .. })) && start.last_seq.is_err(),
        "{start:?}"
    );
    ensure!(
        t0.elapsed() < std::time::Duration::from_secs(1),
        "{:?}",
        t0.elapsed()
    );

    // Back up: the probe finds it within seconds; the resent messages go in once each.
    pg.start_again()?;
    let back = std::time::Instant::now();
    loop {
        match store.insert_event(&robot("kiwi-0"), &event(2, 2_000)).await {
            Ok(new) => {
                ensure!(new, "kiwi-0's message 2 stored now");
                break;
            }
            Err(e) if back.elapsed() < std::time::Duration::from_secs(20) => {
                eprintln!("not yet: {e}");
                tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            }
            Err(e) => return Err(e.into()),
        }
    }
    println!(
        "writes taken again {:?} after the server started",
        back.elapsed()
    );
    for i in 0..ROBOTS {
        let r = robot(&format!("kiwi-{i}"));
        for seq in 2..2 + EVENTS {
            let again = if seq % 2 == 0 {
                store.insert_event(&r, &event(seq, 2_000)).await?
            } else {
                store
                    .insert_telemetry(&r, seq, &[sample("cpu_percent", 2_000, 1.0)])
                    .await?
            };
            ensure!(again == (i != 0 || seq != 2), "{r:?} {seq}: stored once");
        }
        assert_eq!(store.last_seq(&r).await?, Some(1 + EVENTS), "{r:?}");
    }
    Ok(())
}

/// Brings `db` to the state the first `migrations` schema versions left, then runs `rows`
/// (plain SQL, the same text on both backends) in it.
async fn old_schema(db: &Db, migrations: usize, rows: &[&str]) -> Result<()> {
    use sqlx::migrate::Migrator;
    use std::borrow::Cow;

    let first = |all: Migrator| Migrator {
        migrations: Cow::Owned(all.migrations[..migrations].to_vec()),
        ..Migrator::DEFAULT
    };
    match db {
        Db::Sqlite(_) => {
            let options =
                <sqlx::sqlite::SqliteConnectOptions as std::str::FromStr>::from_str(&db.url())?
                    .create_if_missing(true);
            let pool = sqlx::SqlitePool::connect_with(options).await?;
            first(sqlx_macros::migrate!(
                "../operator/event-store/migrations/sqlite"
            ))
            .run(&pool)
            .await?;
            for row in rows {
                sqlx::query(row).execute(&pool).await?;
            }
            pool.close().await;
        }
        Db::Postgres(_) => {
            let pool = sqlx::PgPool::connect(&db.url()).await?;
            first(sqlx_macros::migrate!(
                "../operator/event-store/migrations/postgres"
            ))
            .run(&pool)
            .await?;
            for row in rows {
                sqlx::query(row).execute(&pool).await?;
            }
            pool.close().await;
        }
    }
    Ok(())
}

/// A store as the first schema left it, rows included, gets a receive time (the robot's claim
/// clamped to now) and a size for each row when the gateway opens it.
async fn migration_keeps_old_rows_with_a_clamped_receive_time(db: Db) -> Result<()> {
    const INSERT: &str = "INSERT INTO events \
        (namespace, robot, seq, ts_ms, kind, severity, message, data) \
        VALUES ('fleet-a', 'kiwi-1', 1, 1000, 'k', 'info', 'héllo', '{\"a\":1}'), \
        ('fleet-a', 'kiwi-1', 2, 4000000000000, 'k', 'info', 'héllo', '{\"a\":1}')";
    old_schema(&db, 1, &[INSERT]).await?;
    let store = db.store().await?;
    let r = robot("kiwi-1");
    // The robot's claims are untouched.
    let claims: Vec<i64> = store
        .events(&r, None, 10)
        .await?
        .iter()
        .map(|e| e.ts_ms)
        .collect();
    assert_eq!(claims, [1_000, 4_000_000_000_000]);
    // The past one was received at its own time, the future one now: a prune up to a minute
    // from now deletes both, one up to an hour ago only the first.
    let now = jiff::Timestamp::now().as_millisecond();
    assert_eq!(store.prune(now - 3_600_000).await?.events, 1);
    // Their sizes count: 18 bytes (k + info + héllo + {"a":1}; PostgreSQL's JSONB text adds a
    // space) are there, so a quota that leaves 17 beside a new event is full.
    let new = event(3, 0);
    let size = (new.kind.len() + new.severity.len() + new.message.len()) as u64
        + serde_json::to_string(&new.data)?.len() as u64;
    let quota = |bytes| Quota { rows: 100, bytes };
    let full = db.store().await?.with_quota(quota(size + 17));
    ensure!(
        full.insert_event(&r, &new).await.is_err(),
        "old rows counted"
    );
    let room = db.store().await?.with_quota(quota(size + 19));
    ensure!(room.insert_event(&r, &new).await?, "room left");
    assert_eq!(store.prune(now + 60_000).await?.events, 2);
    Ok(())
}

/// A store the second schema left, with a seq stored both as an event and as telemetry (as
/// gateways did before one seq space), keeps every record when the gateway opens it; from then
/// on a seq stored under any kind is a replay for every kind.
async fn migration_claims_the_seqs_stored_before(db: Db) -> Result<()> {
    old_schema(
        &db,
        2,
        &[
            "INSERT INTO events \
             (namespace, robot, seq, ts_ms, kind, severity, message, data, received_ms, bytes) \
             VALUES ('fleet-a', 'kiwi-1', 5, 1000, 'k', 'info', 'm', '{}', 1000, 8), \
             ('fleet-a', 'kiwi-1', 6, 1000, 'k', 'info', 'm', '{}', 1000, 8)",
            "INSERT INTO telemetry_batches (namespace, robot, seq, max_ts_ms, received_ms, bytes) \
             VALUES ('fleet-a', 'kiwi-1', 5, 1000, 2000, 27), ('fleet-a', 'kiwi-1', 7, 1000, 2000, 27)",
            "INSERT INTO samples (namespace, robot, seq, metric, ts_ms, value, received_ms) \
             VALUES ('fleet-a', 'kiwi-1', 5, 'cpu_percent', 1000, 1.0, 2000), \
             ('fleet-a', 'kiwi-1', 7, 'cpu_percent', 1000, 2.0, 2000)",
        ],
    )
    .await?;
    let store = db.store().await?;
    let r = robot("kiwi-1");
    let seqs = |evs: Vec<StoredEvent>| evs.iter().map(|e| e.seq).collect::<Vec<_>>();
    assert_eq!(seqs(store.events(&r, None, 10).await?), [5, 6]);
    assert_eq!(store.samples(&r, None, 0, 10).await?.len(), 2);
    let cpu = [sample("cpu_percent", 1_000, 3.0)];
    for seq in [5, 6, 7] {
        ensure!(
            !store.insert_event(&r, &event(seq, 1_000)).await?,
            "event {seq} stored again"
        );
        ensure!(
            !store.insert_telemetry(&r, seq, &cpu).await?,
            "telemetry {seq} stored again"
        );
    }
    ensure!(store.insert_event(&r, &event(8, 1_000)).await?);
    assert_eq!(store.last_seq(&r).await?, Some(8));
    // The seq stored twice counts until its later record goes.
    store.prune(1_500).await?;
    ensure!(!store.insert_event(&r, &event(5, 1_000)).await?);
    store.prune(2_500).await?;
    ensure!(store.insert_event(&r, &event(5, 1_000)).await?);
    Ok(())
}

/// Times beyond what RFC 3339 writes (a robot sending 2^63-1 or -2^63) are stored as the nearest
/// bound, by new inserts and, for rows stored before, by the migration; events are listed by
/// when the gateway received them, so each of these is in the last hour's range, and samples
/// are in the widest range a query can name.
async fn extreme_times_are_clamped_into_reach(db: Db) -> Result<()> {
    use lekiwi_event_store::{MAX_TIME_MS, MIN_TIME_MS, TimeRange};

    let now = jiff::Timestamp::now().as_millisecond();
    old_schema(
        &db,
        3,
        &[&format!(
            "INSERT INTO events \
             (namespace, robot, seq, ts_ms, kind, severity, message, data, received_ms, bytes) \
             VALUES ('fleet-a', 'kiwi-1', 1, {}, 'k', 'info', 'm', '{{}}', {now}, 8), \
             ('fleet-a', 'kiwi-1', 2, {}, 'k', 'info', 'm', '{{}}', {now}, 8)",
            i64::MAX,
            i64::MIN
        )],
    )
    .await?;
    let store = db.store().await?;
    let r = robot("kiwi-1");
    for (seq, ts) in [(3, i64::MAX), (4, i64::MIN), (5, now - 365 * 86_400_000)] {
        ensure!(store.insert_event(&r, &event(seq, ts)).await?);
    }
    let samples = [
        sample("cpu_percent", i64::MIN, 1.0),
        sample("cpu_percent", i64::MAX, 2.0),
    ];
    ensure!(store.insert_telemetry(&r, 6, &samples).await?);
    let last_hour = TimeRange {
        since_ms: now - 3_600_000,
        until_ms: i64::MAX,
    };
    let listed: Vec<(u64, i64)> = store
        .events_in_range(&r, None, last_hour, 100)
        .await?
        .iter()
        .map(|e| (e.seq, e.ts_ms))
        .collect();
    assert_eq!(
        listed,
        [
            (1, MAX_TIME_MS),
            (2, MIN_TIME_MS),
            (3, MAX_TIME_MS),
            (4, MIN_TIME_MS),
            (5, now - 365 * 86_400_000)
        ]
    );
    let widest = TimeRange {
        since_ms: MIN_TIME_MS,
        until_ms: i64::MAX,
    };
    let taken: Vec<i64> = store
        .samples_in_range(&r, None, widest, None, 10)
        .await?
        .iter()
        .map(|s| s.sample.ts_ms)
        .collect();
    assert_eq!(taken, [MIN_TIME_MS, MAX_TIME_MS]);
    Ok(())
}

/// One sequence per robot (PROTOCOL.md §6 rule 1): a seq stored as an event is a replay for
/// telemetry and the reverse, also when an event and a telemetry batch of one seq arrive at the
/// same moment (two sessions of the robot): one is stored, the other is told "already stored".
/// Another robot's seqs are its own.
async fn one_seq_space_for_every_kind(db: Db) -> Result<()> {
    const SEQS: u64 = 40;
    let store = db.store().await?;
    let r = robot("kiwi-1");
    let cpu = [sample("cpu_percent", 1_000, 1.0)];
    ensure!(store.insert_event(&r, &event(1, 1_000)).await?);
    ensure!(
        !store.insert_telemetry(&r, 1, &cpu).await?,
        "telemetry stored under an event's seq"
    );
    ensure!(store.insert_telemetry(&r, 2, &cpu).await?);
    ensure!(
        !store.insert_event(&r, &event(2, 1_000)).await?,
        "an event stored under a telemetry batch's seq"
    );
    ensure!(store.insert_telemetry(&robot("kiwi-2"), 1, &cpu).await?);

    let barrier = Arc::new(Barrier::new(2 * SEQS as usize));
    let mut tasks = tokio::task::JoinSet::new();
    for seq in 3..3 + SEQS {
        for telemetry in [false, true] {
            let (store, r, barrier) = (store.clone(), r.clone(), barrier.clone());
            tasks.spawn(async move {
                barrier.wait().await;
                let stored = if telemetry {
                    let samples = [sample("cpu_percent", 1_000, seq as f64)];
                    store.insert_telemetry(&r, seq, &samples).await?
                } else {
                    store.insert_event(&r, &event(seq, 1_000)).await?
                };
                anyhow::Ok((seq, telemetry, stored))
            });
        }
    }
    let (mut events, mut batches) = (vec![1], vec![2]);
    while let Some(joined) = tasks.join_next().await {
        match joined?? {
            (seq, false, true) => events.push(seq),
            (seq, true, true) => batches.push(seq),
            _ => {}
        }
    }
    events.sort_unstable();
    batches.sort_unstable();
    let mut all: Vec<u64> = events.iter().chain(&batches).copied().collect();
    all.sort_unstable();
    assert_eq!(
        all,
        (1..3 + SEQS).collect::<Vec<_>>(),
        "each seq stored once"
    );
    let stored: Vec<u64> = store
        .events(&r, None, 1_000)
        .await?
        .iter()
        .map(|e| e.seq)
        .collect();
    assert_eq!(stored, events);
    let mut sampled: Vec<u64> = store
        .samples(&r, None, 0, 1_000)
        .await?
        .iter()
        .map(|s| s.seq)
        .collect();
    sampled.sort_unstable();
    assert_eq!(sampled, batches);
    println!(
        "{} seqs stored as events, {} as telemetry",
        events.len(),
        batches.len()
    );
    Ok(())
}

/// Many sessions ending at once (a fleet leaving a gateway): their connection records are
/// closed in far fewer statements than sessions, each with its own time and reason, more than
/// one statement's worth included; a later close of a closed record changes nothing.
async fn many_sessions_close_in_batches(db: Db) -> Result<()> {
    const ROBOTS: usize = 1_200;
    let store = db.store().await?;
    let mut ids = Vec::new();
    for i in 0..ROBOTS {
        let r = robot(&format!("kiwi-{i}"));
        ids.push((
            r.clone(),
            store.record_connect(&r, &connection(1_000)).await?,
        ));
    }
    let before = store.close_statements().expect("closes are batched");
    let close_all = |at: i64, reason: &'static str| {
        let mut tasks = tokio::task::JoinSet::new();
        for (i, (_, id)) in ids.iter().enumerate() {
            let (store, id) = (store.clone(), *id);
            tasks.spawn(async move { store.record_disconnect(id, at + i as i64, reason).await });
        }
        tasks
    };
    let mut tasks = close_all(2_000, "closed");
    while let Some(joined) = tasks.join_next().await {
        joined??;
    }
    let statements = store.close_statements().expect("closes are batched") - before;
    println!("{ROBOTS} connection closes in {statements} statements");
    ensure!(
        (statements as usize) < ROBOTS / 4,
        "{statements} statements for {ROBOTS} closes"
    );
    let mut tasks = close_all(9_000, "late");
    while let Some(joined) = tasks.join_next().await {
        joined??;
    }
    for (i, (r, _)) in ids.iter().enumerate() {
        let conns = store.connections(r, 10).await?;
        assert_eq!(conns.len(), 1, "{r:?}");
        assert_eq!(conns[0].disconnected_at_ms, Some(2_000 + i as i64), "{r:?}");
        assert_eq!(conns[0].reason.as_deref(), Some("closed"), "{r:?}");
    }
    Ok(())
}

/// Many sessions opening at once (a fleet arriving at a gateway): their connection records and
/// last-seq reads take far fewer statements than sessions, two sessions of one robot included;
/// each session gets an id of its own record (its close lands on the row it opened) and its
/// robot's last seq, whether events, telemetry or nothing was stored.
async fn many_sessions_open_in_batches(db: Db) -> Result<()> {
    const ROBOTS: usize = 600;
    let store = db.store().await?;
    let robots: Vec<RobotKey> = (0..ROBOTS).map(|i| robot(&format!("kiwi-{i}"))).collect();
    let mut expected = Vec::new();
    for (i, r) in robots.iter().enumerate() {
        expected.push(match i % 3 {
            0 => {
                store.insert_event(r, &event(i as u64, 1_000)).await?;
                Some(i as u64)
            }
            1 => {
                let samples = [sample("cpu_percent", 1_000, 1.0)];
                store.insert_telemetry(r, i as u64 + 5, &samples).await?;
                Some(i as u64 + 5)
            }
            _ => None,
        });
    }
    // Two sessions per robot; for even robots the two records are equal in every column.
    let session = |i: usize, second: bool| {
        let mut rec = connection(1_000 + i as i64);
        if second && i % 2 == 1 {
            rec.address = Some(format!("10.0.1.{}:40112", i % 250));
        }
        rec
    };
    let before = store.open_statements().expect("opens are batched");
    let barrier = Arc::new(Barrier::new(2 * ROBOTS));
    let mut tasks = tokio::task::JoinSet::new();
    for (i, r) in robots.iter().enumerate() {
        for second in [false, true] {
            let (store, r, rec, barrier) = (
                store.clone(),
                r.clone(),
                session(i, second),
                barrier.clone(),
            );
            tasks.spawn(async move {
                barrier.wait().await;
                let start = store.open_session(&r, &rec).await;
                anyhow::Ok((i, rec, start.record_id?, start.last_seq?))
            });
        }
    }
    let mut opened = Vec::new();
    while let Some(joined) = tasks.join_next().await {
        opened.push(joined??);
    }
    let statements = store.open_statements().expect("opens are batched") - before;
    println!("{} session opens in {statements} statements", 2 * ROBOTS);
    ensure!(
        (statements as usize) < ROBOTS / 2,
        "{statements} statements for {} session opens",
        2 * ROBOTS
    );
    let mut ids: Vec<i64> = opened.iter().map(|(_, _, id, _)| *id).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(
        ids.len(),
        2 * ROBOTS,
        "every session has a record of its own"
    );
    // Each session closes its record with a reason naming its robot, address and time: a
    // record whose reason names another was closed through another session's id.
    let said = |r: &RobotKey, address: &Option<String>, at: i64| format!("{r} {address:?} {at}");
    for (i, rec, id, last_seq) in &opened {
        assert_eq!(*last_seq, expected[*i], "{:?}", robots[*i]);
        let reason = said(&robots[*i], &rec.address, rec.connected_at_ms);
        store.record_disconnect(*id, 5_000, &reason).await?;
    }
    for (i, r) in robots.iter().enumerate() {
        let conns = store.connections(r, 10).await?;
        assert_eq!(conns.len(), 2, "{r:?}");
        for c in &conns {
            assert_eq!(c.connected_at_ms, 1_000 + i as i64, "{r:?}");
            let own = said(r, &c.address, c.connected_at_ms);
            assert_eq!(
                c.reason.as_ref(),
                Some(&own),
                "closed through another session's id"
            );
        }
    }
    Ok(())
}

/// Runs each check once per backend, as `sqlite::name` and `postgres::name`.
macro_rules! on_both_backends {
    ($($name:ident),* $(,)?) => {
        mod sqlite {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() -> anyhow::Result<()> {
                    super::$name(super::Db::sqlite()?).await
                }
            )*
        }
        mod postgres {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $name() -> anyhow::Result<()> {
                    super::$name(super::Db::postgres()?).await
                }
            )*
        }
    };
}

on_both_backends!(
    replays_are_stored_once,
    last_seq_spans_events_and_telemetry,
    queries_filter_order_and_limit,
    prune_deletes_old_records_only,
    quota_is_kept_per_robot,
    migration_keeps_old_rows_with_a_clamped_receive_time,
    migration_claims_the_seqs_stored_before,
    one_seq_space_for_every_kind,
    extreme_times_are_clamped_into_reach,
    concurrent_inserts_store_one_row,
    many_sessions_insert_in_batches,
    many_sessions_close_in_batches,
    many_sessions_open_in_batches,
    data_survives_reconnects_and_restarts,
);
