//! The operator image `scripts/image.sh` builds: the same digest and the same bytes when built
//! twice from one commit; minimal (no shell, no package manager), non-root, with the CA bundle and
//! every shared library the binary loads; in step with the chart's defaults; one OCI image index
//! for linux/amd64 and linux/arm64, whose arm64 binary, with its layer's own libraries, runs on an
//! emulated Raspberry Pi 5 against the host's API server. And the test bed's pause image builds.

use std::collections::BTreeMap;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::Context;
use k8s_openapi::api::coordination::v1::Lease;
use kube::Api;
use lekiwi_tests::pi::{GUEST_STATUS_PORT, HOST_FROM_GUEST, PiGuest, Run};
use lekiwi_tests::{ControlPlane, http_get, namespace, repo_root, wait_for};
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

/// Reads a ustar/pax tar (what scripts/lib/oci.py writes): entries by path, directories with a
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

/// An image opened: the `index.json` (or image index) that names it, its config and the one
/// layer's entries.
struct Image {
    index: Value,
    config: Value,
    layer: BTreeMap<String, Entry>,
}

/// A whole archive's files by path, each blob checked against its digest.
fn open_archive(archive: &Path) -> BTreeMap<String, Entry> {
    let outer = read_tar(&std::fs::read(archive).unwrap());
    for (name, entry) in &outer {
        if let Some(hex) = name.strip_prefix("blobs/sha256/").filter(|h| !h.is_empty()) {
            assert_eq!(sha256(&entry.data), format!("sha256:{hex}"), "blob {name}");
        }
    }
    let layout: Value = serde_json::from_slice(&outer["oci-layout"].data).unwrap();
    assert_eq!(layout["imageLayoutVersion"], "1.0.0");
    outer
}

/// The JSON blob a descriptor's digest names.
fn json_blob(outer: &BTreeMap<String, Entry>, digest: &Value) -> Value {
    let hex = digest.as_str().unwrap().strip_prefix("sha256:").unwrap();
    serde_json::from_slice(&outer[&format!("blobs/sha256/{hex}")].data).unwrap()
}

/// The image manifest `descriptor` points to, checking the layer against the config's diff_id.
fn open_manifest(
    outer: &BTreeMap<String, Entry>,
    index: Value,
    descriptor: &Value,
    scratch: &Path,
) -> Image {
    assert_eq!(
        descriptor["mediaType"],
        "application/vnd.oci.image.manifest.v1+json"
    );
    let manifest = json_blob(outer, &descriptor["digest"]);
    let config = json_blob(outer, &manifest["config"]["digest"]);
    let layers = manifest["layers"].as_array().unwrap();
    assert_eq!(layers.len(), 1, "one layer");
    assert_eq!(
        layers[0]["mediaType"],
        "application/vnd.oci.image.layer.v1.tar+gzip"
    );
    let hex = layers[0]["digest"].as_str().unwrap();
    let hex = hex.strip_prefix("sha256:").unwrap();
    let layer_tar = gunzip(&outer[&format!("blobs/sha256/{hex}")].data, scratch);
    assert_eq!(config["rootfs"]["diff_ids"][0], sha256(&layer_tar));
    Image {
        index,
        config,
        layer: read_tar(&layer_tar),
    }
}

/// Opens a single-platform OCI archive.
fn open_image(archive: &Path, scratch: &Path) -> Image {
    let outer = open_archive(archive);
    let index: Value = serde_json::from_slice(&outer["index.json"].data).unwrap();
    assert_eq!(index["manifests"].as_array().unwrap().len(), 1, "one image");
    let descriptor = index["manifests"][0].clone();
    open_manifest(&outer, index, &descriptor, scratch)
}

