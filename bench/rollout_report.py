#!/usr/bin/env python3
"""The Python half of bench/rollout.sh: makes the three releases, drives and times each rollout
against the kube API, snapshots the gateway's per-robot byte counts, and prints the results table.

Subcommands (all paths and ports come from the arguments and the environment bench/rollout.sh
exports: LEKIWI_CP_DIR, APISERVER_PORT, BENCH_NS, BENCH_OPERATOR_NS, BENCH_GW_PORT,
BENCH_ROBOTS):

  gen DIR FILES MBYTES CHANGED_PERCENT   v1, v2 (P% of the files changed), v3 (one more) + JSON
  online TIMEOUT                         waits until BENCH_ROBOTS Robots are Online
  served OUT                             GET /v1/blobs-served (every robot) into OUT
  rollout MODE VERSION DIGEST OUT        install (create), update or rollback (patch), timed
  report WORK                            the table, from WORK/facts.env and the JSON files

Standard library only. The kube API is used over HTTPS with the private control plane's admin
token. Rollouts are timed with watches (the Robots and the deployment), not polls: each time is
the arrival of the event that showed the change, and the API server only sends what changed
(listing 200 Robots every half second, or a kubectl process per poll, would cost the 2-core
machine more CPU than the agents and blur the times by the poll period).
"""

import datetime
import http.client
import json
import os
import random
import re
import ssl
import statistics
import sys
import textwrap
import threading
import time
from pathlib import Path

GROUP = "/apis/fleet.lekiwi.io/v1alpha1"
MB = 1e6
# Cells longer than this are printed on lines of their own below their row.
LONG = 64


def log(msg):
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---- kube API ---------------------------------------------------------------------------------
class Kube:
    """A tiny client of the private API server: JSON in, JSON out, one connection."""

    def __init__(self):
        cp = Path(os.environ["LEKIWI_CP_DIR"])
        self.port = int(os.environ["APISERVER_PORT"])
        self.token = (cp / "admin-token").read_text().strip()
        self.ctx = ssl.create_default_context(cafile=str(cp / "pki" / "ca.crt"))
        self.conn = None

    def request(self, method, path, body=None, content_type="application/json"):
        for attempt in range(5):
            if self.conn is None:
                self.conn = http.client.HTTPSConnection(
                    "127.0.0.1", self.port, context=self.ctx, timeout=30
                )
            headers = {"Authorization": f"Bearer {self.token}", "Accept": "application/json"}
            data = None
            if body is not None:
                data = json.dumps(body).encode()
                headers["Content-Type"] = content_type
            try:
                self.conn.request(method, path, body=data, headers=headers)
                resp = self.conn.getresponse()
                payload = resp.read()
            except (OSError, http.client.HTTPException):
                self.conn.close()
                self.conn = None
                if attempt == 4:
                    raise
                time.sleep(0.2)
                continue
            if resp.status >= 400:
                raise RuntimeError(f"{method} {path}: {resp.status} {payload[:300]!r}")
            return json.loads(payload) if payload else None
        raise RuntimeError("unreachable")

    def robots(self, ns):
        return self.request("GET", f"{GROUP}/namespaces/{ns}/robots")["items"]

    def deployment(self, ns, name):
        return self.request("GET", f"{GROUP}/namespaces/{ns}/robotdeployments/{name}")


def env(name):
    v = os.environ.get(name)
    if not v:
        sys.exit(f"rollout_report.py: {name} is not set")
    return v


