//! Recovery after a gateway replica dies, at small scale with real processes: two gateways
//! (`--role gateway`), a controller and a shared PostgreSQL store on a private control plane.
//! The survivor writes its status slowly on purpose (a fixed 3 writes/s), so most moved robots
//! are still unwritten when the dead gateway's Lease expires. Its Lease claims them meanwhile
//! (`fleet.lekiwi.io/claimed-robots`): none shows `Unknown`, each costs about one write; its
//! moved robots are written before the robots that are simply new to it; a robot that does not
//! come back still turns `Unknown`; one that comes back and leaves again before its write (its
//! claim dropped unwritten) ends `Offline` through the survivor without showing `Unknown`. And a
//! write the dead gateway sent before it died, landing
//! only after its Lease expired and after the robot's session on the survivor opened, shows the
//! robot `Unknown` neither. A robot that reconnects only after the Lease expired (shown
//! `Unknown` meanwhile) is written before the moves queued ahead of it; the controller lists it
//! on the dead gateway's Lease (`fleet.lekiwi.io/marked-unknown`) until the survivor wrote it,
//! and that list alone, with no Robot watch showing the `Unknown`, puts it first.
//!
//! On a private control plane with this tree's CRDs (the gateways write `status.sessionEpoch`).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures::StreamExt;
use k8s_openapi::api::coordination::v1::Lease;
use kube::Api;
use kube::api::{ListParams, Patch, PatchParams};
use kube::runtime::{WatchStreamExt, watcher};
use lekiwi_agent::connection::Socket;
use lekiwi_crds::contract::{CLAIMS_ANNOTATION, MARKED_ANNOTATION, managers, parse_claims};
use lekiwi_crds::{Robot, RobotPhase};
use lekiwi_tests::postgres::Postgres;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, connect_agent, create_robot, gateway_operator, get_robot,
    namespace, robot_token, wait_for,
};

/// The gateways' Lease validity: short, so the killed gateway's Lease expires within seconds.
const GATEWAY_LEASE_SECS: u64 = 3;
/// Robots on the gateway that is killed; all but one reconnect through the survivor.
const ON_A: usize = 30;
/// Robots that connect to the survivor for the first time while the moved ones arrive.
const FRESH: usize = 8;
/// The survivor's fixed status rate (writes per second).
const SLOW_QPS: &str = "3";

/// What a Robot showed, in order, with when the watch delivered it and the resourceVersion
/// that showed it first.
type Seen = Vec<(Option<RobotPhase>, Option<String>, Instant, u64)>;

/// Every change of phase or named gateway of each Robot of a namespace.
#[derive(Clone, Default)]
struct Histories(Arc<Mutex<HashMap<String, Seen>>>);

impl Histories {
    fn watch(client: &kube::Client, ns: &str) -> Self {
        let out = Histories::default();
        let api: Api<Robot> = Api::namespaced(client.clone(), ns);
        let histories = out.clone();
        tokio::spawn(async move {
            let stream = watcher(api, watcher::Config::default())
                .default_backoff()
                .applied_objects();
            let mut robots = std::pin::pin!(stream);
            while let Some(r) = robots.next().await {
                let Ok(robot) = r else { continue };
                let name = robot.metadata.name.clone().unwrap_or_default();
                let status = robot.status.unwrap_or_default();
                let mut all = histories.0.lock().unwrap();
                let seen = all.entry(name).or_default();
                let now = (status.phase, status.gateway.map(String::from));
                if seen.last().map(|(p, g, _, _)| (*p, g.clone())) != Some(now.clone()) {
                    let version = revision(robot.metadata.resource_version.as_deref());
                    seen.push((now.0, now.1, Instant::now(), version));
                }
            }
        });
        out
    }

    fn of(&self, name: &str) -> Seen {
        self.0
            .lock()
            .unwrap()
            .get(name)
            .cloned()
            .unwrap_or_default()
    }

    /// When `name` was first shown Online through `gateway`.
    fn online_via(&self, name: &str, gateway: &str) -> Option<Instant> {
        self.first_online(name, gateway).map(|(t, _)| t)
    }