/// Opens a multi-platform archive: `index.json` names one image index, whose manifests are the
/// platforms' images. Returns `index.json`, and each image (its `index` the image index) with
/// its descriptor there (which gives its `platform`).
fn open_multi(archive: &Path, scratch: &Path) -> (Value, Vec<(Value, Image)>) {
    let outer = open_archive(archive);
    let index: Value = serde_json::from_slice(&outer["index.json"].data).unwrap();
    let top = index["manifests"].as_array().unwrap();
    assert_eq!(top.len(), 1, "index.json names one image index: {index}");
    assert_eq!(
        top[0]["mediaType"],
        "application/vnd.oci.image.index.v1+json"
    );
    let image_index = json_blob(&outer, &top[0]["digest"]);
    let images = image_index["manifests"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            let image = open_manifest(&outer, image_index.clone(), d, scratch);
            (d.clone(), image)
        })
        .collect();
    (index, images)
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

/// The ELF header of `data` (a 64-bit little-endian executable or library): its machine, and
/// its program interpreter if it names one.
fn elf(data: &[u8]) -> (u16, Option<String>) {
    assert_eq!(&data[..4], b"\x7fELF", "not an ELF file");
    assert_eq!((data[4], data[5]), (2, 1), "not 64-bit little-endian");
    let u16_at = |at: usize| u16::from_le_bytes(data[at..at + 2].try_into().unwrap()) as usize;
    let u64_at = |at: usize| u64::from_le_bytes(data[at..at + 8].try_into().unwrap()) as usize;
    let (phoff, phentsize, phnum) = (u64_at(32), u16_at(54), u16_at(56));
    let interp = (0..phnum).map(|i| phoff + i * phentsize).find_map(|ph| {
        // PT_INTERP: a NUL-terminated path at p_offset.
        (u32::from_le_bytes(data[ph..ph + 4].try_into().unwrap()) == 3).then(|| {
            let (at, len) = (u64_at(ph + 8), u64_at(ph + 32));
            text(&data[at..at + len])
        })
    });
    (u16_at(18) as u16, interp)
}

/// ELF machine numbers.
const EM_X86_64: u16 = 62;
const EM_AARCH64: u16 = 183;

/// Exactly linux/amd64 and linux/arm64 (v8), in that order; each image's config says the same,
/// its binary and every library are built for that CPU, and its ELF interpreter is in the image.
fn check_platforms(images: &[(Value, Image)]) {
    let platforms: Vec<&Value> = images.iter().map(|(d, _)| &d["platform"]).collect();
    assert_eq!(
        platforms,
        [
            &serde_json::json!({"architecture": "amd64", "os": "linux"}),
            &serde_json::json!({"architecture": "arm64", "os": "linux", "variant": "v8"}),
        ]
    );
    for (descriptor, image) in images {
        let platform = &descriptor["platform"];
        assert_eq!(image.config["architecture"], platform["architecture"]);
        assert_eq!(image.config["os"], "linux");
        assert_eq!(image.config.get("variant"), platform.get("variant"));
        let want = match platform["architecture"].as_str() {
            Some("amd64") => EM_X86_64,
            _ => EM_AARCH64,
        };
        let (machine, interp) = elf(&image.layer["usr/bin/lekiwi-operator"].data);
        assert_eq!(machine, want, "the {platform} binary's ELF machine");
        let interp = interp.expect("a dynamically linked binary");
        assert!(
            image.layer.contains_key(interp.trim_start_matches('/')),
            "{platform}: no {interp} in the image"
        );
        for (path, entry) in image.layer.iter().filter(|(p, _)| p.contains(".so")) {
            assert_eq!(elf(&entry.data).0, want, "{platform}: /{path}");
        }
    }
}

