//! The blob HTTP client: `GET {base}/v1/blobs/sha256:<hex>` over HTTP/1.1 (TLS by rustls),
//! with keep-alive connections reused across blobs and `Range` to resume partial downloads.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::FutureExt;
use http_body_util::{BodyExt, Empty};
use hyper::body::{Bytes, Incoming};
use hyper::client::conn::http1::{self, SendRequest};
use hyper::header::{AUTHORIZATION, HOST, RANGE};
use hyper::{Request, Response, StatusCode, Uri};
use hyper_util::rt::TokioIo;
use lekiwi_protocol::ROBOT_HEADER;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpStream;
use tracing::debug;

use super::{Error, Result};

/// Time to open a connection (TCP and TLS).
const CONNECT_TIMEOUT: Duration = Duration::from_secs(15);
/// Longest silence of the gateway while a response is awaited or streamed.
const IDLE_TIMEOUT: Duration = Duration::from_secs(30);
/// Error bodies read at most.
const ERROR_BODY_LIMIT: usize = 4096;
/// Idle connections kept for reuse.
const POOL_SIZE: usize = 4;

mod blob;
mod pace;
mod stream;

pub(super) use pace::Pace;

/// How to reach the gateway's blob API.
#[derive(Clone)]
pub struct GatewayAccess {
    /// `http(s)://host[:port]`, without a path.
    pub base_url: String,
    /// The robot's token, sent as `Authorization: Bearer`.
    pub token: String,
    /// The robot, `namespace/name`, sent in the robot header the gateway checks the token for.
    pub robot: String,
    /// PEM file of the CA to trust for `https://` instead of the public web roots.
    pub ca_file: Option<PathBuf>,
}

impl std::fmt::Debug for GatewayAccess {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GatewayAccess")
            .field("base_url", &self.base_url)
            .field("token", &"<redacted>")
            .field("robot", &self.robot)
            .field("ca_file", &self.ca_file)
            .finish()
    }
}

impl GatewayAccess {
    /// Access derived from the gateway's WebSocket URL: `ws`→`http`, `wss`→`https`, path
    /// dropped.
    pub fn from_gateway_url(
        gateway: &str,
        token: impl Into<String>,
        robot: impl Into<String>,
        ca_file: Option<PathBuf>,
    ) -> Result<Self> {
        Ok(Self {
            base_url: base_url(gateway)?,
            token: token.into(),
            robot: robot.into(),
            ca_file,
        })
    }
}

/// The HTTP base URL of a gateway WebSocket URL.
pub fn base_url(gateway: &str) -> Result<String> {
    let uri: Uri = gateway
        .parse()
        .map_err(|e| Error::Access(format!("gateway URL {gateway:?}: {e}")))?;
    let scheme = match uri.scheme_str() {
        Some("ws" | "http") => "http",
        Some("wss" | "https") => "https",
        other => {
            return Err(Error::Access(format!(
                "gateway URL {gateway:?}: scheme {other:?} is not ws, wss, http or https"
            )));
        }
    };
    let authority = uri
        .authority()
        .ok_or_else(|| Error::Access(format!("gateway URL {gateway:?} has no host")))?;
    Ok(format!("{scheme}://{authority}"))
}

type Sender = SendRequest<Empty<Bytes>>;

/// A byte stream to the gateway, plain or TLS.
trait Io: AsyncRead + AsyncWrite + Send + Unpin {}
impl<T: AsyncRead + AsyncWrite + Send + Unpin> Io for T {}

/// The parsed base URL.
#[derive(Clone, Debug)]
struct Target {
    /// For `Host:` (with the port if one was given).
    authority: String,
    /// For connecting and for TLS (no brackets around IPv6).
    host: String,
    port: u16,
}

/// Marker of a blob that landed in the store.
pub(super) struct Fetched;

/// Whom a request speaks for: a robot's token and its `namespace/name`. The agent's own
/// requests use its [`GatewayAccess`]; the fleet simulator shares one client among its robots
/// and names the robot per request.
#[derive(Clone, Copy)]
pub(crate) struct Caller<'a> {
    /// The robot's token, sent as `Authorization: Bearer`.
    pub(crate) token: &'a str,
    /// The robot, `namespace/name`.
    pub(crate) robot: &'a str,
}

/// The client: gateway access, TLS settings and a few idle connections.
// shape: here the requests and retries; blob.rs a download into the store, stream.rs a blob read as
// a stream.
pub(crate) struct Client {
    access: GatewayAccess,
    target: Target,
    tls: Option<tokio_rustls::TlsConnector>,
    idle: Mutex<Vec<Sender>>,
    /// Idle connections kept at most.
    pool: usize,
    /// The download rate cap, shared with the client that replaces this one.
    pub(super) pace: Option<Arc<Pace>>,
}

