//! Deployments against a tiny in-process blob server: differential downloads, verification,
//! resume, rollback, crash recovery and garbage collection, checked on disk and on the wire.

use std::collections::{HashMap, HashSet};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use lekiwi_protocol::Release;
use lekiwi_protocol::release::{ManifestFile, ReleaseManifest};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpListener;
use tokio::sync::mpsc::{UnboundedReceiver, unbounded_channel};

use super::store::{Active, Journal, JournalPhase, Layout, sha256_digest};
use super::*;

const TOKEN: &str = "lkr_test";

/// One request the server saw.
#[derive(Clone, Debug)]
struct Seen {
    path: String,
    range: Option<u64>,
}

#[derive(Default)]
struct ServerState {
    /// Blobs by digest.
    blobs: HashMap<String, Vec<u8>>,
    seen: Vec<Seen>,
    /// Body bytes sent per path.
    sent: HashMap<String, u64>,
    /// Digests served with one byte changed.
    corrupt: HashSet<String>,
    /// Digest → bytes sent before the connection is dropped (once).
    drop_after: HashMap<String, usize>,
    /// Digest → bytes sent before the server stops sending (until the test ends).
    stall_after: HashMap<String, usize>,
}

/// A blob server on 127.0.0.1 that speaks just enough HTTP/1.1 (keep-alive, `Range`).
#[derive(Clone)]
struct Server {
    url: String,
    state: Arc<Mutex<ServerState>>,
}

impl Server {
    async fn start() -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let state = Arc::new(Mutex::new(ServerState::default()));
        let s = state.clone();
        tokio::spawn(async move {
            while let Ok((conn, _)) = listener.accept().await {
                tokio::spawn(serve(conn, s.clone()));
            }
        });
        Self { url, state }
    }

    fn access(&self) -> GatewayAccess {
        GatewayAccess {
            base_url: self.url.clone(),
            token: TOKEN.into(),
            robot: "lab/kiwi-1".into(),
            ca_file: None,
        }
    }

    fn put(&self, bytes: Vec<u8>) -> String {
        let digest = sha256_digest(&bytes);
        self.state
            .lock()
            .unwrap()
            .blobs
            .insert(digest.clone(), bytes);
        digest
    }

    /// Publishes a release of `files` (path, content, mode).
    fn publish(&self, version: &str, files: &[(String, Vec<u8>, u32)]) -> Release {
        let manifest = ReleaseManifest::new(
            version,
            files
                .iter()
                .map(|(path, content, mode)| ManifestFile {
                    path: path.clone(),
                    digest: self.put(content.clone()),
                    size: content.len() as u64,
                    mode: *mode,
                })
                .collect(),
        );
        Release {
            version: version.into(),
            digest: self.put(manifest.to_bytes()),
        }
    }

    fn seen(&self) -> Vec<Seen> {
        self.state.lock().unwrap().seen.clone()
    }

    /// The `Range` start of each request for `path`, in order (`None`: the whole blob).
    fn ranges(&self, path: &str) -> Vec<Option<u64>> {
        self.seen()
            .iter()
            .filter(|s| s.path == path)
            .map(|s| s.range)
            .collect()
    }

    fn requests(&self) -> usize {
        self.state.lock().unwrap().seen.len()
    }

    fn with(&self, f: impl FnOnce(&mut ServerState)) {
        f(&mut self.state.lock().unwrap());
    }
}

