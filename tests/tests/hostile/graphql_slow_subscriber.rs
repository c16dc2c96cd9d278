//! A GraphQL subscriber that stops reading slows no one (issue 15: "throttled per subscriber,
//! latest state wins; a slow client never slows the gateway"). Against the real API server, a
//! gateway serves two subscribers of the same 40 Robots: one reads, one stops reading after its
//! `connection_ack` with a 4 KiB kernel receive buffer and asks for about 40 KB per change (its
//! robots' names under 2,000 aliases). 3,600 status changes (90 rounds) would be over 86 MB to
//! the stalled one; 90 rounds, not 30, because the gateway's RSS wobbles by ~10 MiB whatever the
//! backlog, which 30 rounds' 28 MB could not tell apart (a CI failure). The reading one still
//! sees every robot's last phase and then a marker change; the gateway's memory grows by far
//! less than the stalled one's backlog; when the stalled one reads again it gets the latest
//! phase of every robot, in far fewer messages than there were changes (the ones it missed were
//! folded, not queued).

use std::collections::HashMap;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, ensure};
use futures::StreamExt;
use k8s_openapi::api::rbac::v1::ClusterRole;
use kube::Api;
use kube::api::{DeleteParams, Patch, PatchParams};
use lekiwi_crds::Robot;
use lekiwi_tests::graphql::{Ws, connect_with_buffer, init, next, open, subscribe};
use lekiwi_tests::{ControlPlane, OperatorProcess, account, chart_roles, create_robot, namespace};
use serde_json::json;

const ROBOTS: usize = 40;
const ROUNDS: usize = 90;
const PHASES: [&str; 3] = ["Offline", "Unknown", "Maintenance"];
const ALIASES: usize = 2_000;

/// The gateway's resident memory, bytes.
fn rss(op: &OperatorProcess) -> Result<u64> {
    let status = std::fs::read_to_string(format!("/proc/{}/status", op.pid()))?;
    let kib: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .context("no VmRSS")?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()?;
    Ok(kib * 1024)
}

/// Sets every robot's phase to `phase`, eight patches at a time.
async fn set_all(api: &Api<Robot>, phase: &str) -> Result<()> {
    let patches = (0..ROBOTS).map(|i| {
        let status = json!({"status": {"phase": phase}});
        async move {
            api.patch_status(
                &format!("kiwi-{i}"),
                &PatchParams::default(),
                &Patch::Merge(&status),
            )
            .await
        }
    });
    let results: Vec<_> = futures::stream::iter(patches)
        .buffer_unordered(8)
        .collect()
        .await;
    for r in results {
        r?;
    }
    Ok(())
}

/// Reads `robotChanges` messages of operation `id` into `last` (robot → phase) until `done`
/// holds of it, or nothing comes for `idle`; how many changes were read.
async fn read_changes(
    ws: &mut Ws,
    id: &str,
    last: &mut HashMap<String, String>,
    idle: Duration,
    done: impl Fn(&HashMap<String, String>) -> bool,
) -> Result<usize> {
    let mut read = 0;
    while !done(last) {
        let Ok(msg) = next(ws, idle).await else {
            break;
        };
        ensure!(msg["type"] == "next" && msg["id"] == id, "{msg}");
        let change = &msg["payload"]["data"]["robotChanges"];
        let name = change["name"].as_str().context("a name")?;
        let phase = change["phase"].as_str().context("a phase")?;
        last.insert(name.to_owned(), phase.to_owned());
        read += 1;
    }
    Ok(read)
}

/// Whether every robot was last seen in `phase` (kiwi-0 in `first`).
fn all_in(last: &HashMap<String, String>, first: &str, phase: &str) -> bool {
    (0..ROBOTS).all(|i| {
        let want = if i == 0 { first } else { phase };
        last.get(&format!("kiwi-{i}")).map(String::as_str) == Some(want)
    })
}

