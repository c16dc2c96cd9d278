//! The operator image `scripts/image.sh` builds: the same digest and the same bytes when built
//! twice from one commit; minimal (no shell, no package manager), non-root, with the CA bundle and
//! every shared library the binary loads; in step with the chart's defaults. And the test bed's
//! pause image builds.

use std::collections::BTreeMap;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use lekiwi_tests::repo_root;
use serde_json::Value;
use sha2::{Digest, Sha256};

/// One tar entry: its type flag, mode, owner, mtime, link target and contents.
struct Entry {
    kind: u8,
    mode: u32,
    uid: u64,
    gid: u64,
    mtime: u64,
    link: String,
    data: Vec<u8>,
}

fn octal(field: &[u8]) -> u64 {
    let text = String::from_utf8_lossy(field);
    let text = text.trim_matches(|c: char| c == '\0' || c == ' ');
    u64::from_str_radix(text, 8).unwrap_or_else(|_| panic!("bad octal field {text:?}"))
}

fn text(field: &[u8]) -> String {
    let end = field.iter().position(|&b| b == 0).unwrap_or(field.len());
    String::from_utf8_lossy(&field[..end]).into_owned()
}

/// Reads a ustar/pax tar (what scripts/oci.py writes): entries by path, directories with a
/// trailing `/` removed. A pax `path` record names the entry after it.
fn read_tar(bytes: &[u8]) -> BTreeMap<String, Entry> {
    let mut entries = BTreeMap::new();
    let (mut at, mut long_name) = (0, None::<String>);
    while at + 512 <= bytes.len() && bytes[at..at + 512].iter().any(|&b| b != 0) {
        let h = &bytes[at..at + 512];
        let size = octal(&h[124..136]) as usize;
        let data = bytes[at + 512..at + 512 + size].to_vec();
        at += 512 + size.div_ceil(512) * 512;
        if h[156] == b'x' {
            let records = String::from_utf8_lossy(&data).into_owned();
            long_name = records
                .lines()
                .find_map(|l| l.split_once(" path=").map(|(_, p)| p.to_string()));
            continue;
        }
        let prefix = text(&h[345..500]);
        let name = long_name.take().unwrap_or_else(|| match prefix.as_str() {
            "" => text(&h[0..100]),
            p => format!("{p}/{}", text(&h[0..100])),
        });
        let entry = Entry {
            kind: h[156],
            mode: octal(&h[100..108]) as u32,
            uid: octal(&h[108..116]),
            gid: octal(&h[116..124]),
            mtime: octal(&h[136..148]),
            link: text(&h[157..257]),
            data,
        };
        entries.insert(name.trim_end_matches('/').to_string(), entry);
    }
    entries
}

fn sha256(data: &[u8]) -> String {
    format!("sha256:{}", hex::encode(Sha256::digest(data)))
}

fn gunzip(data: &[u8], scratch: &Path) -> Vec<u8> {
    let file = scratch.join("layer.tar.gz");
    std::fs::write(&file, data).unwrap();
    let out = Command::new("gzip").arg("-dc").arg(&file).output().unwrap();
    assert!(out.status.success(), "gzip -dc failed");
    out.stdout
}

/// An image archive opened: its index, manifest, config and the one layer's entries.
struct Image {
    index: Value,
    config: Value,
    layer: BTreeMap<String, Entry>,
}

/// Opens an OCI archive, checking every blob against its digest and the layer against the
/// config's diff_id.
fn open_image(archive: &Path, scratch: &Path) -> Image {
    let outer = read_tar(&std::fs::read(archive).unwrap());
    for (name, entry) in &outer {
        if let Some(hex) = name.strip_prefix("blobs/sha256/").filter(|h| !h.is_empty()) {
            assert_eq!(sha256(&entry.data), format!("sha256:{hex}"), "blob {name}");
        }
    }
    let blob = |digest: &Value| {
        let hex = digest.as_str().unwrap().strip_prefix("sha256:").unwrap();
        &outer[&format!("blobs/sha256/{hex}")].data
    };
    let layout: Value = serde_json::from_slice(&outer["oci-layout"].data).unwrap();
    assert_eq!(layout["imageLayoutVersion"], "1.0.0");
    let index: Value = serde_json::from_slice(&outer["index.json"].data).unwrap();
    let manifest: Value = serde_json::from_slice(blob(&index["manifests"][0]["digest"])).unwrap();
    let config: Value = serde_json::from_slice(blob(&manifest["config"]["digest"])).unwrap();
    let layers = manifest["layers"].as_array().unwrap();
    assert_eq!(layers.len(), 1, "one layer");
    assert_eq!(
        layers[0]["mediaType"],
        "application/vnd.oci.image.layer.v1.tar+gzip"
    );
    let layer_tar = gunzip(blob(&layers[0]["digest"]), scratch);
    assert_eq!(config["rootfs"]["diff_ids"][0], sha256(&layer_tar));
    Image {
        index,
        config,
        layer: read_tar(&layer_tar),
    }
}

