//! Two gateway replicas (`--role gateway`) and a controller (`--role controller`) sharing one
//! API server and one PostgreSQL event store, as the chart runs them with `replicaCount > 1`: a
//! robot that moves from one replica to the other keeps one live session, never shows Offline or
//! Unknown because of the move, ends with a status naming the replica it moved to, and has every
//! event it sent stored exactly once.
//!
//! On a private control plane with this tree's CRDs: the gateways write `status.sessionEpoch`,
//! which a Robot CRD applied by another checkout's tests on the shared one may lack.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures::{SinkExt, StreamExt};
use kube::Api;
use kube::runtime::{WatchStreamExt, watcher};
use lekiwi_agent::connection::Socket;
use lekiwi_core::RobotKey;
use lekiwi_core::cache::Cache;
use lekiwi_crds::{Robot, RobotPhase};
use lekiwi_metrics::Metrics;
use lekiwi_presence::watched::WatchedRobots;
use lekiwi_presence::{ConnectInfo, HeartbeatInfo, Presence, PresenceConfig};
use lekiwi_protocol::{AgentMessage, ErrorCode, Health, ServerMessage, Severity, encode};
use lekiwi_tests::postgres::Postgres;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, connect_agent, create_robot, gateway_operator, get_robot,
    heartbeat, namespace, recv, robot_token, sample, wait_for,
};
use serde_json::json;
use tokio_tungstenite::tungstenite::Message;
use tokio_util::sync::CancellationToken;

/// The gateways' Lease validity: short, so a killed gateway's robots would turn Unknown soon.
const GATEWAY_LEASE_SECS: u64 = 3;

/// The controller, two gateway replicas, the PostgreSQL store they share and their API server
/// (dropped last).
struct Replicas {
    pg: Postgres,
    client: kube::Client,
    ns: String,
    _controller: OperatorProcess,
    a: OperatorProcess,
    b: OperatorProcess,
    _cp: ControlPlane,
}

impl Replicas {
    async fn start(prefix: &str) -> anyhow::Result<Replicas> {
        let cp = ControlPlane::private()?;
        cp.install_crds()?;
        let client = cp.client().await?;
        let ns = namespace(&client, prefix).await?;
        let pg = Postgres::start()?;
        let url = pg.create_database("lekiwi")?;
        let lease = GATEWAY_LEASE_SECS.to_string();
        let gateway = [
            "--role",
            "gateway",
            "--store-url",
            &url,
            "--gateway-lease-seconds",
            &lease,
        ];
        let controller = gateway_operator(
            &cp,
            &ns,
            "ctl",
            &["--role", "controller", "--store-url", &url],
        )
        .await?;
        let a = gateway_operator(&cp, &ns, "a", &gateway).await?;
        let b = gateway_operator(&cp, &ns, "b", &gateway).await?;
        Ok(Replicas {
            pg,
            client,
            ns,
            _controller: controller,
            a,
            b,
            _cp: cp,
        })
    }

    /// A robot with its own token.
    async fn robot(&self, name: &str) -> anyhow::Result<String> {
        create_robot(&self.client, &self.ns, name, &[]).await?;
        robot_token(&self.client, &self.ns, name).await
    }

    /// Waits until `name` is Online through `gateway`.
    async fn online_via(&self, name: &str, gateway: &str) -> anyhow::Result<()> {
        wait_for(
            &format!("{name} Online via {gateway}"),
            Duration::from_secs(15),
            || async {
                let s = get_robot(&self.client, &self.ns, name).await.ok()?.status?;
                (s.phase == Some(RobotPhase::Online)
                    && s.gateway.as_deref() == Some(gateway)
                    && s.connected == Some(true))
                .then_some(())
            },
        )
        .await
    }

    /// How often each event seq of robot `name` is stored, as `seq:count` in seq order.
    fn stored_events(&self, name: &str) -> anyhow::Result<Vec<String>> {
        let sql = format!(
            "SELECT seq || ':' || count(*) FROM events WHERE namespace = '{}' AND robot = '{name}' \
             GROUP BY seq ORDER BY seq",
            self.ns
        );
        Ok(self
            .pg
            .psql("lekiwi", &sql)?
            .lines()
            .map(str::to_owned)
            .collect())
    }
}

