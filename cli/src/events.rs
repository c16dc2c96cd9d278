//! `kubectl lekiwi events ROBOT`: a robot's stored events, read from the gateway's event store
//! over `GET /v1/robots/{namespace}/{name}/events` with the user's Kubernetes token (RBAC must
//! allow `get` on `robots/events` of group `fleet.lekiwi.io` in the robot's namespace).

use std::time::Duration;

use anyhow::bail;
use clap::Args;
use jiff::Timestamp;
use reqwest::{Method, StatusCode};

use crate::Output;
use crate::release::{Gateway, ServerArgs, message, refused};

/// Events one request asks for (the gateway's maximum).
const PAGE: u32 = 1000;
/// Pages read at most, so a huge store cannot keep the command busy.
const MAX_PAGES: usize = 200;

/// Arguments of `events`.
#[derive(Debug, Args)]
pub struct EventsArgs {
    /// The robot: `name` (in -n's namespace) or `namespace/name`.
    pub robot: String,
    /// Only events from this long ago until now (e.g. 30m, 1h, 2d).
    #[arg(long, default_value = "1h", value_parser = crate::duration::parse)]
    pub since: Duration,
    /// Show at most this many, the newest.
    #[arg(long, default_value_t = 100)]
    pub limit: usize,
    /// Only events of this kind (e.g. agent_started); repeatable.
    #[arg(long)]
    pub kind: Vec<String>,
    /// After the list, print each new event as the gateway stores it (asked every 2 s) until
    /// interrupted.
    #[arg(short = 'w', long)]
    pub watch: bool,
    /// Where the gateway is and which Kubernetes token to present to it.
    #[command(flatten)]
    pub server: ServerArgs,
}

pub use lekiwi_protocol::StoredEvent;

/// Runs `events`.
pub async fn run(
    kube: &crate::KubeContext,
    output: &Output,
    no_headers: bool,
    args: EventsArgs,
) -> anyhow::Result<()> {
    let (ns, name) = match args.robot.split_once('/') {
        Some((ns, name)) => (ns.to_owned(), name.to_owned()),
        None => (kube.namespace.clone(), args.robot.clone()),
    };
    let gateway = Gateway::connect(kube, &args.server, None).await?;
    let now = Timestamp::now();
    let since_ms = now.as_millisecond() - i64::try_from(args.since.as_millis()).unwrap_or(i64::MAX);
    let events = fetch(&gateway, &ns, &name, None).await?;
    let mut seen = Seen::default();
    for e in &events {
        seen.insert(e.seq);
    }
    let shown = select(events, since_ms, &args.kind, args.limit);
    if !(args.watch && shown.is_empty() && output.table()) {
        let text = render(&shown, output, now)?;
        print!(
            "{}",
            crate::list::headers(text, no_headers && output.table())
        );
    }
    if args.watch {
        follow(&gateway, (&ns, &name), &args.kind, output, seen).await?;
    }
    Ok(())
}

/// How often `--watch` asks the gateway for new events.
const WATCH_EVERY: Duration = Duration::from_secs(2);
/// How far below the highest sequence number seen `--watch` still looks for events stored
/// late (an agent resending what the store refused a moment ago).
const LATE_SEQS: u64 = 1000;
/// Every how many polls `--watch` reads that whole window again; the other polls read only
/// what lies above the highest sequence number seen.
const LATE_EVERY: u32 = 15;

/// The sequence numbers `--watch` printed or listed, within [`LATE_SEQS`] of the highest.
#[derive(Default)]
struct Seen {
    seqs: std::collections::BTreeSet<u64>,
}

impl Seen {
    /// Notes `seq`; false if it was seen already.
    fn insert(&mut self, seq: u64) -> bool {
        self.seqs.insert(seq)
    }

    /// Forgets what lies below [`Seen::low_water`], so the set stays bounded.
    fn prune(&mut self) {
        let low = self.low_water();
        self.seqs = self.seqs.split_off(&low);
    }

    /// The highest sequence number seen, if any.
    fn newest(&self) -> Option<u64> {
        self.seqs.last().copied()
    }

