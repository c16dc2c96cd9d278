//! Discovery: the mDNS advertisement of `_lekiwi._tcp.local.` and the local JSON status endpoint.
//!
//! Interface the agent loop uses (keep these signatures):
//! - `StatusSnapshot` (Serialize + Deserialize, camelCase): robot, agentVersion, release,
//!   gateway, connected, teleoperation, outboxPending, lastRttMs, bytesSent, startedAtMs
//! - `serve_status(listener: tokio::net::TcpListener, status: tokio::sync::watch::Receiver<StatusSnapshot>)`
//! - `Advertiser::start(&StatusSnapshot, port: u16) -> Result<Advertiser, Error>`,
//!   `Advertiser::update(&mut self, &StatusSnapshot)`; dropping it withdraws the advertisement
//! - `browse(timeout) -> Result<Vec<Found>, Error>` for `kubectl lekiwi discover`
//!
//! The advertisement is one DNS-SD service: instance [`instance_name`] of the robot, host
//! `<instance>.local.` with every address of the machine's multicast interfaces (mdns-sd leaves
//! out loopback), SRV port = the status port, and the TXT keys `robot`, `agent_version`,
//! `release`, `gateway` and `status_port`. Only those identity facts go into TXT: they change
//! rarely, so the records cached on the LAN stay valid; live state is what `/status` is for.
//!
//! mdns-sd runs its own small thread and binds `0.0.0.0:5353` / `[::]:5353` with `SO_REUSEPORT`,
//! so it coexists with avahi-daemon and with another mdns-sd process on the same host; multicast
//! loop is on, which is how a browser on the same machine sees the advertisement. Loopback is
//! left out on purpose (mdns-sd's default): a host whose only interface is `lo` advertises
//! nothing, which is right for a robot, and tests need a multicast-capable interface such as
//! the container's `eth0`.

use std::collections::BTreeMap;
use std::io;
use std::net::IpAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use lekiwi_protocol::{Release, Teleoperation};
use mdns_sd::{ServiceDaemon, ServiceEvent, ServiceInfo};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, watch};
use tracing::{debug, info, warn};

/// The DNS-SD service type the agent advertises.
pub const SERVICE_TYPE: &str = "_lekiwi._tcp.local.";
/// Largest request head (request line and headers) the status endpoint reads; beyond: 431.
pub const MAX_HEAD_BYTES: usize = 8 * 1024;
/// Time a client has to send its request head.
pub const READ_TIMEOUT: Duration = Duration::from_secs(5);
/// Connections the status endpoint serves at once; more wait in the listen backlog.
pub const MAX_CONNECTIONS: usize = 32;

/// Time to write a response (it is small: this only catches clients that never read).
const WRITE_TIMEOUT: Duration = Duration::from_secs(5);
/// Time to drain what a client still sends after the response, so that closing does not reset
/// the connection and destroy the response before the client has read it.
const LINGER: Duration = Duration::from_secs(2);
/// Bytes drained at most after the response.
const LINGER_BYTES: usize = 64 * 1024;
/// How long `Drop` waits for the mDNS daemon to confirm the goodbye and its exit.
const DAEMON_REPLY_TIMEOUT: Duration = Duration::from_secs(1);
/// A DNS label holds at most 63 bytes.
const MAX_LABEL: usize = 63;