/// The image's run settings and files: non-root, the operator as entrypoint, nothing to log in
/// with or install from, the CA bundle, /tmp 1777, every mtime the commit time, owners 0:0.
fn check_contents(image: &Image, annotations: &Value, tag: &str, arch: &str) {
    let ref_name = format!("ghcr.io/lekiwi-fleet/lekiwi-operator:{tag}");
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
    assert_eq!(image.config["architecture"], arch);
    // amd64 is always release; arm64 what scripts/test.sh asked for (or release).
    let profile = match arch {
        "arm64" => std::env::var("LEKIWI_IMAGE_ARM64_PROFILE").unwrap_or("release".into()),
        _ => "release".into(),
    };
    assert_eq!(
        run["Labels"]["fleet.lekiwi.io/cargo-profile"],
        profile.as_str(),
        "{arch}: the cargo profile label"
    );
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

/// The operator image for linux/amd64 and linux/arm64: one image index; the same bytes twice;
/// each platform's image minimal, for its CPU, and the same as the platform's own archive beside
/// it (what `--load` imports); the chart runs it.
#[test]
fn operator_image_is_reproducible_minimal_and_what_the_chart_runs() {
    let scratch = tempfile::tempdir().unwrap();
    let tag = chart_yaml("Chart.yaml")["appVersion"]
        .as_str()
        .unwrap()
        .to_string();
    let archive = |name: &str| scratch.path().join(format!("{name}.oci.tar"));
    let started = Instant::now();
    let first = archive("first");
    assert_eq!(image_sh(&["--out", first.to_str().unwrap()]), first);
    println!("first build: {:?}", started.elapsed());
    let second = archive("second");
    let started = Instant::now();
    assert_eq!(
        image_sh(&["operator", "--out", second.to_str().unwrap()]),
        second
    );
    println!("second build: {:?}", started.elapsed());
    let pairs = [
        ("first", "second"),
        ("first-amd64", "second-amd64"),
        ("first-arm64", "second-arm64"),
    ];
    for (a, b) in pairs {
        let (x, y) = (
            std::fs::read(archive(a)).unwrap(),
            std::fs::read(archive(b)).unwrap(),
        );
        println!("{a}: {} bytes", x.len());
        assert!(x == y, "two builds of one commit differ: {a}, {b}");
    }

    let (index, images) = open_multi(&first, scratch.path());
    check_platforms(&images);
    let names = &index["manifests"][0]["annotations"];
    for (descriptor, image) in &images {
        let arch = descriptor["platform"]["architecture"].as_str().unwrap();
        check_contents(image, names, &tag, arch);
        let own = open_image(&archive(&format!("first-{arch}")), scratch.path());
        assert_eq!(own.index["manifests"][0]["digest"], descriptor["digest"]);
        check_contents(&own, &own.index["manifests"][0]["annotations"], &tag, arch);
    }
    check_chart_agrees(&tag);
    runs_with_its_own_libraries(&images[0].1, scratch.path());
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

/// Writes `image`'s layer under `root` (directories, files with their modes).
fn unpack(image: &Image, root: &Path) {
    for (path, entry) in &image.layer {
        let dest = root.join(path);
        match entry.kind {
            b'5' => std::fs::create_dir_all(&dest).unwrap(),
            b'0' => std::fs::write(&dest, &entry.data).unwrap(),
            other => panic!("unexpected entry type {} at /{path}", other as char),
        }
        let mode = std::fs::Permissions::from_mode(entry.mode);
        std::fs::set_permissions(&dest, mode).unwrap();
    }
}

/// The shared control plane's kubeconfig as the guest uses it: the API server at the host's
/// address from the guest, and `tls-server-name` a name its certificate holds (it does not
/// hold 10.0.2.2).
fn guest_kubeconfig(cp: &ControlPlane) -> anyhow::Result<String> {
    let text = std::fs::read_to_string(cp.kubeconfig())?;
    let mut config: serde_yaml::Value = serde_yaml::from_str(&text)?;
    let cluster = &mut config["clusters"][0]["cluster"];
    let server = cluster["server"].as_str().context("no server")?.to_owned();
    let port = server.rsplit(':').next().context("no port")?.to_owned();
    cluster["server"] = format!("https://{HOST_FROM_GUEST}:{port}").into();
    cluster["tls-server-name"] = "kubernetes".into();
    Ok(serde_yaml::to_string(&config)?)
}

/// What the guest runs: the image's root filesystem as the container's (chroot, with /proc and
/// /dev), `lekiwi-operator --help` there, then the operator against the host's API server with
/// its HTTP endpoints on the guest's port 9477 (forwarded to the host).
fn guest_script(ns: &str, identity: &str) -> String {
    format!(
        r#"R=/lekiwi/rootfs
mkdir -p $R/proc $R/dev && mount -t proc proc $R/proc && mount -o bind /dev $R/dev
chroot $R /usr/bin/lekiwi-operator --help >/tmp/help 2>&1
rc=$?
sed 's/^/LEKIWI-OP-USAGE /' /tmp/help
echo "LEKIWI-OP-HELP status=$rc"
exec chroot $R /usr/bin/lekiwi-operator --kubeconfig /kubeconfig --namespace {ns} \
  --watch-namespace {ns} --identity {identity} --http-addr 0.0.0.0:{GUEST_STATUS_PORT} \
  --gateway-addr 0.0.0.0:8081 --gateway-name gw-{identity} --store-url sqlite:///tmp/events.db \
  --blob-dir /tmp/blobs
"#
    )
}

/// The arm64 operator binary taken from the image's arm64 layer, with that layer's libraries
/// only, runs on an emulated Pi 5 (Cortex-A76): `--help`, then against the host's API server
/// (reached at 10.0.2.2): `/healthz` and `/readyz` answer 200 and it holds its leader Lease.
#[tokio::test]
async fn arm64_operator_from_the_image_runs_on_an_emulated_pi5() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "arm64img").await?;
    let scratch = tempfile::tempdir()?;
    let archive = scratch.path().join("operator.oci.tar");
    image_sh(&["--out", archive.to_str().unwrap()]);
    let (_, images) = open_multi(&archive, scratch.path());
    let (_, arm64) = images
        .iter()
        .find(|(d, _)| d["platform"]["architecture"] == "arm64")
        .context("no arm64 image")?;
    let payload = scratch.path().join("payload");
    unpack(arm64, &payload.join("rootfs"));
    std::fs::write(payload.join("rootfs/kubeconfig"), guest_kubeconfig(cp)?)?;
    let identity = "pi-operator";
    std::fs::write(payload.join("run.sh"), guest_script(&ns, identity))?;

    let name = format!("operator-{}", std::process::id());
    let guest = PiGuest::boot(&name, Run::Script, Some(&payload), &[])?;
    let status = wait_for("--help in the guest", Duration::from_secs(120), || async {
        guest.marker("LEKIWI-OP-HELP")
    })
    .await
    .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(40)))?;
    let cpu = guest.marker("LEKIWI-CPU").unwrap_or_default();
    assert!(cpu.contains("0xd0b"), "not a Cortex-A76: {cpu:?}");
    let usage: Vec<String> = guest
        .console()
        .lines()
        .filter_map(|l| l.strip_prefix("LEKIWI-OP-USAGE ").map(str::to_owned))
        .collect();
    assert_eq!(status, "status=0", "--help:\n{}", usage.join("\n"));
    assert!(
        usage
            .iter()
            .any(|l| l.starts_with("Usage: lekiwi-operator")),
        "{usage:?}"
    );
    assert!(
        usage.iter().any(|l| l.contains("--kubeconfig")),
        "{usage:?}"
    );

    let port = guest.status_port;
    for path in ["/healthz", "/readyz"] {
        let body = wait_for(path, Duration::from_secs(180), || async {
            match http_get(port, path).await {
                Ok((200, body)) => Some(body),
                _ => None,
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}\nconsole tail:\n{}", guest.console_tail(40)))?;
        eprintln!("{path} answered 200 after {:?}", guest.booted.elapsed());
        if path == "/healthz" {
            assert_eq!(body, "ok\n");
        }
    }
    let lease = Api::<Lease>::namespaced(client.clone(), &ns)
        .get("lekiwi-operator")
        .await?;
    let holder = lease.spec.and_then(|s| s.holder_identity);
    assert_eq!(holder.as_deref(), Some(identity), "the leader Lease");
    Ok(())
}
