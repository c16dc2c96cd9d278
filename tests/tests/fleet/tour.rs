//! The tour, run as written: every command block of the book's Getting started (the README's
//! tour included where the page includes it), in order, in one shell, against a quickstart of
//! its own (its own state directory, control plane and ports, started by the page's first
//! block, `bash scripts/quickstart.sh`). A renamed flag, a changed output the tour waits for, or
//! a command that stopped working breaks this test, not a lab's afternoon.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use lekiwi_tests::markdown::code_blocks;
use lekiwi_tests::{free_ports, log_dir, repo_root};

/// The page the test runs.
const PAGE: &str = "docs/src/getting-started.md";
/// How long the whole tour may take (a quickstart, three rollouts and a rollback).
const TIMEOUT: Duration = Duration::from_secs(25 * 60);

fn is_tour(info: &str) -> bool {
    let mut words = info.split_whitespace();
    words.next() == Some("sh") && words.any(|w| w == "tour")
}

/// The lines of `text` between `ANCHOR: name` and `ANCHOR_END: name`, as mdBook includes them.
fn anchored(text: &str, name: &str) -> Option<String> {
    let start = text.find(&format!("ANCHOR: {name}"))?;
    let start = start + text[start..].find('\n')? + 1;
    let end = start + text[start..].find(&format!("ANCHOR_END: {name}"))?;
    let end = text[..end].rfind('\n')?;
    Some(text[start..end].to_owned())
}

/// `page` with its `{{#include PATH}}` and `{{#include PATH:ANCHOR}}` lines replaced by what
/// they include, as mdBook does.
fn expand(page: &Path) -> String {
    let text = std::fs::read_to_string(page).unwrap();
    let mut out = String::new();
    for line in text.lines() {
        let directive = line
            .trim()
            .strip_prefix("{{#include ")
            .and_then(|l| l.strip_suffix("}}"));
        let Some(directive) = directive else {
            out.push_str(line);
            out.push('\n');
            continue;
        };
        let (path, anchor) = match directive.split_once(':') {
            Some((p, a)) => (p, Some(a)),
            None => (directive, None),
        };
        let included = std::fs::read_to_string(page.parent().unwrap().join(path)).unwrap();
        match anchor {
            Some(a) => out.push_str(&anchored(&included, a).expect("the anchor is in the file")),
            None => out.push_str(&included),
        }
        out.push('\n');
    }
    out
}

/// Every command block of the page and of the README's tour is marked to run, and the README
/// has no tour block outside what the page includes: nothing a reader is told to run escapes
/// the test below.
#[test]
fn every_command_block_of_the_tour_is_marked_and_run() {
    let root = repo_root();
    let page = code_blocks(&expand(&root.join(PAGE)));
    assert!(page.len() >= 6, "only {} blocks on the page", page.len());
    for (info, code) in &page {
        assert!(
            is_tour(info),
            "a block of {PAGE} not marked `sh tour`:\n{code}"
        );
    }
    assert_eq!(
        page[0].1.trim(),
        "bash scripts/quickstart.sh",
        "the page starts the quickstart"
    );
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let tour = anchored(&readme, "tour").expect("README.md has the tour anchors");
    let inside = code_blocks(&tour);
    assert!(
        inside.iter().all(|(info, _)| is_tour(info)),
        "README tour blocks not marked"
    );
    let all_tour = code_blocks(&readme)
        .into_iter()
        .filter(|(i, _)| is_tour(i))
        .count();
    assert_eq!(
        all_tour,
        inside.len(),
        "README has tour blocks outside its tour anchors"
    );
    assert!(
        page.iter()
            .filter(|(_, c)| inside.iter().any(|(_, t)| t == c))
            .count()
            == inside.len(),
        "{PAGE} does not include the README's tour"
    );
}

