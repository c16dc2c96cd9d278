//! A TCP proxy that hands on what the server sends a set time late: a client behind it (a
//! gateway replica's Kubernetes client) sees every answer and watch event that much after
//! everyone else, as a replica whose watch is behind does. What the client sends goes through at
//! once. The lag can change while connections are open (it starts at zero, so the client can
//! start up at full speed).
//!
//! It can also hand on what the server sends at a set rate per connection
//! ([`LagProxy::set_rate`]): a large answer (a list of thousands of objects) then takes long to
//! arrive while small ones (a watch's events) still come in time, as on an API server that is
//! slow to send big lists.
//!
//! It can also lag only the answers in flight on the connections open at one moment
//! ([`LagProxy::lag_open`]): a client's watches (each one long answer) then run behind while the
//! requests it sends afterwards, on kept-alive or new connections, are answered in time, as on an
//! API server whose watches fall behind under load.
//!
//! It can also play an API server that restarts badly: [`LagProxy::cut_and_hold`] closes every
//! open connection and takes the next ones in without ever answering them, as a server that
//! accepted requests while it started and lost them; [`LagProxy::release`] forwards connections
//! opened after it again (those held stay unanswered).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

use anyhow::Result;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// Chunks read from the server and not yet handed on, per connection (bounded: reading waits).
const IN_FLIGHT: usize = 256;

/// The proxy; it stops accepting when dropped.
pub struct LagProxy {
    /// Where clients connect: `127.0.0.1:port`.
    pub addr: SocketAddr,
    lag_ms: Arc<AtomicU64>,
    /// Bytes per second handed on per connection; 0: no limit.
    rate: Arc<AtomicU64>,
    /// Bumped to close every connection forwarded so far.
    cuts: watch::Sender<u64>,
    /// While set, connections are taken in and never answered.
    holding: Arc<AtomicBool>,
    /// Each forwarded connection's own lag in milliseconds, while it is open.
    open: Arc<Mutex<Vec<Weak<AtomicU64>>>>,
    accept: JoinHandle<()>,
}

impl LagProxy {
    /// Listens on a free loopback port and forwards each connection to `upstream`, with no lag
    /// until [`LagProxy::set_lag`].
    pub async fn start(upstream: SocketAddr) -> Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let lag_ms = Arc::new(AtomicU64::new(0));
        let rate = Arc::new(AtomicU64::new(0));
        let (cuts, cut) = watch::channel(0);
        let holding = Arc::new(AtomicBool::new(false));
        let open = Arc::new(Mutex::new(Vec::<Weak<AtomicU64>>::new()));
        let (pace, hold, conns) = (
            (lag_ms.clone(), rate.clone()),
            holding.clone(),
            open.clone(),
        );
        let accept = tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                if hold.load(Ordering::Relaxed) {
                    tokio::spawn(never_answer(client));
                    continue;
                }
                let own = Arc::new(AtomicU64::new(0));
                if let Ok(mut conns) = conns.lock() {
                    conns.retain(|c| c.strong_count() > 0);
                    conns.push(Arc::downgrade(&own));
                }
                let pace = Pace {
                    lag_ms: pace.0.clone(),
                    own_lag_ms: own,
                    rate: pace.1.clone(),
                };
                tokio::spawn(forward(client, upstream, pace, cut.clone()));
            }
        });
        Ok(Self {
            addr,
            lag_ms,
            rate,
            cuts,
            holding,
            open,
            accept,
        })
    }

    /// Closes every connection forwarded so far and, until [`LagProxy::release`], takes new
    /// connections in without ever answering them (not even after the release).
    pub fn cut_and_hold(&self) {
        self.holding.store(true, Ordering::Relaxed);
        self.cuts.send_modify(|n| *n += 1);
    }

    /// Forwards the connections opened from now on again.
    pub fn release(&self) {
        self.holding.store(false, Ordering::Relaxed);
    }

    /// From now on, what the server sends is handed on `lag` late, on open connections too.
    pub fn set_lag(&self, lag: Duration) {
        let ms = u64::try_from(lag.as_millis()).unwrap_or(u64::MAX);
        self.lag_ms.store(ms, Ordering::Relaxed);
    }

    /// From now on, what the server sends on the connections open now is handed on `lag` late
    /// (or the lag of [`LagProxy::set_lag`], if longer), until the client sends on that
    /// connection again: a watch's answer runs behind to its end, while a new request on a
    /// kept-alive connection (HTTP/1.1 sends one after the answer before it has come) or on a
    /// connection opened later is answered in time.
    pub fn lag_open(&self, lag: Duration) {
        let ms = u64::try_from(lag.as_millis()).unwrap_or(u64::MAX);
        if let Ok(conns) = self.open.lock() {
            for own in conns.iter().filter_map(Weak::upgrade) {
                own.store(ms, Ordering::Relaxed);
            }
        }
    }

    /// From now on, each connection hands on at most `bytes_per_second` of what the server
    /// sends (`0`: as fast as it comes), on open connections too.
    pub fn set_rate(&self, bytes_per_second: u64) {
        self.rate.store(bytes_per_second, Ordering::Relaxed);
    }
}

