//! TLS for gateway connections on rustls's unbuffered API: a connection holds no TLS buffer while
//! it is idle (rustls's buffered connection keeps a 4 KiB read buffer in each, for life), and the
//! buffers it holds while busy are bounded.
//!
//! Received bytes are read only when the socket is readable, through a buffer on the stack, and
//! kept on the heap only until their records are complete; decrypted data is kept until the
//! reader takes it; encrypted data until the socket takes it. Each buffer is freed when it
//! empties. The TLS state machine is rustls's; this module only moves bytes.

use std::future::poll_fn;
use std::io;
use std::mem::MaybeUninit;
use std::path::Path;
use std::pin::Pin;
use std::sync::{Arc, RwLock};
use std::task::{Context, Poll, Waker, ready};

use rustls::ServerConfig;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::UnbufferedServerConnection;
use rustls::unbuffered::ConnectionState;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;

use records::{append, take_records, write_traffic};

/// The largest TLS record on the wire: a header, 16 KiB of data, and the most a cipher adds.
const MAX_RECORD: usize = 5 + 16_384 + 2_048;
/// The most received bytes a connection holds unprocessed: one handshake message may span
/// records up to 64 KiB (rustls's own bound), and one more record may follow it.
const MAX_INCOMING: usize = 0xffff + MAX_RECORD;
/// Bytes read from the socket at once: one whole record of the largest size.
const READ_CHUNK: usize = MAX_RECORD;
/// Application bytes encrypted into one record.
const MAX_FRAGMENT: usize = 16_384;
/// Room a record adds to its data (header, content type, tag); a larger need is retried.
const RECORD_OVERHEAD: usize = 64;

/// Accepts TLS connections with the server configuration of the moment: [`reload`] replaces it
/// when the certificate files change, and each handshake takes the one current when it starts
/// (open connections keep theirs).
#[derive(Clone)]
pub struct Acceptor {
    config: Arc<RwLock<Arc<ServerConfig>>>,
}

impl Acceptor {
    /// An acceptor for the PEM certificate chain and key files, the CA certificate(s) in `ca`
    /// (if any) sent after the chain so that `lekiwi-agent join` can pin the CA.
    pub async fn from_pem_files(cert: &Path, key: &Path, ca: Option<&Path>) -> io::Result<Self> {
        let mut chain = tokio::fs::read(cert).await?;
        if let Some(ca) = ca {
            append_pem(&mut chain, &tokio::fs::read(ca).await?);
        }
        let key = tokio::fs::read(key).await?;
        Self::from_pem(&chain, &key)
    }

    /// An acceptor for a PEM certificate chain (the gateway's own certificate first) and its key.
    pub fn from_pem(cert: &[u8], key: &[u8]) -> io::Result<Self> {
        Ok(Self {
            config: Arc::new(RwLock::new(Arc::new(server_config(cert, key)?))),
        })
    }

    /// Serves `cert` and `key` to the handshakes that start from now on; on an error (no
    /// certificate, a key that is not the certificate's) the configuration stays as it was.
    pub fn replace(&self, cert: &[u8], key: &[u8]) -> io::Result<()> {
        let config = Arc::new(server_config(cert, key)?);
        *self.config.write().unwrap_or_else(|p| p.into_inner()) = config;
        Ok(())
    }