    /// The sequence number below which events are no longer looked for.
    fn low_water(&self) -> u64 {
        self.newest().map_or(0, |max| max.saturating_sub(LATE_SEQS))
    }
}

/// Prints the robot's new events as they are stored, one object (or row) each, until the
/// gateway stops answering or the user interrupts.
async fn follow(
    gateway: &Gateway,
    (ns, name): (&str, &str),
    kinds: &[String],
    output: &Output,
    mut seen: Seen,
) -> anyhow::Result<()> {
    use std::io::Write as _;
    for poll in (1..=LATE_EVERY).cycle() {
        tokio::time::sleep(WATCH_EVERY).await;
        let after = if poll == LATE_EVERY {
            seen.low_water().checked_sub(1)
        } else {
            seen.newest()
        };
        let fresh: Vec<StoredEvent> = fetch(gateway, ns, name, after)
            .await?
            .into_iter()
            .filter(|e| seen.insert(e.seq) && (kinds.is_empty() || kinds.contains(&e.kind)))
            .collect();
        seen.prune();
        let now = Timestamp::now();
        for e in &fresh {
            let text = match output {
                Output::Table | Output::Wide => {
                    crate::list::headers(render(std::slice::from_ref(e), output, now)?, true)
                }
                Output::Name => output
                    .rows(std::slice::from_ref(e), |e| e.seq.to_string())?
                    .unwrap_or_default(),
                _ => output.structured(e)?.unwrap_or_default(),
            };
            print!("{text}");
        }
        std::io::stdout().flush()?;
    }
    Ok(())
}

/// Reads every stored event of the robot with a sequence number above `after` (all if `None`),
/// page by page.
async fn fetch(
    gateway: &Gateway,
    ns: &str,
    name: &str,
    mut after: Option<u64>,
) -> anyhow::Result<Vec<StoredEvent>> {
    let mut all = Vec::new();
    for _ in 0..MAX_PAGES {
        let mut path = format!("/v1/robots/{ns}/{name}/events?limit={PAGE}");
        if let Some(seq) = after {
            path.push_str(&format!("&after_seq={seq}"));
        }
        let resp = match gateway.request(Method::GET, &path).send().await {
            Ok(r) => r,
            Err(e) => bail!(
                "the gateway at {} did not answer ({}); check --server or LEKIWI_SERVER",
                gateway.base,
                crate::http_error(&e)
            ),
        };
        match resp.status() {
            StatusCode::OK => {}
            StatusCode::UNAUTHORIZED | StatusCode::FORBIDDEN => {
                bail!("reading events of {ns}/{name}: {}", refused(resp, "").await)
            }
            StatusCode::NOT_FOUND => {
                let why = message(resp).await;
                if why.contains("not found") {
                    bail!("{why}");
                }
                bail!(
                    "the gateway at {} has no events API (404): is it older than this plugin?",
                    gateway.base
                )
            }
            s => bail!(
                "reading events of {ns}/{name}: {s}: {}",
                message(resp).await
            ),
        }
        let page: Vec<StoredEvent> = resp.json().await?;
        let full = page.len() >= PAGE as usize;
        after = page.last().map(|e| e.seq).or(after);
        all.extend(page);
        if !full {
            return Ok(all);
        }
    }
    eprintln!("warning: stopped after {} events", all.len());
    Ok(all)
}

/// The newest `limit` events at or after `since_ms` of the given kinds (all if none), oldest
/// first.
pub fn select(
    events: Vec<StoredEvent>,
    since_ms: i64,
    kinds: &[String],
    limit: usize,
) -> Vec<StoredEvent> {
    let mut kept: Vec<StoredEvent> = events
        .into_iter()
        .filter(|e| e.ts_ms >= since_ms && (kinds.is_empty() || kinds.contains(&e.kind)))
        .collect();
    let skip = kept.len().saturating_sub(limit);
    kept.drain(..skip);
    kept
}