/// Errors of mDNS advertisement and browsing.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The mDNS daemon (its thread and sockets) could not start.
    #[error("cannot start the mDNS daemon: {0}")]
    StartDaemon(#[source] mdns_sd::Error),
    /// The service description was rejected, e.g. a TXT key is invalid.
    #[error("invalid mDNS service {instance}: {source}")]
    ServiceInfo {
        instance: String,
        source: mdns_sd::Error,
    },
    /// The daemon did not take the registration.
    #[error("cannot register mDNS service {instance}: {source}")]
    Register {
        instance: String,
        source: mdns_sd::Error,
    },
    /// The daemon did not take the browse request.
    #[error("cannot browse for {SERVICE_TYPE}: {0}")]
    Browse(#[source] mdns_sd::Error),
}

/// Result of this module.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// What the agent knows about itself right now: served as `/status`, and the source of the
/// mDNS TXT records.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "camelCase", default)]
pub struct StatusSnapshot {
    /// Robot, `namespace/name` or `name`.
    pub robot: String,
    /// Version of this agent.
    pub agent_version: String,
    /// Release the robot runs, if any.
    pub release: Option<Release>,
    /// Gateway URL the agent connects to.
    pub gateway: String,
    /// Whether the gateway connection is up.
    pub connected: bool,
    /// Latest teleoperation verdict.
    pub teleoperation: Option<Teleoperation>,
    /// Durable messages not yet acknowledged by the gateway.
    pub outbox_pending: u64,
    /// Latest heartbeat round trip, milliseconds.
    pub last_rtt_ms: Option<f64>,
    /// Bytes sent to the gateway since the start.
    pub bytes_sent: u64,
    /// Start of the agent, Unix milliseconds.
    pub started_at_ms: i64,
}

/// The DNS-safe instance (and host) label for a robot: `name-namespace` for `namespace/name`,
/// lowercase letters, digits and `-` only, at most 63 bytes.
///
/// Dots are not allowed: mdns-sd writes every `.` as a label boundary and does not escape it,
/// so `name.namespace` would turn into a different service type for other resolvers. The
/// mapping is not injective (`a-b/c` and `b/c-a` meet), which is why the TXT record `robot`,
/// not the instance name, identifies the robot. A name longer than a label is cut and
/// suffixed with a hash of the full name to stay distinct.
pub fn instance_name(robot: &str) -> String {
    let joined = match robot.split_once('/') {
        Some((namespace, name)) => format!("{name}-{namespace}"),
        None => robot.to_owned(),
    };
    let mut label = String::with_capacity(joined.len());
    for c in joined.chars() {
        let c = if c.is_ascii_alphanumeric() {
            c.to_ascii_lowercase()
        } else {
            '-'
        };
        // Runs of separators collapse into one, which also keeps `--` out of the label.
        if !(c == '-' && (label.is_empty() || label.ends_with('-'))) {
            label.push(c);
        }
    }
    while label.ends_with('-') {
        label.pop();
    }
    if label.is_empty() {
        label.push_str("lekiwi");
    }
    if label.len() > MAX_LABEL {
        let suffix = format!("-{:08x}", fnv1a(robot.as_bytes()));
        label.truncate(MAX_LABEL - suffix.len());
        while label.ends_with('-') {
            label.pop();
        }
        label.push_str(&suffix);
    }
    label
}

/// 32-bit FNV-1a: a stable hash (unlike `DefaultHasher`) for shortened instance names.
fn fnv1a(bytes: &[u8]) -> u32 {
    bytes.iter().fold(0x811c_9dc5, |hash, b| {
        (hash ^ u32::from(*b)).wrapping_mul(0x0100_0193)
    })
}

/// The TXT records of a snapshot, in the order they are advertised.
fn txt_records(snapshot: &StatusSnapshot, port: u16) -> Vec<(&'static str, String)> {
    vec![
        ("robot", snapshot.robot.clone()),
        ("agent_version", snapshot.agent_version.clone()),
        (
            "release",
            snapshot
                .release
                .as_ref()
                .map(|r| r.version.clone())
                .unwrap_or_default(),
        ),
        ("gateway", snapshot.gateway.clone()),
        ("status_port", port.to_string()),
    ]
}

/// An mDNS advertisement of this agent, withdrawn (with goodbye packets) when dropped.
pub struct Advertiser {
    daemon: ServiceDaemon,
    port: u16,
    instance: String,
    fullname: String,
    txt: Vec<(&'static str, String)>,
}

impl Advertiser {
    /// Starts an mDNS daemon and advertises the robot of `snapshot` with the status `port`.
    ///
    /// The addresses are those of the machine's interfaces, kept current by mdns-sd; `port`
    /// is only reachable from the LAN if the status endpoint listens beyond loopback.
    pub fn start(snapshot: &StatusSnapshot, port: u16) -> Result<Advertiser> {
        let daemon = ServiceDaemon::new().map_err(Error::StartDaemon)?;
        let instance = instance_name(&snapshot.robot);
        let advertiser = Advertiser {
            daemon,
            port,
            fullname: format!("{instance}.{SERVICE_TYPE}"),
            instance,
            txt: txt_records(snapshot, port),
        };
        // On failure the advertiser drops here, which shuts the daemon down again.
        advertiser.register()?;
        info!(
            instance = %advertiser.instance,
            robot = %snapshot.robot,
            port,
            "advertising over mDNS"
        );
        Ok(advertiser)
    }

    /// Re-announces the service if a TXT-relevant field (robot, agent version, release,
    /// gateway) changed; otherwise does nothing, so it can be called on every status change.
    pub fn update(&mut self, snapshot: &StatusSnapshot) -> Result<()> {
        let txt = txt_records(snapshot, self.port);
        if txt == self.txt {
            return Ok(());
        }
        let instance = instance_name(&snapshot.robot);
        if instance != self.instance {
            // A new name is a new service: withdraw the old one instead of leaving it to expire.
            self.unregister();
            self.fullname = format!("{instance}.{SERVICE_TYPE}");
            self.instance = instance;
        }
        self.txt = txt;
        // Registering the same name again makes mdns-sd announce the new records; receivers
        // replace the cached TXT because mDNS answers carry the cache-flush bit.
        self.register()?;
        debug!(instance = %self.instance, release = %self.txt[2].1, "mDNS advertisement updated");
        Ok(())
    }

    /// The instance label, e.g. `kiwi-01-lab`.
    pub fn instance(&self) -> &str {
        &self.instance
    }

    /// The full service name, e.g. `kiwi-01-lab._lekiwi._tcp.local.`.
    pub fn fullname(&self) -> &str {
        &self.fullname
    }

    fn register(&self) -> Result<()> {
        let host = format!("{}.local.", self.instance);
        let info = ServiceInfo::new(
            SERVICE_TYPE,
            &self.instance,
            &host,
            (),
            self.port,
            &self.txt[..],
        )
        .map_err(|source| Error::ServiceInfo {
            instance: self.instance.clone(),
            source,
        })?
        .enable_addr_auto();
        self.daemon
            .register(info)
            .map_err(|source| Error::Register {
                instance: self.instance.clone(),
                source,
            })
    }

    /// Sends the goodbye for the current name and waits briefly for the daemon to confirm.
    fn unregister(&self) {
        match self.daemon.unregister(&self.fullname) {
            Ok(done) => {
                if done.recv_timeout(DAEMON_REPLY_TIMEOUT).is_err() {
                    debug!(instance = %self.instance, "mDNS daemon did not confirm the unregistration");
                }
            }
            Err(error) => debug!(instance = %self.instance, %error, "mDNS unregistration failed"),
        }
    }
}

impl Drop for Advertiser {
    fn drop(&mut self) {
        self.unregister();
        match self.daemon.shutdown() {
            Ok(done) => {
                let _ = done.recv_timeout(DAEMON_REPLY_TIMEOUT);
            }
            Err(error) => debug!(%error, "mDNS daemon shutdown failed"),
        }
        info!(instance = %self.instance, "mDNS advertisement withdrawn");
    }
}

impl std::fmt::Debug for Advertiser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Advertiser")
            .field("fullname", &self.fullname)
            .field("port", &self.port)
            .field("txt", &self.txt)
            .finish_non_exhaustive()
    }
}

