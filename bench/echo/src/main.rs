//! `lekiwi-bench-echo`: the floor of the gateway benchmark. A bare tokio-tungstenite server that
//! speaks just enough of the agent protocol for `lekiwi-sim` (`hello` → `welcome`, `heartbeat` →
//! `heartbeat_ack`), with no authentication, no Kubernetes and no storage, so the round trip it
//! gives is what the loopback network, the WebSocket layer and JSON cost on this machine.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};

use anyhow::Context as _;
use clap::Parser;
use futures::{SinkExt, StreamExt};
use lekiwi_protocol::{
    AGENT_PATH, AgentMessage, ErrorCode, MAX_FRAME_BYTES, PROTOCOL_VERSION, ROBOT_HEADER,
    ServerMessage, decode, encode,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::StatusCode;
use tokio_tungstenite::tungstenite::protocol::WebSocketConfig;

/// Number of finite RTT histogram buckets. The bounds are the gateway's own
/// (`exponential_buckets(0.0005, 2.0, 14)`: 0.5 ms, 1 ms, ... 4.096 s), so the benchmark reads the
/// floor and the gateway the same way.
const BUCKETS: usize = 14;

/// A bare WebSocket server acknowledging agent heartbeats: the floor for the gateway benchmark.
#[derive(Debug, Parser)]
#[command(name = "lekiwi-bench-echo", version, about)]
struct Args {
    /// Address of the WebSocket endpoint (`/v1/agent`).
    #[arg(
        long,
        env = "LEKIWI_BENCH_ECHO_LISTEN",
        default_value = "127.0.0.1:8091"
    )]
    listen: SocketAddr,

    /// Address of a plain-HTTP `/metrics` endpoint (Prometheus text format); off without it.
    #[arg(long, env = "LEKIWI_BENCH_ECHO_METRICS")]
    metrics: Option<SocketAddr>,

    /// Heartbeat interval announced in `welcome`, seconds.
    #[arg(
        long,
        env = "LEKIWI_BENCH_ECHO_HEARTBEAT_INTERVAL",
        default_value_t = 5
    )]
    heartbeat_interval: u32,
}

/// Counters shared by all sessions; lock-free so that measuring costs nothing noticeable.
#[derive(Default)]
struct Stats {
    connections: AtomicI64,
    sessions: AtomicU64,
    heartbeats: AtomicU64,
    error_frames: AtomicU64,
    /// Non-cumulative counts per bucket; the last one is `+Inf`.
    rtt_buckets: [AtomicU64; BUCKETS + 1],
    rtt_sum_us: AtomicU64,
}

fn bucket_bound(i: usize) -> f64 {
    0.0005 * f64::from(1u32 << i)
}

impl Stats {
    /// Records the round trip of the previous heartbeat, as the agent reports it.
    fn observe_rtt(&self, rtt_ms: f64) {
        let seconds = rtt_ms / 1000.0;
        let bucket = (0..BUCKETS)
            .find(|&i| seconds <= bucket_bound(i))
            .unwrap_or(BUCKETS);
        self.rtt_buckets[bucket].fetch_add(1, Ordering::Relaxed);
        self.rtt_sum_us
            .fetch_add((rtt_ms * 1000.0).round() as u64, Ordering::Relaxed);
    }

    /// Prometheus text exposition, with the same histogram layout as the gateway's
    /// `lekiwi_gateway_heartbeat_rtt_seconds`.
    fn render(&self) -> String {
        let mut out = String::new();
        let mut line = |s: String| {
            out.push_str(&s);
            out.push('\n');
        };
        line("# TYPE lekiwi_bench_echo_connections gauge".into());
        line(format!(
            "lekiwi_bench_echo_connections {}",
            self.connections.load(Ordering::Relaxed)
        ));
        line("# TYPE lekiwi_bench_echo_sessions_total counter".into());
        line(format!(
            "lekiwi_bench_echo_sessions_total {}",
            self.sessions.load(Ordering::Relaxed)
        ));
        line("# TYPE lekiwi_bench_echo_heartbeats_total counter".into());
        line(format!(
            "lekiwi_bench_echo_heartbeats_total {}",
            self.heartbeats.load(Ordering::Relaxed)
        ));
        line("# TYPE lekiwi_bench_echo_error_frames_total counter".into());
        line(format!(
            "lekiwi_bench_echo_error_frames_total {}",
            self.error_frames.load(Ordering::Relaxed)
        ));
        line("# TYPE lekiwi_bench_echo_heartbeat_rtt_seconds histogram".into());
        let mut cumulative = 0;
        for (i, bucket) in self.rtt_buckets.iter().enumerate() {
            cumulative += bucket.load(Ordering::Relaxed);
            let le = if i < BUCKETS {
                bucket_bound(i).to_string()
            } else {
                "+Inf".to_owned()
            };
            line(format!(
                "lekiwi_bench_echo_heartbeat_rtt_seconds_bucket{{le=\"{le}\"}} {cumulative}"
            ));
        }
        line(format!(
            "lekiwi_bench_echo_heartbeat_rtt_seconds_sum {}",
            self.rtt_sum_us.load(Ordering::Relaxed) as f64 / 1e6
        ));
        line(format!(
            "lekiwi_bench_echo_heartbeat_rtt_seconds_count {cumulative}"
        ));
        out
    }
}