/// The environment of the tour's shell: the test runner's cargo variables removed (they would
/// make the quickstart's `cargo build` rebuild the TLS stack), the quickstart's state, control
/// plane and ports its own.
fn tour_command(script: &Path, dir: &Path) -> Command {
    let mut cmd = Command::new("bash");
    for (key, _) in std::env::vars_os() {
        let key = key.to_string_lossy().into_owned();
        let keep = matches!(key.as_str(), "CARGO_HOME" | "CARGO_TARGET_DIR");
        if !keep && (key.starts_with("CARGO") || key.starts_with("RUSTUP_TOOLCHAIN")) {
            cmd.env_remove(&key);
        }
    }
    let ports = free_ports(2);
    cmd.arg(script)
        .current_dir(repo_root())
        .env("LEKIWI_QUICKSTART_DIR", dir.join("quickstart"))
        .env("LEKIWI_CP_DIR", dir.join("control-plane"))
        .env("LEKIWI_HTTP_PORT", ports[0].to_string())
        .env("LEKIWI_GATEWAY_PORT", ports[1].to_string())
        .env("TMPDIR", dir)
        .stdin(Stdio::null());
    cmd
}

/// Stops what the tour started, whatever happened: the quickstart (by its pid files), the
/// control plane (purged), and anything left in the tour's process group.
struct Cleanup {
    dir: PathBuf,
    group: Option<i32>,
}

impl Drop for Cleanup {
    fn drop(&mut self) {
        let env = [
            ("LEKIWI_QUICKSTART_DIR", self.dir.join("quickstart")),
            ("LEKIWI_CP_DIR", self.dir.join("control-plane")),
        ];
        for args in [
            &["scripts/quickstart.sh", "down"][..],
            &["scripts/testbed/control-plane.sh", "down", "--purge"],
        ] {
            let _ = Command::new("bash")
                .args(args)
                .envs(env.iter().map(|(k, v)| (k, v)))
                .current_dir(repo_root())
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status();
        }
        // By the system call: procps-ng 4.0's kill(1) reads `-KILL -12345` as `kill(-1)`, every
        // process on the machine, whenever the group's id starts with a 1. Never group 1 either.
        if let Some(group) = self
            .group
            .and_then(rustix::process::Pid::from_raw)
            .filter(|g| *g != rustix::process::Pid::INIT)
        {
            let _ = rustix::process::kill_process_group(group, rustix::process::Signal::KILL);
        }
    }
}

#[test]
fn the_tour_runs_against_a_quickstart_of_its_own() {
    use std::os::unix::process::CommandExt as _;
    let root = repo_root();
    let page = code_blocks(&expand(&root.join(PAGE)));
    let dir = tempfile::tempdir().unwrap();
    let mut script = String::from("set -euo pipefail\nPS4='+ tour: '\nset -x\n");
    for (_, code) in &page {
        script.push_str(code);
        script.push('\n');
    }
    let script_path = dir.path().join("tour.sh");
    std::fs::write(&script_path, script).unwrap();
    let log_path = log_dir().join("tour.log");
    let log = std::fs::File::create(&log_path).unwrap();
    let mut cleanup = Cleanup {
        dir: dir.path().to_owned(),
        group: None,
    };
    let mut child = tour_command(&script_path, dir.path())
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .process_group(0)
        .spawn()
        .expect("run bash");
    cleanup.group = i32::try_from(child.id()).ok();
    let started = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break Some(status);
        }
        if started.elapsed() > TIMEOUT {
            break None;
        }
        std::thread::sleep(Duration::from_secs(1));
    };
    let took = started.elapsed();
    drop(cleanup);
    let text = std::fs::read_to_string(&log_path).unwrap_or_default();
    let tail: Vec<&str> = text
        .lines()
        .rev()
        .take(60)
        .collect::<Vec<_>>()
        .into_iter()
        .rev()
        .collect();
    match status {
        Some(s) if s.success() => {
            eprintln!("the tour ran in {took:?} (log: {})", log_path.display())
        }
        Some(s) => panic!(
            "the tour failed ({s}) after {took:?}; log {}:\n{}",
            log_path.display(),
            tail.join("\n")
        ),
        None => panic!(
            "the tour did not end within {TIMEOUT:?}; log {}:\n{}",
            log_path.display(),
            tail.join("\n")
        ),
    }
}