/// An agent found on the network by [`browse`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "camelCase")]
pub struct Found {
    /// Instance label, e.g. `kiwi-01-lab`.
    pub instance: String,
    /// Robot, `namespace/name` or `name` (TXT `robot`).
    pub robot: String,
    /// Agent version (TXT `agent_version`).
    pub agent_version: String,
    /// Release version, if the robot runs one (TXT `release`).
    pub release: Option<String>,
    /// Gateway URL (TXT `gateway`).
    pub gateway: String,
    /// The robot's addresses, sorted.
    pub addresses: Vec<IpAddr>,
    /// Port of its status endpoint.
    pub port: u16,
}

impl Found {
    fn from_info(info: &ServiceInfo) -> Found {
        let txt = |key: &str| {
            info.get_property_val_str(key)
                .unwrap_or_default()
                .to_owned()
        };
        let mut addresses: Vec<IpAddr> = info.get_addresses().iter().copied().collect();
        addresses.sort();
        let release = txt("release");
        Found {
            instance: instance_of(info.get_fullname()).to_owned(),
            robot: txt("robot"),
            agent_version: txt("agent_version"),
            release: (!release.is_empty()).then_some(release),
            gateway: txt("gateway"),
            addresses,
            port: info.get_port(),
        }
    }
}

/// The instance part of a full service name.
fn instance_of(fullname: &str) -> &str {
    fullname
        .strip_suffix(SERVICE_TYPE)
        .and_then(|s| s.strip_suffix('.'))
        .unwrap_or(fullname)
}

