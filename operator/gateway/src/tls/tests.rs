//! The unbuffered TLS stream against rustls's own client (tokio-rustls) over real loopback
//! sockets: both protocol versions, data both ways at once, a handshake one byte at a time, key
//! updates, clean and bare closes, and hostile bytes.

use std::path::Path;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, ServerName};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::timeout;

use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;

use super::reload::{self, CertFiles, TlsMetrics};
use super::{Acceptor, TlsStream};
use lekiwi_metrics::KindLabels;

type Client<S = TcpStream> = tokio_rustls::client::TlsStream<S>;

/// A CA and an ECDSA P-256 certificate for 127.0.0.1 it signed, made with openssl.
fn certificates(dir: &Path) {
    let script = r#"set -e
openssl ecparam -name prime256v1 -genkey -noout -out ca.key
openssl req -x509 -new -key ca.key -days 1 -subj /CN=tls-test-ca -out ca.crt
openssl ecparam -name prime256v1 -genkey -noout -out tls.key
openssl req -new -key tls.key -subj /CN=127.0.0.1 -out tls.csr
printf 'subjectAltName=IP:127.0.0.1\n' > ext
openssl x509 -req -in tls.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 1 -extfile ext -out tls.crt 2>/dev/null
"#;
    let status = std::process::Command::new("sh")
        .args(["-c", script])
        .current_dir(dir)
        .status()
        .expect("openssl runs");
    assert!(status.success(), "openssl made the certificates");
}

/// The pieces of one test: an acceptor, a listener and a client configuration.
struct Bed {
    _dir: tempfile::TempDir,
    acceptor: Acceptor,
    listener: TcpListener,
    client: Arc<rustls::ClientConfig>,
}

async fn bed(versions: &[&'static rustls::SupportedProtocolVersion]) -> Bed {
    let dir = tempfile::tempdir().unwrap();
    certificates(dir.path());
    let acceptor = Acceptor::from_pem_files(
        &dir.path().join("tls.crt"),
        &dir.path().join("tls.key"),
        None,
    )
    .await
    .unwrap();
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_file_iter(dir.path().join("ca.crt")).unwrap() {
        roots.add(cert.unwrap()).unwrap();
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let client = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(versions)
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    Bed {
        _dir: dir,
        acceptor,
        listener: TcpListener::bind("127.0.0.1:0").await.unwrap(),
        client: Arc::new(client),
    }
}

impl Bed {
    /// A raw TCP connection to the listener and the server's side of it.
    async fn raw(&self) -> (TcpStream, TcpStream) {
        let addr = self.listener.local_addr().unwrap();
        let (client, accepted) = tokio::join!(TcpStream::connect(addr), self.listener.accept());
        (client.unwrap(), accepted.unwrap().0)
    }

    /// A TLS connection, client and server, over `wrap`ped client socket.
    async fn pair_over<S>(&self, wrap: impl FnOnce(TcpStream) -> S) -> (Client<S>, TlsStream)
    where
        S: AsyncRead + AsyncWrite + Unpin,
    {
        let (client, server) = self.raw().await;
        let connector = tokio_rustls::TlsConnector::from(self.client.clone());
        let name = ServerName::try_from("127.0.0.1").unwrap();
        let (client, server) = tokio::join!(
            connector.connect(name, wrap(client)),
            self.acceptor.accept(server)
        );
        (client.unwrap(), server.unwrap())
    }

    async fn pair(&self) -> (Client, TlsStream) {
        self.pair_over(|s| s).await
    }
}

/// `len` bytes of a pattern that shifts with `seed`.
fn pattern(len: usize, seed: u8) -> Vec<u8> {
    (0..len).map(|i| (i % 251) as u8 ^ seed).collect()
}

/// Reads everything until end of file, in reads of at most 512 bytes (as the WebSocket layer
/// reads).
async fn read_small(reader: &mut (impl AsyncRead + Unpin), len: usize) -> Vec<u8> {
    let mut all = Vec::new();
    let mut buf = [0u8; 512];
    while all.len() < len {
        let n = reader.read(&mut buf).await.unwrap();
        assert!(n > 0, "end of file after {} of {len} bytes", all.len());
        all.extend_from_slice(&buf[..n]);
    }
    all
}

/// 1 MiB each way at once, then the server's buffers are all freed.
async fn exchange(client: Client, server: TlsStream) -> TlsStream {
    const LEN: usize = 1 << 20;
    let (mut client_read, mut client_write) = tokio::io::split(client);
    let (mut server_read, mut server_write) = tokio::io::split(server);
    let up = pattern(LEN, 1);
    let down = pattern(LEN, 2);
    let (got_up, got_down, (), ()) = tokio::join!(
        read_small(&mut server_read, LEN),
        read_small(&mut client_read, LEN),
        async {
            client_write.write_all(&up).await.unwrap();
            client_write.flush().await.unwrap();
        },
        async {
            server_write.write_all(&down).await.unwrap();
            server_write.flush().await.unwrap();
        },
    );
    assert!(got_up == up, "the server read what the client wrote");
    assert!(got_down == down, "the client read what the server wrote");
    let server = server_read.unsplit(server_write);
    assert_eq!(
        server.buffered_capacity(),
        0,
        "an idle connection holds no buffer"
    );
    server
}

#[tokio::test]
async fn tls13_carries_data_both_ways_and_an_idle_connection_holds_no_buffer() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (client, server) = bed.pair().await;
    assert_eq!(
        server.buffered_capacity(),
        0,
        "nothing held after the handshake"
    );
    exchange(client, server).await;
}

#[tokio::test]
async fn tls12_carries_data_both_ways() {
    let bed = bed(&[&rustls::version::TLS12]).await;
    let (client, server) = bed.pair().await;
    exchange(client, server).await;
}

/// A socket that writes one byte at a time, each flushed on its own.
struct Dribble(TcpStream);

impl AsyncRead for Dribble {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.0).poll_read(cx, buf)
    }
}