async fn serve(conn: tokio::net::TcpStream, state: Arc<Mutex<ServerState>>) {
    let (read, mut write) = conn.into_split();
    let mut read = BufReader::new(read);
    loop {
        let mut line = String::new();
        if read.read_line(&mut line).await.unwrap_or(0) == 0 {
            return;
        }
        let path = line
            .split_whitespace()
            .nth(1)
            .unwrap_or_default()
            .to_owned();
        let (mut auth, mut range) = (String::new(), None);
        loop {
            let mut h = String::new();
            if read.read_line(&mut h).await.unwrap_or(0) == 0 {
                return;
            }
            let h = h.trim_end();
            if h.is_empty() {
                break;
            }
            let (name, value) = h.split_once(':').unwrap_or((h, ""));
            match name.to_ascii_lowercase().as_str() {
                "authorization" => auth = value.trim().to_owned(),
                "range" => {
                    range = value
                        .trim()
                        .strip_prefix("bytes=")
                        .and_then(|r| r.strip_suffix('-'))
                        .and_then(|n| n.parse::<u64>().ok());
                }
                _ => {}
            }
        }
        let digest = path
            .strip_prefix("/v1/blobs/")
            .unwrap_or_default()
            .to_owned();
        enum Fault {
            None,
            Drop(usize),
            Stall(usize),
        }
        let (blob, fault) = {
            let mut s = state.lock().unwrap();
            s.seen.push(Seen {
                path: path.clone(),
                range,
            });
            let mut blob = s.blobs.get(&digest).cloned();
            if let Some(b) = &mut blob
                && s.corrupt.contains(&digest)
                && !b.is_empty()
            {
                b[0] ^= 0xff;
            }
            let fault = if let Some(n) = s.drop_after.remove(&digest) {
                Fault::Drop(n)
            } else if let Some(n) = s.stall_after.get(&digest) {
                Fault::Stall(*n)
            } else {
                Fault::None
            };
            (blob, fault)
        };
        if auth != format!("Bearer {TOKEN}") {
            let body = r#"{"error":"unauthorized","message":"bad robot token"}"#;
            let head = format!(
                "HTTP/1.1 401 Unauthorized\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n",
                body.len()
            );
            let _ = write.write_all(format!("{head}{body}").as_bytes()).await;
            continue;
        }
        let Some(blob) = blob else {
            let body = r#"{"error":"not_found","message":"unknown digest"}"#;
            let head = format!(
                "HTTP/1.1 404 Not Found\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n",
                body.len()
            );
            let _ = write.write_all(format!("{head}{body}").as_bytes()).await;
            continue;
        };
        let from = range.unwrap_or(0).min(blob.len() as u64) as usize;
        let body = &blob[from..];
        let head = if range.is_some() {
            format!(
                "HTTP/1.1 206 Partial Content\r\ncontent-length: {}\r\ncontent-range: bytes {from}-{}/{}\r\n\r\n",
                body.len(),
                blob.len().saturating_sub(1),
                blob.len()
            )
        } else {
            format!("HTTP/1.1 200 OK\r\ncontent-length: {}\r\n\r\n", body.len())
        };
        let n = match fault {
            Fault::None => body.len(),
            Fault::Drop(n) | Fault::Stall(n) => n.min(body.len()),
        };
        if write.write_all(head.as_bytes()).await.is_err()
            || write.write_all(&body[..n]).await.is_err()
            || write.flush().await.is_err()
        {
            return;
        }
        *state.lock().unwrap().sent.entry(path).or_default() += n as u64;
        match fault {
            Fault::None => {}
            Fault::Drop(_) => return,
            Fault::Stall(_) => {
                tokio::time::sleep(Duration::from_secs(3600)).await;
                return;
            }
        }
    }
}

/// `count` files `f<i>.txt` whose content depends on `seed` for those in `changed`.
fn files(count: usize, changed: &[usize], seed: &str) -> Vec<(String, Vec<u8>, u32)> {
    let mut v: Vec<_> = (0..count)
        .map(|i| {
            let content = if changed.contains(&i) {
                format!("file {i} of {seed}\n")
            } else {
                format!("file {i}\n")
            };
            (
                format!("dir{}/f{i}.txt", i % 5),
                content.into_bytes(),
                0o644,
            )
        })
        .collect();
    v.push(("bin/run".into(), b"#!/bin/sh\necho run\n".to_vec(), 0o755));
    v
}

fn healthy(mut files: Vec<(String, Vec<u8>, u32)>) -> Vec<(String, Vec<u8>, u32)> {
    files.push(("healthy".into(), b"yes\n".to_vec(), 0o644));
    files
}

struct Fixture {
    _dir: tempfile::TempDir,
    state: PathBuf,
    server: Server,
    config: Config,
}