/// Browses for `_lekiwi._tcp.local.` until `timeout` has passed (blocking) and returns the
/// agents resolved in that time, one per instance with its latest records, sorted by instance.
pub fn browse(timeout: Duration) -> Result<Vec<Found>> {
    let daemon = ServiceDaemon::new().map_err(Error::StartDaemon)?;
    let found = collect(&daemon, timeout);
    let _ = daemon.stop_browse(SERVICE_TYPE);
    if let Ok(done) = daemon.shutdown() {
        let _ = done.recv_timeout(DAEMON_REPLY_TIMEOUT);
    }
    Ok(found?.into_values().collect())
}

fn collect(daemon: &ServiceDaemon, timeout: Duration) -> Result<BTreeMap<String, Found>> {
    let events = daemon.browse(SERVICE_TYPE).map_err(Error::Browse)?;
    let deadline = Instant::now() + timeout;
    let mut found = BTreeMap::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            break;
        }
        match events.recv_timeout(left) {
            Ok(ServiceEvent::ServiceResolved(info)) => {
                let agent = Found::from_info(&info);
                found.insert(agent.instance.clone(), agent);
            }
            Ok(ServiceEvent::ServiceRemoved(_, fullname)) => {
                found.remove(instance_of(&fullname));
            }
            Ok(_) => {}
            // Timed out, or the daemon is gone: either way nothing more will come.
            Err(_) => break,
        }
    }
    Ok(found)
}

/// Serves the local status endpoint on `listener` until the task is dropped.
///
/// A deliberately tiny HTTP/1.1 server: `GET /status` (the snapshot as JSON), `GET /healthz`
/// (`ok`), `HEAD` of both; other paths 404, other methods 405, one request per connection.
pub async fn serve_status(listener: TcpListener, status: watch::Receiver<StatusSnapshot>) {
    if let Ok(addr) = listener.local_addr() {
        debug!(%addr, "status endpoint serving");
    }
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        // Taking a slot before accepting leaves excess clients in the kernel's backlog.
        let Ok(slot) = slots.clone().acquire_owned().await else {
            return;
        };
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(error) => {
                // Out of file descriptors and the like: pause instead of spinning.
                warn!(%error, "status endpoint cannot accept");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let status = status.clone();
        tokio::spawn(async move {
            let _slot = slot;
            if let Err(error) = handle_connection(stream, &status).await {
                debug!(%peer, %error, "status connection failed");
            }
        });
    }
}

/// Reads one request head, answers it, and closes the connection gracefully.
async fn handle_connection(
    mut stream: TcpStream,
    status: &watch::Receiver<StatusSnapshot>,
) -> io::Result<()> {
    let mut head = Vec::with_capacity(1024);
    let response = match tokio::time::timeout(READ_TIMEOUT, read_head(&mut stream, &mut head)).await
    {
        Err(_) if head.is_empty() => None,
        Err(_) => Some((
            Response::error(408, "request head not received in time"),
            false,
        )),
        Ok(Err(error)) => return Err(error),
        Ok(Ok(HeadRead::Closed)) => None,
        Ok(Ok(HeadRead::Truncated)) => Some((Response::error(400, "incomplete request"), false)),
        Ok(Ok(HeadRead::TooLarge)) => Some((
            Response::error(431, "request head larger than 8 KiB"),
            false,
        )),
        Ok(Ok(HeadRead::Complete)) => {
            let request = parse_request(&head);
            debug!(?request, "status request");
            Some(respond(request, status))
        }
    };
    if let Some((response, head_only)) = response {
        let bytes = response.to_bytes(head_only);
        match tokio::time::timeout(WRITE_TIMEOUT, stream.write_all(&bytes)).await {
            Ok(result) => result?,
            Err(_) => return Err(io::Error::new(io::ErrorKind::TimedOut, "write timed out")),
        }
    }
    stream.shutdown().await?;
    let _ = tokio::time::timeout(LINGER, drain(&mut stream)).await;
    Ok(())
}

/// Reads and discards what the peer still sends, until it closes or a limit is reached.
async fn drain(stream: &mut TcpStream) {
    let mut sink = [0u8; 4096];
    let mut total = 0;
    while total < LINGER_BYTES {
        match stream.read(&mut sink).await {
            Ok(0) | Err(_) => return,
            Ok(n) => total += n,
        }
    }
}

