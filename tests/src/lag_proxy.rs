//! A TCP proxy that hands on what the server sends a set time late: a client behind it (a
//! gateway replica's Kubernetes client) sees every answer and watch event that much after
//! everyone else, as a replica whose watch is behind does. What the client sends goes through at
//! once. The lag can change while connections are open (it starts at zero, so the client can
//! start up at full speed).

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use anyhow::Result;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// Chunks read from the server and not yet handed on, per connection (bounded: reading waits).
const IN_FLIGHT: usize = 256;

/// The proxy; it stops accepting when dropped.
pub struct LagProxy {
    /// Where clients connect: `127.0.0.1:port`.
    pub addr: SocketAddr,
    lag_ms: Arc<AtomicU64>,
    accept: JoinHandle<()>,
}

impl LagProxy {
    /// Listens on a free loopback port and forwards each connection to `upstream`, with no lag
    /// until [`LagProxy::set_lag`].
    pub async fn start(upstream: SocketAddr) -> Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let lag_ms = Arc::new(AtomicU64::new(0));
        let lag = lag_ms.clone();
        let accept = tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                tokio::spawn(forward(client, upstream, lag.clone()));
            }
        });
        Ok(Self {
            addr,
            lag_ms,
            accept,
        })
    }

    /// From now on, what the server sends is handed on `lag` late, on open connections too.
    pub fn set_lag(&self, lag: Duration) {
        let ms = u64::try_from(lag.as_millis()).unwrap_or(u64::MAX);
        self.lag_ms.store(ms, Ordering::Relaxed);
    }
}

impl Drop for LagProxy {
    fn drop(&mut self) {
        self.accept.abort();
    }
}

/// One connection: client to server as it comes, server to client the lag late, in order.
async fn forward(client: TcpStream, upstream: SocketAddr, lag_ms: Arc<AtomicU64>) {
    let Ok(server) = TcpStream::connect(upstream).await else {
        return;
    };
    let (mut client_read, mut client_write) = client.into_split();
    let (mut server_read, mut server_write) = server.into_split();
    let up = tokio::spawn(async move {
        let _ = tokio::io::copy(&mut client_read, &mut server_write).await;
        let _ = server_write.shutdown().await;
    });
    let (tx, mut rx) = mpsc::channel::<(Instant, Vec<u8>)>(IN_FLIGHT);
    let read = tokio::spawn(async move {
        let mut buf = vec![0u8; 64 * 1024];
        while let Ok(n) = server_read.read(&mut buf).await {
            let lag = Duration::from_millis(lag_ms.load(Ordering::Relaxed));
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
    while let Some((at, chunk)) = rx.recv().await {
        tokio::time::sleep_until(at).await;
        if client_write.write_all(&chunk).await.is_err() {
            break;
        }
    }
    let _ = client_write.shutdown().await;
    read.abort();
    up.abort();
}
