#!/usr/bin/env python3
"""Writes a reproducible OCI image archive (an OCI image layout in a tar file) from host files.

The archive holds `oci-layout`, `index.json` and `blobs/sha256/*`: one image with one gzip layer.
`ctr -n k8s.io images import`, `skopeo copy oci-archive:FILE ...` and `podman load` accept it, and
name the image after `--ref` (annotations `io.containerd.image.name` and
`org.opencontainers.image.ref.name` in `index.json`).

With `--merge` it instead joins single-platform archives (as written above, one per architecture)
into one multi-platform archive: `index.json` names one image index (the `--ref` annotations on
its descriptor), whose manifests are the archives' images, each with its `platform`, in the order
given. A runtime takes its own platform's image from it; `skopeo copy --all` pushes them all.
(Not the two manifests in `index.json` itself: `ctr images import` names the image after each in
turn and keeps only the last platform's.)

Reproducible: the same inputs give a byte-identical archive. Tar entries are sorted, owned by
0:0 with no user or group names, their mtimes are `--epoch` (default `SOURCE_DATE_EPOCH`, else 0);
the gzip header has mtime 0 and no file name; JSON has sorted keys and no spaces.

    python3 scripts/lib/oci.py --out FILE.tar --ref NAME:TAG [--file SRC:DEST[:MODE]]...
        [--dir DEST[:MODE]]... [--symlink TARGET:DEST]... [--entrypoint JSON_ARRAY]
        [--cmd JSON_ARRAY] [--user UID:GID] [--env K=V]... [--workdir DIR] [--label K=V]...
        [--arch amd64|arm64] [--epoch SECONDS]
    python3 scripts/lib/oci.py --out FILE.tar --ref NAME:TAG --merge A.tar --merge B.tar [--epoch SECONDS]

Prints the manifest digest and the archive size. Python 3.11 standard library only.
"""

from __future__ import annotations

import argparse
import datetime
import gzip
import hashlib
import io
import json
import os
import posixpath
import sys
import tarfile

MANIFEST_TYPE = "application/vnd.oci.image.manifest.v1+json"
CONFIG_TYPE = "application/vnd.oci.image.config.v1+json"
LAYER_TYPE = "application/vnd.oci.image.layer.v1.tar+gzip"
INDEX_TYPE = "application/vnd.oci.image.index.v1+json"
DEFAULT_PATH = "PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"


class Entry:
    """One layer entry: a regular file (`data`), a directory, or a symlink (`target`)."""

    def __init__(self, kind: bytes, mode: int, data: bytes = b"", target: str = ""):
        self.kind, self.mode, self.data, self.target = kind, mode, data, target


def fail(msg: str) -> None:
    print(f"oci.py: {msg}", file=sys.stderr)
    sys.exit(2)


def image_path(dest: str) -> str:
    """`/usr/bin/x` -> `usr/bin/x`: absolute, normalised, without `..`."""
    if not dest.startswith("/"):
        fail(f"{dest!r}: paths in the image must be absolute")
    norm = posixpath.normpath(dest).lstrip("/")
    if not norm or norm == "." or ".." in norm.split("/"):
        fail(f"{dest!r}: not a usable path in the image")
    return norm


def parse_mode(text: str, what: str) -> int:
    try:
        mode = int(text, 8)
    except ValueError:
        fail(f"{what}: mode {text!r} is not octal")
    if not 0 <= mode <= 0o7777:
        fail(f"{what}: mode {text!r} out of range")
    return mode


def add(entries: dict[str, Entry], path: str, entry: Entry) -> None:
    if path in entries and not (entries[path].kind == entry.kind == tarfile.DIRTYPE):
        fail(f"/{path} is given twice")
    entries[path] = entry


def collect(args: argparse.Namespace) -> dict[str, Entry]:
    """The layer's entries by image path, with every missing parent directory (0755)."""
    entries: dict[str, Entry] = {}
    for spec in args.file:
        parts = spec.split(":")
        if len(parts) not in (2, 3):
            fail(f"--file {spec!r}: expected SRC:DEST[:MODE]")
        src, dest = parts[0], image_path(parts[1])
        try:
            with open(src, "rb") as f:
                data = f.read()
            executable = os.stat(src).st_mode & 0o111
        except OSError as e:
            fail(f"--file {spec!r}: {e}")
        mode = parse_mode(parts[2], spec) if len(parts) == 3 else (0o755 if executable else 0o644)
        add(entries, dest, Entry(tarfile.REGTYPE, mode, data=data))
    for spec in args.dir:
        parts = spec.split(":")
        if len(parts) not in (1, 2):
            fail(f"--dir {spec!r}: expected DEST[:MODE]")
        mode = parse_mode(parts[1], spec) if len(parts) == 2 else 0o755
        add(entries, image_path(parts[0]), Entry(tarfile.DIRTYPE, mode))
    for spec in args.symlink:
        target, sep, dest = spec.rpartition(":")
        if not sep or not target:
            fail(f"--symlink {spec!r}: expected TARGET:DEST")
        add(entries, image_path(dest), Entry(tarfile.SYMTYPE, 0o777, target=target))
    for path in list(entries):
        parent = posixpath.dirname(path)
        while parent:
            entry = entries.setdefault(parent, Entry(tarfile.DIRTYPE, 0o755))
            if entry.kind != tarfile.DIRTYPE:
                fail(f"/{parent} is a parent directory of /{path} but is given as a file")
            parent = posixpath.dirname(parent)
    return entries