# ---- gen: the releases ------------------------------------------------------------------------
def gen(root, files, mbytes, changed_percent):
    """v1: FILES random files totalling MBYTES * 10^6 bytes in nested directories (sizes vary
    from 0.5x to 1.5x the mean); v2: v1 with round(FILES * P / 100) files rewritten with new
    random content of the same size (the others hard links to v1's); v3: v2 with one more."""
    root = Path(root)
    rng = random.Random(20261122)
    total = mbytes * 1_000_000
    weights = [rng.uniform(0.5, 1.5) for _ in range(files)]
    scale = total / sum(weights)
    sizes = [int(w * scale) for w in weights]
    sizes[-1] += total - sum(sizes)
    paths = []
    for i in range(files):
        # A robot-software-like tree: packages with sub-packages, two to three levels deep.
        pkg, sub = i % 7, (i // 7) % 5
        if i % 3 == 0:
            paths.append(f"lekiwi/pkg{pkg}/data/file{i:04d}.bin")
        else:
            paths.append(f"lekiwi/pkg{pkg}/sub{sub}/file{i:04d}.bin")
    n_changed = max(1, round(files * changed_percent / 100)) if changed_percent > 0 else 0
    changed_v2 = sorted(rng.sample(range(files), n_changed))
    rest = [i for i in range(files) if i not in set(changed_v2)]
    changed_v3 = [rng.choice(rest)] if rest else [changed_v2[0]]

    def write_random(path, size):
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as f:
            left = size
            while left > 0:
                n = min(left, 1 << 20)
                f.write(os.urandom(n))
                left -= n

    v1, v2, v3 = root / "v1", root / "v2", root / "v3"
    for i in range(files):
        write_random(v1 / paths[i], sizes[i])
    for prev, cur, changed in ((v1, v2, set(changed_v2)), (v2, v3, set(changed_v3))):
        for i in range(files):
            dest = cur / paths[i]
            dest.parent.mkdir(parents=True, exist_ok=True)
            if i in changed:
                write_random(dest, sizes[i])
            else:
                os.link(prev / paths[i], dest)
    info = {
        "files": files,
        "bytes": total,
        "changed_percent": changed_percent,
        "v2_changed_files": [paths[i] for i in changed_v2],
        "v2_changed_bytes": sum(sizes[i] for i in changed_v2),
        "v3_changed_files": [paths[i] for i in changed_v3],
        "v3_changed_bytes": sum(sizes[i] for i in changed_v3),
        "size_min": min(sizes),
        "size_max": max(sizes),
    }
    (root / "releases.json").write_text(json.dumps(info, indent=1))
    print(
        f"{files} files, {total / MB:.1f} MB; v2 changes {n_changed} files "
        f"({info['v2_changed_bytes'] / MB:.2f} MB), v3 one more "
        f"({info['v3_changed_bytes'] / MB:.2f} MB)"
    )


# ---- online ------------------------------------------------------------------------------------
def online(timeout):
    kube, ns, want = Kube(), env("BENCH_NS"), int(env("BENCH_ROBOTS"))
    t0 = time.monotonic()
    last = 0.0
    while True:
        robots = kube.robots(ns)
        n = sum(1 for r in robots if (r.get("status") or {}).get("phase") == "Online")
        if n >= want:
            print(f"{time.monotonic() - t0:.1f}")
            return
        if time.monotonic() - t0 > timeout:
            sys.exit(f"only {n} of {want} robots Online after {timeout} s")
        if time.monotonic() - last > 10:
            last = time.monotonic()
            log(f"  {n}/{want} robots Online ({len(robots)} Robots exist)")
        time.sleep(1)


# ---- served ------------------------------------------------------------------------------------
def served(out):
    # A Kubernetes user's token (the admin's: RBAC allows it `list robots` everywhere).
    token = Kube().token
    conn = http.client.HTTPConnection("127.0.0.1", int(env("BENCH_GW_PORT")), timeout=30)
    conn.request("GET", "/v1/blobs-served", headers={"Authorization": f"Bearer {token}"})
    resp = conn.getresponse()
    body = resp.read()
    if resp.status != 200:
        sys.exit(f"/v1/blobs-served answered {resp.status}: {body[:300]!r}")
    robots = json.loads(body)["robots"]
    # One robot through the per-robot query too, so both forms of the endpoint agree.
    if robots:
        key = sorted(robots)[0]
        conn.request(
            "GET", f"/v1/blobs-served?robot={key}", headers={"Authorization": f"Bearer {token}"}
        )
        resp = conn.getresponse()
        one = json.loads(resp.read())
        if one.get("bytes") != robots[key]["bytes"]:
            log(f"warning: /v1/blobs-served?robot={key} says {one} but the list says {robots[key]}")
    Path(out).write_text(json.dumps(robots))


# ---- rollout -----------------------------------------------------------------------------------
def cpu_ticks(pid):
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return int(fields[11]) + int(fields[12])
    except (OSError, IndexError, ValueError):
        return 0


def machine_ticks():
    f = Path("/proc/stat").read_text().splitlines()[0].split()
    return sum(int(x) for x in (f[1], f[2], f[3], f[6], f[7]))


def strategy():
    """The issue's strategy; every other field keeps the product's default."""
    return {
        "batchSize": os.environ.get("BENCH_BATCH", "10%"),
        "canary": 0,
        "successThreshold": 0.8,
        "pauseBetweenBatchesSeconds": 0,
    }


class Watch(threading.Thread):
    """Lists a collection, then watches it (from the list's resourceVersion, again after the
    server ends the watch), calling on_event(type, object, t) with t the arrival time of the
    event on the caller's clock. Its own connection; a daemon thread, ending with the process."""

    def __init__(self, path, on_event, clock):
        super().__init__(daemon=True)
        self.path, self.on_event, self.clock = path, on_event, clock
        self.synced = threading.Event()
        self.error = None

    def run(self):
        try:
            kube = Kube()
            sep = "&" if "?" in self.path else "?"
            items = kube.request("GET", self.path)
            rv = items["metadata"]["resourceVersion"]
            for obj in items["items"]:
                self.on_event("ADDED", obj, self.clock())
            self.synced.set()
            while True:
                conn = http.client.HTTPSConnection("127.0.0.1", kube.port, context=kube.ctx)
                conn.request(
                    "GET",
                    f"{self.path}{sep}watch=1&allowWatchBookmarks=true&timeoutSeconds=600"
                    f"&resourceVersion={rv}",
                    headers={"Authorization": f"Bearer {kube.token}"},
                )
                resp = conn.getresponse()
                if resp.status != 200:
                    raise RuntimeError(f"watch {self.path}: {resp.status} {resp.read()[:300]!r}")
                for line in resp:
                    t = self.clock()
                    ev = json.loads(line)
                    if ev["type"] == "ERROR":
                        raise RuntimeError(f"watch {self.path}: {ev['object']}")
                    rv = ev["object"]["metadata"]["resourceVersion"]
                    if ev["type"] != "BOOKMARK":
                        self.on_event(ev["type"], ev["object"], t)
                conn.close()
        except Exception as e:  # reported by the main thread
            self.error = e
            self.synced.set()


def rollout(mode, version, digest, out):
    """install: create the RobotDeployment `fleet` with VERSION; update / rollback: patch it to
    VERSION. Watches the deployment and the Robots until the rollout's end (Completed and every
    robot reporting VERSION; for rollback: RolledBack and every robot back on the release it ran
    before) and writes what it saw, each time being the arrival of the watch event that showed
    it, in seconds since the create/patch request was sent."""
    kube, ns, robots_n = Kube(), env("BENCH_NS"), int(env("BENCH_ROBOTS"))
    timeout = float(os.environ.get("BENCH_ROLLOUT_TIMEOUT", "600"))
    pids = dict(item.split(":") for item in os.environ.get("BENCH_PIDS", "").split())
    pids["bench"] = str(os.getpid())
    name = "fleet"
    release = {"version": version, "digest": digest}
    path = f"{GROUP}/namespaces/{ns}/robotdeployments"

    lock = threading.Lock()
    t0 = None

    def clock():
        return None if t0 is None else time.monotonic() - t0

    # Robots: name -> version they report.
    current = {}
    r = {"on_target": None, "max_on_target": 0, "all_back": None, "back_to": None}
    # Deployment: phases first seen (current generation), batches first seen, last status.
    d = {"generation": None, "phases": {}, "batches": {}, "status": {}}

    def hist():
        h = {}
        for v in current.values():
            h[v] = h.get(v, 0) + 1
        return h

    def check(t):
        # Called with the lock held, after any change, at the time of the event causing it.
        if t is None:
            return
        h = hist()
        n = h.get(version, 0)
        r["max_on_target"] = max(r["max_on_target"], n)
        if r["on_target"] is None and n >= robots_n:
            r["on_target"] = t
        if (
            mode == "rollback"
            and r["all_back"] is None
            and "RollingBack" in d["phases"]
            and h.get(r["back_to"], 0) >= robots_n
        ):
            r["all_back"] = t

    def on_robot(kind, obj, t):
        with lock:
            key = obj["metadata"]["name"]
            if kind == "DELETED":
                current.pop(key, None)
            else:
                cur = ((obj.get("status") or {}).get("currentRelease") or {}).get("version")
                current[key] = cur
            check(t)

    def drain():
        # Called with the lock held. Events of the deployment can arrive before the patch's
        # answer tells the generation: they wait in d["queue"] until it is known.
        if d["generation"] is None:
            return
        for t, obj in d.pop("queue", []):
            st = obj.get("status") or {}
            if st.get("observedGeneration") != d["generation"]:
                continue
            d["status"] = st
            phase = st.get("phase")
            if phase and phase not in d["phases"]:
                d["phases"][phase] = t
                log(f"  {t:6.1f} s: phase {phase} ({st.get('message', '')})")
            b = st.get("currentBatch")
            total = st.get("totalBatches")
            if (
                b is not None
                and b not in d["batches"]
                and (total is None or b < total)
                and phase in ("Progressing", "Paused")
            ):
                d["batches"][b] = t
            check(t)
        d["queue"] = []

    def on_deployment(kind, obj, t):
        with lock:
            if t is not None:
                d.setdefault("queue", []).append((t, obj))
                drain()

    robots_watch = Watch(f"{GROUP}/namespaces/{ns}/robots", on_robot, clock)
    deploy_watch = Watch(f"{path}?fieldSelector=metadata.name%3D{name}", on_deployment, clock)
    for w in (robots_watch, deploy_watch):
        w.start()
        w.synced.wait(30)
        if w.error:
            sys.exit(f"watch failed: {w.error}")

    with lock:
        if mode == "rollback":
            before = hist()
            if len(before) != 1:
                sys.exit(f"the rollback run needs the whole fleet on one release; found {before}")
            r["back_to"] = next(iter(before))

    cpu0 = {k: cpu_ticks(p) for k, p in pids.items()}
    m0 = machine_ticks()
    wall0 = time.time()
    body_strategy = strategy()
    with lock:
        t0 = time.monotonic()
    if mode == "install":
        obj = kube.request(
            "POST",
            path,
            {
                "apiVersion": "fleet.lekiwi.io/v1alpha1",
                "kind": "RobotDeployment",
                "metadata": {"name": name},
                "spec": {"selector": {}, "release": release, "strategy": body_strategy},
            },
        )
    else:
        obj = kube.request(
            "PATCH",
            f"{path}/{name}",
            {"spec": {"release": release, "strategy": body_strategy}},
            content_type="application/merge-patch+json",
        )
    t_write = time.monotonic() - t0
    with lock:
        d["generation"] = obj["metadata"]["generation"]
        drain()

    last_log = 0.0
    done = None
    while True:
        time.sleep(0.05)
        now = time.monotonic() - t0
        for w in (robots_watch, deploy_watch):
            if w.error:
                done = f"watch failed: {w.error}"
        with lock:
            st = d["status"]
            phase = st.get("phase")
            h = hist()
            if mode in ("install", "update"):
                if phase == "Completed" and r["on_target"] is not None:
                    done = done or "ok"
                elif phase in ("RolledBack", "Failed"):
                    done = done or f"unexpected phase {phase}: {st.get('message')}"
            else:
                if phase == "RolledBack" and r["all_back"] is not None:
                    done = done or "ok"
                elif phase in ("Completed", "Failed"):
                    done = done or f"unexpected phase {phase}: {st.get('message')}"
        if now - last_log >= 5:
            last_log = now
            log(
                f"  {now:6.1f} s: {phase} batch {st.get('batchProgress')} "
                f"progress {st.get('progress')} failed {st.get('failed')}; robots on {h}"
            )
        if done:
            break
        if now > timeout:
            done = f"timeout after {timeout:.0f} s in phase {phase}"
            break
    elapsed = time.monotonic() - t0
    tck = os.sysconf("SC_CLK_TCK")
    cpu = {k: (cpu_ticks(p) - cpu0[k]) / tck / elapsed for k, p in pids.items()}
    cpu["machine"] = (machine_ticks() - m0) / tck / elapsed
    cpu["other"] = max(0.0, cpu["machine"] - sum(v for k, v in cpu.items() if k != "machine"))
    with lock:
        st = d["status"]
        result = {
            "mode": mode,
            "version": version,
            "digest": digest,
            "generation": d["generation"],
            "start_wall": wall0,
            "write_seconds": t_write,
            "phases": d["phases"],
            "batches": {str(k): v for k, v in sorted(d["batches"].items())},
            "all_on_target": r["on_target"],
            "max_on_target": r["max_on_target"],
            "back_to": r["back_to"],
            "all_back": r["all_back"],
            "end": done,
            "elapsed": elapsed,
            "cpu_cores": cpu,
            "releases_at_end": hist(),
            "status": {
                k: st.get(k)
                for k in (
                    "phase",
                    "message",
                    "progress",
                    "batchProgress",
                    "totalBatches",
                    "targeted",
                    "updated",
                    "failed",
                    "skipped",
                    "startTime",
                    "completionTime",
                    "conditions",
                )
            },
            "robot_results": st.get("robots", []),
        }
    Path(out).write_text(json.dumps(result, indent=1))
    if done != "ok":
        sys.exit(f"{mode} rollout of {version}: {done}")


# ---- report ------------------------------------------------------------------------------------
def facts(work):
    out = {}
    p = Path(work) / "facts.env"
    if p.exists():
        for line in p.read_text().splitlines():
            k, _, v = line.partition("=")
            out[k] = v
    return out


def load(work, name):
    p = Path(work) / name
    return json.loads(p.read_text()) if p.exists() else None


def secs(v):
    return "-" if v is None else f"{v:.1f} s"


def mb(v):
    return f"{v / MB:.2f} MB" if v < 10 * 1e9 else f"{v / 1e9:.2f} GB"


def deltas(work, a, b, ns):
    """Per-robot bytes served between two snapshots, for the robots of namespace ns."""
    sa, sb = load(work, a) or {}, load(work, b) or {}
    out = {}
    for key, v in sb.items():
        if key.startswith(ns + "/"):
            out[key] = v["bytes"] - sa.get(key, {}).get("bytes", 0)
    return out


PROGRESS = re.compile(
    r"^(\S+)\s+INFO lekiwi_agent::release: release progress command_id=(\S+) phase=(\S+) (.*)$"
)
ANSI = re.compile(r"\x1b\[[0-9;]*m")


def agent_phases(work, version):
    """Median seconds per phase of the agents' deploys of VERSION, from lekiwi-fleet's log
    (`release progress` lines at RUST_LOG=lekiwi_agent::release=info): a phase lasts from its
    first line to the first line of the next one. Returns (robots, {phase: median}, median
    total, max total)."""
    p = Path(work) / "fleet.log"
    if not p.exists():
        return None
    deploys = {}
    for line in p.read_text(errors="replace").splitlines():
        m = PROGRESS.match(ANSI.sub("", line))
        if m:
            t = datetime.datetime.fromisoformat(m.group(1).replace("Z", "+00:00")).timestamp()
            deploys.setdefault(m.group(2), []).append((t, m.group(3), m.group(4)))
    per, totals = {}, []
    for events in deploys.values():
        if not events or f"manifest of {version}" not in events[0][2]:
            continue
        firsts = []
        for t, phase, _ in events:
            if not firsts or firsts[-1][1] != phase:
                firsts.append((t, phase))
        for (t1, ph), (t2, _) in zip(firsts, firsts[1:]):
            per.setdefault(ph, []).append(t2 - t1)
        totals.append(events[-1][0] - events[0][0])
    if not totals:
        return None
    return (
        len(totals),
        {k: statistics.median(v) for k, v in per.items()},
        statistics.median(totals),
        max(totals),
    )


def report(work):
    f = facts(work)
    rel = load(work, "releases/releases.json") or {}
    ns = f.get("namespace", "bench")
    robots = int(f.get("robots", "0"))
    rows = []

    warnings = []

    def row(what, measured, target="", verdict=""):
        rows.append((what, measured, target, verdict))

    def cpu_row(what, cpu):
        if not cpu:
            return
        row(
            what,
            ", ".join(f"{k} {v:.2f}" for k, v in cpu.items() if k not in ("machine", "other"))
            + f", other processes {cpu.get('other', 0):.2f}; machine {cpu.get('machine', 0):.2f}"
            f" of {f.get('cpus', '?')}",
        )
        if cpu.get("other", 0) > 0.3:
            warnings.append(
                f"other processes used {cpu['other']:.2f} cores during "
                f"{what.strip().removeprefix('CPU during ').removesuffix(' (cores)')}; "
                "the times may be inflated by contention"
            )

    # Pushes.
    for v in ("v1", "v2", "v3"):
        if f"push_{v}_seconds" in f:
            up = int(f.get(f"push_{v}_blob_bytes", "0"))
            row(
                f"push {v} (kubectl lekiwi release push)",
                f"{float(f[f'push_{v}_seconds']):.1f} s, {mb(up)} uploaded",
            )

    inst = load(work, "rollout-install.json")
    if inst:
        d = deltas(work, "served-0.json", "served-1.json", ns)
        row(
            f"initial install v1 -> {robots} robots (patch -> Completed)",
            secs(inst["phases"].get("Completed")),
            "(reported)",
        )
        if d:
            row(
                "  served in the install (all robots)",
                f"{mb(sum(d.values()))} ({mb(statistics.median(d.values()))} per robot)",
            )

    upd = load(work, "rollout-update.json")
    target = float(f.get("target_seconds", "60"))
    if upd:
        t = upd["phases"].get("Completed")
        row(
            f"rollout v2 -> {robots} robots: patch -> Completed",
            secs(t),
            f"< {target:.0f} s",
            "PASS" if t is not None and t < target else "FAIL",
        )
        row("  patch -> every Robot reports v2", secs(upd.get("all_on_target")))
        b = upd.get("batches") or {}
        if len(b) >= 2:
            times = [b[k] for k in sorted(b, key=int)] + [t or upd["elapsed"]]
            per = [y - x for x, y in zip(times, times[1:])]
            row(
                f"  per batch ({len(per)} of {upd['status'].get('totalBatches')} seen): min / median / max",
                f"{min(per):.1f} / {statistics.median(per):.1f} / {max(per):.1f} s",
            )
            row("  patch -> first status showing batch 0", secs(times[0]))
        st = upd["status"]
        row(
            "  status at the end",
            f"{st.get('phase')}, updated {st.get('updated')}, failed {st.get('failed')}, "
            f"skipped {st.get('skipped')}",
        )
        d = deltas(work, "served-1.json", "served-2.json", ns)
        changed = rel.get("v2_changed_bytes", 0)
        if d:
            vals = sorted(d.values())
            row(
                "  bytes served per robot: min / median / max",
                f"{mb(vals[0])} / {mb(statistics.median(vals))} / {mb(vals[-1])}",
            )
            row(
                "  changed bytes (v1 -> v2) / full release",
                f"{mb(changed)} ({len(rel.get('v2_changed_files', []))} files) / "
                f"{mb(rel.get('bytes', 0))}",
            )
            if changed:
                row(
                    "  served / changed bytes (median)",
                    f"{statistics.median(vals) / changed:.3f}x "
                    f"({100 * statistics.median(vals) / rel['bytes']:.1f} % of the release)",
                )
            row("  robots served (of the fleet)", f"{sum(1 for v in vals if v > 0)} of {robots}")
            row("  served to the fleet in total", mb(sum(vals)))
        ph = agent_phases(work, "v2")
        if ph:
            n, med, total_med, total_max = ph
            row(
                f"  one robot's deploy, median of {n} (max)",
                f"{total_med:.1f} s ({total_max:.1f} s)",
            )
            row(
                "  of which, median per phase",
                ", ".join(f"{k.replace('_', ' ')} {v:.2f} s" for k, v in med.items())
                + " (downloading includes the manifest; verifying re-hashes the files already"
                " held)",
            )
        cpu_row("  CPU during the rollout (cores)", upd.get("cpu_cores"))

    rb = load(work, "rollout-rollback.json")
    if rb:
        ph = rb["phases"]
        rolling, rolled, back = ph.get("RollingBack"), ph.get("RolledBack"), rb.get("all_back")
        row(
            "failing batch -> fleet back on v2 (RollingBack -> all v2)",
            secs(back - rolling if back is not None and rolling is not None else None),
            "(reported)",
        )
        row("  patch v3 -> RollingBack (failing batch detected)", secs(rolling))
        row("  patch v3 -> RolledBack", secs(rolled))
        row("  patch v3 -> every Robot reports v2 again", secs(back))
        row("  robots that reached v3 (most at once)", str(rb.get("max_on_target")))
        st = rb["status"]
        row(
            "  status at the end",
            f"{st.get('phase')}, failed {st.get('failed')}: {st.get('message')}",
        )
        d = deltas(work, "served-2.json", "served-3.json", ns)
        if d:
            vals = sorted(d.values())
            row(
                "  bytes served per robot: max / sum",
                f"{mb(vals[-1])} / {mb(sum(vals))} (v3 changes "
                f"{mb(rel.get('v3_changed_bytes', 0))})",
            )
        cpu_row("  CPU during the rollback run (cores)", rb.get("cpu_cores"))

    out = []
    out.append(f"LeKiwi rollout benchmark, {f.get('date', '?')}")
    out.append(f"host: {f.get('host', '?')}")
    out.append(f"source: {f.get('source', '?')}")
    out.append(f"command: {f.get('command', '?')}")
    if rel:
        out.append(
            f"release: v1 = {rel['files']} random files, {mb(rel['bytes'])} "
            f"({mb(rel['size_min'])} to {mb(rel['size_max'])} each, nested directories); "
            f"v2 = v1 with {len(rel['v2_changed_files'])} files "
            f"({rel['changed_percent']} %) rewritten, same sizes; v3 = v2 with 1 more"
        )
    out.append(f"fleet: {f.get('fleet', '?')}")
    out.append(f"operator: {f.get('operator', '?')}")
    out.append(f"strategy: {f.get('strategy', '?')}")
    out.append(f"rollback run: {f.get('failing', '?')}")
    out.append(f"times: {f.get('timing', '?')}")
    out.append("")
    # Long cells (status messages) go on lines of their own, so the columns stay narrow.
    w = max(len(r[0]) for r in rows) + 2 if rows else 40
    wm = max([len(r[1]) for r in rows if len(r[1]) <= LONG] + [8]) + 2
    out.append(f"{'phase':<{w}}{'measured':<{wm}}target")
    for what, measured, tgt, verdict in rows:
        if len(measured) > LONG:
            out.append(what)
            out.extend(textwrap.wrap(measured, 100, initial_indent=" " * 6, subsequent_indent=" " * 6))
            continue
        out.append(f"{what:<{w}}{measured:<{wm}}{tgt}{'   ' + verdict if verdict else ''}".rstrip())
    out.append("")
    out.append(
        "old system (the issue): 5-10 minutes per robot, i.e. "
        f"{robots * 5 / 60:.0f}-{robots * 10 / 60:.0f} hours for {robots} robots one at a time"
    )
    wp = Path(work) / "fleet-warnings.txt"
    if wp.exists():
        lines = [ANSI.sub("", x) for x in wp.read_text(errors="replace").splitlines() if x]
        errors = sum(1 for x in lines if " ERROR " in x[:40])
        row_text = (
            f"agents' log: {len(lines) - errors} warning(s), {errors} error(s) "
            f"(expected: one 'rolling back' warning per robot failing its health check)"
        )
        out.append(row_text)
    for w in warnings:
        out.append(f"WARNING: {w}")
    print("\n".join(out))


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    cmd, args = sys.argv[1], sys.argv[2:]
    if cmd == "gen":
        gen(args[0], int(args[1]), int(args[2]), float(args[3]))
    elif cmd == "online":
        online(float(args[0]))
    elif cmd == "served":
        served(args[0])
    elif cmd == "rollout":
        rollout(*args)
    elif cmd == "report":
        report(args[0])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