/// Runs `scripts/image.sh ARGS` (which drops the test runner's CARGO_* variables itself, so its
/// build is the one a person gets). Returns the path it printed.
fn image_sh(args: &[&str]) -> PathBuf {
    let out = Command::new("bash")
        .arg(repo_root().join("scripts/image.sh"))
        .args(args)
        .output()
        .expect("run scripts/image.sh");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "scripts/image.sh {args:?}:\n{stderr}");
    let stdout = String::from_utf8(out.stdout).unwrap();
    PathBuf::from(stdout.lines().last().expect("the archive's path").trim())
}

fn commit_time() -> u64 {
    let out = Command::new("git")
        .args(["log", "-1", "--format=%ct"])
        .current_dir(repo_root())
        .output()
        .unwrap();
    String::from_utf8(out.stdout)
        .unwrap()
        .trim()
        .parse()
        .unwrap()
}

fn chart_yaml(path: &str) -> serde_yaml::Value {
    let text = std::fs::read_to_string(repo_root().join("charts/lekiwi-operator").join(path));
    serde_yaml::from_str(&text.unwrap()).unwrap()
}

/// No shell, no package manager: none of these names anywhere in the layer.
const FORBIDDEN: &[&str] = &[
    "sh", "bash", "dash", "ash", "zsh", "busybox", "apt", "apt-get", "dpkg", "rpm", "apk",
];