def tar_bytes(entries: dict[str, Entry], epoch: int) -> bytes:
    """An uncompressed tar of `entries`, sorted by path, owned by 0:0, all mtimes `epoch`."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for path in sorted(entries):
            e = entries[path]
            info = tarfile.TarInfo(path)
            info.type, info.mode, info.mtime = e.kind, e.mode, epoch
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            info.linkname = e.target
            info.size = len(e.data) if e.kind == tarfile.REGTYPE else 0
            tar.addfile(info, io.BytesIO(e.data) if e.kind == tarfile.REGTYPE else None)
    return buf.getvalue()


def gzip_bytes(data: bytes) -> bytes:
    """gzip with header mtime 0 and no file name, so the output depends on `data` only."""
    buf = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buf, mtime=0, compresslevel=9) as gz:
        gz.write(data)
    return buf.getvalue()


def canonical(obj: object) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()


def sha256(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


def key_values(items: list[str], flag: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            fail(f"{flag} {item!r}: expected K=V")
        out[key] = value
    return out


def json_array(text: str | None, flag: str) -> list[str] | None:
    if text is None:
        return None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        fail(f"{flag}: not JSON ({e})")
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        fail(f"{flag}: expected a JSON array of strings")
    return value


def image_config(args: argparse.Namespace, diff_id: str, epoch: int) -> dict:
    """The OCI image configuration: run settings, the platform and the layer's diff_id."""
    env = args.env if any(e.startswith("PATH=") for e in args.env) else [DEFAULT_PATH, *args.env]
    key_values(env, "--env")
    run = {"Env": env}
    for key, value in (
        ("Entrypoint", json_array(args.entrypoint, "--entrypoint")),
        ("Cmd", json_array(args.cmd, "--cmd")),
        ("User", args.user),
        ("WorkingDir", args.workdir),
        ("Labels", key_values(args.label, "--label") or None),
    ):
        if value is not None:
            run[key] = value
    created = datetime.datetime.fromtimestamp(epoch, datetime.timezone.utc)
    config = {
        "architecture": args.arch,
        "os": "linux",
        "created": created.strftime("%Y-%m-%dT%H:%M:%SZ"),
        "config": run,
        "rootfs": {"type": "layers", "diff_ids": [diff_id]},
        "history": [{"created": created.strftime("%Y-%m-%dT%H:%M:%SZ"), "created_by": "scripts/lib/oci.py"}],
    }
    if args.arch == "arm64":
        config["variant"] = "v8"
    return config


def write_archive(out: str, blobs: dict[str, bytes], index: bytes, epoch: int) -> None:
    """The OCI layout as a tar file, written next to `out` and renamed over it."""
    files = {"oci-layout": canonical({"imageLayoutVersion": "1.0.0"}), "index.json": index}
    for digest, data in blobs.items():
        files["blobs/sha256/" + digest.removeprefix("sha256:")] = data
    entries = {path: Entry(tarfile.REGTYPE, 0o644, data=data) for path, data in files.items()}
    for d in ("blobs", "blobs/sha256"):
        entries[d] = Entry(tarfile.DIRTYPE, 0o755)
    tmp = f"{out}.tmp{os.getpid()}"
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(tmp, "wb") as f:
        f.write(tar_bytes(entries, epoch))
    os.replace(tmp, out)


def build(args: argparse.Namespace) -> str:
    """Writes the archive; returns the manifest digest."""
    epoch = args.epoch if args.epoch is not None else int(os.environ.get("SOURCE_DATE_EPOCH") or 0)
    layer_tar = tar_bytes(collect(args), epoch)
    layer = gzip_bytes(layer_tar)
    config = canonical(image_config(args, sha256(layer_tar), epoch))
    manifest = canonical({
        "schemaVersion": 2,
        "mediaType": MANIFEST_TYPE,
        "config": {"mediaType": CONFIG_TYPE, "digest": sha256(config), "size": len(config)},
        "layers": [{"mediaType": LAYER_TYPE, "digest": sha256(layer), "size": len(layer)}],
    })
    platform = {"architecture": args.arch, "os": "linux"}
    if args.arch == "arm64":
        platform["variant"] = "v8"
    index = canonical({
        "schemaVersion": 2,
        "mediaType": INDEX_TYPE,
        "manifests": [{
            "mediaType": MANIFEST_TYPE,
            "digest": sha256(manifest),
            "size": len(manifest),
            "platform": platform,
            "annotations": {
                "io.containerd.image.name": args.ref,
                "org.opencontainers.image.ref.name": args.ref,
            },
        }],
    })
    blobs = {sha256(b): b for b in (layer, config, manifest)}
    write_archive(args.out, blobs, index, epoch)
    return sha256(manifest)


