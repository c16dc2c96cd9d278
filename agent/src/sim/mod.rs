//! The fleet simulator: N real agent connections from one process, each with a heartbeat loop,
//! reporting connect time, heartbeat round-trip percentiles, errors and reconnects. Each robot
//! sends telemetry as an agent does (synthetic readings through the agent's own collector) and
//! optionally durable events, counted so a benchmark can compare sent with stored. Every robot
//! carries out the gateway's commands as the agent does ([`commands`]).

pub mod commands;
mod outbox;
mod session;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use clap::Parser;

pub use commands::{CommandArgs, CommandSummary, Fault, Hook};

/// Simulates a fleet of LeKiwi agents against a gateway.
#[derive(Clone, Debug, Parser)]
#[command(
    name = "lekiwi-sim",
    version,
    about = "Simulates a fleet of LeKiwi agents against a gateway: N robot connections from one process"
)]
pub struct Args {
    /// Gateway WebSocket URL; several, comma-separated, spread the robots over them (robot i
    /// uses URL i mod count), e.g. to go past one address pair's ~28,000 ephemeral ports.
    #[arg(
        long,
        env = "LEKIWI_GATEWAY_URL",
        default_value = "ws://127.0.0.1:8081/v1/agent",
        value_delimiter = ','
    )]
    pub gateway: Vec<String>,
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
    /// Stop after this many seconds (default: run until killed). SIGTERM stops the run the
    /// same way: drain (see `--drain-seconds`), write the summary, exit.
    #[arg(long)]
    pub duration: Option<f64>,
    /// Seconds between progress lines.
    #[arg(long, default_value_t = 5.0)]
    pub report_every: f64,
    /// Write the final summary as JSON to this file.
    #[arg(long)]
    pub json: Option<std::path::PathBuf>,
    /// Release every robot runs at start (with a made-up digest, and no files: a rollback to
    /// it downloads nothing); empty: none, as a robot fresh from enrollment.
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
    /// PEM file of the CA certificate(s) to trust for `wss://` gateway URLs (default: the public
    /// web roots), as the agent's `--ca-file`.
    #[arg(long, env = "LEKIWI_CA_FILE")]
    pub ca_file: Option<std::path::PathBuf>,
    /// Seconds to wait for `welcome` (enrollment of a large fleet queues on the gateway).
    #[arg(long, default_value_t = 120.0)]
    pub connect_timeout: f64,
    /// Durable events each robot sends per minute (default: none), kept until acknowledged and
    /// resent after a reconnect; the summary counts generated and acknowledged ones.
    #[arg(long)]
    pub events_per_minute: Option<f64>,
    /// When `--duration` ends, stop making durable messages (events, telemetry batches,
    /// command reports) and wait up to this many seconds for the unacknowledged ones to be
    /// acknowledged before exiting.
    #[arg(long, default_value_t = 0.0)]
    pub drain_seconds: f64,
    /// Share (0 to 1) of the robots that, after losing a session, wait `--late-delay` seconds
    /// more before connecting again, as robots on a poor network would; the same robots every
    /// run (chosen by a hash of the name).
    #[arg(long, default_value_t = 0.0)]
    pub late_share: f64,
    /// Extra wait, seconds, of the robots of `--late-share` before they reconnect.
    #[arg(long, default_value_t = 30.0)]
    pub late_delay: f64,
    /// Seconds every robot's clock is off (negative: behind): the times of its events and
    /// telemetry samples are shifted by this much, as a robot whose clock drifted would send.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    pub clock_offset_seconds: i64,
    /// How the robots carry out commands.
    #[command(flatten)]
    pub commands: CommandArgs,
    /// Seconds between a robot's CPU and network samples (synthetic readings, the agent's
    /// collector and delta compression; memory every 2×, temperature 6×, disk 12×, as the
    /// agent's defaults); heartbeats carry the latest readings. 0: no telemetry, and
    /// heartbeats carry fixed vitals.
    #[arg(long, default_value_t = 5)]
    pub telemetry_interval_s: u64,
    /// Seconds between a robot's telemetry batches (durable `telemetry` messages), as the
    /// agent's `telemetryBatchIntervalS`.
    #[arg(long, default_value_t = 60)]
    pub telemetry_batch_interval_s: u64,
}

impl Args {
    /// The extra wait of robot `name` before it reconnects after losing a session (see
    /// `--late-share`).
    pub(crate) fn late_delay_of(&self, name: &str) -> Duration {
        use std::hash::{Hash, Hasher};
        let mut hasher = std::hash::DefaultHasher::new();
        name.hash(&mut hasher);
        let point = (hasher.finish() % 1_000_000) as f64 / 1_000_000.0;
        if point < self.late_share.clamp(0.0, 1.0) {
            Duration::from_secs_f64(self.late_delay.max(0.0))
        } else {
            Duration::ZERO
        }
    }
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
    events_generated: AtomicU64,
    events_acked: AtomicU64,
    events_resent: AtomicU64,
    telemetry_generated: AtomicU64,
    telemetry_acked: AtomicU64,
    samples_generated: AtomicU64,
    draining: AtomicBool,
}