/// Every phase the Robot showed and the gateway its status named then, in order, as its watch
/// delivered them.
#[derive(Clone, Default)]
struct PhaseHistory(Arc<Mutex<Vec<Seen>>>);

/// A phase and the gateway the status named with it.
type Seen = (Option<RobotPhase>, Option<String>);

impl PhaseHistory {
    /// Records each change of the robot's phase or of the gateway its status names.
    fn watch(client: &kube::Client, ns: &str, name: &str) -> Self {
        let history = PhaseHistory::default();
        let api: Api<Robot> = Api::namespaced(client.clone(), ns);
        let config = watcher::Config::default().fields(&format!("metadata.name={name}"));
        let out = history.clone();
        tokio::spawn(async move {
            let mut robots =
                std::pin::pin!(watcher(api, config).default_backoff().applied_objects());
            while let Some(r) = robots.next().await {
                let Ok(robot) = r else { continue };
                let status = robot.status.unwrap_or_default();
                let mut seen = out.0.lock().unwrap();
                let now = (status.phase, status.gateway.map(String::from));
                if seen.last() != Some(&now) {
                    seen.push(now);
                }
            }
        });
        history
    }

    /// Fails if the robot showed anything but Online after it first was.
    fn assert_online_since_first(&self) {
        let seen = self.0.lock().unwrap().clone();
        println!("phase history: {seen:?}");
        let first = seen
            .iter()
            .position(|(p, _)| *p == Some(RobotPhase::Online))
            .expect("the robot was Online");
        assert!(
            seen[first..]
                .iter()
                .all(|(p, _)| *p == Some(RobotPhase::Online)),
            "the robot left Online after it first was: {seen:?}"
        );
    }
}

fn event(seq: u64) -> AgentMessage {
    AgentMessage::Event {
        seq,
        ts_ms: 1_763_800_000_000 + seq as i64,
        kind: "moved_test".into(),
        severity: Severity::Info,
        message: format!("event {seq}"),
        data: json!({ "seq": seq }),
    }
}

/// Sends events `seqs` and expects each acknowledged in turn.
async fn send_events(ws: &mut Socket, seqs: impl IntoIterator<Item = u64>) {
    for seq in seqs {
        ws.send(Message::text(encode(&event(seq))))
            .await
            .expect("send");
        assert_eq!(recv(ws).await, Some(ServerMessage::Ack { seq }));
    }
}

/// The gateway answers a heartbeat on `ws`.
async fn heartbeat_answered(ws: &mut Socket) {
    ws.send(Message::text(encode(&heartbeat())))
        .await
        .expect("send");
    assert!(matches!(
        recv(ws).await,
        Some(ServerMessage::HeartbeatAck { .. })
    ));
}

/// The seqs `from..=to`, each stored once, as [`Replicas::stored_events`] lists them.
fn once_each(from: u64, to: u64) -> Vec<String> {
    (from..=to).map(|s| format!("{s}:1")).collect()
}

/// One private control plane for both moves: it is the costly part.
#[tokio::test]
async fn a_robot_moves_between_replicas() -> anyhow::Result<()> {
    let mut r = Replicas::start("replicas").await?;
    // Kept connected through B while the second robot's replica dies.
    let _on_b = a_newer_session_on_another_replica_ends_the_old_one(&r).await?;
    a_robot_moves_when_its_replica_is_killed(&mut r).await?;
    an_older_sessions_writes_are_fenced(&r).await?;
    writes_run_ahead_of_a_cache_that_runs_behind(&r).await
}

