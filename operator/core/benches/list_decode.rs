//! The memory a whole list of Robots costs its reader: decoded whole and then trimmed (as
//! kube's `Api::list` and a trim after it) against decoded one object at a time, each trimmed
//! as it is read (`lekiwi_core::list::decode`). Each way runs in a process of its own, with the
//! operator's allocator, over the same answer text (a Robot as a soak hour's API server served
//! it, managed fields and all, under 10,000 names); the table gives the peak RSS while decoding
//! and the RSS left once the answer's text is dropped, both above the RSS before decoding.
//!
//! `cargo bench -p lekiwi-core --bench list_decode [-- ROBOTS]`

use std::process::Command;

use kube::Resource;
use kube::core::ObjectList;
use lekiwi_core::list::decode;
use lekiwi_core::watch::drop_field_sets;
use lekiwi_crds::Robot;

#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// One Robot, as a soak hour's API server served it (with its managed fields).
const ROBOT: &str = include_str!("robot.json");

/// How a reader trims each Robot.
type Trim = fn(&mut Robot);

/// The readers' trims, by who reads so.
const TRIMS: [(&str, Trim); 2] = [
    (
        "no managed fields (gateway, Fleet API)",
        drop_managed_fields,
    ),
    (
        "managed fields without field sets (controller)",
        drop_field_sets::<Robot>,
    ),
];

fn drop_managed_fields(robot: &mut Robot) {
    robot.meta_mut().managed_fields = None;
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("--child") {
        return child(&args[1], args[2].parse().unwrap(), args[3].parse().unwrap());
    }
    // `cargo bench` passes `--bench`; the first number is the fleet's size.
    let robots: usize = args.iter().find_map(|a| a.parse().ok()).unwrap_or(10_000);
    let me = std::env::current_exe().expect("the bench's own path");
    let compact = serde_json::to_string(&serde_json::from_str::<serde_json::Value>(ROBOT).unwrap());
    println!(
        "list decode: {robots} Robots of {} bytes each (JSON as served, managed fields and all)",
        compact.unwrap().len()
    );
    println!(
        "{:<48} {:<10} {:>10} {:>10} {:>12}",
        "trim", "decoded", "peak MiB", "kept MiB", "kept / whole"
    );
    for (t, (trim, _)) in TRIMS.iter().enumerate() {
        let mut whole_kept = None;
        for way in ["whole", "streamed"] {
            let out = Command::new(&me)
                .args(["--child", way, &t.to_string(), &robots.to_string()])
                .output()
                .expect("the bench runs itself");
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            let text = String::from_utf8(out.stdout).unwrap();
            let (peak, kept) = text.trim().split_once(' ').unwrap();
            let (peak, kept): (f64, f64) = (peak.parse().unwrap(), kept.parse().unwrap());
            let ratio = whole_kept.map_or("1.00".to_owned(), |w: f64| format!("{:.2}", kept / w));
            whole_kept.get_or_insert(kept);
            println!("{trim:<48} {way:<10} {peak:>10.1} {kept:>10.1} {ratio:>12}");
        }
    }
}

/// Decodes the list one way and prints its peak and kept RSS above the start, in MiB.
fn child(way: &str, trim: usize, robots: usize) {
    let trim = TRIMS[trim].1;
    let text = list_text(robots);
    let before = rss_kib("VmRSS");
    // Resets the peak to the RSS now (Linux's clear_refs, 5).
    std::fs::write("/proc/self/clear_refs", "5").expect("the peak RSS reset");
    let items: Vec<Robot> = match way {
        "whole" => {
            let mut list: ObjectList<Robot> = serde_json::from_str(&text).unwrap();
            list.items.iter_mut().for_each(trim);
            list.items
        }
        _ => decode(&text, trim).unwrap(),
    };
    let peak = rss_kib("VmHWM");
    drop(text);
    assert_eq!(items.len(), robots);
    let kept = rss_kib("VmRSS");
    let mib = |kib: u64| kib.saturating_sub(before) as f64 / 1024.0;
    println!("{:.1} {:.1}", mib(peak), mib(kept));
    drop(items);
}

/// A list answer of `robots` copies of [`ROBOT`], each under a name of its own, built as text
/// only (no decoded garbage left behind to be reused by what is measured).
fn list_text(robots: usize) -> String {
    let mut robot: serde_json::Value = serde_json::from_str(ROBOT).unwrap();
    robot["metadata"]["name"] = "@NAME@".into();
    let one = serde_json::to_string(&robot).unwrap();
    let mut text = String::with_capacity((one.len() + 1) * robots + 200);
    text.push_str(r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotList","#);
    text.push_str(r#""metadata":{"resourceVersion":"1"},"items":["#);
    for i in 0..robots {
        if i > 0 {
            text.push(',');
        }
        text.push_str(&one.replace("@NAME@", &format!("sim-{i:05}")));
    }
    text.push_str("]}");
    text
}

/// A `/proc/self/status` field, in KiB.
fn rss_kib(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.trim().trim_end_matches(" kB").parse().ok())
        .unwrap_or_else(|| panic!("no {field} in /proc/self/status"))
}