/// The reading subscriber, subscribed once a change of kiwi-0 arrives through it.
async fn reader(op: &OperatorProcess, api: &Api<Robot>, ns: &str, token: &str) -> Result<Ws> {
    let mut ws = open(op, token).await?;
    ensure!(next(&mut ws, Duration::from_secs(30)).await?["type"] == "connection_ack");
    let query = format!(r#"subscription {{ robotChanges(namespace: "{ns}") {{ name phase }} }}"#);
    subscribe(&mut ws, "reader", &query).await?;
    for phase in PHASES.iter().cycle().take(60) {
        let status = json!({"status": {"phase": phase}});
        api.patch_status("kiwi-0", &PatchParams::default(), &Patch::Merge(&status))
            .await?;
        if next(&mut ws, Duration::from_secs(1)).await.is_ok() {
            return Ok(ws);
        }
    }
    anyhow::bail!("no change of kiwi-0 reached the reading subscriber")
}

/// The stalled subscriber: acknowledged and subscribed, then never read until the end.
async fn stalled(op: &OperatorProcess, ns: &str, token: &str) -> Result<Ws> {
    let mut ws = connect_with_buffer(op, Some(4096)).await?;
    init(&mut ws, token).await?;
    ensure!(next(&mut ws, Duration::from_secs(30)).await?["type"] == "connection_ack");
    let aliases: String = (0..ALIASES).map(|i| format!(" a{i}: name")).collect();
    let query =
        format!(r#"subscription {{ robotChanges(namespace: "{ns}") {{ name phase{aliases} }} }}"#);
    subscribe(&mut ws, "stalled", &query).await?;
    Ok(ws)
}

#[tokio::test]
async fn a_subscriber_that_never_reads_slows_no_one() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "gqlslow").await?;
    let roles = chart_roles(cp, &client, &ns).await?;
    let viewer = account(cp, &client, &ns, "viewer", Some(&roles[0])).await?;
    for i in 0..ROBOTS {
        create_robot(&client, &ns, &format!("kiwi-{i}"), &[]).await?;
    }
    let args = ["--role", "gateway", "--api-burst", "200"];
    let op = lekiwi_tests::gateway_operator(cp, &ns, "gqlslow", &args).await?;
    let api = Api::<Robot>::namespaced(client.clone(), &ns);
    let mut reading = reader(&op, &api, &ns, &viewer).await?;
    let mut stalled = stalled(&op, &ns, &viewer).await?;
    let rss_before = rss(&op)?;

    // 3,600 changes; the reader keeps up (it reads while the patches go on).
    let final_phase = PHASES[(ROUNDS - 1) % PHASES.len()];
    let flood = {
        let api = api.clone();
        tokio::spawn(async move {
            for round in 0..ROUNDS {
                set_all(&api, PHASES[round % PHASES.len()]).await?;
            }
            anyhow::Ok(())
        })
    };
    let mut seen = HashMap::new();
    let read = read_changes(
        &mut reading,
        "reader",
        &mut seen,
        Duration::from_secs(30),
        |l| flood.is_finished() && all_in(l, final_phase, final_phase),
    )
    .await?;
    flood.await??;
    ensure!(
        all_in(&seen, final_phase, final_phase),
        "the reader stopped seeing changes: {seen:?}"
    );
    let rss_flooded = rss(&op)?;

    // A marker change reaches the reader while the stalled one still reads nothing.
    let marked = Instant::now();
    let status = json!({"status": {"phase": "Online"}});
    api.patch_status("kiwi-0", &PatchParams::default(), &Patch::Merge(&status))
        .await?;
    read_changes(
        &mut reading,
        "reader",
        &mut seen,
        Duration::from_secs(30),
        |l| all_in(l, "Online", final_phase),
    )
    .await?;
    let marker_latency = marked.elapsed();
    ensure!(
        all_in(&seen, "Online", final_phase),
        "the marker never reached the reader: {seen:?}"
    );

    // The stalled one reads at last: the latest phase of every robot, folded.
    let mut last = HashMap::new();
    let folded = read_changes(
        &mut stalled,
        "stalled",
        &mut last,
        Duration::from_secs(30),
        |l| all_in(l, "Online", final_phase),
    )
    .await?;
    ensure!(
        all_in(&last, "Online", final_phase),
        "the stalled subscriber did not get every robot's latest phase: {last:?}"
    );
    let changes = ROUNDS * ROBOTS + 1;
    let backlog = changes * (ALIASES * 12);
    let grew = rss_flooded.saturating_sub(rss_before);
    println!(
        "changes {changes}; reader read {read} then saw the marker after {marker_latency:?}; \
         the stalled subscriber's backlog would have been {} MB, it read {folded} messages; \
         gateway RSS {} -> {} MiB",
        backlog / 1_000_000,
        rss_before >> 20,
        rss_flooded >> 20
    );
    ensure!(
        folded < changes / 2,
        "the stalled subscriber got {folded} of {changes} changes: they were queued, not folded"
    );
    ensure!(
        grew < (backlog as u64) / 3,
        "the gateway grew by {} MiB while one subscriber stalled",
        grew >> 20
    );
    for role in roles {
        Api::<ClusterRole>::all(client.clone())
            .delete(&role, &DeleteParams::default())
            .await?;
    }
    Ok(())
}