/// The same identity connects through B while its session on A lives: A's session ends within
/// seconds, A writes nothing after, events are stored once.
async fn a_newer_session_on_another_replica_ends_the_old_one(
    r: &Replicas,
) -> anyhow::Result<Socket> {
    let token = r.robot("kiwi").await?;
    let history = PhaseHistory::watch(&r.client, &r.ns, "kiwi");
    let robot = format!("{}/kiwi", r.ns);

    let (mut on_a, _) = connect_agent(&r.a, &token, &robot).await?;
    r.online_via("kiwi", "gw-a").await?;
    send_events(&mut on_a, 1..=5).await;

    // The same identity connects through B while A's session lives: A's session ends.
    let (mut on_b, welcome) = connect_agent(&r.b, &token, &robot).await?;
    let moved = Instant::now();
    assert_eq!(welcome.stored_seq, Some(5), "both replicas read one store");
    match recv(&mut on_a).await {
        Some(ServerMessage::Error {
            code: ErrorCode::Replaced,
            fatal: true,
            ..
        }) => {}
        other => panic!("the session on A got {other:?} instead of `replaced`"),
    }
    assert!(recv(&mut on_a).await.is_none(), "A closed the old session");
    let ended = moved.elapsed();
    println!("A's session ended {ended:?} after B's welcome");
    assert!(
        ended < Duration::from_secs(5),
        "A's session lived {ended:?}"
    );

    // Only B serves the robot now; a replay of what A stored is stored once.
    send_events(&mut on_b, 4..=8).await;
    heartbeat_answered(&mut on_b).await;
    r.online_via("kiwi", "gw-b").await?;
    // Whatever A still writes late must not undo B's status.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let status = get_robot(&r.client, &r.ns, "kiwi").await?.status.unwrap();
    assert_eq!(status.gateway.as_deref(), Some("gw-b"), "{status:?}");
    assert_eq!(status.connected, Some(true));
    assert_eq!(status.phase, Some(RobotPhase::Online));
    assert!(status.session_epoch.is_some());
    assert_eq!(
        r.a.metric("lekiwi_gateway_sessions_ended_total{kind=\"moved\"}")
            .await,
        Some(1.0)
    );
    history.assert_online_since_first();
    assert_eq!(r.stored_events("kiwi")?, once_each(1, 8));
    Ok(on_b)
}