    fn current(&self) -> Arc<ServerConfig> {
        self.config
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Runs the server side of a handshake on `io`; the caller bounds it in time.
    pub async fn accept(&self, io: TcpStream) -> io::Result<TlsStream> {
        let conn = UnbufferedServerConnection::new(self.current()).map_err(invalid)?;
        let mut tls = TlsStream {
            io,
            conn,
            incoming: Vec::new(),
            plaintext: Vec::new(),
            plaintext_read: 0,
            outgoing: Vec::new(),
            outgoing_sent: 0,
            peer_closed: false,
            close_sent: false,
            eof: false,
            broken: false,
            read_waker: None,
        };
        poll_fn(|cx| tls.poll_handshake(cx)).await?;
        Ok(tls)
    }
}

/// A server-side TLS connection over TCP, for hyper and the WebSocket sessions.
pub struct TlsStream {
    io: TcpStream,
    conn: UnbufferedServerConnection,
    /// Received bytes whose records are not complete yet (empty, unallocated, while idle).
    incoming: Vec<u8>,
    /// Decrypted data the reader has not taken yet, from `plaintext_read` on.
    plaintext: Vec<u8>,
    plaintext_read: usize,
    /// Encrypted bytes the socket has not taken yet, from `outgoing_sent` on.
    outgoing: Vec<u8>,
    outgoing_sent: usize,
    /// The peer sent close_notify: once its data is read, reads give end of file.
    peer_closed: bool,
    /// This side queued its close_notify: no more data may be written.
    close_sent: bool,
    /// The socket gave end of file.
    eof: bool,
    /// A step failed (rustls refused what the peer sent, say): every later read or write fails
    /// at once (stepping again would meet the same bytes).
    broken: bool,
    /// The task waiting to read, woken when a write decrypts data it had not seen.
    read_waker: Option<Waker>,
}

/// What the connection wants from one step of rustls's state machine.
#[derive(Clone, Copy)]
enum Want<'a> {
    Read,
    Write(&'a [u8]),
    Close,
}

/// What one step did.
#[derive(Debug, PartialEq)]
enum Step {
    /// Something changed: step again.
    Progress,
    /// Nothing more to do with the bytes held; a read needs more from the socket.
    Blocked,
    /// Encrypted this many bytes of the data to write (0 for a close_notify).
    Wrote(usize),
    /// Both sides have closed.
    Closed,
}

impl TlsStream {
    /// The bytes this connection holds in its own buffers.
    #[cfg(test)]
    fn buffered_capacity(&self) -> usize {
        self.incoming.capacity() + self.plaintext.capacity() + self.outgoing.capacity()
    }