/// How reading a request head ended.
#[derive(Debug, PartialEq)]
enum HeadRead {
    /// The head is complete; the buffer holds exactly the head.
    Complete,
    /// The peer closed before sending anything.
    Closed,
    /// The peer closed in the middle of the head.
    Truncated,
    /// The head exceeds [`MAX_HEAD_BYTES`].
    TooLarge,
}

async fn read_head(stream: &mut TcpStream, buf: &mut Vec<u8>) -> io::Result<HeadRead> {
    let mut chunk = [0u8; 2048];
    loop {
        let n = stream.read(&mut chunk).await?;
        if n == 0 {
            return Ok(if buf.is_empty() {
                HeadRead::Closed
            } else {
                HeadRead::Truncated
            });
        }
        // The terminator may straddle two reads.
        let from = buf.len().saturating_sub(3);
        buf.extend_from_slice(&chunk[..n]);
        if let Some(end) = head_end(&buf[from..]).map(|end| from + end) {
            if end > MAX_HEAD_BYTES {
                return Ok(HeadRead::TooLarge);
            }
            buf.truncate(end);
            return Ok(HeadRead::Complete);
        }
        if buf.len() >= MAX_HEAD_BYTES {
            return Ok(HeadRead::TooLarge);
        }
    }
}

/// Length of the head including its terminating empty line (bare `\n` line ends accepted).
fn head_end(bytes: &[u8]) -> Option<usize> {
    bytes.windows(2).enumerate().find_map(|(i, w)| match w {
        b"\n\n" => Some(i + 2),
        b"\n\r" if bytes.get(i + 2) == Some(&b'\n') => Some(i + 3),
        _ => None,
    })
}

/// What a request asks for, decided from its head alone.
#[derive(Debug, PartialEq)]
enum Request {
    /// `GET` (or `HEAD` when `head_only`) of `/status`.
    Status { head_only: bool },
    /// `GET` (or `HEAD`) of `/healthz`.
    Healthz { head_only: bool },
    /// A path this server does not have.
    NotFound,
    /// A known path with a method other than GET and HEAD.
    MethodNotAllowed,
    /// An HTTP version other than 1.0 and 1.1.
    VersionNotSupported,
    /// Not an HTTP request line.
    Bad,
}

fn parse_request(head: &[u8]) -> Request {
    // Servers should skip empty lines before the request line (RFC 9112, section 2.2).
    let start = head
        .iter()
        .position(|b| *b != b'\r' && *b != b'\n')
        .unwrap_or(head.len());
    let head = &head[start..];
    let line_end = head.iter().position(|b| *b == b'\n').unwrap_or(head.len());
    let Ok(line) = std::str::from_utf8(&head[..line_end]) else {
        return Request::Bad;
    };
    let mut parts = line.trim_end_matches('\r').split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Request::Bad;
    };
    let token = |s: &str| {
        !s.is_empty()
            && s.bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"!#$%&'*+-.^_`|~".contains(&b))
    };
    if !token(method) || !target.starts_with('/') {
        return Request::Bad;
    }
    match version {
        "HTTP/1.1" | "HTTP/1.0" => {}
        v if v.starts_with("HTTP/") => return Request::VersionNotSupported,
        _ => return Request::Bad,
    }
    let path = target.split(['?', '#']).next().unwrap_or_default();
    let head_only = match method {
        "GET" => false,
        "HEAD" => true,
        _ if matches!(path, "/status" | "/healthz") => return Request::MethodNotAllowed,
        _ => return Request::NotFound,
    };
    match path {
        "/status" => Request::Status { head_only },
        "/healthz" => Request::Healthz { head_only },
        _ => Request::NotFound,
    }
}

/// The response to a request and whether to leave out the body (HEAD).
fn respond(request: Request, status: &watch::Receiver<StatusSnapshot>) -> (Response, bool) {
    match request {
        Request::Status { head_only } => {
            // Serialised under the borrow: no await, so the sender is never held up for long.
            let json = serde_json::to_vec(&*status.borrow());
            let response = match json {
                Ok(body) => Response {
                    code: 200,
                    content_type: "application/json",
                    body,
                    allow: false,
                },
                Err(error) => {
                    warn!(%error, "cannot serialise the status snapshot");
                    Response::error(500, "internal error")
                }
            };
            (response, head_only)
        }
        Request::Healthz { head_only } => (
            Response {
                code: 200,
                content_type: "text/plain; charset=utf-8",
                body: b"ok".to_vec(),
                allow: false,
            },
            head_only,
        ),
        Request::NotFound => (Response::error(404, "not found"), false),
        Request::MethodNotAllowed => {
            let mut response = Response::error(405, "method not allowed");
            response.allow = true;
            (response, false)
        }
        Request::VersionNotSupported => (Response::error(505, "HTTP version not supported"), false),
        Request::Bad => (Response::error(400, "bad request"), false),
    }
}

