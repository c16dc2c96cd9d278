//! Unit tests of a simulated robot's commands against a small blob server on 127.0.0.1 that
//! serves whole blobs and byte ranges, and records every request.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use clap::Parser;
use lekiwi_protocol::release::{ManifestFile, ReleaseManifest, blob_path};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::*;
use crate::release::sha256_digest;

/// Requests the blob server answered: path and the `Range` start asked for.
type Requests = Arc<Mutex<Vec<(String, u64)>>>;

/// Serves `blobs` (by path) over HTTP/1.1 with keep-alive; `404` for anything else.
async fn blob_server(blobs: HashMap<String, Vec<u8>>) -> (u16, Requests) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let requests: Requests = Arc::default();
    let (blobs, seen) = (Arc::new(blobs), requests.clone());
    tokio::spawn(async move {
        loop {
            let (mut conn, _) = listener.accept().await.unwrap();
            let (blobs, seen) = (blobs.clone(), seen.clone());
            tokio::spawn(async move {
                let mut buf = Vec::new();
                loop {
                    let mut chunk = [0u8; 4096];
                    let Ok(n) = conn.read(&mut chunk).await else {
                        return;
                    };
                    if n == 0 {
                        return;
                    }
                    buf.extend_from_slice(&chunk[..n]);
                    while let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
                        let head = String::from_utf8_lossy(&buf[..end]).into_owned();
                        buf.drain(..end + 4);
                        let answer = answer(&head, &blobs, &seen);
                        if conn.write_all(&answer).await.is_err() {
                            return;
                        }
                    }
                }
            });
        }
    });
    (port, requests)
}

/// The response to one request head.
fn answer(head: &str, blobs: &HashMap<String, Vec<u8>>, seen: &Requests) -> Vec<u8> {
    let path = head.split(' ').nth(1).unwrap_or_default().to_owned();
    let from = head
        .lines()
        .find_map(|l| {
            l.to_ascii_lowercase()
                .strip_prefix("range: bytes=")
                .map(str::to_owned)
        })
        .and_then(|r| r.trim_end_matches('-').parse::<u64>().ok())
        .unwrap_or(0);
    seen.lock().unwrap().push((path.clone(), from));
    let Some(blob) = blobs.get(&path) else {
        return b"HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\n\r\n".to_vec();
    };
    let mut out = if from > 0 {
        format!(
            "HTTP/1.1 206 Partial Content\r\ncontent-range: bytes {from}-{}/{}\r\ncontent-length: {}\r\n\r\n",
            blob.len() - 1,
            blob.len(),
            blob.len() as u64 - from
        )
    } else {
        format!("HTTP/1.1 200 OK\r\ncontent-length: {}\r\n\r\n", blob.len())
    }
    .into_bytes();
    out.extend_from_slice(&blob[from as usize..]);
    out
}

/// Releases and agent builds the blob server holds.
#[derive(Default)]
struct Blobs(HashMap<String, Vec<u8>>);

impl Blobs {
    /// Adds a release of files with these contents; the release.
    fn release(&mut self, version: &str, contents: &[Vec<u8>]) -> Release {
        let files = contents
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let digest = self.blob(c.clone());
                ManifestFile {
                    path: format!("lekiwi/f{i}"),
                    digest,
                    size: c.len() as u64,
                    mode: 0o644,
                }
            })
            .collect();
        let bytes = ReleaseManifest::new(version, files).to_bytes();
        Release {
            version: version.to_owned(),
            digest: self.blob(bytes),
        }
    }

    /// Adds a blob; its digest.
    fn blob(&mut self, bytes: Vec<u8>) -> String {
        let digest = sha256_digest(&bytes);
        self.0.insert(blob_path(&digest), bytes);
        digest
    }
}

/// A robot whose blob server holds `blobs`, with the command flags `flags`.
async fn robot(blobs: Blobs, flags: &[&str]) -> (Commands, RobotId, Requests) {
    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        commands: CommandArgs,
    }
    let args = Cli::parse_from(std::iter::once("sim").chain(flags.iter().copied())).commands;
    let (port, requests) = blob_server(blobs.0).await;
    let gateway = format!("ws://127.0.0.1:{port}/v1/agent");
    let shared = Shared::new(args, &[gateway], None, "0.9.0").unwrap();
    let id = RobotId {
        name: "sim-00001".into(),
        robot: "lab/sim-00001".into(),
        token: "lkr_test".into(),
        gateway: 0,
    };
    (Commands::new(Arc::new(shared)), id, requests)
}