impl AsyncWrite for Dribble {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        let one = &buf[..buf.len().min(1)];
        Pin::new(&mut self.0).poll_write(cx, one)
    }
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.0).poll_flush(cx)
    }
    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.0).poll_shutdown(cx)
    }
}

#[tokio::test]
async fn a_handshake_and_records_sent_one_byte_at_a_time_arrive_whole() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (mut client, mut server) = bed
        .pair_over(|s| {
            s.set_nodelay(true).unwrap();
            Dribble(s)
        })
        .await;
    let message = pattern(3000, 7);
    let (got, ()) = tokio::join!(read_small(&mut server, message.len()), async {
        client.write_all(&message).await.unwrap();
        client.flush().await.unwrap();
    });
    assert_eq!(got, message);
    assert_eq!(server.buffered_capacity(), 0);
}

#[tokio::test]
async fn key_updates_from_the_client_are_answered() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (mut client, mut server) = bed.pair().await;
    for round in 0..3u8 {
        client.get_mut().1.refresh_traffic_keys().unwrap();
        let up = pattern(20_000, round);
        client.write_all(&up).await.unwrap();
        client.flush().await.unwrap();
        assert_eq!(read_small(&mut server, up.len()).await, up);
        let down = pattern(20_000, round ^ 0x55);
        server.write_all(&down).await.unwrap();
        server.flush().await.unwrap();
        assert_eq!(read_small(&mut client, down.len()).await, down);
    }
}

/// `from` writes `words` and closes with close_notify; `to` reads them, then a clean end of file.
async fn last_words(
    from: &mut (impl AsyncWrite + Unpin),
    to: &mut (impl AsyncRead + Unpin),
    words: &[u8],
) {
    from.write_all(words).await.unwrap();
    from.shutdown().await.unwrap();
    let mut got = Vec::new();
    to.read_to_end(&mut got).await.unwrap();
    assert_eq!(got, words);
}

#[tokio::test]
async fn close_notify_ends_reads_cleanly_both_ways() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (mut client, mut server) = bed.pair().await;
    last_words(&mut client, &mut server, b"last words").await;

    let (mut client, mut server) = bed.pair().await;
    last_words(&mut server, &mut client, b"goodbye").await;
    let refused = server.write_all(b"more").await.unwrap_err();
    assert_eq!(refused.kind(), std::io::ErrorKind::BrokenPipe);
}

#[tokio::test]
async fn a_connection_cut_without_close_notify_is_an_error_not_an_end() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (client, mut server) = bed.pair().await;
    // A FIN, with no close_notify before it.
    let mut raw = client.into_inner().0;
    raw.shutdown().await.unwrap();
    let mut got = Vec::new();
    let err = server.read_to_end(&mut got).await.unwrap_err();
    assert_eq!(err.kind(), std::io::ErrorKind::UnexpectedEof, "{err}");
}