/// A complete response; every response closes the connection.
struct Response {
    code: u16,
    content_type: &'static str,
    body: Vec<u8>,
    /// Whether to send `Allow: GET, HEAD` (with 405).
    allow: bool,
}

impl Response {
    fn error(code: u16, message: &str) -> Response {
        Response {
            code,
            content_type: "application/json",
            body: serde_json::json!({ "error": message })
                .to_string()
                .into_bytes(),
            allow: false,
        }
    }

    fn to_bytes(&self, head_only: bool) -> Vec<u8> {
        let reason = match self.code {
            200 => "OK",
            400 => "Bad Request",
            404 => "Not Found",
            405 => "Method Not Allowed",
            408 => "Request Timeout",
            431 => "Request Header Fields Too Large",
            505 => "HTTP Version Not Supported",
            _ => "Internal Server Error",
        };
        let allow = if self.allow {
            "Allow: GET, HEAD\r\n"
        } else {
            ""
        };
        let mut bytes = format!(
            "HTTP/1.1 {} {reason}\r\nContent-Type: {}\r\nContent-Length: {}\r\n{allow}\
             Cache-Control: no-store\r\nConnection: close\r\n\r\n",
            self.code,
            self.content_type,
            self.body.len(),
        )
        .into_bytes();
        if !head_only {
            bytes.extend_from_slice(&self.body);
        }
        bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_names_are_single_dns_labels() {
        assert_eq!(instance_name("lab/kiwi-01"), "kiwi-01-lab");
        assert_eq!(instance_name("kiwi-01"), "kiwi-01");
        assert_eq!(instance_name("Lab/Kiwi_01.a"), "kiwi-01-a-lab");
        assert_eq!(instance_name("/"), "lekiwi");
        assert_eq!(instance_name(""), "lekiwi");
        assert_eq!(instance_name("ns/--x--"), "x-ns");

        let long = format!("fleet/{}", "k".repeat(80));
        let other = format!("fleet/{}x", "k".repeat(80));
        let (a, b) = (instance_name(&long), instance_name(&other));
        assert_eq!(a.len(), MAX_LABEL);
        assert_ne!(a, b, "shortened names stay distinct");
        assert!(
            a.bytes()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'-')
        );
    }

    #[test]
    fn txt_records_carry_identity_only() {
        let mut snapshot = StatusSnapshot {
            robot: "lab/kiwi".into(),
            agent_version: "1.2.3".into(),
            gateway: "wss://gw/v1/agent".into(),
            ..StatusSnapshot::default()
        };
        let txt = txt_records(&snapshot, 9477);
        assert_eq!(txt[2], ("release", String::new()));
        assert_eq!(txt[4], ("status_port", "9477".into()));
        snapshot.connected = true;
        snapshot.bytes_sent = 42;
        assert_eq!(
            txt_records(&snapshot, 9477),
            txt,
            "live state does not re-announce"
        );
        snapshot.release = Some(Release {
            version: "v2".into(),
            digest: "sha256:00".into(),
        });
        assert_eq!(txt_records(&snapshot, 9477)[2], ("release", "v2".into()));
    }