impl Fixture {
    async fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        std::fs::create_dir(&state).unwrap();
        let log = state.join("restarts.log");
        let config = Config {
            state_dir: state.clone(),
            release_restart_command: format!(
                "echo \"$LEKIWI_RELEASE_VERSION after $LEKIWI_PREVIOUS_VERSION\" >> {}",
                log.display()
            ),
            release_health_command: "test -e \"$LEKIWI_RELEASE_DIR/healthy\"".into(),
            release_health_timeout_s: 1,
            release_keep: 3,
            ..Config::default()
        };
        Self {
            _dir: dir,
            state,
            server: Server::start().await,
            config,
        }
    }

    fn open(&self) -> Releases {
        let mut r = Releases::open(&self.config, self.server.access()).unwrap();
        // The timeout stays 1 s (from the config): generous for a loaded CI machine, short
        // enough for the tests that wait for a health check to fail.
        r.hooks.health_interval = Duration::from_millis(100);
        r
    }

    fn restarts(&self) -> Vec<String> {
        std::fs::read_to_string(self.state.join("restarts.log"))
            .unwrap_or_default()
            .lines()
            .map(str::to_owned)
            .collect()
    }

    fn current_file(&self, path: &str) -> String {
        std::fs::read_to_string(self.state.join("current").join(path)).unwrap()
    }

    fn layout(&self) -> Layout {
        Layout::new(&self.state)
    }

    fn dir_names(&self, sub: &str) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(self.state.join(sub))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }
}

async fn deploy(r: &mut Releases, id: &str, release: &Release) -> (Outcome, Vec<Progress>) {
    let (tx, mut rx) = unbounded_channel();
    let url = lekiwi_protocol::release::blob_path(&release.digest);
    let outcome = r.deploy(id, release, &url, &tx).await;
    (outcome, drain(&mut rx))
}

fn drain(rx: &mut UnboundedReceiver<Progress>) -> Vec<Progress> {
    let mut v = Vec::new();
    while let Ok(p) = rx.try_recv() {
        v.push(p);
    }
    v
}

fn phases(progress: &[Progress]) -> Vec<Phase> {
    let mut v: Vec<Phase> = Vec::new();
    for p in progress {
        if v.last() != Some(&p.phase) {
            v.push(p.phase);
        }
    }
    v
}

#[tokio::test]
async fn first_deploy_downloads_everything_and_the_next_only_what_changed() {
    let fx = Fixture::new().await;
    let v1 = fx.server.publish("1.0.0", &healthy(files(50, &[], "v1")));
    let mut r = fx.open();
    assert_eq!(r.current(), None);

    let (out, progress) = deploy(&mut r, "c1", &v1).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    assert_eq!(out.current.as_ref(), Some(&v1));
    assert_eq!((out.files_downloaded, out.files_reused), (52, 0));
    assert_eq!(fx.server.requests(), 53, "manifest + 52 blobs");
    assert_eq!(
        phases(&progress),
        [
            Phase::Downloading,
            Phase::Verifying,
            Phase::Assembling,
            Phase::Switching,
            Phase::Restarting,
            Phase::HealthCheck,
            Phase::Done
        ]
    );
    let last = progress.last().unwrap();
    assert_eq!(
        (last.command_id.as_str(), last.percent),
        ("c1", Some(100.0))
    );
    assert_eq!(last.bytes_downloaded, out.bytes_downloaded);
    assert!(progress.len() < 20, "rate-limited: {}", progress.len());
    assert_eq!(fx.current_file("dir3/f13.txt"), "file 13\n");
    let run = fx.state.join("current/bin/run");
    assert_eq!(
        std::fs::metadata(&run).unwrap().permissions().mode() & 0o777,
        0o755
    );
    assert_eq!(
        std::fs::read_link(fx.state.join("current")).unwrap(),
        Path::new("releases/1.0.0")
    );
    assert_eq!(r.current(), Some(v1.clone()));

    // Three of 52 files change: three blobs and the manifest cross the wire.
    let v2 = fx
        .server
        .publish("1.1.0", &healthy(files(50, &[3, 17, 42], "v2")));
    let before = fx.server.requests();
    let (out, _) = deploy(&mut r, "c2", &v2).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    assert_eq!((out.files_downloaded, out.files_reused), (3, 49));
    let seen = fx.server.seen();
    let new: Vec<&str> = seen[before..].iter().map(|s| s.path.as_str()).collect();
    assert_eq!(new.len(), 4, "{new:?}");
    assert_eq!(new[0], format!("/v1/blobs/{}", v2.digest));
    assert_eq!(fx.current_file("dir2/f17.txt"), "file 17 of v2\n");
    assert_eq!(fx.current_file("dir3/f18.txt"), "file 18\n");
    assert_eq!(fx.restarts(), ["1.0.0 after ", "1.1.0 after 1.0.0"]);

    // Idempotent: the current release again, and a repeated command id, do nothing.
    let before = fx.server.requests();
    let (out, progress) = deploy(&mut r, "c3", &v2).await;
    assert_eq!(out.phase, Phase::Done);
    assert!(out.message.contains("already current"), "{}", out.message);
    assert_eq!(phases(&progress), [Phase::Done]);
    let (out, _) = deploy(&mut r, "c1", &v1).await;
    assert_eq!(out.phase, Phase::Done);
    assert!(out.message.contains("already executed"), "{}", out.message);
    assert_eq!(r.current(), Some(v2));
    assert_eq!(fx.server.requests(), before);
    assert_eq!(fx.restarts().len(), 2);
}