impl Client {
    pub(crate) fn new(access: GatewayAccess) -> Result<Self> {
        let uri: Uri = access
            .base_url
            .parse()
            .map_err(|e| Error::Access(format!("base URL {:?}: {e}", access.base_url)))?;
        let tls = match uri.scheme_str() {
            Some("https") => true,
            Some("http") => false,
            other => {
                return Err(Error::Access(format!(
                    "base URL {:?}: scheme {other:?} is not http or https",
                    access.base_url
                )));
            }
        };
        let authority = uri
            .authority()
            .ok_or_else(|| Error::Access(format!("base URL {:?} has no host", access.base_url)))?;
        let host = authority
            .host()
            .trim_start_matches('[')
            .trim_end_matches(']')
            .to_owned();
        let port = authority.port_u16().unwrap_or(if tls { 443 } else { 80 });
        let target = Target {
            authority: authority.as_str().to_owned(),
            host,
            port,
        };
        let connector = if tls {
            Some(tls_connector(access.ca_file.as_deref())?)
        } else {
            None
        };
        Ok(Self {
            access,
            target,
            tls: connector,
            idle: Mutex::new(Vec::new()),
            pool: POOL_SIZE,
            pace: None,
        })
    }

    /// Keeps up to `pool` idle connections instead of [`POOL_SIZE`] (a client shared by many
    /// robots keeps as many as it runs requests at once).
    pub(crate) fn with_pool(mut self, pool: usize) -> Self {
        self.pool = pool.max(1);
        self
    }

    /// The caller named by this client's own access.
    fn own(&self) -> Caller<'_> {
        Caller {
            token: &self.access.token,
            robot: &self.access.robot,
        }
    }

    pub(super) fn set_token(&mut self, token: String) {
        self.access.token = token;
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.access.base_url)
    }

    async fn connect(&self) -> Result<Sender> {
        let t = &self.target;
        let transport = |message: String| Error::Transport {
            url: self.access.base_url.clone(),
            message,
        };
        let open = async {
            let tcp = TcpStream::connect((t.host.as_str(), t.port))
                .await
                .map_err(|e| transport(format!("connect: {e}")))?;
            let _ = tcp.set_nodelay(true);
            let io: Box<dyn Io> = match &self.tls {
                None => Box::new(tcp),
                Some(tls) => {
                    let name = rustls_pki_types::ServerName::try_from(t.host.clone())
                        .map_err(|e| Error::Access(format!("host {:?}: {e}", t.host)))?;
                    Box::new(
                        tls.connect(name, tcp)
                            .await
                            .map_err(|e| transport(format!("TLS: {e}")))?,
                    )
                }
            };
            http1::handshake(TokioIo::new(io))
                .await
                .map_err(|e| transport(format!("HTTP handshake: {e}")))
        };
        let (sender, conn) = tokio::time::timeout(CONNECT_TIMEOUT, open)
            .await
            .map_err(|_| transport("connect timed out".into()))??;
        tokio::spawn(async move {
            if let Err(e) = conn.await {
                debug!(error = %e, "blob connection ended");
            }
        });
        Ok(sender)
    }

    /// An idle connection that is still open, or a new one.
    async fn sender(&self) -> Result<(Sender, bool)> {
        loop {
            let idle = self.idle.lock().map(|mut v| v.pop()).unwrap_or_default();
            match idle {
                Some(mut s) if !s.is_closed() => {
                    if s.ready().await.is_ok() {
                        return Ok((s, true));
                    }
                }
                Some(_) => {}
                None => return Ok((self.connect().await?, false)),
            }
        }
    }

    fn release(&self, sender: Sender) {
        if sender.is_closed() {
            return;
        }
        if let Ok(mut idle) = self.idle.lock()
            && idle.len() < self.pool
        {
            idle.push(sender);
        }
    }

    /// Sends a GET as this client's own caller.
    async fn get(&self, path: &str, range_from: u64) -> Result<(Response<Incoming>, Sender)> {
        self.get_as(path, range_from, self.own()).await
    }

    /// Sends a GET for `caller`; a reused connection that the gateway closed meanwhile is
    /// replaced once.
    async fn get_as(
        &self,
        path: &str,
        range_from: u64,
        caller: Caller<'_>,
    ) -> Result<(Response<Incoming>, Sender)> {
        let url = self.url(path);
        let mut request = Request::get(path)
            .header(HOST, &self.target.authority)
            .header(AUTHORIZATION, format!("Bearer {}", caller.token))
            .header(ROBOT_HEADER, caller.robot);
        if range_from > 0 {
            request = request.header(RANGE, format!("bytes={range_from}-"));
        }
        let request = request
            .body(Empty::<Bytes>::new())
            .map_err(|e| Error::Access(format!("request for {url}: {e}")))?;
        let mut retried = false;
        loop {
            let (mut sender, reused) = self.sender().await?;
            let sent =
                tokio::time::timeout(IDLE_TIMEOUT, sender.send_request(clone_request(&request)))
                    .await;
            match sent {
                Ok(Ok(response)) => return Ok((response, sender)),
                Ok(Err(e)) if reused && !retried => {
                    debug!(error = %e, "reused connection was closed; reconnecting");
                    retried = true;
                }
                Ok(Err(e)) => {
                    return Err(Error::Transport {
                        url,
                        message: e.to_string(),
                    });
                }
                Err(_) => {
                    return Err(Error::Transport {
                        url,
                        message: "no response in time".into(),
                    });
                }
            }
        }
    }

    /// A small resource (the manifest) in memory, at most `limit` bytes.
    pub(super) async fn get_small(&self, path: &str, limit: usize) -> Result<Vec<u8>> {
        self.get_small_as(path, limit, self.own()).await
    }

    /// [`Client::get_small`] for `caller`.
    pub(crate) async fn get_small_as(
        &self,
        path: &str,
        limit: usize,
        caller: Caller<'_>,
    ) -> Result<Vec<u8>> {
        if !path.starts_with('/') {
            return Err(Error::Invalid(format!(
                "manifest URL {path:?} is not a path on the gateway"
            )));
        }
        let url = self.url(path);
        let (response, sender) = self.get_as(path, 0, caller).boxed().await?;
        let status = response.status();
        let mut body = response.into_body();
        if status != StatusCode::OK {
            return Err(self.status_error(&url, status, body).await);
        }
        let mut bytes = Vec::new();
        while let Some(chunk) = next_chunk(&mut body, &url).await? {
            if bytes.len() + chunk.len() > limit {
                return Err(Error::Transport {
                    url,
                    message: format!("more than {limit} bytes"),
                });
            }
            bytes.extend_from_slice(&chunk);
        }
        self.release(sender);
        Ok(bytes)
    }

    /// The error for a non-success status, with the gateway's `message` if it sent one.
    async fn status_error(&self, url: &str, status: StatusCode, mut body: Incoming) -> Error {
        let mut bytes = Vec::new();
        while bytes.len() < ERROR_BODY_LIMIT {
            match tokio::time::timeout(IDLE_TIMEOUT, body.frame()).await {
                Ok(Some(Ok(frame))) => {
                    if let Some(d) = frame.data_ref() {
                        bytes.extend_from_slice(d);
                    }
                }
                _ => break,
            }
        }
        bytes.truncate(ERROR_BODY_LIMIT);
        let message = serde_json::from_slice::<serde_json::Value>(&bytes)
            .ok()
            .and_then(|v| v.get("message").and_then(|m| m.as_str()).map(str::to_owned))
            .unwrap_or_else(|| String::from_utf8_lossy(&bytes).trim().to_owned());
        let url = url.to_owned();
        match status {
            StatusCode::UNAUTHORIZED => Error::Unauthorized { url, message },
            _ => Error::Status {
                url,
                status: status.as_u16(),
                message,
            },
        }
    }
}