impl Drop for LagProxy {
    fn drop(&mut self) {
        self.accept.abort();
    }
}

/// A connection taken in and never answered: what the client sends is read and dropped.
async fn never_answer(mut client: TcpStream) {
    let mut buf = vec![0u8; 16 * 1024];
    while matches!(client.read(&mut buf).await, Ok(n) if n > 0) {}
}

/// One connection: client to server as it comes, server to client the lag late, in order, until
/// the proxy cuts it.
async fn forward(
    client: TcpStream,
    upstream: SocketAddr,
    pace: Pace,
    mut cut: watch::Receiver<u64>,
) {
    cut.mark_unchanged();
    tokio::select! {
        () = relay(client, upstream, pace) => {}
        _ = cut.changed() => {}
    }
}

/// How one connection hands on what the server sends.
struct Pace {
    /// The proxy's lag for every connection, in milliseconds.
    lag_ms: Arc<AtomicU64>,
    /// This connection's own (see [`LagProxy::lag_open`]); the longer of the two counts. Back to
    /// 0 when the client sends.
    own_lag_ms: Arc<AtomicU64>,
    /// Bytes per second; 0: no limit.
    rate: Arc<AtomicU64>,
}

/// The most handed on at once when a rate is set: pieces this small keep the pace even.
const PIECE: usize = 4 * 1024;

async fn relay(client: TcpStream, upstream: SocketAddr, pace: Pace) {
    let Pace {
        lag_ms,
        own_lag_ms,
        rate,
    } = pace;
    let Ok(server) = TcpStream::connect(upstream).await else {
        return;
    };
    let (mut client_read, mut client_write) = client.into_split();
    let (mut server_read, mut server_write) = server.into_split();
    // Both halves' tasks end with this future, also when a cut drops it.
    let mut tasks = tokio::task::JoinSet::new();
    let unlag = own_lag_ms.clone();
    tasks.spawn(async move {
        let mut buf = vec![0u8; 16 * 1024];
        while let Ok(n) = client_read.read(&mut buf).await {
            // A client that sends again has had the answer it waited for: a new request.
            unlag.store(0, Ordering::Relaxed);
            if n == 0 || server_write.write_all(&buf[..n]).await.is_err() {
                break;
            }
        }
        let _ = server_write.shutdown().await;
    });
    let (tx, mut rx) = mpsc::channel::<(Instant, Vec<u8>)>(IN_FLIGHT);
    tasks.spawn(async move {
        let mut buf = vec![0u8; 64 * 1024];
        while let Ok(n) = server_read.read(&mut buf).await {
            let ms = lag_ms
                .load(Ordering::Relaxed)
                .max(own_lag_ms.load(Ordering::Relaxed));
            let lag = Duration::from_millis(ms);
            if n == 0
                || tx
                    .send((Instant::now() + lag, buf[..n].to_vec()))
                    .await
                    .is_err()
            {
                break;
            }
        }
    });
    // Paced by sleeping each piece's share of a second: a test bed's stand-in for a slow link,
    // no rate limiter of the product's.
    'chunks: while let Some((at, chunk)) = rx.recv().await {
        tokio::time::sleep_until(at).await;
        for piece in chunk.chunks(PIECE) {
            if client_write.write_all(piece).await.is_err() {
                break 'chunks;
            }
            let len = u64::try_from(piece.len()).unwrap_or(u64::MAX);
            let per_second = rate.load(Ordering::Relaxed);
            if let Some(micros) = (len * 1_000_000).checked_div(per_second) {
                tokio::time::sleep(Duration::from_micros(micros)).await;
            }
        }
    }
    let _ = client_write.shutdown().await;
}