/// Renders events in the given format; `now` is passed in so ages are testable.
pub fn render(events: &[StoredEvent], output: &Output, now: Timestamp) -> anyhow::Result<String> {
    Ok(match output.rows(events, |e| e.seq.to_string())? {
        Some(text) => text,
        None => {
            let wide = output.wide();
            let mut rows = vec![
                ["SEQ", "AGE", "SEVERITY", "KIND", "MESSAGE", "DATA"]
                    .iter()
                    .take(if wide { 6 } else { 5 })
                    .map(|s| s.to_string())
                    .collect::<Vec<_>>(),
            ];
            for e in events {
                let age = Timestamp::from_millisecond(e.ts_ms)
                    .map(|t| crate::robots::age(now, t))
                    .unwrap_or_else(|_| "-".into());
                let mut row = vec![
                    e.seq.to_string(),
                    age,
                    e.severity.clone(),
                    e.kind.clone(),
                    e.message.clone(),
                ];
                if wide {
                    row.push(if e.data.is_null() {
                        "-".into()
                    } else {
                        e.data.to_string()
                    });
                }
                rows.push(row);
            }
            if events.is_empty() {
                return Ok("No events found.\n".into());
            }
            crate::robots::format_table(rows)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(seq: u64, ts_ms: i64, kind: &str) -> StoredEvent {
        StoredEvent {
            seq,
            ts_ms,
            kind: kind.into(),
            severity: "info".into(),
            message: format!("event {seq}"),
            data: serde_json::Value::Null,
        }
    }

    #[test]
    fn watch_remembers_a_bounded_window_below_the_newest() {
        let mut seen = Seen::default();
        assert!(seen.insert(5));
        assert!(!seen.insert(5));
        assert_eq!(seen.low_water(), 0);
        assert!(seen.insert(5000));
        seen.prune();
        assert_eq!(seen.newest(), Some(5000));
        assert_eq!(seen.low_water(), 5000 - LATE_SEQS);
        // Far below the window: forgotten, and no longer asked for.
        assert!(!seen.seqs.contains(&5));
        // A late event within the window is still new once, then seen.
        assert!(seen.insert(4500));
        assert!(!seen.insert(4500));
        seen.prune();
        assert!(seen.seqs.len() <= LATE_SEQS as usize + 1);
    }

    #[test]
    fn select_keeps_the_newest_of_the_window_and_kinds() {
        let events = vec![
            ev(1, 100, "agent_started"),
            ev(2, 200, "x"),
            ev(3, 300, "agent_started"),
            ev(4, 400, "agent_started"),
        ];
        let got = select(events.clone(), 150, &["agent_started".into()], 10);
        assert_eq!(got.iter().map(|e| e.seq).collect::<Vec<_>>(), [3, 4]);
        let got = select(events, 0, &[], 2);
        assert_eq!(got.iter().map(|e| e.seq).collect::<Vec<_>>(), [3, 4]);
    }

    #[test]
    fn table_has_age_and_kind() {
        let now: Timestamp = "2026-01-01T00:01:00Z".parse().unwrap();
        let out = render(
            &[ev(7, now.as_millisecond() - 30_000, "agent_started")],
            &Output::Table,
            now,
        )
        .unwrap();
        let lines: Vec<&str> = out.lines().collect();
        assert!(lines[0].starts_with("SEQ"));
        assert_eq!(
            lines[1].split_whitespace().collect::<Vec<_>>(),
            ["7", "30s", "ago", "info", "agent_started", "event", "7"]
        );
    }

    #[test]
    fn tables_escape_what_robots_report() {
        let now: Timestamp = "2026-01-01T00:01:00Z".parse().unwrap();
        let mut e = ev(1, now.as_millisecond(), "note");
        e.message = "\x1b[2Jcleared\nforged row".into();
        e.data = serde_json::json!({ "x": "\x1b]0;title\x07" });
        let out = render(&[e], &Output::Wide, now).unwrap();
        assert!(!out.contains(['\x1b', '\x07']), "{out}");
        assert_eq!(out.lines().count(), 2, "one header, one row: {out}");
        assert!(out.contains(r"\u{1b}[2Jcleared\u{a}forged row"), "{out}");
    }
}