#[tokio::test]
async fn a_release_with_an_empty_file_deploys_it_without_a_download() {
    let fx = Fixture::new().await;
    let mut content = healthy(files(3, &[], "e"));
    content.push(("config/empty.flag".into(), Vec::new(), 0o600));
    let v1 = fx.server.publish("1.0.0", &content);
    let mut r = fx.open();
    let (out, _) = deploy(&mut r, "c1", &v1).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    assert_eq!(fx.current_file("config/empty.flag"), "");
    let empty = sha256_digest(b"");
    assert!(
        fx.server
            .seen()
            .iter()
            .all(|s| !s.path.contains(&empty[7..])),
        "the empty blob is not downloaded"
    );
}

#[tokio::test]
async fn a_corrupted_blob_fails_the_deploy_and_leaves_current_alone() {
    let fx = Fixture::new().await;
    let v1 = fx.server.publish("1", &healthy(files(5, &[], "v1")));
    let v2 = fx.server.publish("2", &healthy(files(5, &[2], "v2")));
    let bad = sha256_digest(b"file 2 of v2\n");
    fx.server.with(|s| {
        s.corrupt.insert(bad.clone());
    });
    let mut r = fx.open();
    assert_eq!(deploy(&mut r, "c1", &v1).await.0.phase, Phase::Done);
    let (out, progress) = deploy(&mut r, "c2", &v2).await;
    assert_eq!(out.phase, Phase::Failed);
    assert!(
        out.message
            .contains(&format!("expected {bad}, got sha256:")),
        "{}",
        out.message
    );
    assert!(out.message.contains("dir2/f2.txt"), "{}", out.message);
    assert_eq!(progress.last().unwrap().phase, Phase::Failed);
    assert_eq!(out.current, Some(v1.clone()));
    assert_eq!(r.current(), Some(v1));
    assert_eq!(fx.current_file("dir2/f2.txt"), "file 2\n");
    assert!(!fx.layout().blob_path(&bad).unwrap().exists());
    assert!(fx.dir_names("blobs/tmp").is_empty(), "partial deleted");
    assert_eq!(fx.dir_names("releases"), ["1"]);
    assert_eq!(fx.restarts().len(), 1);
}

#[tokio::test]
async fn a_failing_health_check_rolls_back_to_the_previous_release() {
    let fx = Fixture::new().await;
    let v1 = fx.server.publish("1", &healthy(files(3, &[], "v1")));
    let v2 = fx.server.publish("2", &files(3, &[1], "v2"));
    let mut r = fx.open();
    assert_eq!(deploy(&mut r, "c1", &v1).await.0.phase, Phase::Done);
    let (out, progress) = deploy(&mut r, "c2", &v2).await;
    assert_eq!(out.phase, Phase::RolledBack, "{}", out.message);
    assert!(
        out.message.contains("health check of 2 failed")
            && out.message.contains("rolled back to 1"),
        "{}",
        out.message
    );
    assert_eq!(out.current, Some(v1.clone()));
    assert_eq!(r.current(), Some(v1));
    assert_eq!(fx.current_file("dir1/f1.txt"), "file 1\n");
    assert_eq!(fx.restarts(), ["1 after ", "2 after 1", "1 after 2"]);
    assert_eq!(progress.last().unwrap().phase, Phase::RolledBack);
    assert!(phases(&progress).contains(&Phase::HealthCheck));
}