/// Writes `bytes` under the client's TLS (as an attacker on the path could), after one round
/// trip (so the client has taken the server's session tickets), and returns the server's read
/// error and what the client's socket received after it.
async fn inject(bytes: &[u8]) -> (std::io::Error, Vec<u8>) {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (mut client, mut server) = bed.pair().await;
    server.write_all(b"ready").await.unwrap();
    assert_eq!(read_small(&mut client, 5).await, b"ready");
    let mut raw = client.into_inner().0;
    raw.write_all(bytes).await.unwrap();
    let mut buf = [0u8; 64];
    let err = timeout(Duration::from_secs(10), server.read(&mut buf))
        .await
        .expect("the server gives up at once")
        .unwrap_err();
    // Once failed, it stays failed: no second alert, no panic.
    assert!(server.read(&mut buf).await.is_err());
    assert!(server.write_all(b"x").await.is_err());
    drop(server);
    let mut answer = Vec::new();
    let _ = timeout(Duration::from_secs(10), raw.read_to_end(&mut answer)).await;
    (err, answer)
}

/// One TLS 1.3 record holding an encrypted alert: the header, then the alert (2 bytes), its
/// content type (1) and the AEAD tag (16).
const ENCRYPTED_ALERT: [u8; 5] = [0x17, 0x03, 0x03, 0x00, 0x13];

#[tokio::test]
async fn a_forged_record_fails_with_an_alert() {
    let mut forged = vec![0x17, 0x03, 0x03, 0x00, 0x20];
    forged.extend_from_slice(&[0xAB; 0x20]);
    let (err, answer) = inject(&forged).await;
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidData, "{err}");
    assert_eq!(answer.len(), 5 + 0x13, "one alert record: {answer:02x?}");
    assert_eq!(answer[..5], ENCRYPTED_ALERT);
}

#[tokio::test]
async fn an_oversized_record_is_refused_from_its_header() {
    let (err, answer) = inject(&[0x17, 0x03, 0x03, 0xFF, 0xFF]).await;
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidData, "{err}");
    assert_eq!(answer.get(..5), Some(&ENCRYPTED_ALERT[..]), "{answer:02x?}");
}

#[tokio::test]
async fn plain_http_is_refused_at_the_handshake() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (mut client, server) = bed.raw().await;
    client
        .write_all(b"GET / HTTP/1.1\r\nhost: x\r\n\r\n")
        .await
        .unwrap();
    let err = bed.acceptor.accept(server).await.err().expect("refused");
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidData, "{err}");
}

#[tokio::test]
async fn a_handshake_message_larger_than_allowed_is_refused_from_its_header() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (mut client, server) = bed.raw().await;
    // A ClientHello announcing 16 MiB (rustls takes at most 64 KiB), then nothing more: the
    // server must refuse it from the header, not wait for (and buffer) the rest.
    let mut record = vec![0x16, 0x03, 0x01, 0x40, 0x00, 0x01, 0xFF, 0xFF, 0xFF];
    record.resize(5 + 0x4000, 0);
    client.write_all(&record).await.unwrap();
    let err = timeout(Duration::from_secs(10), bed.acceptor.accept(server))
        .await
        .expect("the server gives up without more bytes")
        .err()
        .expect("refused");
    assert_eq!(err.kind(), std::io::ErrorKind::InvalidData, "{err}");
}

#[tokio::test]
async fn a_peer_that_stops_reading_holds_the_writer_to_one_record() {
    let bed = bed(&[&rustls::version::TLS13]).await;
    let (_client, mut server) = bed.pair().await;
    let flood = vec![0x5A; 64 << 20];
    let written = timeout(Duration::from_secs(2), server.write_all(&flood)).await;
    assert!(written.is_err(), "the write waits for the peer");
    let held = server.buffered_capacity();
    assert!(
        held <= super::MAX_FRAGMENT + super::RECORD_OVERHEAD,
        "held {held} bytes"
    );
}

/// Makes a new key and a certificate for 127.0.0.1 from the same CA in `dir`, valid a day longer
/// than the first, and puts them in place of `tls.crt` and `tls.key`, each by a rename (as a
/// Secret volume swaps its files).
fn renew(dir: &Path) {
    let script = r#"set -e
openssl ecparam -name prime256v1 -genkey -noout -out new.key
openssl req -new -key new.key -subj /CN=127.0.0.1 -out new.csr
openssl x509 -req -in new.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 2 -extfile ext -out new.crt 2>/dev/null
mv new.crt tls.crt
mv new.key tls.key
"#;
    let status = std::process::Command::new("sh")
        .args(["-c", script])
        .current_dir(dir)
        .status()
        .expect("openssl runs");
    assert!(status.success(), "openssl renewed the certificate");
}

