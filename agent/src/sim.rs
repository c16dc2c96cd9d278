//! The fleet simulator: N real agent connections from one process, each with a heartbeat loop,
//! reporting connect time, heartbeat round-trip percentiles, errors and reconnects.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use clap::Parser;
use futures::{SinkExt, StreamExt};
use lekiwi_protocol::{
    AgentMessage, ErrorCode, Health, PROTOCOL_VERSION, Release, ServerMessage, SystemFacts,
    Teleoperation, Vitals, decode, encode,
};
use rand::Rng;
use tokio_tungstenite::tungstenite::Message;

use crate::connection::{ConnectError, Credentials, connect};

/// Simulates a fleet of LeKiwi agents against a gateway.
#[derive(Clone, Debug, Parser)]
#[command(name = "lekiwi-sim", version, about)]
pub struct Args {
    /// Gateway WebSocket URL.
    #[arg(
        long,
        env = "LEKIWI_GATEWAY_URL",
        default_value = "ws://127.0.0.1:8081/v1/agent"
    )]
    pub gateway: String,
    /// Fleet enrollment token (robots enroll on first connect and keep their own token).
    #[arg(long, env = "LEKIWI_ENROLLMENT_TOKEN")]
    pub enrollment_token: String,
    /// Namespace the robots belong to.
    #[arg(long, default_value = "lekiwi-demo")]
    pub namespace: String,
    /// Number of robots.
    #[arg(long, default_value_t = 20)]
    pub robots: usize,
    /// Robot names are PREFIX-00001, PREFIX-00002, ...
    #[arg(long, default_value = "sim")]
    pub prefix: String,
    /// Heartbeat interval in seconds (default: what the gateway says).
    #[arg(long)]
    pub heartbeat_interval: Option<f64>,
    /// New connections per second while ramping up.
    #[arg(long, default_value_t = 500.0)]
    pub connect_rate: f64,
    /// Stop after this many seconds (default: run until killed).
    #[arg(long)]
    pub duration: Option<f64>,
    /// Seconds between progress lines.
    #[arg(long, default_value_t = 5.0)]
    pub report_every: f64,
    /// Write the final summary as JSON to this file.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    /// Release the robots report (version:sha256hex).
    #[arg(long, default_value = "1.0.0")]
    pub release_version: String,
    /// Keep the robots' own tokens in this JSON file (name → token), as real agents keep theirs
    /// in their state directory: robots found in it connect with their token instead of
    /// enrolling again.
    #[arg(long)]
    pub token_file: Option<std::path::PathBuf>,
    /// Exit as soon as every robot has connected once.
    #[arg(long)]
    pub exit_when_connected: bool,
    /// Seconds to wait for `welcome` (enrollment of a large fleet queues on the gateway).
    #[arg(long, default_value_t = 120.0)]
    pub connect_timeout: f64,
}

type Tokens = Arc<Mutex<std::collections::BTreeMap<String, String>>>;

fn save_tokens(path: &std::path::Path, tokens: &Tokens) -> anyhow::Result<()> {
    let json = serde_json::to_string(&*lock(tokens))?;
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, json)?;
    std::fs::rename(tmp, path)?;
    Ok(())
}

#[derive(Default)]
struct Stats {
    connected: AtomicU64,
    ever_connected: AtomicU64,
    connect_errors: AtomicU64,
    reconnects: AtomicU64,
    error_frames: AtomicU64,
    heartbeats: AtomicU64,
    rtts_us: Mutex<Vec<u32>>,
    all_connected_after: Mutex<Option<Duration>>,
}

/// Summary of a run.
#[derive(Debug, serde::Serialize)]
pub struct Summary {
    /// Robots simulated (`--robots`).
    pub robots: usize,
    /// Robots connected at the end.
    pub connected: u64,
    /// Seconds until every robot had connected once (None if some never did).
    pub all_connected_seconds: Option<f64>,
    /// Heartbeats acknowledged.
    pub heartbeats: u64,
    /// Median heartbeat round trip, milliseconds.
    pub rtt_p50_ms: f64,
    /// 99th percentile of the heartbeat round trip, milliseconds.
    pub rtt_p99_ms: f64,
    /// Slowest heartbeat round trip, milliseconds.
    pub rtt_max_ms: f64,
    /// Failed connection attempts.
    pub connect_errors: u64,
    /// Sessions re-established after a drop.
    pub reconnects: u64,
    /// Error frames the gateway sent (rate limits, refusals, replacements).
    pub error_frames: u64,
}

fn percentile(sorted: &[u32], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let idx = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    f64::from(sorted[idx.min(sorted.len() - 1)]) / 1000.0
}

/// Runs the simulation and returns its summary.
pub async fn run(args: Args) -> anyhow::Result<Summary> {
    let _ = rlimit::increase_nofile_limit(u64::MAX);
    let fleet = Fleet {
        stats: Arc::new(Stats::default()),
        tokens: load_tokens(&args)?,
        start: Instant::now(),
        release: Release {
            version: args.release_version.clone(),
            digest: format!("sha256:{}", "0".repeat(64)),
        },
        args,
    };
    let tasks = fleet.spawn_robots().await;
    fleet.wait_until_done().await;
    for t in &tasks {
        t.abort();
    }
    if let Some(path) = &fleet.args.token_file {
        save_tokens(path, &fleet.tokens)?;
    }
    let summary = fleet.summary();
    if let Some(path) = &fleet.args.json {
        std::fs::write(path, serde_json::to_string_pretty(&summary)?)?;
    }
    Ok(summary)
}