    #[test]
    fn snapshot_json_is_camel_case_and_lenient() {
        let json = serde_json::to_value(StatusSnapshot::default()).unwrap();
        for key in ["agentVersion", "outboxPending", "lastRttMs", "startedAtMs"] {
            assert!(json.get(key).is_some(), "{key} in {json}");
        }
        let parsed: StatusSnapshot = serde_json::from_str(r#"{"robot":"x","future":1}"#).unwrap();
        assert_eq!(parsed.robot, "x");
    }

    #[test]
    fn instance_of_strips_the_service_type() {
        assert_eq!(instance_of("kiwi-lab._lekiwi._tcp.local."), "kiwi-lab");
        assert_eq!(instance_of("odd"), "odd");
    }

    #[test]
    fn head_end_finds_the_empty_line() {
        assert_eq!(head_end(b"GET / HTTP/1.1\r\n\r\nbody"), Some(18));
        assert_eq!(head_end(b"GET / HTTP/1.1\n\n"), Some(16));
        assert_eq!(head_end(b"GET / HTTP/1.1\r\nHost: x\r\n"), None);
        assert_eq!(head_end(b""), None);
    }

    #[test]
    fn requests_are_routed() {
        let p = |s: &str| parse_request(s.as_bytes());
        assert_eq!(
            p("GET /status HTTP/1.1\r\nHost: x\r\n\r\n"),
            Request::Status { head_only: false }
        );
        assert_eq!(
            p("\r\nGET /status?pretty HTTP/1.0\r\n\r\n"),
            Request::Status { head_only: false }
        );
        assert_eq!(
            p("HEAD /healthz HTTP/1.1\r\n\r\n"),
            Request::Healthz { head_only: true }
        );
        assert_eq!(p("GET /nope HTTP/1.1\r\n\r\n"), Request::NotFound);
        assert_eq!(p("POST /nope HTTP/1.1\r\n\r\n"), Request::NotFound);
        assert_eq!(
            p("POST /status HTTP/1.1\r\n\r\n"),
            Request::MethodNotAllowed
        );
        assert_eq!(
            p("DELETE /healthz HTTP/1.1\r\n\r\n"),
            Request::MethodNotAllowed
        );
        assert_eq!(
            p("GET /status HTTP/2.0\r\n\r\n"),
            Request::VersionNotSupported
        );
        assert_eq!(p("GET /status\r\n\r\n"), Request::Bad);
        assert_eq!(p("GET  /status HTTP/1.1\r\n\r\n"), Request::Bad);
        assert_eq!(p("GET status HTTP/1.1\r\n\r\n"), Request::Bad);
        assert_eq!(p("G(T /status HTTP/1.1\r\n\r\n"), Request::Bad);
        assert_eq!(p("\r\n\r\n"), Request::Bad);
        assert_eq!(
            parse_request(b"\xff\xfe /status HTTP/1.1\r\n\r\n"),
            Request::Bad
        );
    }

    #[test]
    fn responses_close_and_head_has_no_body() {
        let (_tx, rx) = watch::channel(StatusSnapshot::default());
        let (response, head_only) = respond(Request::Healthz { head_only: true }, &rx);
        let text = String::from_utf8(response.to_bytes(head_only)).unwrap();
        assert!(text.starts_with("HTTP/1.1 200 OK\r\n"), "{text}");
        assert!(text.contains("Content-Length: 2\r\n"), "{text}");
        assert!(text.contains("Connection: close\r\n"), "{text}");
        assert!(text.ends_with("\r\n\r\n"), "{text}");

        let (response, head_only) = respond(Request::MethodNotAllowed, &rx);
        let text = String::from_utf8(response.to_bytes(head_only)).unwrap();
        assert!(
            text.starts_with("HTTP/1.1 405 Method Not Allowed\r\n"),
            "{text}"
        );
        assert!(text.contains("Allow: GET, HEAD\r\n"), "{text}");
        assert!(
            text.ends_with(r#"{"error":"method not allowed"}"#),
            "{text}"
        );
    }

    /// The answer to one request (sent, then the write side closed) from a fresh server.
    async fn exchange(request: &[u8]) -> String {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (_tx, rx) = watch::channel(StatusSnapshot {
            robot: "lab/kiwi".into(),
            ..StatusSnapshot::default()
        });
        let server = tokio::spawn(serve_status(listener, rx));
        let mut stream = TcpStream::connect(addr).await.unwrap();
        stream.write_all(request).await.unwrap();
        stream.shutdown().await.unwrap();
        let mut answer = Vec::new();
        stream.read_to_end(&mut answer).await.unwrap();
        server.abort();
        String::from_utf8_lossy(&answer).into_owned()
    }

    #[tokio::test]
    async fn serves_over_a_socket() {
        let text = exchange(b"GET /status HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(text.starts_with("HTTP/1.1 200 OK\r\n"), "{text}");
        assert!(
            text.ends_with("}") && text.contains(r#""robot":"lab/kiwi""#),
            "{text}"
        );

        let text = exchange(&[b'a'; MAX_HEAD_BYTES + 10]).await;
        assert!(text.starts_with("HTTP/1.1 431 "), "{text}");

        let text = exchange(b"GET /healthz HTTP/1.1\r\nHost: x").await;
        assert!(text.starts_with("HTTP/1.1 400 "), "{text}");
    }
}
