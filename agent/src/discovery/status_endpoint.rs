//! The agent's local status endpoint: a deliberately tiny HTTP/1.1 server for `GET /status`
//! (the [`StatusSnapshot`] as JSON) and `GET /healthz`, one request per connection.

use std::io;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, watch};
use tracing::{debug, warn};

use super::StatusSnapshot;

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