/// The robots' tokens from `--token-file`, if it exists.
fn load_tokens(args: &Args) -> anyhow::Result<Tokens> {
    Ok(Arc::new(Mutex::new(match &args.token_file {
        Some(path) if path.exists() => serde_json::from_str(&std::fs::read_to_string(path)?)?,
        _ => Default::default(),
    })))
}

/// What every simulated robot shares: the arguments, the counters, the token store, the start
/// time and the release they all report.
#[derive(Clone)]
struct Fleet {
    args: Args,
    stats: Arc<Stats>,
    tokens: Tokens,
    start: Instant,
    release: Release,
}

impl Fleet {
    /// Starts one task per robot, at `--connect-rate` per second.
    async fn spawn_robots(&self) -> Vec<tokio::task::JoinHandle<()>> {
        let mut tasks = Vec::with_capacity(self.args.robots);
        let gap = Duration::from_secs_f64(1.0 / self.args.connect_rate.max(1.0));
        for i in 0..self.args.robots {
            let name = format!("{}-{:05}", self.args.prefix, i + 1);
            tasks.push(tokio::spawn(robot(self.clone(), name)));
            tokio::time::sleep(gap).await;
        }
        tasks
    }

    /// Prints progress every `--report-every` seconds until `--duration` ends or, with
    /// `--exit-when-connected`, every robot has connected once.
    async fn wait_until_done(&self) {
        let deadline = self
            .args
            .duration
            .map(|d| self.start + Duration::from_secs_f64(d));
        let mut last_report = Instant::now();
        loop {
            tokio::time::sleep(Duration::from_millis(200)).await;
            if last_report.elapsed().as_secs_f64() >= self.args.report_every {
                last_report = Instant::now();
                self.report();
            }
            if deadline.is_some_and(|d| Instant::now() >= d)
                || (self.args.exit_when_connected
                    && self.stats.ever_connected.load(Ordering::Relaxed) as usize
                        >= self.args.robots)
            {
                break;
            }
        }
    }

    /// One progress line on stdout.
    fn report(&self) {
        let stats = &self.stats;
        let rtts = take_sorted_rtts(stats);
        println!(
            "[{:>6.1}s] connected {}/{}  heartbeats {}  rtt p50 {:.2} ms p99 {:.2} ms max {:.2} ms  connect errors {}  reconnects {}  error frames {}",
            self.start.elapsed().as_secs_f64(),
            stats.connected.load(Ordering::Relaxed),
            self.args.robots,
            stats.heartbeats.load(Ordering::Relaxed),
            percentile(&rtts, 0.5),
            percentile(&rtts, 0.99),
            percentile(&rtts, 1.0),
            stats.connect_errors.load(Ordering::Relaxed),
            stats.reconnects.load(Ordering::Relaxed),
            stats.error_frames.load(Ordering::Relaxed),
        );
        // Keep them for the final summary too.
        lock(&stats.rtts_us).extend(rtts);
    }

    fn summary(&self) -> Summary {
        let stats = &self.stats;
        let rtts = take_sorted_rtts(stats);
        Summary {
            robots: self.args.robots,
            connected: stats.connected.load(Ordering::Relaxed),
            all_connected_seconds: lock(&stats.all_connected_after).map(|d| d.as_secs_f64()),
            heartbeats: stats.heartbeats.load(Ordering::Relaxed),
            rtt_p50_ms: percentile(&rtts, 0.5),
            rtt_p99_ms: percentile(&rtts, 0.99),
            rtt_max_ms: percentile(&rtts, 1.0),
            connect_errors: stats.connect_errors.load(Ordering::Relaxed),
            reconnects: stats.reconnects.load(Ordering::Relaxed),
            error_frames: stats.error_frames.load(Ordering::Relaxed),
        }
    }

    /// Counts a session: the first of a robot (noting when the whole fleet had connected
    /// once), or a reconnect.
    fn count_session(&self, first: bool) {
        let stats = &self.stats;
        if first {
            let n = stats.ever_connected.fetch_add(1, Ordering::Relaxed) + 1;
            if n as usize == self.args.robots {
                *lock(&stats.all_connected_after) = Some(self.start.elapsed());
            }
        } else {
            stats.reconnects.fetch_add(1, Ordering::Relaxed);
        }
        stats.connected.fetch_add(1, Ordering::Relaxed);
    }
}

/// Locks a mutex of the counters; a panicked robot task does not poison them for the rest.
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// The round trips measured since the last call, sorted.
fn take_sorted_rtts(stats: &Stats) -> Vec<u32> {
    let mut rtts = std::mem::take(&mut *lock(&stats.rtts_us));
    rtts.sort_unstable();
    rtts
}