#[tokio::test]
async fn a_sick_first_release_leaves_no_current_release() {
    let fx = Fixture::new().await;
    let v1 = fx.server.publish("1", &files(2, &[], "v1"));
    let mut r = fx.open();
    let (out, _) = deploy(&mut r, "c1", &v1).await;
    assert_eq!(out.phase, Phase::RolledBack, "{}", out.message);
    assert!(out.message.contains("current removed"), "{}", out.message);
    assert_eq!((out.current, r.current()), (None, None));
    assert!(!fx.state.join("current").exists());
    assert_eq!(fx.restarts(), ["1 after "]);
}

#[tokio::test]
async fn a_failing_pre_switch_command_switches_nothing() {
    let mut fx = Fixture::new().await;
    fx.config.release_pre_switch_command = "echo checking >&2; test -e bin/missing".into();
    let v1 = fx.server.publish("1", &healthy(files(3, &[], "v1")));
    let mut r = fx.open();
    let (out, _) = deploy(&mut r, "c1", &v1).await;
    assert_eq!(out.phase, Phase::Failed);
    assert!(
        out.message.contains("pre-switch command failed"),
        "{}",
        out.message
    );
    assert!(
        out.message.contains("checking"),
        "output in the message: {}",
        out.message
    );
    assert_eq!(r.current(), None);
    assert!(fx.restarts().is_empty());
}

#[tokio::test]
async fn an_interrupted_download_resumes_with_range() {
    let fx = Fixture::new().await;
    let big: Vec<u8> = (0..200_000u32).map(|i| (i % 251) as u8).collect();
    let mut f = healthy(files(2, &[], "v1"));
    f.push(("model.bin".into(), big.clone(), 0o644));
    let v1 = fx.server.publish("1", &f);
    let digest = sha256_digest(&big);
    let path = format!("/v1/blobs/{digest}");
    fx.server.with(|s| {
        s.drop_after.insert(digest.clone(), 70_000);
    });
    let mut r = fx.open();
    let (out, _) = deploy(&mut r, "c1", &v1).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    let ranges = fx.server.ranges(&path);
    assert_eq!(ranges, [None, Some(70_000)]);
    assert_eq!(fx.server.state.lock().unwrap().sent[&path], 200_000);
    assert_eq!(
        std::fs::read(fx.state.join("current/model.bin")).unwrap(),
        big
    );

    // A partial file left by a killed agent is resumed too.
    let mut f2 = f.clone();
    let big2: Vec<u8> = big.iter().rev().copied().collect();
    f2.last_mut().unwrap().1 = big2.clone();
    let v2 = fx.server.publish("2", &f2);
    let d2 = sha256_digest(&big2);
    let partial = fx.layout().partial_path(&d2).unwrap();
    std::fs::write(&partial, &big2[..12_345]).unwrap();
    let (out, _) = deploy(&mut r, "c2", &v2).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    let seen = fx.server.ranges(&format!("/v1/blobs/{d2}"));
    assert_eq!(seen, [Some(12_345)]);
    assert_eq!(
        out.bytes_downloaded,
        (200_000 - 12_345) + fx.server.state.lock().unwrap().blobs[&v2.digest].len() as u64
    );
    assert!(!partial.exists());

    // A complete but corrupt partial file is thrown away and fetched again from scratch.
    let mut f3 = f.clone();
    let big3: Vec<u8> = big.iter().map(|b| b ^ 0x55).collect();
    f3.last_mut().unwrap().1 = big3.clone();
    let v3 = fx.server.publish("3", &f3);
    let d3 = sha256_digest(&big3);
    std::fs::write(
        fx.layout().partial_path(&d3).unwrap(),
        vec![0u8; big3.len()],
    )
    .unwrap();
    let (out, _) = deploy(&mut r, "c3", &v3).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    let path3 = format!("/v1/blobs/{d3}");
    let seen = fx.server.ranges(&path3);
    assert_eq!(seen, [None]);
    assert_eq!(
        std::fs::read(fx.state.join("current/model.bin")).unwrap(),
        big3
    );
}