/// Every file the dynamic loader needs: run the image's copy of the binary with the image's
/// own loader and libraries only (`--inhibit-cache`, `--library-path` into the unpacked layer).
fn runs_with_its_own_libraries(image: &Image, scratch: &Path) {
    let root = scratch.join("rootfs");
    for (path, entry) in &image.layer {
        let dest = root.join(path);
        match entry.kind {
            b'5' => std::fs::create_dir_all(&dest).unwrap(),
            b'0' => std::fs::write(&dest, &entry.data).unwrap(),
            other => panic!("unexpected entry type {} at /{path}", other as char),
        }
    }
    let bin = root.join("usr/bin/lekiwi-operator");
    let ldd = Command::new("ldd").arg(&bin).output().unwrap();
    let ldd = String::from_utf8(ldd.stdout).unwrap();
    let mut loader = None;
    for line in ldd.lines() {
        let path = match line.split_whitespace().collect::<Vec<_>>()[..] {
            [_, "=>", path, ..] if path.starts_with('/') => path,
            [path, ..] if path.starts_with('/') => {
                loader = Some(path.to_string());
                path
            }
            _ => continue,
        };
        assert!(
            image.layer.contains_key(path.trim_start_matches('/')),
            "the binary needs {path}, which the image lacks (ldd:\n{ldd})"
        );
    }
    let loader = root.join(loader.expect("an ELF interpreter").trim_start_matches('/'));
    let dirs: Vec<String> = ["lib/x86_64-linux-gnu", "usr/lib/x86_64-linux-gnu"]
        .iter()
        .map(|d| root.join(d).display().to_string())
        .collect();
    for exe in [&loader, &bin] {
        std::fs::set_permissions(exe, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    let out = Command::new(&loader)
        .args(["--inhibit-cache", "--library-path", &dirs.join(":")])
        .arg(&bin)
        .arg("--help")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "the image's binary with the image's libraries: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The image's run settings and files: non-root, the operator as entrypoint, nothing to log in
/// with or install from, the CA bundle, /tmp 1777, every mtime the commit time, owners 0:0.
fn check_contents(image: &Image, tag: &str) {
    let ref_name = format!("ghcr.io/lekiwi-fleet/lekiwi-operator:{tag}");
    let annotations = &image.index["manifests"][0]["annotations"];
    assert_eq!(annotations["io.containerd.image.name"], ref_name.as_str());
    assert_eq!(
        annotations["org.opencontainers.image.ref.name"],
        ref_name.as_str()
    );
    let run = &image.config["config"];
    assert_eq!(run["User"], "65532:65532", "non-root user");
    assert_eq!(
        run["Entrypoint"],
        serde_json::json!(["/usr/bin/lekiwi-operator"])
    );
    assert!(run.get("Cmd").is_none(), "the chart passes args only");
    assert_eq!(image.config["architecture"], "amd64");
    let epoch = commit_time();
    for (path, entry) in &image.layer {
        let base = path.rsplit('/').next().unwrap();
        assert!(!FORBIDDEN.contains(&base), "/{path} is in the image");
        assert!(
            !path.starts_with("var/lib/dpkg") && !path.starts_with("etc/apt"),
            "/{path}"
        );
        assert_eq!(entry.mtime, epoch, "mtime of /{path}");
        assert_eq!((entry.uid, entry.gid), (0, 0), "owner of /{path}");
        assert!(entry.link.is_empty(), "/{path} is a link");
    }
    let ca = std::fs::read("/etc/ssl/certs/ca-certificates.crt").unwrap();
    assert!(image.layer["etc/ssl/certs/ca-certificates.crt"].data == ca);
    assert_eq!(image.layer["tmp"].mode, 0o1777);
    let passwd = String::from_utf8_lossy(&image.layer["etc/passwd"].data).into_owned();
    assert!(passwd.contains(":65532:65532:"), "{passwd}");
    assert!(!passwd.contains("/bin/sh"), "{passwd}");
}

/// The chart runs what the image provides: its default image is this one (tag = appVersion),
/// the pod's UID is the image's user, and the Deployment passes args to the entrypoint.
fn check_chart_agrees(tag: &str) {
    let values = chart_yaml("values.yaml");
    assert_eq!(
        values["image"]["repository"].as_str(),
        Some("ghcr.io/lekiwi-fleet/lekiwi-operator")
    );
    assert_eq!(
        values["image"]["tag"].as_str(),
        Some(""),
        "tag defaults to appVersion"
    );
    assert_eq!(values["image"]["pullPolicy"].as_str(), Some("IfNotPresent"));
    assert_eq!(
        values["podSecurityContext"]["runAsUser"].as_u64(),
        Some(65532)
    );
    assert_eq!(
        values["podSecurityContext"]["runAsGroup"].as_u64(),
        Some(65532)
    );
    let deployment = std::fs::read_to_string(
        repo_root().join("charts/lekiwi-operator/templates/deployment.yaml"),
    )
    .unwrap();
    assert!(deployment.contains("default .Chart.AppVersion"));
    assert!(
        !deployment.contains("command:"),
        "the image's entrypoint runs"
    );
    for mount in ["mountPath: /var/lib/lekiwi", "mountPath: /tmp"] {
        assert!(deployment.contains(mount), "{mount}");
    }
    assert!(!tag.is_empty());
}

#[test]
fn operator_image_is_reproducible_minimal_and_what_the_chart_runs() {
    let scratch = tempfile::tempdir().unwrap();
    let tag = chart_yaml("Chart.yaml")["appVersion"]
        .as_str()
        .unwrap()
        .to_string();
    let first = scratch.path().join("first.oci.tar");
    let started = Instant::now();
    assert_eq!(image_sh(&["--out", first.to_str().unwrap()]), first);
    println!("first build: {:?}", started.elapsed());
    let second = scratch.path().join("second.oci.tar");
    let started = Instant::now();
    assert_eq!(
        image_sh(&["operator", "--out", second.to_str().unwrap()]),
        second
    );
    println!("second build: {:?}", started.elapsed());
    let (a, b) = (
        std::fs::read(&first).unwrap(),
        std::fs::read(&second).unwrap(),
    );
    println!("image: {} bytes", a.len());
    assert!(a == b, "two builds of one commit differ");

    let image = open_image(&first, scratch.path());
    check_contents(&image, &tag);
    check_chart_agrees(&tag);
    runs_with_its_own_libraries(&image, scratch.path());
}

#[test]
fn pause_image_builds() {
    let scratch = tempfile::tempdir().unwrap();
    let out = scratch.path().join("pause.oci.tar");
    assert_eq!(image_sh(&["pause", "--out", out.to_str().unwrap()]), out);
    let image = open_image(&out, scratch.path());
    let annotations = &image.index["manifests"][0]["annotations"];
    assert_eq!(
        annotations["io.containerd.image.name"],
        "lekiwi.local/pause:3.2"
    );
    let entrypoint = image.config["config"]["Entrypoint"].as_array().unwrap();
    assert_eq!(entrypoint[0], "/bin/busybox");
    assert!(image.layer["bin/busybox"].data == std::fs::read("/bin/busybox").unwrap());
    assert_ne!(image.config["config"]["User"], "0:0");
}