/// One agent connection: upgrade at `/v1/agent`, then answer frames until it closes.
async fn session(stream: TcpStream, stats: Arc<Stats>, heartbeat_interval_s: u32) {
    let mut robot = None;
    // The signature is tungstenite's handshake `Callback`; its error type is not ours to shrink.
    #[allow(clippy::result_large_err)]
    let callback = |req: &Request, resp: Response| -> Result<Response, ErrorResponse> {
        if req.uri().path() != AGENT_PATH {
            let mut refusal = ErrorResponse::new(Some(format!("only {AGENT_PATH} is served\n")));
            *refusal.status_mut() = StatusCode::NOT_FOUND;
            return Err(refusal);
        }
        robot = req
            .headers()
            .get(ROBOT_HEADER)
            .and_then(|v| v.to_str().ok())
            .map(str::to_owned);
        Ok(resp)
    };
    // The gateway's socket settings (see `operator/gateway/src/lib.rs`), so only the work
    // behind the socket differs.
    let config = WebSocketConfig::default()
        .read_buffer_size(2 * 1024)
        .write_buffer_size(0)
        .max_message_size(Some(MAX_FRAME_BYTES * 4))
        .max_frame_size(Some(MAX_FRAME_BYTES * 4));
    let Ok(mut ws) =
        tokio_tungstenite::accept_hdr_async_with_config(stream, callback, Some(config)).await
    else {
        return;
    };
    let robot = robot.unwrap_or_else(|| "bench/x".to_owned());
    stats.connections.fetch_add(1, Ordering::Relaxed);
    stats.sessions.fetch_add(1, Ordering::Relaxed);
    while let Some(Ok(frame)) = ws.next().await {
        let text = match frame {
            Message::Text(t) => t,
            Message::Close(_) => break,
            _ => continue,
        };
        let reply = answer(text.as_str(), &robot, &stats, heartbeat_interval_s);
        if ws.send(Message::text(encode(&reply))).await.is_err() {
            break;
        }
    }
    stats.connections.fetch_sub(1, Ordering::Relaxed);
}

/// The echo server's reply to one text frame: `welcome` for `hello`, an ack for a heartbeat,
/// an error frame for anything else.
fn answer(frame: &str, robot: &str, stats: &Stats, heartbeat_interval_s: u32) -> ServerMessage {
    match decode::<AgentMessage>(frame, MAX_FRAME_BYTES) {
        Ok(AgentMessage::Hello { .. }) => ServerMessage::Welcome {
            protocol_version: PROTOCOL_VERSION,
            robot: robot.to_owned(),
            heartbeat_interval_s,
            max_frame_bytes: MAX_FRAME_BYTES,
            max_messages_per_second: 20,
            stored_seq: None,
            robot_token: None,
        },
        Ok(AgentMessage::Heartbeat {
            sent_at_ms, rtt_ms, ..
        }) => {
            if let Some(rtt) = rtt_ms.filter(|r| r.is_finite() && *r >= 0.0) {
                stats.observe_rtt(rtt);
            }
            stats.heartbeats.fetch_add(1, Ordering::Relaxed);
            ServerMessage::HeartbeatAck {
                sent_at_ms,
                server_time_ms: lekiwi_protocol::now_ms(),
            }
        }
        Ok(other) => {
            stats.error_frames.fetch_add(1, Ordering::Relaxed);
            ServerMessage::Error {
                code: ErrorCode::UnexpectedMessage,
                message: "the benchmark echo server answers only hello and heartbeat".into(),
                fatal: false,
                seq: other.seq(),
            }
        }
        Err(e) => {
            stats.error_frames.fetch_add(1, Ordering::Relaxed);
            ServerMessage::Error {
                code: e.code(),
                message: e.to_string(),
                fatal: false,
                seq: None,
            }
        }
    }
}

/// A minimal HTTP/1.1 responder for `GET /metrics`; one request per connection.
async fn serve_metrics(listener: TcpListener, stats: Arc<Stats>) {
    loop {
        let Ok((mut stream, _)) = listener.accept().await else {
            continue;
        };
        let stats = stats.clone();
        tokio::spawn(async move {
            let mut request = Vec::with_capacity(1024);
            let mut buf = [0u8; 1024];
            while !request.windows(4).any(|w| w == b"\r\n\r\n") && request.len() < 16 * 1024 {
                match stream.read(&mut buf).await {
                    Ok(0) | Err(_) => break,
                    Ok(n) => request.extend_from_slice(&buf[..n]),
                }
            }
            let (status, body) = if request.starts_with(b"GET /metrics ") {
                ("200 OK", stats.render())
            } else {
                ("404 Not Found", "only GET /metrics is served\n".to_owned())
            };
            let response = format!(
                "HTTP/1.1 {status}\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = stream.write_all(response.as_bytes()).await;
            let _ = stream.shutdown().await;
        });
    }
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    // One file descriptor per simulated robot.
    let _ = rlimit::increase_nofile_limit(u64::MAX);
    let stats = Arc::new(Stats::default());
    let listener = TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    if let Some(addr) = args.metrics {
        let metrics = TcpListener::bind(addr)
            .await
            .with_context(|| format!("cannot listen on {addr}"))?;
        tokio::spawn(serve_metrics(metrics, stats.clone()));
        println!("lekiwi-bench-echo: metrics on http://{addr}/metrics");
    }
    println!(
        "lekiwi-bench-echo: listening on ws://{}{AGENT_PATH}",
        listener.local_addr()?
    );
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    tokio::spawn(session(stream, stats.clone(), args.heartbeat_interval));
                }
                // Out of file descriptors or similar: keep serving the connections we have.
                Err(e) => {
                    eprintln!("lekiwi-bench-echo: accept failed: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                }
            },
            _ = tokio::signal::ctrl_c() => return Ok(()),
        }
    }
}