/// What a robot sent or did, in order.
#[derive(Debug, PartialEq)]
enum Seen {
    /// A progress report: command id and phase.
    Progress(String, &'static str),
    /// An event of this kind, with its data.
    Event(&'static str, serde_json::Value),
    Offline,
    Restart,
}

/// Handles reports until the robot is idle (or, with `until`, has sent that phase).
async fn drive(c: &mut Commands, robot: &RobotId, until: Option<&str>) -> Vec<Seen> {
    let mut seen = Vec::new();
    loop {
        if until.is_none() && c.running.is_none() && c.rx.is_empty() {
            return seen;
        }
        let report = tokio::time::timeout(Duration::from_secs(10), c.next())
            .await
            .unwrap_or_else(|_| panic!("no report in 10 s; so far {seen:?}"));
        let got = match c.handle(robot, report) {
            Handled::Durable(d) => match *d {
                Durable::Progress(p) => Seen::Progress(p.command_id, p.phase.as_str()),
                Durable::Event { kind, data, .. } => Seen::Event(kind, data),
            },
            Handled::Finished => continue,
            Handled::Offline(_) => Seen::Offline,
            Handled::Restart => Seen::Restart,
        };
        let reached = matches!(&got, Seen::Progress(_, p) if Some(*p) == until);
        seen.push(got);
        if reached {
            return seen;
        }
    }
}

/// The events waiting now.
fn waiting(c: &mut Commands, robot: &RobotId) -> Vec<Seen> {
    let mut seen = Vec::new();
    while let Some(report) = c.try_next() {
        if let Handled::Durable(d) = c.handle(robot, report)
            && let Durable::Event { kind, data, .. } = *d
        {
            seen.push(Seen::Event(kind, data));
        }
    }
    seen
}

/// The phases reported for `command_id`, consecutive repeats (download progress) merged.
fn phases(seen: &[Seen], command_id: &str) -> Vec<&'static str> {
    let mut out: Vec<&'static str> = Vec::new();
    for s in seen {
        if let Seen::Progress(id, phase) = s
            && id == command_id
            && out.last() != Some(phase)
        {
            out.push(phase);
        }
    }
    out
}

fn deploy(release: &Release) -> Command {
    Command::Deploy {
        release: release.clone(),
        manifest_url: blob_path(&release.digest),
    }
}

/// `n` files of about 30 KB, different for each `tag`.
fn files(n: usize, tag: &str) -> Vec<Vec<u8>> {
    (0..n)
        .map(|i| format!("file {i} {tag}\n").repeat(3000).into_bytes())
        .collect()
}

const FULL: [&str; 8] = [
    "downloading",
    "verifying",
    "assembling",
    "pre_switch",
    "switching",
    "restarting",
    "health_check",
    "done",
];

/// A first deploy fetches the manifest and every file, reporting every phase; a second one
/// only the changed file; one of the current release reports `done` at once.
#[tokio::test]
async fn a_deploy_goes_through_every_phase_and_a_second_fetches_only_changes() {
    let mut blobs = Blobs::default();
    let v1_files = files(4, "a");
    let mut v2_files = v1_files.clone();
    v2_files[2] = b"changed".repeat(1000);
    let v1 = blobs.release("1.0.0", &v1_files);
    let v2 = blobs.release("2.0.0", &v2_files);
    let (mut c, id, requests) = robot(blobs, &[]).await;
    c.on_command(&id, "c1".into(), deploy(&v1));
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(phases(&seen, "c1"), FULL);
    assert_eq!(c.current(), Some(&v1));
    assert_eq!(
        requests.lock().unwrap().len(),
        5,
        "the manifest and 4 files"
    );
    let before = requests.lock().unwrap().len();
    c.on_command(&id, "c2".into(), deploy(&v2));
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(phases(&seen, "c2"), FULL);
    let second: Vec<_> = requests.lock().unwrap()[before..].to_vec();
    assert_eq!(
        second.len(),
        2,
        "the manifest and the changed file: {second:?}"
    );
    assert_eq!(second[1].0, blob_path(&sha256_digest(&v2_files[2])));
    c.on_command(&id, "c3".into(), deploy(&v2));
    assert_eq!(phases(&drive(&mut c, &id, None).await, "c3"), ["done"]);
    let s = c.shared.counters.summary();
    assert_eq!((s.deploys_done, s.deploys_failed), (3, 0));
    let sizes: u64 = v1_files
        .iter()
        .chain([&v2_files[2]])
        .map(|f| f.len() as u64)
        .sum();
    assert!(
        s.bytes_downloaded > sizes && s.bytes_downloaded < sizes + 4096,
        "{s:?}"
    );
}

/// A robot that fails its health check switches back and restarts the release before; a
/// rollback to it later switches without a download; hooks turned off are not reported.
#[tokio::test]
async fn a_failing_health_check_rolls_back_and_a_rollback_downloads_nothing() {
    let mut blobs = Blobs::default();
    let v1 = blobs.release("1.0.0", &files(2, "a"));
    let v2 = blobs.release("2.0.0", &files(2, "b"));
    let flags = [
        "--fail-health-share",
        "1",
        "--fail-health-versions",
        "2.0.0",
        "--health-timeout-seconds",
        "0.2",
        "--pre-switch-seconds",
        "off",
    ];
    let (mut c, id, requests) = robot(blobs, &flags).await;
    c.on_command(&id, "c1".into(), deploy(&v1));
    drive(&mut c, &id, None).await;
    c.on_command(&id, "c2".into(), deploy(&v2));
    let seen = drive(&mut c, &id, None).await;
    let rolled_back = [
        "downloading",
        "verifying",
        "assembling",
        "switching",
        "restarting",
        "health_check",
        "switching",
        "restarting",
        "rolled_back",
    ];
    assert_eq!(phases(&seen, "c2"), rolled_back);
    assert_eq!(c.current(), Some(&v1), "back on 1.0.0");
    let n = requests.lock().unwrap().len();
    c.on_command(
        &id,
        "c3".into(),
        Command::Rollback {
            release: v1.clone(),
        },
    );
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(
        phases(&seen, "c3"),
        ["done"],
        "1.0.0 is current: nothing to do"
    );
    // Back to the factory release, kept on disk: no download.
    let factory = c.shared.factory.as_ref().unwrap().release.clone();
    c.on_command(
        &id,
        "c4".into(),
        Command::Rollback {
            release: factory.clone(),
        },
    );
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(
        phases(&seen, "c4"),
        [
            "assembling",
            "switching",
            "restarting",
            "health_check",
            "done"
        ]
    );
    assert_eq!(c.current(), Some(&factory));
    assert_eq!(requests.lock().unwrap().len(), n, "nothing downloaded");
    assert_eq!(c.shared.counters.summary().deploys_rolled_back, 1);
}

/// A stalled download (`--timeout-share`) ends only when cancelled: `cancelled`, and the
/// cancel itself `done`; a command queued behind it is cancelled too, and a second deploy of
/// the same release joins the one running and gets its final report.
#[tokio::test]
async fn a_stalled_download_is_cancelled_with_what_waited() {
    let mut blobs = Blobs::default();
    let v1 = blobs.release("1.0.0", &files(2, "a"));
    let v2 = blobs.release("2.0.0", &files(2, "b"));
    let (mut c, id, _) = robot(blobs, &["--timeout-share", "1"]).await;
    c.on_command(&id, "c1".into(), deploy(&v1));
    let seen = drive(&mut c, &id, Some("downloading")).await;
    assert_eq!(phases(&seen, "c1"), ["downloading"]);
    // The manifest, then "downloading 2 files": then nothing.
    let more = drive(&mut c, &id, Some("downloading")).await;
    assert!(
        tokio::time::timeout(Duration::from_millis(300), c.next())
            .await
            .is_err(),
        "{more:?}"
    );
    c.on_command(&id, "c2".into(), deploy(&v1));
    c.on_command(&id, "c3".into(), deploy(&v2));
    c.on_command(&id, "c4".into(), Command::Cancel);
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(phases(&seen, "c3"), ["cancelled"], "{seen:?}");
    assert_eq!(phases(&seen, "c4"), ["done"]);
    assert_eq!(phases(&seen, "c1"), ["cancelled"]);
    assert_eq!(
        phases(&seen, "c2"),
        ["cancelled"],
        "the alias gets the same end"
    );
    assert_eq!(c.current().map(|r| r.version.as_str()), Some("0.9.0"));
    c.on_command(&id, "c5".into(), Command::Cancel);
    assert_eq!(phases(&drive(&mut c, &id, None).await, "c5"), ["done"]);
}

/// A robot that goes offline mid-download fails the deploy and asks to be offline; the
/// retried deploy resumes the cut blob where it stopped (`Range`) and completes.
#[tokio::test]
async fn an_offline_robot_resumes_its_download_on_the_retry() {
    let mut blobs = Blobs::default();
    let big = vec![
        (0..200_000u32)
            .map(|i| (i % 251) as u8)
            .collect::<Vec<u8>>(),
    ];
    let v1 = blobs.release("1.0.0", &big);
    let flags = [
        "--offline-mid-download-share",
        "1",
        "--offline-seconds",
        "7",
    ];
    let (mut c, id, requests) = robot(blobs, &flags).await;
    c.on_command(&id, "c1".into(), deploy(&v1));
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(phases(&seen, "c1"), ["downloading", "failed"]);
    assert!(seen.contains(&Seen::Offline), "{seen:?}");
    c.on_command(&id, "c2".into(), deploy(&v1));
    let seen = drive(&mut c, &id, None).await;
    assert_eq!(phases(&seen, "c2"), FULL);
    let requests = requests.lock().unwrap().clone();
    let file = blob_path(&sha256_digest(&big[0]));
    let asked: Vec<u64> = requests
        .iter()
        .filter(|(p, _)| *p == file)
        .map(|(_, from)| *from)
        .collect();
    assert_eq!(asked.len(), 2, "{requests:?}");
    assert_eq!(asked[0], 0);
    assert!(
        asked[1] > 0 && asked[1] < 200_000,
        "resumed from {}",
        asked[1]
    );
    assert_eq!(requests.len(), 3, "the manifest once: {requests:?}");
    let bytes = c.shared.counters.summary().bytes_downloaded;
    assert!(
        bytes < 200_000 + 4096,
        "{bytes} bytes: nothing fetched twice"
    );
}

/// `update_agent`: the build is downloaded and verified, `agent_update_started` is sent and
/// the robot restarts as the new build, which reports `agent_update_succeeded` once welcomed;
/// an update back to the build before downloads nothing; one to the build that runs does
/// nothing at all.
#[tokio::test]
async fn an_agent_update_restarts_as_the_new_build_and_a_return_downloads_nothing() {
    let mut blobs = Blobs::default();
    let build = b"#!/bin/sh\necho agent B\n".repeat(100);
    let digest = blobs.blob(build.clone());
    let (mut c, id, requests) = robot(blobs, &[]).await;
    let (a_version, a_digest) = (c.agent().0.to_owned(), c.agent().1.to_owned());
    let update = |version: &str, digest: &str| Command::UpdateAgent {
        version: version.into(),
        digest: digest.into(),
        url: blob_path(digest),
    };
    c.on_command(&id, "u1".into(), update("9.0.0", &digest));
    let seen = drive(&mut c, &id, None).await;
    let Seen::Event("agent_update_started", data) = &seen[0] else {
        panic!("{seen:?}")
    };
    assert_eq!(data["bytes"], build.len() as u64);
    assert_eq!(data["from"], a_version.as_str());
    assert_eq!(seen[1], Seen::Restart);
    assert_eq!(c.agent(), ("9.0.0", digest.as_str()));
    c.welcomed();
    let seen = waiting(&mut c, &id);
    assert!(
        matches!(&seen[0], Seen::Event("agent_update_succeeded", d) if d["command_id"] == "u1")
    );
    let n = requests.lock().unwrap().len();
    c.on_command(&id, "u2".into(), update(&a_version, &a_digest));
    let seen = drive(&mut c, &id, None).await;
    assert!(matches!(&seen[0], Seen::Event("agent_update_started", d) if d["bytes"] == 0));
    assert_eq!(
        requests.lock().unwrap().len(),
        n,
        "the kept build: no download"
    );
    c.welcomed();
    assert_eq!(waiting(&mut c, &id).len(), 1, "agent_update_succeeded");
    c.on_command(&id, "u3".into(), update(&a_version, &a_digest));
    assert!(drive(&mut c, &id, None).await.is_empty(), "runs already");
    let s = c.shared.counters.summary();
    assert_eq!((s.agent_updates, s.agent_updates_failed), (2, 0));
}