fn clone_request(r: &Request<Empty<Bytes>>) -> Request<Empty<Bytes>> {
    let mut c = Request::new(Empty::new());
    *c.method_mut() = r.method().clone();
    *c.uri_mut() = r.uri().clone();
    *c.headers_mut() = r.headers().clone();
    c
}

/// The next data chunk of a body, `None` at its end.
async fn next_chunk(body: &mut Incoming, url: &str) -> Result<Option<Bytes>> {
    loop {
        let frame = tokio::time::timeout(IDLE_TIMEOUT, body.frame())
            .await
            .map_err(|_| Error::Transport {
                url: url.to_owned(),
                message: format!("no data for {}s", IDLE_TIMEOUT.as_secs()),
            })?;
        match frame {
            None => return Ok(None),
            Some(Err(e)) => {
                return Err(Error::Transport {
                    url: url.to_owned(),
                    message: format!("transfer broke off: {e}"),
                });
            }
            Some(Ok(frame)) => {
                if let Ok(data) = frame.into_data() {
                    return Ok(Some(data));
                }
            }
        }
    }
}

/// TLS settings trusting the CA in `ca_file`, or the public web roots.
fn tls_connector(ca_file: Option<&std::path::Path>) -> Result<tokio_rustls::TlsConnector> {
    use rustls_pki_types::CertificateDer;
    use rustls_pki_types::pem::PemObject;
    let mut roots = rustls::RootCertStore::empty();
    match ca_file {
        Some(ca_file) => {
            let bad = |e: &dyn std::fmt::Display| {
                Error::Access(format!("CA file {}: {e}", ca_file.display()))
            };
            for cert in CertificateDer::pem_file_iter(ca_file).map_err(|e| bad(&e))? {
                roots.add(cert.map_err(|e| bad(&e))?).map_err(|e| bad(&e))?;
            }
            if roots.is_empty() {
                return Err(bad(&"no certificate in the file"));
            }
        }
        None => roots.extend(webpki_roots::TLS_SERVER_ROOTS.iter().cloned()),
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| Error::Access(e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsConnector::from(Arc::new(config)))
}