impl Stats {
    /// Counts an acknowledged heartbeat; its round trip in milliseconds.
    fn record_rtt(&self, rtt: Duration) -> f64 {
        self.heartbeats.fetch_add(1, Ordering::Relaxed);
        lock(&self.rtts_us).push(rtt.as_micros().min(u128::from(u32::MAX)) as u32);
        rtt.as_secs_f64() * 1000.0
    }
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
    /// Durable messages the robots made: events, and their commands' progress reports and
    /// agent update events (the gateway stores each as an event).
    pub events_generated: u64,
    /// Of those, acknowledged by the gateway (an `ack`, or covered by `welcome.stored_seq`).
    pub events_acked: u64,
    /// Durable frames sent again because they were not acknowledged: after a reconnect, or
    /// after a heartbeat interval without an ack (refused, or the ack lost).
    pub events_resent: u64,
    /// What the robots did with the gateway's commands.
    #[serde(flatten)]
    pub commands: CommandSummary,
    /// Telemetry batches (durable `telemetry` messages) the robots made.
    pub telemetry_batches: u64,
    /// Of those, acknowledged by the gateway.
    pub telemetry_batches_acked: u64,
    /// Samples in those batches.
    pub telemetry_samples: u64,
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
    anyhow::ensure!(!args.gateway.is_empty(), "--gateway needs at least one URL");
    let _ = rlimit::increase_nofile_limit(u64::MAX);
    let commands = commands::Shared::new(
        args.commands.clone(),
        &args.gateway,
        args.ca_file.as_deref(),
        &args.release_version,
    )?;
    let fleet = Fleet {
        stats: Arc::new(Stats::default()),
        tokens: load_tokens(&args)?,
        start: Instant::now(),
        commands: Arc::new(commands),
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
/// time and what their commands share.
#[derive(Clone)]
struct Fleet {
    args: Args,
    stats: Arc<Stats>,
    tokens: Tokens,
    start: Instant,
    commands: Arc<commands::Shared>,
}

impl Fleet {
    /// Starts one task per robot, at `--connect-rate` per second.
    async fn spawn_robots(&self) -> Vec<tokio::task::JoinHandle<()>> {
        let mut tasks = Vec::with_capacity(self.args.robots);
        let gap = Duration::from_secs_f64(1.0 / self.args.connect_rate.max(1.0));
        for i in 0..self.args.robots {
            let name = format!("{}-{:05}", self.args.prefix, i + 1);
            let gateway = i % self.args.gateway.len().max(1);
            tasks.push(tokio::spawn(session::robot(self.clone(), name, gateway)));
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
        // SIGTERM ends the run like `--duration` does (drain included), so a script can end it
        // when it has measured what it wanted; without the handler the default kills at once.
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .map_err(|e| eprintln!("lekiwi-sim: no SIGTERM handler: {e}"))
            .ok();
        loop {
            let terminated = match term.as_mut() {
                Some(t) => tokio::select! {
                    _ = t.recv() => true,
                    _ = tokio::time::sleep(Duration::from_millis(200)) => false,
                },
                None => {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                    false
                }
            };
            if last_report.elapsed().as_secs_f64() >= self.args.report_every {
                last_report = Instant::now();
                self.report();
            }
            if terminated || deadline.is_some_and(|d| Instant::now() >= d) {
                self.drain().await;
                break;
            }
            if self.args.exit_when_connected
                && self.stats.ever_connected.load(Ordering::Relaxed) as usize >= self.args.robots
            {
                break;
            }
        }
    }

    /// Whether robots still make new events and telemetry batches (not once the run drains).
    fn generating(&self) -> bool {
        !self.stats.draining.load(Ordering::Relaxed)
    }

    /// Stops new durable messages (events, telemetry batches, command reports) and waits up to
    /// `--drain-seconds` for the rest to be acknowledged. The first look comes a moment after
    /// the stop, so a message a robot was making as it came is counted.
    async fn drain(&self) {
        self.stats.draining.store(true, Ordering::Relaxed);
        let end = Instant::now() + Duration::from_secs_f64(self.args.drain_seconds);
        loop {
            tokio::time::sleep(Duration::from_millis(200)).await;
            if Instant::now() >= end || self.unacked() == 0 {
                break;
            }
        }
        self.report();
    }

    /// Durable messages (events, telemetry batches) made and not acknowledged yet.
    fn unacked(&self) -> u64 {
        let s = &self.stats;
        let made = s.events_generated.load(Ordering::Relaxed)
            + s.telemetry_generated.load(Ordering::Relaxed);
        let acked =
            s.events_acked.load(Ordering::Relaxed) + s.telemetry_acked.load(Ordering::Relaxed);
        made.saturating_sub(acked)
    }

    /// One progress line on stdout.
    fn report(&self) {
        let stats = &self.stats;
        let rtts = take_sorted_rtts(stats);
        println!(
            "[{:>6.1}s] connected {}/{}  heartbeats {}  rtt p50 {:.2} ms p99 {:.2} ms max {:.2} ms  connect errors {}  reconnects {}  error frames {}  events {}  telemetry batches {}  unacked {}  {}",
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
            stats.events_generated.load(Ordering::Relaxed),
            stats.telemetry_generated.load(Ordering::Relaxed),
            self.unacked(),
            self.commands.counters.summary(),
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
            events_generated: stats.events_generated.load(Ordering::Relaxed),
            events_acked: stats.events_acked.load(Ordering::Relaxed),
            events_resent: stats.events_resent.load(Ordering::Relaxed),
            commands: self.commands.counters.summary(),
            telemetry_batches: stats.telemetry_generated.load(Ordering::Relaxed),
            telemetry_batches_acked: stats.telemetry_acked.load(Ordering::Relaxed),
            telemetry_samples: stats.samples_generated.load(Ordering::Relaxed),
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
