//! The gateway's own accept loop: HTTP/1.1 (plain or TLS) with bounded headers, a header-read
//! deadline that also ends idle kept-alive connections, a TLS handshake deadline, and caps on
//! connections that have not yet made an authenticated request (per client address and in
//! all), so stalled or slow clients cannot exhaust the gateway's memory or sockets.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::Router;
use axum::extract::{ConnectInfo, Request};
use axum::middleware::Next;
use axum::response::Response;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio_util::sync::CancellationToken;
use tower::ServiceExt;
use tracing::{debug, warn};

use super::tls::Acceptor;
use lekiwi_metrics::KindLabels;

/// How the gateway treats connections before they are authenticated.
#[derive(Clone, Debug)]
pub struct ConnLimits {
    /// Time from connecting (after TLS), or from the end of the previous response, until a
    /// request's headers are complete.
    pub header_timeout: Duration,
    /// Time a client has to complete the TLS handshake.
    pub tls_handshake_timeout: Duration,
    /// Largest request head (request line and headers), in bytes.
    pub max_header_bytes: usize,
    /// Unauthenticated connections one client address may hold at once (0: no limit).
    pub per_address: usize,
    /// Unauthenticated connections the gateway holds at once.
    pub unauthenticated: usize,
}

/// The unauthenticated connections held now: per client address and in all.
struct PreAuth {
    per_address: usize,
    by_address: Mutex<HashMap<IpAddr, usize>>,
    all: Arc<Semaphore>,
}

impl PreAuth {
    /// A slot for a new connection from `ip`, or the limit it is over.
    fn hold(self: &Arc<Self>, ip: IpAddr) -> Result<ConnSlot, &'static str> {
        let permit = self
            .all
            .clone()
            .try_acquire_owned()
            .map_err(|_| "unauthenticated_limit")?;
        let mut by_address = self.by_address.lock().unwrap_or_else(|p| p.into_inner());
        let count = by_address.entry(ip).or_insert(0);
        if self.per_address > 0 && *count >= self.per_address {
            return Err("per_address_limit");
        }
        *count += 1;
        let held = Held {
            pre_auth: self.clone(),
            ip,
            _permit: permit,
        };
        Ok(ConnSlot(Arc::new(Mutex::new(Some(held)))))
    }
}

/// One connection's claim on the unauthenticated limits; released when dropped.
struct Held {
    pre_auth: Arc<PreAuth>,
    ip: IpAddr,
    _permit: OwnedSemaphorePermit,
}

impl Drop for Held {
    fn drop(&mut self) {
        let mut by_address = self
            .pre_auth
            .by_address
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        if let Some(count) = by_address.get_mut(&self.ip) {
            *count -= 1;
            if *count == 0 {
                by_address.remove(&self.ip);
            }
        }
    }
}

/// A connection's place under the unauthenticated limits, in every request's extensions; the
/// first authenticated request gives it up, so authenticated robots (many behind one NAT
/// address) are limited only by `--max-connections`.
#[derive(Clone)]
pub struct ConnSlot(Arc<Mutex<Option<Held>>>);

impl ConnSlot {
    /// The connection made an authenticated request: it no longer counts as unauthenticated.
    fn authenticated(&self) {
        let held = self.0.lock().unwrap_or_else(|p| p.into_inner()).take();
        drop(held);
    }
}

/// Middleware for routes that require credentials: a success (2xx, or 101 for a WebSocket)
/// means the request was authenticated, and its connection leaves the unauthenticated count.
pub async fn authenticated_on_success(request: Request, next: Next) -> Response {
    let slot = request.extensions().get::<ConnSlot>().cloned();
    let response = next.run(request).await;
    let status = response.status();
    let succeeded = status.is_success() || status == axum::http::StatusCode::SWITCHING_PROTOCOLS;
    if let (true, Some(slot)) = (succeeded, slot) {
        slot.authenticated();
    }
    response
}

/// What every connection task shares.
struct Serving {
    app: Router,
    tls: Option<Acceptor>,
    http: http1::Builder,
    limits: ConnLimits,
    dropped: Family<KindLabels, Counter>,
    /// Fires when the server stops: connections finish their request and close.
    stop: CancellationToken,
    open: AtomicUsize,
}

impl Serving {
    fn dropped(&self, why: &'static str) {
        self.dropped.get_or_create(&KindLabels { kind: why }).inc();
    }
}