    /// One step of the state machine over the received bytes held; after a failure, none.
    fn step(&mut self, want: Want<'_>) -> io::Result<Step> {
        if self.broken {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                "the TLS connection failed earlier",
            ));
        }
        let step = self.step_once(want);
        self.broken = step.is_err();
        step
    }

    /// Hands rustls the received bytes, does what the state it returns asks, and discards the
    /// bytes it consumed (freeing the buffer when it empties).
    fn step_once(&mut self, want: Want<'_>) -> io::Result<Step> {
        let Self {
            conn,
            incoming,
            plaintext,
            outgoing,
            peer_closed,
            close_sent,
            ..
        } = self;
        let status = conn.process_tls_records(incoming);
        let mut discard = status.discard;
        let step = match status.state {
            Err(error) => Err(error),
            Ok(ConnectionState::ReadTraffic(mut traffic)) => take_records(&mut traffic, plaintext)
                .map(|more| {
                    discard += more;
                    Step::Progress
                }),
            Ok(ConnectionState::EncodeTlsData(mut data)) => {
                append(outgoing, 0, |out| data.encode(out))?;
                Ok(Step::Progress)
            }
            Ok(ConnectionState::TransmitTlsData(data)) => {
                // The encoded bytes wait in `outgoing`, which the socket takes in order before
                // anything encoded later: for rustls they are as good as sent.
                data.done();
                Ok(Step::Progress)
            }
            Ok(ConnectionState::PeerClosed) => {
                *peer_closed = true;
                Ok(Step::Progress)
            }
            Ok(ConnectionState::Closed) => {
                *peer_closed = true;
                Ok(Step::Closed)
            }
            Ok(ConnectionState::BlockedHandshake) => Ok(Step::Blocked),
            Ok(ConnectionState::WriteTraffic(mut traffic)) => {
                Ok(write_traffic(&mut traffic, want, outgoing, close_sent)?)
            }
            // The server never accepts early data (its config allows none).
            Ok(ConnectionState::ReadEarlyData(_)) => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    "TLS early data, which this server does not accept",
                ));
            }
            Ok(other) => {
                return Err(io::Error::other(format!("unexpected TLS state {other:?}")));
            }
        };
        incoming.drain(..discard.min(incoming.len()));
        if incoming.is_empty() {
            *incoming = Vec::new();
        }
        step.map_err(|error| self.fail(error))
    }

    /// The connection failed: rustls has queued an alert telling the peer why, which is sent if
    /// the socket takes it now (the connection is dropped either way). The state machine is not
    /// stepped past what is queued: it would meet the same bad bytes again.
    fn fail(&mut self, error: rustls::Error) -> io::Error {
        while self.conn.wants_write() {
            let status = self.conn.process_tls_records(&mut self.incoming);
            match status.state {
                Ok(ConnectionState::EncodeTlsData(mut data)) => {
                    if append(&mut self.outgoing, 0, |out| data.encode(out)).is_err() {
                        break;
                    }
                }
                _ => break,
            }
        }
        self.try_flush();
        invalid(error)
    }

    /// Steps until the held bytes give nothing more, for reading.
    fn step_read(&mut self) -> io::Result<()> {
        loop {
            match self.step(Want::Read)? {
                Step::Progress => continue,
                Step::Blocked | Step::Closed | Step::Wrote(_) => return Ok(()),
            }
        }
    }

    /// The server's side of the handshake, until both sides may send data and this side's
    /// handshake bytes are on the wire.
    fn poll_handshake(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        loop {
            self.step_read()?;
            ready!(self.poll_flush_outgoing(cx))?;
            if self.peer_closed {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "the peer closed the connection during the TLS handshake",
                )));
            }
            if !self.conn.is_handshaking() {
                return Poll::Ready(Ok(()));
            }
            if self.eof {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "the connection ended during the TLS handshake",
                )));
            }
            ready!(self.poll_fill(cx))?;
        }
    }

    /// Waits until the socket is readable and appends what it has (at most one record's worth,
    /// read through the stack) to the received bytes; at end of file, sets `eof`.
    fn poll_fill(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let room = MAX_INCOMING.saturating_sub(self.incoming.len());
        if room == 0 {
            return Poll::Ready(Err(io::Error::new(
                io::ErrorKind::InvalidData,
                "a TLS message larger than this server accepts",
            )));
        }
        let mut chunk = [MaybeUninit::<u8>::uninit(); READ_CHUNK];
        let mut read = ReadBuf::uninit(&mut chunk[..room.min(READ_CHUNK)]);
        ready!(Pin::new(&mut self.io).poll_read(cx, &mut read))?;
        match read.filled() {
            [] => self.eof = true,
            bytes => self.incoming.extend_from_slice(bytes),
        }
        Poll::Ready(Ok(()))
    }

    /// Writes the encrypted bytes waiting, freeing their buffer once the socket took them all.
    fn poll_flush_outgoing(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        while self.outgoing_sent < self.outgoing.len() {
            let pending = &self.outgoing[self.outgoing_sent..];
            let n = ready!(Pin::new(&mut self.io).poll_write(cx, pending))?;
            if n == 0 {
                return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
            }
            self.outgoing_sent += n;
        }
        self.outgoing = Vec::new();
        self.outgoing_sent = 0;
        Poll::Ready(Ok(()))
    }

    /// Writes what the socket takes now of the encrypted bytes waiting, without waiting (a read
    /// must not claim the writer's wake-up); the rest goes with the next write or flush, which
    /// also reports a failed socket.
    fn try_flush(&mut self) {
        while self.outgoing_sent < self.outgoing.len() {
            match self.io.try_write(&self.outgoing[self.outgoing_sent..]) {
                Ok(n) if n > 0 => self.outgoing_sent += n,
                _ => return,
            }
        }
        self.outgoing = Vec::new();
        self.outgoing_sent = 0;
    }

    /// Wakes a waiting reader if data it has not seen was decrypted since it had `before`.
    fn wake_reader(&mut self, before: usize) {
        if self.plaintext.len() > before
            && let Some(waker) = self.read_waker.take()
        {
            waker.wake();
        }
    }
}