/// Rewrites the journal as an agent killed right after switching to `target` leaves it.
fn killed_after_switch(fx: &Fixture, target: &Release, previous: &Release) {
    let layout = fx.layout();
    layout.switch(Some(&target.version)).unwrap();
    let mut journal = Journal::load(&layout).unwrap();
    journal.recent.retain(|f| f.command_id != "c2");
    journal.active = Some(Active {
        command_id: "c2".into(),
        target: target.clone(),
        previous: Some(previous.clone()),
        phase: JournalPhase::Switching,
        reason: String::new(),
    });
    journal.save(&layout).unwrap();
}

#[tokio::test]
async fn recovery_after_the_switch_finishes_a_healthy_release_and_rolls_back_a_sick_one() {
    let mut fx = Fixture::new().await;
    let v1 = fx.server.publish("1", &healthy(files(3, &[], "v1")));
    let v2 = fx.server.publish("2", &healthy(files(3, &[0], "v2")));
    let v3 = fx.server.publish("3", &files(3, &[1], "v3"));
    let (tx, mut rx) = unbounded_channel();

    // Install all three while health checks are off, then go back to 1.
    let health = std::mem::take(&mut fx.config.release_health_command);
    let mut r = fx.open();
    for (id, v) in [("a", &v1), ("b", &v2), ("c", &v3), ("d", &v1)] {
        assert_eq!(deploy(&mut r, id, v).await.0.phase, Phase::Done);
    }
    fx.config.release_health_command = health;
    assert_eq!(r.recover(&tx).await, None, "nothing interrupted");

    // Killed after switching to the healthy 2: recovery restarts and checks it.
    killed_after_switch(&fx, &v2, &v1);
    let mut r = fx.open();
    let out = r.recover(&tx).await.unwrap();
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    assert!(
        out.message.contains("after an agent restart"),
        "{}",
        out.message
    );
    assert_eq!(r.current(), Some(v2.clone()));
    assert_eq!(fx.restarts().last().unwrap(), "2 after 1");
    let progress = drain(&mut rx);
    assert_eq!(progress.last().unwrap().command_id, "c2");
    assert_eq!(progress.last().unwrap().phase, Phase::Done);
    assert_eq!(Journal::load(&fx.layout()).unwrap().active, None);
    assert_eq!(r.recover(&tx).await, None);

    // Killed after switching to the sick 3: recovery switches back to 2.
    killed_after_switch(&fx, &v3, &v2);
    let mut r = fx.open();
    let out = r.recover(&tx).await.unwrap();
    assert_eq!(out.phase, Phase::RolledBack, "{}", out.message);
    assert_eq!(r.current(), Some(v2.clone()));
    assert_eq!(
        fx.restarts()[fx.restarts().len() - 2..],
        ["3 after 2", "2 after 3"]
    );
    // The command is remembered: the gateway resending it changes nothing.
    let before = fx.restarts().len();
    let (out, _) = deploy(&mut r, "c2", &v3).await;
    assert_eq!(out.phase, Phase::RolledBack);
    assert_eq!((fx.restarts().len(), r.current()), (before, Some(v2)));
}