    /// [`Self::online_via`], waiting up to 5 s for this watch to bring the change: a read of
    /// the API server can see a status before the watch has delivered it.
    async fn seen_online_via(&self, name: &str, gateway: &str) -> Option<Instant> {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let seen = self.online_via(name, gateway);
            if seen.is_some() || Instant::now() > deadline {
                return seen;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// The resourceVersion that first showed `name` Online through `gateway`: the API
    /// server's order of writes, whatever this watch's delay.
    fn online_version(&self, name: &str, gateway: &str) -> Option<u64> {
        self.first_online(name, gateway).map(|(_, v)| v)
    }

    /// When and in which resourceVersion `name` was first shown Online through `gateway`.
    fn first_online(&self, name: &str, gateway: &str) -> Option<(Instant, u64)> {
        self.of(name)
            .into_iter()
            .find(|(p, g, _, _)| *p == Some(RobotPhase::Online) && g.as_deref() == Some(gateway))
            .map(|(_, _, t, v)| (t, v))
    }
}

/// A resourceVersion as a number. Opaque to clients in general; this API server's are etcd
/// revisions, which rise with every write, so they order writes (test code only).
fn revision(version: Option<&str>) -> u64 {
    version.and_then(|v| v.parse().ok()).unwrap_or_default()
}

/// The API server's revision now: that of a list read from etcd (no resourceVersion given).
async fn revision_now(client: &kube::Client, ns: &str) -> anyhow::Result<u64> {
    let robots: Api<Robot> = Api::namespaced(client.clone(), ns);
    let list = robots.list(&ListParams::default().limit(1)).await?;
    Ok(revision(list.metadata.resource_version.as_deref()))
}

/// Robot and Event writes (create, update, patch, apply, delete) the API server has served.
fn robot_and_event_writes(cp: &ControlPlane) -> anyhow::Result<f64> {
    let out = cp.kubectl(&["get", "--raw", "/metrics"]);
    anyhow::ensure!(out.status.success(), "kubectl get --raw /metrics failed");
    let text = String::from_utf8(out.stdout)?;
    let writes = ["POST", "PUT", "PATCH", "APPLY", "DELETE"];
    Ok(text
        .lines()
        .filter(|l| l.starts_with("apiserver_request_total{"))
        .filter(|l| l.contains("resource=\"robots\"") || l.contains("resource=\"events\""))
        .filter(|l| writes.iter().any(|v| l.contains(&format!("verb=\"{v}\""))))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum())
}

/// The lines of `op`'s log about robot `name`, and its watch errors: what decided when it was
/// written.
fn log_of(op: &OperatorProcess, name: &str) -> String {
    let robot = format!("robot={name} ");
    op.log_text()
        .lines()
        .filter(|l| {
            l.contains(&robot)
                || l.contains(&format!("/{name} "))
                || l.contains("watch")
                || l.contains("lagged")
        })
        .filter(|l| !l.contains("desired"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The controller, gateway A (default status rate), gateway B (slow, fixed) and their store.
struct Fleet {
    client: kube::Client,
    ns: String,
    a: OperatorProcess,
    b: OperatorProcess,
    controller: OperatorProcess,
    _pg: Postgres,
    cp: ControlPlane,
}

impl Fleet {
    async fn start() -> anyhow::Result<Fleet> {
        let cp = ControlPlane::private()?;
        cp.install_crds()?;
        let client = cp.client().await?;
        let ns = namespace(&client, "recovery").await?;
        let pg = Postgres::start()?;
        let url = pg.create_database("lekiwi")?;
        let lease = GATEWAY_LEASE_SECS.to_string();
        let gateway = ["--role", "gateway", "--store-url", &url];
        let gateway = [&gateway[..], &["--gateway-lease-seconds", &lease]].concat();
        let controller = ["--role", "controller", "--store-url", &url];
        let controller = gateway_operator(&cp, &ns, "ctl", &controller).await?;
        let a = gateway_operator(&cp, &ns, "a", &gateway).await?;
        let slow = ["--status-qps", SLOW_QPS, "--status-qps-max", SLOW_QPS];
        let slow = [&gateway[..], &slow, &["--status-burst", "1"]].concat();
        let b = gateway_operator(&cp, &ns, "b", &slow).await?;
        Ok(Fleet {
            client,
            ns,
            a,
            b,
            controller,
            _pg: pg,
            cp,
        })
    }

    /// Robots `name-0..n`, each with its token.
    async fn robots(&self, name: &str, n: usize) -> anyhow::Result<Vec<(String, String)>> {
        let mut out = Vec::new();
        for i in 0..n {
            let robot = format!("{name}-{i}");
            create_robot(&self.client, &self.ns, &robot, &[]).await?;
            let token = robot_token(&self.client, &self.ns, &robot).await?;
            out.push((robot, token));
        }
        Ok(out)
    }

    /// Connects each robot to `op`.
    async fn connect(
        &self,
        op: &OperatorProcess,
        robots: &[(String, String)],
    ) -> anyhow::Result<Vec<Socket>> {
        let mut sockets = Vec::new();
        for (name, token) in robots {
            let robot = format!("{}/{name}", self.ns);
            let (ws, _) = connect_agent(op, token, &robot)
                .await
                .map_err(|e| anyhow::anyhow!("{name}: {e:?}"))?;
            sockets.push(ws);
        }
        Ok(sockets)
    }

    /// Waits until gateway B's Lease claims robot `name`.
    async fn claimed_by_b(&self, name: &str) -> anyhow::Result<()> {
        let robot = format!("{}/{name}", self.ns);
        wait_for(
            &format!("gw-b's Lease claiming {name}"),
            Duration::from_secs(10),
            || async {
                let claims = self.listed("gw-b", CLAIMS_ANNOTATION).await?;
                claims.contains(&robot).then_some(())
            },
        )
        .await
    }

    /// The robots (`namespace/name`) gateway `gateway`'s Lease lists in `annotation` (none
    /// without it); `None` if the Lease cannot be read.
    async fn listed(&self, gateway: &str, annotation: &str) -> Option<Vec<String>> {
        let leases: Api<Lease> = Api::namespaced(self.client.clone(), &self.ns);
        let lease = leases.get(gateway).await.ok()?;
        let mut annotations = lease.metadata.annotations.unwrap_or_default();
        let value = annotations.remove(annotation).unwrap_or_default();
        Some(parse_claims(&value).collect())
    }

    /// Waits until gateway `gateway`'s Lease lists exactly `names` as marked `Unknown` (none:
    /// has no such list).
    async fn marked_on(&self, gateway: &str, names: &[&str]) -> anyhow::Result<()> {
        let want: Vec<String> = names.iter().map(|n| format!("{}/{n}", self.ns)).collect();
        let what = format!("{gateway}'s Lease listing {names:?} as marked Unknown");
        let found = wait_for(&what, Duration::from_secs(20), || async {
            let robots = self.listed(gateway, MARKED_ANNOTATION).await?;
            (robots == want).then_some(())
        })
        .await;
        match found {
            Ok(()) => Ok(()),
            Err(e) => anyhow::bail!(
                "{e}; it lists {:?}",
                self.listed(gateway, MARKED_ANNOTATION).await
            ),
        }
    }

    /// Lists robot `name` on gateway `gateway`'s Lease as marked `Unknown`, as the Robot
    /// controller does.
    async fn mark(&self, gateway: &str, name: &str) -> anyhow::Result<()> {
        let leases: Api<Lease> = Api::namespaced(self.client.clone(), &self.ns);
        let value = format!("{}/{name}", self.ns);
        let patch =
            serde_json::json!({ "metadata": { "annotations": { MARKED_ANNOTATION: value } } });
        let params = PatchParams {
            field_manager: Some(managers::ROBOT_CONTROLLER.to_owned()),
            ..PatchParams::default()
        };
        leases
            .patch(gateway, &params, &Patch::Merge(&patch))
            .await?;
        Ok(())
    }

    /// Waits until every robot of `names` is Online through `gateway`.
    async fn all_online_via(&self, names: &[&str], gateway: &str) -> anyhow::Result<()> {
        wait_for(
            &format!("{} robots Online via {gateway}", names.len()),
            Duration::from_secs(40),
            || async {
                for name in names {
                    let s = get_robot(&self.client, &self.ns, name).await.ok()?.status?;
                    let online = s.phase == Some(RobotPhase::Online)
                        && s.gateway.as_deref() == Some(gateway);
                    if !online {
                        return None;
                    }
                }
                Some(())
            },
        )
        .await
    }
}

/// Gateway A dies holding 30 robots; 29 reconnect through B at once, next to 8 robots new to B.
#[tokio::test]
async fn moved_robots_skip_unknown_and_go_first() -> anyhow::Result<()> {
    let mut f = Fleet::start().await?;
    let history = Histories::watch(&f.client, &f.ns);
    let on_a = f.robots("kiwi", ON_A).await?;
    let fresh = f.robots("new", FRESH).await?;
    let leaver = f.robots("leaver", 1).await?;
    let sockets_a = f.connect(&f.a, &on_a).await?;
    let leaver_a = f.connect(&f.a, &leaver).await?;
    let names: Vec<&str> = on_a
        .iter()
        .chain(&leaver)
        .map(|(n, _)| n.as_str())
        .collect();
    f.all_online_via(&names, "gw-a").await?;
    // B's Robot watch has seen them on A.
    tokio::time::sleep(Duration::from_secs(1)).await;

    let before = robot_and_event_writes(&f.cp)?;
    f.a.kill();
    let killed = Instant::now();
    drop((sockets_a, leaver_a));
    // The new robots connect first, then the moved ones: B writes the moved ones first anyway.
    let _fresh_b = f.connect(&f.b, &fresh).await?;
    let (moved, lost) = on_a.split_at(ON_A - 1);
    let _moved_b = f.connect(&f.b, moved).await?;
    println!("reconnected {:?} after the kill", killed.elapsed());
    // The leaver comes back last (written last) and leaves once B's Lease claims it.
    let leaver_b = f.connect(&f.b, &leaver).await?;
    let leaver = leaver[0].0.as_str();
    f.claimed_by_b(leaver).await?;
    drop(leaver_b);

    let moved_names: Vec<&str> = moved.iter().map(|(n, _)| n.as_str()).collect();
    f.all_online_via(&moved_names, "gw-b").await?;
    let recovered = killed.elapsed();
    let lost = lost[0].0.as_str();
    let within = Duration::from_secs(20);
    lekiwi_tests::wait_phase(&f.client, &f.ns, lost, RobotPhase::Unknown, within).await?;
    let fresh_names: Vec<&str> = fresh.iter().map(|(n, _)| n.as_str()).collect();
    f.all_online_via(&fresh_names, "gw-b").await?;
    lekiwi_tests::wait_phase(&f.client, &f.ns, leaver, RobotPhase::Offline, within).await?;
    // Room for any late controller write before counting.
    tokio::time::sleep(Duration::from_secs(2 * GATEWAY_LEASE_SECS)).await;
    // The new robots, the lost one and the leaver may cost a status write and an Event each;
    // the rest is what the moved robots cost.
    let writes = robot_and_event_writes(&f.cp)? - before;
    let others = 2.0 * (FRESH + 2) as f64;
    let per_moved = (writes - others).max(0.0) / moved.len() as f64;
    println!(
        "all {} moved robots Online via gw-b {recovered:?} after the kill; {writes} Robot/Event \
         writes, at most {others} of them for the others: {per_moved:.2} per moved robot",
        moved.len()
    );

    // No moved robot showed anything but Online from the kill on.
    let wrong: Vec<_> = moved_names
        .iter()
        .filter(|name| {
            let seen = history.of(name);
            let mut after = seen.iter().filter(|(_, _, t, _)| *t >= killed);
            after.any(|(p, _, _, _)| *p != Some(RobotPhase::Online))
        })
        .collect();
    println!(
        "{} moved robots showed another phase than Online",
        wrong.len()
    );
    // Moved robots are written before the robots merely new to B (at most the first writes of
    // those, taken before the moved ones arrived, go earlier).
    let last_moved = moved_names
        .iter()
        .filter_map(|n| history.online_via(n, "gw-b"))
        .max()
        .expect("moved robots were Online via gw-b");
    let fresh_before = fresh_names
        .iter()
        .filter(|n| {
            history
                .online_via(n, "gw-b")
                .is_some_and(|t| t < last_moved)
        })
        .count();
    println!("{fresh_before} of {FRESH} new robots were written before the last moved one");
    // The leaver's claim was dropped before B wrote it: the controller still counts it as
    // claimed, so it goes from Online through A to Offline through B, nothing in between.
    let left: Vec<_> = history
        .of(leaver)
        .into_iter()
        .filter(|(_, _, t, _)| *t >= killed)
        .map(|(p, g, _, _)| (p, g))
        .collect();
    println!("{leaver} showed {left:?} after the kill");
    let offline_b = (Some(RobotPhase::Offline), Some("gw-b".to_owned()));
    assert_eq!(left, [offline_b], "{leaver} after the kill");
    assert!(wrong.is_empty(), "{wrong:?} left Online after the kill");
    assert!(fresh_before <= 3, "{fresh_before} new robots went first");
    assert!(
        per_moved <= 1.2,
        "{writes} Robot/Event writes for {} moved robots and {others} others",
        moved.len()
    );
    let claimed = f.b.metric("lekiwi_gateway_claimed_robots").await;
    assert_eq!(
        claimed,
        Some(0.0),
        "B claims nothing once its watch shows every write"
    );
    Ok(())
}

/// A status write of gateway A that lands late (A sent it before it died; the API server applies
/// it after A's Lease expired and after the robot's session on B opened, so B's Robot cache did
/// not show the move when the session started): the robot never shows `Unknown`. The controller
/// holds the `Unknown` back for a write that landed after its gateway's Lease expired, and B
/// claims the robot once its watch shows the write (the test prints how many of the robots
/// queued ahead of it B wrote after it).
#[tokio::test]
async fn a_late_write_of_a_dead_gateway_turns_no_robot_unknown() -> anyhow::Result<()> {
    let mut f = Fleet::start().await?;
    let history = Histories::watch(&f.client, &f.ns);
    let queued = f.robots("new", FRESH).await?;
    let late = f.robots("late", 1).await?;
    let name = late[0].0.clone();
    f.a.kill();
    // A's Lease expires.
    tokio::time::sleep(Duration::from_secs(GATEWAY_LEASE_SECS + 2)).await;
    // B's slow writer has FRESH robots to write before the late one; the late one's status
    // names no gateway yet, so its session opens as a robot new to B.
    let _queued_b = f.connect(&f.b, &queued).await?;
    let _late_b = f.connect(&f.b, &late).await?;
    // What A sent before it died: the robot connected through A, with A's earlier epoch.
    let landed = Instant::now();
    let robots: Api<lekiwi_crds::Robot> = Api::namespaced(f.client.clone(), &f.ns);
    let status = serde_json::json!({
        "apiVersion": "fleet.lekiwi.io/v1alpha1",
        "kind": "Robot",
        "metadata": { "name": name },
        "status": {
            "phase": "Online",
            "connected": true,
            "gateway": "gw-a",
            "sessionEpoch": 1,
            "lastHeartbeatTime": jiff::Timestamp::now().to_string(),
        },
    });
    let apply = PatchParams::apply(lekiwi_crds::contract::managers::GATEWAY).force();
    robots
        .patch_status(&name, &apply, &Patch::Apply(&status))
        .await?;
    f.all_online_via(&[name.as_str()], "gw-b").await?;
    let online_b = history
        .seen_online_via(&name, "gw-b")
        .await
        .expect("seen Online via gw-b");
    // Room for a late controller write.
    tokio::time::sleep(Duration::from_secs(2 * GATEWAY_LEASE_SECS)).await;
    let shown: Vec<_> = history
        .of(&name)
        .into_iter()
        .filter(|(_, _, t, _)| *t >= landed)
        .map(|(p, g, _, _)| (p, g))
        .collect();
    println!("{name} showed {shown:?} after the late write");
    let unknown = shown
        .iter()
        .any(|(p, _)| matches!(p, Some(RobotPhase::Unknown | RobotPhase::Offline)));
    assert!(!unknown, "{name} showed {shown:?}");
    let queued_after = queued
        .iter()
        .filter(|(n, _)| history.online_via(n, "gw-b").is_none_or(|t| t > online_b))
        .count();
    println!("{queued_after} of {FRESH} robots queued ahead were written after the late one");
    Ok(())
}

/// A robot of the dead gateway that reconnects only after its Lease expired is `Unknown`
/// meanwhile (rightly), and once back through B it is written before the moves queued ahead of
/// it, which still show `Online`: it is the one robot shown wrong. B writes 3 a second, so the
/// 60 moves take 20 s, longer than A's Lease and the controller take to mark it. The controller
/// lists it on A's Lease as marked `Unknown` (not the moves, which B claims) until B wrote it.
#[tokio::test]
async fn a_robot_shown_unknown_goes_before_the_moves() -> anyhow::Result<()> {
    late_robot_goes_before_the_moves(Late::ShownUnknown).await
}

/// The same robot goes first when nothing but A's Lease tells B it is marked `Unknown`: the
/// controller is stopped before the kill, and the test lists the robot on A's Lease as the
/// controller would, after its session on B opened and without writing it `Unknown` (as when
/// B's Robot watch runs a minute late, which a saturated API server does).
#[tokio::test]
async fn a_robot_listed_as_marked_on_the_dead_gateways_lease_goes_before_the_moves()
-> anyhow::Result<()> {
    late_robot_goes_before_the_moves(Late::Listed).await
}

/// What tells gateway B that the late robot is shown `Unknown`.
#[derive(PartialEq)]
enum Late {
    /// The controller marked it `Unknown`: B's Robot watch shows that, and A's Lease lists it.
    ShownUnknown,
    /// A's Lease alone lists it (no controller runs).
    Listed,
}

/// 60 robots move from A (killed) to B, which writes 3 a second; one more reconnects late, as
/// `late_is` says: it is written before the moves still waiting.
async fn late_robot_goes_before_the_moves(late_is: Late) -> anyhow::Result<()> {
    let mut f = Fleet::start().await?;
    let history = Histories::watch(&f.client, &f.ns);
    let on_a = f.robots("kiwi", 2 * ON_A).await?;
    let late = f.robots("late", 1).await?;
    let sockets_a = f.connect(&f.a, &on_a).await?;
    let late_a = f.connect(&f.a, &late).await?;
    let name = late[0].0.clone();
    let moved: Vec<&str> = on_a.iter().map(|(n, _)| n.as_str()).collect();
    f.all_online_via(&[&moved[..], &[name.as_str()]].concat(), "gw-a")
        .await?;
    tokio::time::sleep(Duration::from_secs(1)).await;

    if late_is == Late::Listed {
        f.controller.kill();
    }
    f.a.kill();
    drop((sockets_a, late_a));
    let _moved_b = f.connect(&f.b, &on_a).await?;
    if late_is == Late::ShownUnknown {
        let within = Duration::from_secs(20);
        lekiwi_tests::wait_phase(&f.client, &f.ns, &name, RobotPhase::Unknown, within).await?;
        f.marked_on("gw-a", &[name.as_str()]).await?;
    } else {
        // A's last renewal was before the kill.
        tokio::time::sleep(Duration::from_secs(GATEWAY_LEASE_SECS + 2)).await;
    }
    // Counted by the API server's order of writes (resourceVersions), not by when the test's
    // watch delivered them: a watch seconds behind makes a robot written first look last.
    let connected = revision_now(&f.client, &f.ns).await?;
    let _late_b = f.connect(&f.b, &late).await?;
    if late_is == Late::Listed {
        // Its session on B is open (connect returns after the welcome): it waits behind the
        // moves until the list reaches B.
        f.mark("gw-a", &name).await?;
    }
    f.all_online_via(&[name.as_str()], "gw-b").await?;
    f.all_online_via(&moved, "gw-b").await?;
    let names = [&moved[..], &[name.as_str()]].concat();
    let versions = wait_for(
        "the test's watch to show them",
        Duration::from_secs(20),
        || {
            let versions: Option<Vec<u64>> = names
                .iter()
                .map(|n| history.online_version(n, "gw-b"))
                .collect();
            async move { versions }
        },
    )
    .await?;
    let (late_version, moves) = versions.split_last().expect("the late robot");
    let waiting = moves.iter().filter(|v| **v > connected).count();
    let after = moves.iter().filter(|v| *v > late_version).count();
    println!("{name} reconnected with {waiting} moves unwritten; {after} were written after it");
    let shown: Vec<_> = history
        .of(&name)
        .into_iter()
        .map(|(p, g, _, _)| (p, g))
        .collect();
    println!("{name} showed {shown:?}");
    assert!(
        waiting >= 10,
        "only {waiting} moves left to overtake: no test"
    );
    // At most the writes in flight or being taken when it connected go before it.
    assert!(
        after + 4 >= waiting,
        "{name} waited behind the moves: {after} of the {waiting} waiting were written after \
         it; gw-b's log of it:\n{}",
        log_of(&f.b, &name)
    );
    match late_is {
        // Written through B, it names B: the controller's list on A's Lease drops it.
        Late::ShownUnknown => f.marked_on("gw-a", &[]).await?,
        Late::Listed => {
            let gone = |p: &Option<RobotPhase>| {
                matches!(p, Some(RobotPhase::Unknown | RobotPhase::Offline))
            };
            assert!(
                !shown.iter().any(|(p, _)| gone(p)),
                "with no controller {name} never shows Unknown: {shown:?}"
            );
        }
    }
    Ok(())
}