impl AsyncRead for TlsStream {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        if buf.remaining() == 0 {
            return Poll::Ready(Ok(()));
        }
        loop {
            this.step_read()?;
            // A key update answer, say: sent if the socket takes it now, else with the next write.
            this.try_flush();
            if this.plaintext_read < this.plaintext.len() {
                let held = &this.plaintext[this.plaintext_read..];
                let n = held.len().min(buf.remaining());
                buf.put_slice(&held[..n]);
                this.plaintext_read += n;
                if this.plaintext_read == this.plaintext.len() {
                    this.plaintext = Vec::new();
                    this.plaintext_read = 0;
                }
                return Poll::Ready(Ok(()));
            }
            if this.peer_closed {
                return Poll::Ready(Ok(()));
            }
            if this.eof {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "the peer closed the connection without a TLS close_notify",
                )));
            }
            if !this
                .read_waker
                .as_ref()
                .is_some_and(|w| w.will_wake(cx.waker()))
            {
                this.read_waker = Some(cx.waker().clone());
            }
            ready!(this.poll_fill(cx))?;
        }
    }
}

impl AsyncWrite for TlsStream {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        if buf.is_empty() {
            return Poll::Ready(Ok(0));
        }
        if this.close_sent {
            return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into()));
        }
        // One record at a time: the last one must be on its way before this one is made.
        ready!(this.poll_flush_outgoing(cx))?;
        let before = this.plaintext.len();
        loop {
            match this.step(Want::Write(buf)) {
                Ok(Step::Progress) => continue,
                Ok(Step::Wrote(n)) => {
                    this.wake_reader(before);
                    // Sent now if the socket takes it; otherwise the next write or flush sends it.
                    if let Poll::Ready(Err(e)) = this.poll_flush_outgoing(cx) {
                        return Poll::Ready(Err(e));
                    }
                    return Poll::Ready(Ok(n));
                }
                Ok(Step::Closed) => return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into())),
                Ok(Step::Blocked) => {
                    return Poll::Ready(Err(io::Error::other(
                        "a write before the TLS handshake completed",
                    )));
                }
                Err(e) => {
                    this.wake_reader(before);
                    return Poll::Ready(Err(e));
                }
            }
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(this.poll_flush_outgoing(cx))?;
        Pin::new(&mut this.io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        while !this.close_sent {
            match this.step(Want::Close)? {
                Step::Progress => continue,
                // Closed already, or (never after the handshake) no close_notify to send.
                Step::Closed | Step::Blocked => break,
                Step::Wrote(_) => {}
            }
        }
        ready!(this.poll_flush_outgoing(cx))?;
        Pin::new(&mut this.io).poll_shutdown(cx)
    }
}

/// The server configuration for a PEM certificate chain and key: HTTP/1.1 only (agents speak
/// WebSocket over HTTP/1.1; the gateway serves no HTTP/2). Refuses a key that is not the
/// certificate's.
fn server_config(cert: &[u8], key: &[u8]) -> io::Result<ServerConfig> {
    let _ = rustls::crypto::ring::default_provider().install_default();
    let bad_pem = |what: &str, e: rustls::pki_types::pem::Error| {
        io::Error::new(io::ErrorKind::InvalidData, format!("{what}: {e}"))
    };
    let chain = CertificateDer::pem_slice_iter(cert)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| bad_pem("the certificate file", e))?;
    if chain.is_empty() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            "the certificate file holds no PEM certificate",
        ));
    }
    let key = PrivateKeyDer::from_pem_slice(key).map_err(|e| bad_pem("the key file", e))?;
    let mut config = ServerConfig::builder()
        .with_no_client_auth()
        .with_single_cert(chain, key)
        .map_err(invalid)?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(config)
}

/// Appends the PEM text `more` to `chain`, on a line of its own.
pub(crate) fn append_pem(chain: &mut Vec<u8>, more: &[u8]) {
    if !chain.is_empty() && !chain.ends_with(b"\n") {
        chain.push(b'\n');
    }
    chain.extend_from_slice(more);
}

fn invalid(error: rustls::Error) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, error)
}

mod records;
pub mod reload;
#[cfg(test)]
mod tests;