#[tokio::test]
async fn an_agent_killed_before_the_switch_leaves_a_complete_current_release() {
    let fx = Fixture::new().await;
    let v1 = fx.server.publish("1", &healthy(files(4, &[], "v1")));
    let big: Vec<u8> = (0..100_000u32).map(|i| (i % 7) as u8).collect();
    let mut f = healthy(files(4, &[0, 1, 2, 3], "v2"));
    f.push(("model.bin".into(), big.clone(), 0o644));
    let v2 = fx.server.publish("2", &f);
    let d = sha256_digest(&big);
    fx.server.with(|s| {
        s.stall_after.insert(d.clone(), 30_000);
    });
    let mut r = fx.open();
    assert_eq!(deploy(&mut r, "c1", &v1).await.0.phase, Phase::Done);

    // The deployment runs in its own task (as the run loop spawns it) and is killed mid-download.
    let partial = fx.layout().partial_path(&d).unwrap();
    let v2c = v2.clone();
    let task = tokio::spawn(async move {
        let (tx, _rx) = unbounded_channel();
        let url = lekiwi_protocol::release::blob_path(&v2c.digest);
        r.deploy("c2", &v2c, &url, &tx).await
    });
    for _ in 0..200 {
        if std::fs::metadata(&partial).is_ok_and(|m| m.len() == 30_000) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    task.abort();
    let _ = task.await;
    assert_eq!(std::fs::metadata(&partial).unwrap().len(), 30_000);

    let mut r = fx.open();
    assert_eq!(r.current(), Some(v1.clone()));
    for i in 0..4 {
        assert_eq!(
            fx.current_file(&format!("dir{i}/f{i}.txt")),
            format!("file {i}\n")
        );
    }
    assert_eq!(
        Journal::load(&fx.layout()).unwrap().active.map(|a| a.phase),
        Some(JournalPhase::Preparing)
    );
    let (tx, _rx) = unbounded_channel();
    let out = r.recover(&tx).await.unwrap();
    assert_eq!(out.phase, Phase::Failed);
    assert_eq!(
        out.message,
        "interrupted before the switch; the gateway will resend"
    );
    assert_eq!(out.current, Some(v1));
    assert_eq!(fx.dir_names("releases"), ["1"]);

    // The resent command (same id) runs and resumes the partial download.
    fx.server.with(|s| {
        s.stall_after.clear();
    });
    let (out, _) = deploy(&mut r, "c2", &v2).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    let path = format!("/v1/blobs/{d}");
    let last = fx
        .server
        .seen()
        .into_iter()
        .rfind(|s| s.path == path)
        .unwrap();
    assert_eq!(last.range, Some(30_000));
    assert_eq!(
        std::fs::read(fx.state.join("current/model.bin")).unwrap(),
        big
    );
}

#[tokio::test]
async fn old_releases_and_their_blobs_are_collected_and_rollback_uses_kept_ones() {
    let mut fx = Fixture::new().await;
    fx.config.release_keep = 2;
    let v: Vec<Release> = (1..=3)
        .map(|i| {
            fx.server
                .publish(&i.to_string(), &healthy(files(4, &[i], &format!("v{i}"))))
        })
        .collect();
    let mut r = fx.open();
    for (i, rel) in v.iter().enumerate() {
        assert_eq!(
            deploy(&mut r, &format!("c{i}"), rel).await.0.phase,
            Phase::Done
        );
    }
    assert_eq!(fx.dir_names("releases"), ["2", "3"]);
    // Blobs of 2 and 3: 4 shared-or-own files + bin/run + healthy, and the two manifests.
    let mut want = HashSet::new();
    for rel in &v[1..] {
        want.insert(rel.digest.clone());
        let m = std::fs::read(
            fx.state
                .join("releases")
                .join(&rel.version)
                .join(".lekiwi/manifest.json"),
        )
        .unwrap();
        for f in ReleaseManifest::parse(&m).unwrap().files {
            want.insert(f.digest);
        }
    }
    let have: HashSet<String> = fx
        .dir_names("blobs/sha256")
        .into_iter()
        .map(|h| format!("sha256:{h}"))
        .collect();
    assert_eq!(have, want);

    // Back to the kept 2: nothing downloaded, restarted on it.
    let before = fx.server.requests();
    let (tx, mut rx) = unbounded_channel();
    let out = r.rollback("r1", &v[1], &tx).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    assert_eq!((out.files_downloaded, out.bytes_downloaded), (0, 0));
    assert_eq!(fx.server.requests(), before);
    assert_eq!(r.current(), Some(v[1].clone()));
    assert_eq!(fx.restarts().last().unwrap(), "2 after 3");
    assert_eq!(drain(&mut rx).last().unwrap().phase, Phase::Done);

    // Back to the collected 1: fetched again from its manifest blob, only what is missing.
    let out = r.rollback("r2", &v[0], &tx).await;
    assert_eq!(out.phase, Phase::Done, "{}", out.message);
    let seen = fx.server.seen();
    assert_eq!(seen[before].path, format!("/v1/blobs/{}", v[0].digest));
    assert_eq!(
        out.files_downloaded, 1,
        "only f1 of v1 differs from what 2 and 3 hold"
    );
    assert_eq!(r.current(), Some(v[0].clone()));
    assert_eq!(fx.dir_names("releases"), ["1", "2"]);
}

#[tokio::test]
async fn unknown_releases_and_refused_tokens_are_clear_failures() {
    let fx = Fixture::new().await;
    let mut r = fx.open();
    let ghost = Release {
        version: "9".into(),
        digest: format!("sha256:{}", "0".repeat(64)),
    };
    let (out, _) = deploy(&mut r, "c1", &ghost).await;
    assert_eq!(out.phase, Phase::Failed);
    assert_eq!(
        out.message,
        format!("release {} unknown to the gateway", ghost.digest)
    );

    let v1 = fx.server.publish("1", &files(1, &[], "v1"));
    r.set_token("wrong");
    let (out, _) = deploy(&mut r, "c2", &v1).await;
    assert_eq!(out.phase, Phase::Failed);
    assert!(
        out.message.contains("refused the robot's token")
            && out.message.contains("bad robot token"),
        "{}",
        out.message
    );
    r.set_token(TOKEN);

    let bad = Release {
        version: "../x".into(),
        digest: v1.digest.clone(),
    };
    assert_eq!(deploy(&mut r, "c3", &bad).await.0.phase, Phase::Failed);
    let hidden = Release {
        version: ".tmp-1".into(),
        digest: v1.digest.clone(),
    };
    let (out, _) = deploy(&mut r, "c3b", &hidden).await;
    assert!(out.message.contains("invalid version"), "{}", out.message);
    let mislabelled = Release {
        version: "2".into(),
        digest: v1.digest.clone(),
    };
    let (out, _) = deploy(&mut r, "c4", &mislabelled).await;
    assert!(
        out.message.contains("manifest names version"),
        "{}",
        out.message
    );
    assert_eq!(r.current(), None);
}

#[test]
fn base_urls_come_from_the_gateway_url() {
    assert_eq!(
        fetch::base_url("wss://fleet.example.com/v1/agent").unwrap(),
        "https://fleet.example.com"
    );
    assert_eq!(
        fetch::base_url("ws://127.0.0.1:8080/v1/agent").unwrap(),
        "http://127.0.0.1:8080"
    );
    assert!(fetch::base_url("ftp://x/").is_err());
    let a = GatewayAccess::from_gateway_url("ws://[::1]:9/v1/agent", "t", "ns/r", None).unwrap();
    assert_eq!(a.base_url, "http://[::1]:9");
}

#[test]
fn digests_match_the_sha256_test_vectors() {
    assert_eq!(
        sha256_digest(b""),
        "sha256:e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
    );
    let mut h = super::store::Hasher::new();
    h.update(b"a");
    h.update(b"bc");
    assert_eq!(
        h.finish(),
        "sha256:ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    );
}

#[test]
fn journal_keeps_recent_commands_and_history_bounded() {
    let mut j = Journal::default();
    for i in 0..100 {
        j.remember(super::store::Finished {
            command_id: format!("c{i}"),
            phase: Phase::Done,
            message: String::new(),
        });
        j.touch(&format!("{}", i % 70));
    }
    assert_eq!(j.recent.len(), 64);
    assert_eq!(j.recent.back().unwrap().command_id, "c99");
    assert_eq!(j.history.len(), 64);
    assert_eq!(j.history.last().unwrap(), "29");
}

/// The run loop spawns deployments: the futures must be `Send`.
#[allow(dead_code)]
fn futures_are_send(
    r: &mut Releases,
    rel: &Release,
    tx: &tokio::sync::mpsc::UnboundedSender<Progress>,
) {
    fn send<T: Send>(_: T) {}
    send(r.deploy("c", rel, "/", tx));
    send(r.rollback("c", rel, tx));
    send(r.recover(tx));
}