/// The certificate the server presented to `client`.
fn presented(client: &Client) -> Vec<u8> {
    client.get_ref().1.peer_certificates().unwrap()[0].to_vec()
}

/// The certificate in `dir/tls.crt`, as DER.
fn on_disk(dir: &Path) -> Vec<u8> {
    CertificateDer::from_pem_file(dir.join("tls.crt"))
        .unwrap()
        .to_vec()
}

/// Waits (up to 5 s) until `reloads` counts `n` of `kind`.
async fn counted(reloads: &Family<KindLabels, Counter>, kind: &'static str, n: u64) {
    let wait = async {
        while reloads.get_or_create(&KindLabels { kind }).get() < n {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    };
    timeout(Duration::from_secs(5), wait)
        .await
        .unwrap_or_else(|_| panic!("no {n} {kind} reload(s)"));
}

#[tokio::test]
async fn new_files_serve_new_connections_while_open_ones_stay_and_bad_ones_are_not_served() {
    let mut bed = bed(&[&rustls::version::TLS13]).await;
    let dir = bed._dir.path().to_owned();
    let files = CertFiles {
        cert: dir.join("tls.crt"),
        key: dir.join("tls.key"),
        ca: None,
    };
    let (acceptor, loaded) = files.load().await.unwrap();
    bed.acceptor = acceptor.clone();
    let metrics = TlsMetrics::default();
    let reloads = metrics.reloads.clone();
    let cancel = tokio_util::sync::CancellationToken::new();
    let every = Duration::from_millis(20);
    let watch = reload::watch(
        acceptor,
        files,
        loaded,
        every,
        metrics.clone(),
        cancel.clone(),
    );
    tokio::spawn(watch);
    let first = on_disk(&dir);
    let (old_client, old_server) = bed.pair().await;
    assert_eq!(presented(&old_client), first);
    let first_expiry = openssl_not_after(&dir.join("tls.crt"));
    assert_eq!(metrics.expiry.get(), first_expiry, "the expiry served");

    renew(&dir);
    counted(&reloads, "reloaded", 1).await;
    let second_expiry = openssl_not_after(&dir.join("tls.crt"));
    assert_eq!(metrics.expiry.get(), second_expiry, "the renewed expiry");
    assert!(second_expiry - first_expiry > 86_000, "a day later");
    let second = on_disk(&dir);
    assert_ne!(second, first, "a new certificate");
    let (client, _server) = bed.pair().await;
    assert_eq!(
        presented(&client),
        second,
        "a new connection gets the new one"
    );
    // The connection made before carries data as before.
    exchange(old_client, old_server).await;

    // A key of another certificate: refused, counted, the last good pair still served.
    std::fs::copy(dir.join("ca.key"), dir.join("tls.key")).unwrap();
    counted(&reloads, "failed", 1).await;
    let (client, _server) = bed.pair().await;
    assert_eq!(presented(&client), second);
    assert_eq!(
        reloads
            .get_or_create(&KindLabels { kind: "reloaded" })
            .get(),
        1
    );
    assert_eq!(
        metrics.expiry.get(),
        second_expiry,
        "still the served one's"
    );
    cancel.cancel();
}

/// The notAfter of the certificate in `file` as openssl reads it, in Unix seconds.
fn openssl_not_after(file: &Path) -> i64 {
    let out = std::process::Command::new("openssl")
        .args(["x509", "-noout", "-enddate", "-dateopt", "iso_8601", "-in"])
        .arg(file)
        .output()
        .expect("openssl runs");
    let text = String::from_utf8(out.stdout).unwrap();
    let at = text.trim().strip_prefix("notAfter=").expect(&text);
    at.parse::<jiff::Timestamp>().expect(at).as_second()
}

#[test]
fn not_after_reads_what_openssl_reads_and_nothing_from_garbage() {
    let dir = tempfile::tempdir().unwrap();
    certificates(dir.path());
    for file in ["tls.crt", "ca.crt"] {
        let pem = std::fs::read(dir.path().join(file)).unwrap();
        let expected = openssl_not_after(&dir.path().join(file));
        assert_eq!(reload::not_after(&pem), Some(expected), "{file}");
    }
    assert_eq!(reload::not_after(b"not a certificate"), None);
    let garbage = b"-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n";
    assert_eq!(reload::not_after(garbage), None);
}