/// The `hello` of a simulated robot: a Raspberry Pi running the fleet's release.
fn hello(name: &str, release: &Release) -> AgentMessage {
    AgentMessage::Hello {
        protocol_version: PROTOCOL_VERSION,
        agent_version: concat!("sim-", env!("CARGO_PKG_VERSION")).to_owned(),
        system: SystemFacts {
            hostname: Some(name.to_owned()),
            os: Some("Debian GNU/Linux 12 (bookworm)".into()),
            arch: Some("aarch64".into()),
            cpus: Some(4),
            memory_bytes: Some(8 << 30),
            kernel: None,
        },
        current_release: Some(release.clone()),
        last_acked_seq: None,
        health: Some(Health {
            healthy: true,
            message: None,
        }),
        teleoperation: Some(Teleoperation {
            active: false,
            score: Some(0.0),
        }),
    }
}

/// One simulated robot: connects (enrolling the first time), heartbeats until the session
/// ends, and reconnects with backoff, forever.
async fn robot(fleet: Fleet, name: String) {
    let args = &fleet.args;
    let own = lock(&fleet.tokens).get(&name).cloned();
    let mut creds = Credentials {
        token: own.unwrap_or_else(|| args.enrollment_token.clone()),
        robot: format!("{}/{}", args.namespace, name),
    };
    let mut first = true;
    let mut backoff =
        crate::backoff::Backoff::new(Duration::from_millis(500), Duration::from_secs(30));
    let timeout = Duration::from_secs_f64(args.connect_timeout);
    loop {
        let mut retry_after = Duration::ZERO;
        match connect(
            &args.gateway,
            &creds,
            &hello(&name, &fleet.release),
            timeout,
        )
        .await
        {
            Ok((ws, welcome)) => {
                backoff.reset();
                if let Some(token) = welcome.robot_token.clone() {
                    lock(&fleet.tokens).insert(name.clone(), token.clone());
                    creds.token = token;
                }
                creds.robot = welcome.robot.clone();
                fleet.count_session(std::mem::take(&mut first));
                let interval = args
                    .heartbeat_interval
                    .map(Duration::from_secs_f64)
                    .unwrap_or(welcome.heartbeat_interval);
                heartbeats(ws, interval, &fleet.stats).await;
                fleet.stats.connected.fetch_sub(1, Ordering::Relaxed);
            }
            Err(e) => {
                fleet.stats.connect_errors.fetch_add(1, Ordering::Relaxed);
                retry_after = e.retry_after().unwrap_or_default();
                if matches!(e, ConnectError::Unauthorized(_)) {
                    eprintln!("{name}: {e}");
                    // A stale token (rotated elsewhere): enroll again.
                    creds.token = args.enrollment_token.clone();
                }
            }
        }
        // Full jitter, so a fleet does not come back in lockstep; a gateway's `Retry-After`
        // (a 429, or enrollment admission's 503) comes first, as the agent does it.
        tokio::time::sleep(retry_after + backoff.next_delay()).await;
    }
}

async fn heartbeats(ws: crate::connection::Socket, interval: Duration, stats: &Stats) {
    let (mut tx, mut rx) = ws.split();
    // Spread the first heartbeat over one interval.
    let offset = rand::rng().random_range(Duration::ZERO..=interval);
    let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + offset, interval);
    let mut pending: Option<(i64, Instant)> = None;
    let mut last_rtt: Option<f64> = None;
    loop {
        tokio::select! {
            _ = tick.tick() => {
                let sent_at_ms = lekiwi_protocol::now_ms();
                let hb = AgentMessage::Heartbeat {
                    sent_at_ms,
                    rtt_ms: last_rtt,
                    vitals: Vitals { cpu_percent: Some(12.0), memory_percent: Some(30.0), temperature_c: Some(50.0), ..Vitals::default() },
                    current_release: None,
                    health: None,
                    teleoperation: None,
                };
                pending = Some((sent_at_ms, Instant::now()));
                if tx.send(Message::text(encode(&hb))).await.is_err() {
                    return;
                }
            }
            frame = rx.next() => {
                let Some(Ok(frame)) = frame else { return };
                let Message::Text(text) = frame else {
                    if matches!(frame, Message::Close(_)) { return; }
                    continue;
                };
                match decode::<ServerMessage>(text.as_str(), usize::MAX) {
                    Ok(ServerMessage::HeartbeatAck { sent_at_ms, .. }) => {
                        if let Some((sent, at)) = pending.take_if(|(s, _)| *s == sent_at_ms) {
                            let _ = sent;
                            let rtt = at.elapsed();
                            last_rtt = Some(rtt.as_secs_f64() * 1000.0);
                            stats.heartbeats.fetch_add(1, Ordering::Relaxed);
                            lock(&stats.rtts_us).push(rtt.as_micros().min(u128::from(u32::MAX)) as u32);
                        }
                    }
                    Ok(ServerMessage::Error { code, fatal, .. }) => {
                        stats.error_frames.fetch_add(1, Ordering::Relaxed);
                        if fatal || code == ErrorCode::Replaced {
                            return;
                        }
                    }
                    _ => {}
                }
            }
        }
    }
}
