//! Subscription fan-out load client for `bench/api.sh`: opens `--subscribers` WebSockets to a
//! gateway's `/api/v1/graphql` (`graphql-transport-ws`, the token in `connection_init`), each
//! subscribing to `robotChanges` of `--namespace` with `--selector`, then flips `--robot`'s
//! phase (Offline/Online, a merge patch of its status with the `KUBECONFIG` credentials)
//! `--rounds` times and measures, for every subscriber, the time from just before the write
//! to the message's receipt. Prints one JSON line: subscribers, rounds, samples, missed, p50,
//! p99 and max in milliseconds.
//!
//! Usage: graphql-fanout --port P --token T --namespace NS --robot NAME --selector SEL
//!        [--subscribers 1000] [--rounds 5]

use std::collections::HashMap;
use std::time::{Duration, Instant};

use anyhow::{Context as _, Result, bail, ensure};
use futures::{SinkExt, StreamExt};
use kube::Api;
use kube::api::{Patch, PatchParams};
use lekiwi_crds::Robot;
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;

/// What one subscriber saw: its index, the robot's phase, when.
type Receipt = (usize, String, Instant);

struct Args {
    port: u16,
    token: String,
    namespace: String,
    robot: String,
    selector: String,
    subscribers: usize,
    rounds: usize,
}

fn args() -> Result<Args> {
    let mut flags: HashMap<String, String> = HashMap::new();
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let value = it.next().with_context(|| format!("{flag} needs a value"))?;
        flags.insert(flag.trim_start_matches("--").to_owned(), value);
    }
    let get = |k: &str| {
        flags
            .get(k)
            .cloned()
            .with_context(|| format!("--{k} is required"))
    };
    Ok(Args {
        port: get("port")?.parse()?,
        token: get("token")?,
        namespace: get("namespace")?,
        robot: get("robot")?,
        selector: get("selector")?,
        subscribers: flags.get("subscribers").map_or(Ok(1000), |v| v.parse())?,
        rounds: flags.get("rounds").map_or(Ok(5), |v| v.parse())?,
    })
}

/// One subscriber: connects, subscribes, reports every change of the robot until closed.
async fn subscriber(
    i: usize,
    a: &Args,
    ready: mpsc::Sender<()>,
    out: mpsc::UnboundedSender<Receipt>,
) -> Result<()> {
    let mut request = format!("ws://127.0.0.1:{}/api/v1/graphql", a.port).into_client_request()?;
    request
        .headers_mut()
        .insert("sec-websocket-protocol", "graphql-transport-ws".parse()?);
    let (mut ws, _) = tokio_tungstenite::connect_async(request).await?;
    let init = json!({"type": "connection_init", "payload": {"authorization": format!("Bearer {}", a.token)}});
    ws.send(Message::text(init.to_string())).await?;
    let query = format!(
        r#"subscription {{ robotChanges(namespace: "{}", labelSelector: "{}") {{ name phase }} }}"#,
        a.namespace, a.selector
    );
    let mut acked = false;
    while let Some(msg) = ws.next().await {
        let text = match msg? {
            Message::Text(text) => text,
            // A refusal (e.g. the per-user connection limit) closes the socket: say why,
            // instead of leaving the run to time out waiting for this subscriber.
            Message::Close(frame) => bail!("subscriber {i}: closed by the gateway: {frame:?}"),
            _ => continue,
        };
        let v: Value = serde_json::from_str(&text)?;
        match v["type"].as_str() {
            Some("connection_ack") if !acked => {
                acked = true;
                let sub = json!({"id": "1", "type": "subscribe", "payload": {"query": query}});
                ws.send(Message::text(sub.to_string())).await?;
                ready.send(()).await?;
            }
            Some("ping") => ws.send(Message::text(r#"{"type":"pong"}"#)).await?,
            Some("next") => {
                let change = &v["payload"]["data"]["robotChanges"];
                if change["name"] == a.robot.as_str() {
                    let phase = change["phase"].as_str().unwrap_or_default().to_owned();
                    let _ = out.send((i, phase, Instant::now()));
                }
            }
            _ => bail!("subscriber {i}: {text}"),
        }
    }
    ensure!(
        acked,
        "subscriber {i}: the connection ended before connection_ack"
    );
    Ok(())
}

async fn set_phase(api: &Api<Robot>, robot: &str, phase: &str) -> Result<Instant> {
    let t0 = Instant::now();
    let status = json!({"status": {"phase": phase}});
    api.patch_status(robot, &PatchParams::default(), &Patch::Merge(&status))
        .await?;
    Ok(t0)
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 * p).ceil() as usize).clamp(1, sorted.len()) - 1]
}

#[tokio::main]
async fn main() -> Result<()> {
    let a: &'static Args = Box::leak(Box::new(args()?));
    let api: Api<Robot> = Api::namespaced(kube::Client::try_default().await?, &a.namespace);
    let (ready_tx, mut ready) = mpsc::channel(a.subscribers);
    let (out, mut receipts) = mpsc::unbounded_channel();
    for i in 0..a.subscribers {
        let (ready_tx, out) = (ready_tx.clone(), out.clone());
        tokio::spawn(async move {
            if let Err(e) = subscriber(i, a, ready_tx, out).await {
                eprintln!("subscriber {i}: {e:#}");
            }
        });
    }
    for _ in 0..a.subscribers {
        tokio::time::timeout(Duration::from_secs(120), ready.recv())
            .await?
            .context("a subscriber failed")?;
    }
    // Warm-up: flip until every subscriber has seen a change (all subscriptions are live).
    let mut seen = vec![false; a.subscribers];
    for flip in 0.. {
        ensure!(
            flip < 60,
            "after 60 flips only {} subscribers saw a change",
            seen.iter().filter(|s| **s).count()
        );
        set_phase(&api, &a.robot, ["Unknown", "Offline"][flip % 2]).await?;
        let until = Instant::now() + Duration::from_secs(1);
        while let Ok(Some((i, _, _))) = tokio::time::timeout_at(until.into(), receipts.recv()).await
        {
            seen[i] = true;
        }
        if seen.iter().all(|s| *s) {
            break;
        }
    }
    let (mut samples, mut missed) = (Vec::new(), 0);
    for round in 0..a.rounds {
        let phase = ["Online", "Offline"][round % 2];
        let t0 = set_phase(&api, &a.robot, phase).await?;
        let mut got = vec![false; a.subscribers];
        let until = Instant::now() + Duration::from_secs(10);
        while got.iter().any(|g| !*g) {
            match tokio::time::timeout_at(until.into(), receipts.recv()).await {
                Ok(Some((i, p, at))) if p == phase && !got[i] => {
                    got[i] = true;
                    samples.push(at.duration_since(t0).as_secs_f64() * 1000.0);
                }
                Ok(Some(_)) => {}
                _ => break,
            }
        }
        missed += got.iter().filter(|g| !**g).count();
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    samples.sort_by(f64::total_cmp);
    let report = json!({
        "subscribers": a.subscribers, "rounds": a.rounds, "samples": samples.len(), "missed": missed,
        "p50_ms": percentile(&samples, 0.5), "p99_ms": percentile(&samples, 0.99),
        "max_ms": samples.last().copied().unwrap_or(f64::NAN),
    });
    println!("{report}");
    Ok(())
}