def read_archive(path: str) -> tuple[dict, dict[str, bytes]]:
    """A single-image archive's `index.json` descriptor (with its platform) and its blobs."""
    try:
        with tarfile.open(path) as tar:
            files = {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}
    except (OSError, tarfile.TarError) as e:
        fail(f"--merge {path!r}: {e}")
    manifests = json.loads(files.get("index.json", b"{}")).get("manifests", [])
    if len(manifests) != 1 or manifests[0].get("mediaType") != MANIFEST_TYPE \
            or "platform" not in manifests[0]:
        fail(f"--merge {path!r}: expected one image with a platform in index.json")
    blobs = {"sha256:" + name.removeprefix("blobs/sha256/"): data
             for name, data in files.items() if name.startswith("blobs/sha256/")}
    return manifests[0], blobs


def merge(args: argparse.Namespace) -> str:
    """Writes the multi-platform archive; returns the image index's digest."""
    epoch = args.epoch if args.epoch is not None else int(os.environ.get("SOURCE_DATE_EPOCH") or 0)
    blobs: dict[str, bytes] = {}
    manifests, platforms = [], set()
    for path in args.merge:
        desc, more = read_archive(path)
        platform = json.dumps(desc["platform"], sort_keys=True)
        if platform in platforms:
            fail(f"--merge {path!r}: platform {platform} is given twice")
        platforms.add(platform)
        manifests.append({k: desc[k] for k in ("mediaType", "digest", "size", "platform")})
        blobs.update(more)
    image_index = canonical({"schemaVersion": 2, "mediaType": INDEX_TYPE, "manifests": manifests})
    blobs[sha256(image_index)] = image_index
    index = canonical({
        "schemaVersion": 2,
        "mediaType": INDEX_TYPE,
        "manifests": [{
            "mediaType": INDEX_TYPE,
            "digest": sha256(image_index),
            "size": len(image_index),
            "annotations": {
                "io.containerd.image.name": args.ref,
                "org.opencontainers.image.ref.name": args.ref,
            },
        }],
    })
    write_archive(args.out, dict(sorted(blobs.items())), index, epoch)
    return sha256(image_index)


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="oci.py", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="the archive to write (FILE.tar)")
    p.add_argument("--ref", required=True, help="image name, e.g. ghcr.io/org/name:1.0.0")
    p.add_argument("--file", action="append", default=[], metavar="SRC:DEST[:MODE]",
                   help="a host file into the image (mode: octal; default 0755 if executable, else 0644)")
    p.add_argument("--dir", action="append", default=[], metavar="DEST[:MODE]",
                   help="an empty directory (default mode 0755), e.g. /tmp:1777")
    p.add_argument("--symlink", action="append", default=[], metavar="TARGET:DEST")
    p.add_argument("--entrypoint", metavar="JSON_ARRAY")
    p.add_argument("--cmd", metavar="JSON_ARRAY")
    p.add_argument("--user", metavar="UID:GID")
    p.add_argument("--env", action="append", default=[], metavar="K=V",
                   help="environment (a default PATH is added unless given)")
    p.add_argument("--workdir", metavar="DIR")
    p.add_argument("--label", action="append", default=[], metavar="K=V")
    p.add_argument("--arch", choices=["amd64", "arm64"], default="amd64")
    p.add_argument("--merge", action="append", default=[], metavar="ARCHIVE",
                   help="join these single-platform archives into one multi-platform archive "
                        "(no --file/--dir/... then)")
    p.add_argument("--epoch", type=int, metavar="SECONDS",
                   help="mtime of every entry and the image's creation time "
                        "(default SOURCE_DATE_EPOCH, else 0)")
    args = p.parse_args(argv)
    if ":" not in args.ref.rsplit("/", 1)[-1]:
        fail(f"--ref {args.ref!r}: expected NAME:TAG")
    image_flags = (args.file, args.dir, args.symlink, args.entrypoint, args.cmd, args.user,
                   args.env, args.workdir, args.label)
    if args.merge and any(image_flags):
        fail("--merge joins archives: it takes only --out, --ref and --epoch")
    return args


def main(argv: list[str]) -> None:
    args = parse_args(argv)
    digest = merge(args) if args.merge else build(args)
    print(f"digest: {digest}")
    print(f"size: {os.path.getsize(args.out)} bytes ({args.out})")


if __name__ == "__main__":
    main(sys.argv[1:])