/// Serves `app` on `listener` (over TLS with `tls`) until `cancel` fires, then gives open
/// connections up to 5 s to finish (WebSocket sessions end on the same `cancel`).
pub async fn serve(
    listener: TcpListener,
    app: Router,
    tls: Option<Acceptor>,
    limits: ConnLimits,
    dropped: Family<KindLabels, Counter>,
    cancel: CancellationToken,
) -> std::io::Result<()> {
    let mut http = http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(limits.header_timeout)
        // hyper's read buffer is at least 8 KiB; a longer head gets 431 and the connection ends.
        .max_buf_size(limits.max_header_bytes.max(8192))
        .max_headers(100);
    let pre_auth = Arc::new(PreAuth {
        per_address: limits.per_address,
        by_address: Mutex::default(),
        all: Arc::new(Semaphore::new(limits.unauthenticated)),
    });
    let serving = Arc::new(Serving {
        app,
        tls,
        http,
        limits,
        dropped,
        stop: cancel.child_token(),
        open: AtomicUsize::new(0),
    });
    loop {
        let (stream, peer) = tokio::select! {
            () = cancel.cancelled() => break,
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                Err(e) => {
                    // Out of file descriptors or a connection reset before accept: not fatal.
                    warn!(error = %e, "cannot accept a gateway connection");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        match pre_auth.hold(peer.ip()) {
            Ok(slot) => {
                serving.open.fetch_add(1, Ordering::AcqRel);
                tokio::spawn(connection(serving.clone(), stream, peer, slot));
            }
            Err(why) => {
                debug!(%peer, why, "closed a connection over the unauthenticated limit");
                serving.dropped(why);
            }
        }
    }
    let drained = async {
        while serving.open.load(Ordering::Acquire) > 0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    };
    let _ = tokio::time::timeout(Duration::from_secs(5), drained).await;
    Ok(())
}

/// One connection: the TLS handshake within its deadline, then HTTP/1.1 until the client or
/// the gateway closes it.
async fn connection(serving: Arc<Serving>, stream: TcpStream, peer: SocketAddr, slot: ConnSlot) {
    let _ = stream.set_nodelay(true);
    match &serving.tls {
        Some(acceptor) => {
            let handshake = acceptor.accept(stream);
            match tokio::time::timeout(serving.limits.tls_handshake_timeout, handshake).await {
                Ok(Ok(tls)) => http(&serving, tls, peer, slot).await,
                Ok(Err(e)) => {
                    debug!(%peer, error = %e, "TLS handshake failed");
                    serving.dropped("tls_handshake");
                }
                Err(_) => {
                    debug!(%peer, "TLS handshake timed out");
                    serving.dropped("tls_handshake");
                }
            }
        }
        None => http(&serving, stream, peer, slot).await,
    }
    serving.open.fetch_sub(1, Ordering::AcqRel);
}

/// Serves HTTP/1.1 (with upgrades, for WebSockets) on `io`.
async fn http<I>(serving: &Serving, io: I, peer: SocketAddr, slot: ConnSlot)
where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let service =
        serving
            .app
            .clone()
            .map_request(move |mut request: Request<hyper::body::Incoming>| {
                request.extensions_mut().insert(ConnectInfo(peer));
                request.extensions_mut().insert(slot.clone());
                request
            });
    let conn = serving
        .http
        .serve_connection(TokioIo::new(io), TowerToHyperService::new(service))
        .with_upgrades();
    tokio::pin!(conn);
    let result = tokio::select! {
        r = conn.as_mut() => r,
        () = serving.stop.cancelled() => {
            conn.as_mut().graceful_shutdown();
            conn.await
        }
    };
    if let Err(e) = result {
        if e.is_timeout() {
            serving.dropped("header_timeout");
        } else if e.is_parse_too_large() {
            serving.dropped("header_too_large");
        }
        debug!(%peer, error = %e, "gateway connection ended with an error");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pre_auth(per_address: usize, all: usize) -> Arc<PreAuth> {
        Arc::new(PreAuth {
            per_address,
            by_address: Mutex::default(),
            all: Arc::new(Semaphore::new(all)),
        })
    }

    #[test]
    fn unauthenticated_connections_are_capped_per_address_until_authenticated() {
        let limits = pre_auth(2, 10);
        let (a, b): (IpAddr, IpAddr) = ("10.0.0.1".parse().unwrap(), "10.0.0.2".parse().unwrap());
        let first = limits.hold(a).unwrap();
        let second = limits.hold(a).unwrap();
        assert_eq!(limits.hold(a).err(), Some("per_address_limit"));
        assert!(limits.hold(b).is_ok(), "another address has its own count");
        // An authenticated connection leaves the count (twice is harmless); a closed one too.
        first.authenticated();
        first.authenticated();
        let third = limits.hold(a).unwrap();
        drop(second);
        let _fourth = limits.hold(a).unwrap();
        assert_eq!(limits.hold(a).err(), Some("per_address_limit"));
        drop((first, third));
        assert_eq!(limits.by_address.lock().unwrap().get(&a), Some(&1));
    }

    #[test]
    fn the_total_of_unauthenticated_connections_is_capped() {
        let limits = pre_auth(0, 2);
        let ip: IpAddr = "10.0.0.1".parse().unwrap();
        let held = [limits.hold(ip).unwrap(), limits.hold(ip).unwrap()];
        assert_eq!(limits.hold(ip).err(), Some("unauthenticated_limit"));
        held[0].authenticated();
        assert!(limits.hold(ip).is_ok());
    }
}