/// A is killed while it holds the robot; the robot reconnects through B: Online through B,
/// never Unknown when A's Lease expires, events stored once; A restarted takes nothing back.
async fn a_robot_moves_when_its_replica_is_killed(r: &mut Replicas) -> anyhow::Result<()> {
    let token = r.robot("kiwi-k").await?;
    let history = PhaseHistory::watch(&r.client, &r.ns, "kiwi-k");
    let robot = format!("{}/kiwi-k", r.ns);

    let (mut on_a, _) = connect_agent(&r.a, &token, &robot).await?;
    r.online_via("kiwi-k", "gw-a").await?;
    send_events(&mut on_a, 1..=5).await;

    // A crashes; the agent reconnects through B and resends what it has not seen acked.
    r.a.kill();
    let killed = Instant::now();
    let (mut on_b, welcome) = connect_agent(&r.b, &token, &robot).await?;
    assert_eq!(welcome.stored_seq, Some(5), "both replicas read one store");
    send_events(&mut on_b, 5..=9).await;
    r.online_via("kiwi-k", "gw-b").await?;
    println!("Online via B {:?} after the kill", killed.elapsed());

    // A's Lease expires meanwhile: the robot, held by B, must not turn Unknown.
    let expired = Duration::from_secs(3 * GATEWAY_LEASE_SECS);
    while killed.elapsed() < expired {
        heartbeat_answered(&mut on_b).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    // A comes back under the same name: it takes nothing back.
    r.a.restart()?;
    r.a.wait_ready().await?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    heartbeat_answered(&mut on_b).await;
    let status = get_robot(&r.client, &r.ns, "kiwi-k").await?.status.unwrap();
    assert_eq!(status.gateway.as_deref(), Some("gw-b"), "{status:?}");
    assert_eq!(status.phase, Some(RobotPhase::Online));
    history.assert_online_since_first();
    assert_eq!(r.stored_events("kiwi-k")?, once_each(1, 9));
    Ok(())
}

/// A gateway's status writer for `gateway` that reads who holds a robot from `cache` first,
/// writing until the token is cancelled.
fn status_writer(
    client: &kube::Client,
    gateway: &str,
    cache: &WatchedRobots,
) -> (Presence, Metrics, CancellationToken) {
    let metrics = Metrics::new(false);
    let presence = Presence::new(
        PresenceConfig {
            gateway: gateway.into(),
            status_refresh: Duration::from_secs(60),
            poll_grace: Duration::from_secs(60),
            qps: 50.0,
            adaptive: None,
            burst: 50,
            concurrency: 4,
        },
        metrics.clone(),
    );
    let cancel = CancellationToken::new();
    tokio::spawn(
        presence
            .clone()
            .run_writer(client.clone(), Some(cache.clone()), cancel.clone()),
    );
    (presence, metrics, cancel)
}

/// How many high-priority status writes of `metrics` ended with `result`.
fn writes(metrics: &Metrics, result: &str) -> f64 {
    let series =
        format!("lekiwi_gateway_status_writes_total{{priority=\"high\",result=\"{result}\"}}");
    sample(&metrics.encode(), &series).unwrap_or(0.0)
}

/// The writes of a session that lost the robot to a later one, made before its gateway knows
/// (a status change, then its disconnect), never overwrite the later session's status. Two
/// status writers stand for the two replicas, without the Robot watch that would end the older
/// session first: only the fence decides. Their Robot cache is stuck at the robot's creation, so
/// every write meets a conflict first and decides on the Robot read again.
async fn an_older_sessions_writes_are_fenced(r: &Replicas) -> anyhow::Result<()> {
    let created = create_robot(&r.client, &r.ns, "kiwi-f", &[]).await?;
    let cache = WatchedRobots(Arc::new(Cache::listed([created])));
    let key = RobotKey::new(&r.ns, "kiwi-f");
    let (old, old_metrics, old_cancel) = status_writer(&r.client, "gw-old", &cache);
    let (new, new_metrics, new_cancel) = status_writer(&r.client, "gw-new", &cache);
    let healthy = |healthy: bool| {
        Some(Health {
            healthy,
            message: None,
            reason: None,
        })
    };
    let holder = |gateway: &'static str| {
        let (client, ns) = (r.client.clone(), r.ns.clone());
        async move {
            let s = get_robot(&client, &ns, "kiwi-f").await.ok()?.status?;
            (s.gateway.as_deref() == Some(gateway) && s.connected == Some(true)).then_some(s)
        }
    };
    let info = ConnectInfo {
        protocol: "websocket",
        health: healthy(true),
        ..ConnectInfo::default()
    };
    old.connect(&key, 1, 1_000, info.clone());
    wait_for("the old session written", Duration::from_secs(10), || {
        holder("gw-old")
    })
    .await?;
    new.connect(&key, 1, 2_000, info);
    wait_for("the new session written", Duration::from_secs(10), || {
        holder("gw-new")
    })
    .await?;

    // The old session reports a change, then ends; its gateway has not heard of the new one.
    old.heartbeat(
        &key,
        1,
        HeartbeatInfo {
            health: healthy(false),
            ..HeartbeatInfo::default()
        },
    );
    wait_for("the old write tried", Duration::from_secs(10), || async {
        (old.queued() == 0).then_some(())
    })
    .await?;
    old.disconnect(&key, 1);
    tokio::time::sleep(Duration::from_secs(2)).await;
    assert_eq!(old.queued(), 0, "the fenced writes are not retried");
    let status = get_robot(&r.client, &r.ns, "kiwi-f").await?.status.unwrap();
    assert_eq!(status.gateway.as_deref(), Some("gw-new"), "{status:?}");
    assert_eq!(status.connected, Some(true));
    assert_eq!(status.session_epoch, Some(2_000));
    assert!(
        status.health.is_some_and(|h| h.healthy),
        "the old write landed"
    );
    // Every write went through the fresh read: the new session's landed, the old one's did not.
    assert_eq!(writes(&new_metrics, "ok"), 1.0);
    assert!(writes(&old_metrics, "superseded") >= 1.0);
    assert_eq!(writes(&old_metrics, "ok"), 1.0, "only its connect landed");
    old_cancel.cancel();
    new_cancel.cancel();
    Ok(())
}

/// A session's writes in a row, while the gateway's Robot cache runs behind (stuck at the
/// robot's creation, as a watch minutes behind an API server that restarted on a busy machine):
/// each is fenced on the version the one before it left, so none meets a conflict and none
/// needs a read of the Robot first. Fenced on the cache's version, every write after the first
/// was refused once and read the Robot: three requests for one, when the API server can least
/// spare them. A write of another writer in between still meets its conflict.
async fn writes_run_ahead_of_a_cache_that_runs_behind(r: &Replicas) -> anyhow::Result<()> {
    // A namespace no operator of the fixture watches: this writer is the Robot's only writer
    // (the Robot controller would write each robot's phase after it).
    let ns = namespace(&r.client, "behind").await?;
    let created = create_robot(&r.client, &ns, "kiwi-behind", &[]).await?;
    let cache = WatchedRobots(Arc::new(Cache::listed([created])));
    let key = RobotKey::new(&ns, "kiwi-behind");
    let (writer, metrics, cancel) = status_writer(&r.client, "gw-a", &cache);
    let conflicts = |metrics: &Metrics| {
        sample(
            &metrics.encode(),
            "lekiwi_gateway_status_write_conflicts_total",
        )
        .unwrap_or(0.0)
    };
    let health = |healthy: bool| {
        Some(Health {
            healthy,
            message: None,
            reason: None,
        })
    };
    let info = ConnectInfo {
        protocol: "websocket",
        health: health(true),
        ..ConnectInfo::default()
    };
    let shows = |healthy: bool| {
        let (client, ns) = (r.client.clone(), ns.clone());
        async move {
            let s = get_robot(&client, &ns, "kiwi-behind").await.ok()?.status?;
            (s.connected == Some(true) && s.health.as_ref()?.healthy == healthy).then_some(())
        }
    };
    // The session reports a health change; waits until the API server shows it.
    let change = |healthy: bool| {
        writer.heartbeat(
            &key,
            1,
            HeartbeatInfo {
                health: health(healthy),
                ..HeartbeatInfo::default()
            },
        );
        wait_for("the change written", Duration::from_secs(10), move || {
            shows(healthy)
        })
    };
    writer.connect(&key, 1, 1_000, info);
    wait_for("the session written", Duration::from_secs(10), || {
        shows(true)
    })
    .await?;
    // The API server can show a write before the writer has its answer and counts it.
    let counted = |n: f64| {
        let metrics = &metrics;
        wait_for("the writes counted", Duration::from_secs(10), move || {
            let done = writes(metrics, "ok") >= n;
            async move { done.then_some(()) }
        })
    };
    for round in 0..4 {
        change(round % 2 == 1).await?;
    }
    counted(5.0).await?;
    assert_eq!(writes(&metrics, "ok"), 5.0);
    assert_eq!(
        conflicts(&metrics),
        0.0,
        "a write was fenced on the cache's old version"
    );

    // Another writer changes the Robot: the next write meets that change, reads, and lands.
    let robots: Api<Robot> = Api::namespaced(r.client.clone(), &ns);
    robots
        .patch(
            "kiwi-behind",
            &kube::api::PatchParams::apply("lekiwi-test"),
            &kube::api::Patch::Apply(json!({
                "apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot",
                "metadata": {"labels": {"moved-by": "another-writer"}},
            })),
        )
        .await?;
    change(false).await?;
    counted(6.0).await?;
    assert_eq!(conflicts(&metrics), 1.0);
    assert_eq!(writes(&metrics, "ok"), 6.0);
    cancel.cancel();
    Ok(())
}
