#!/usr/bin/env python3
"""The soak's driver (bench/soak.sh sets up the control plane, PostgreSQL and the Robots, then
runs this): starts the operator's processes, HAProxy and the fleet, rolls releases out back to
back, breaks one thing every --fault-every seconds, samples every process and every robot every
10 s, and writes report.txt (one table, PASS/FAIL) to the work directory.

Standard library, curl and kubectl only. Usage: soak_driver.py CONFIG_JSON."""
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time

from soak_report import Samples, report

C = json.load(open(sys.argv[1]))
WORK = C["work"]
BIN = C["bin"]
NS = "soak"
GRACE_DEAD_GATEWAY = 45  # the gateway Lease (15 s) and the controller's next pass
GRACE_NOT_ONLINE = 300  # a robot with a live session is Online again within this
STALL_SECONDS = 120
DISK_FULL_SECONDS = 120
ABORT_SETTLE = 30  # after an aborted rollout, before its robots are counted
ROLLOUT_LIMIT = 1200  # a rollout not ended this long after its apply fails as "not ended"
LOG = open(os.path.join(WORK, "driver-events.log"), "a", buffering=1)


def log(msg):
    line = f"[soak {time.strftime('%H:%M:%S')}] {msg}"
    print(line, flush=True)
    LOG.write(line + "\n")


def run(*args, check=True, timeout=120, **kw):
    env = dict(os.environ, KUBECONFIG=C["kubeconfig"])
    p = subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=env, **kw)
    if check and p.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:4])}... failed: {p.stderr.strip()[-400:]}")
    return p


def free_port():
    out = run("python3", os.path.join(C["root"], "scripts/lib/free-ports.py"), "1").stdout
    return int(out.split()[0])


def curl(url, timeout=10):
    try:
        return subprocess.run(["curl", "-fsS", "--max-time", str(timeout), url],
                              capture_output=True, text=True, timeout=timeout + 5).stdout
    except subprocess.TimeoutExpired:
        return ""


def metric(text, name):
    """The sum of the series of `name` (with this exact label set if given)."""
    total, found = 0.0, False
    for line in text.splitlines():
        if line.startswith(name + " ") or (line.startswith(name + "{") and "{" not in name):
            try:
                total += float(line.rsplit(" ", 1)[1])
                found = True
            except ValueError:
                pass
    return total if found else None


class Proc:
    """A long-running process of the soak, restartable, its log appended across restarts."""

    def __init__(self, name, argv, env=None, nice=0):
        self.name, self.argv, self.env, self.nice = name, argv, env or {}, nice
        self.p = None
        self.restarts = 0

    def start(self):
        out = open(os.path.join(WORK, f"{self.name}.log"), "a")
        env = dict(os.environ, **self.env)
        argv = (["nice", "-n", str(self.nice)] if self.nice else []) + self.argv
        self.p = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env,
                                  stdin=subprocess.DEVNULL, start_new_session=True)
        return self

    @property
    def pid(self):
        return self.p.pid if self.p else None

    def alive(self):
        return self.p is not None and self.p.poll() is None

    def kill(self, sig=signal.SIGKILL):
        if self.alive():
            # The whole group: a process's own children (the watch's curl) go with it.
            os.killpg(self.p.pid, sig)
            if sig in (signal.SIGKILL, signal.SIGTERM):
                try:
                    self.p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.kill(self.p.pid, signal.SIGKILL)
                    self.p.wait()

    def restart(self):
        self.kill()
        self.restarts += 1
        return self.start()


class Soak:
    def __init__(self):
        self.procs = {}
        self.ports = {}
        self.samples = Samples()
        self.rollouts = []  # dicts: version, kind, expected, phase, started, ended, seconds
        self.faults = []  # dicts: kind, at, healed_s, notes
        self.stall = None  # (start, end) of the cut-off while it lasts
        self.stalls = []  # [start, end] of every cut-off (end None while it lasts)
        self.down = []  # [gateway, killed, restarted] (restarted None while it is down)
        self.robot_state = {}  # name -> (phase, gateway, status.connected)
        # The moment this driver's view of the Robots shows: the latest write its watch has
        # brought (the API server's own time of that write), and how far behind it ran at most.
        self.view_time = None
        self.max_view_lag = 0.0
        self.not_online_since = {}
        self.online_dead_since = {}
        self.violations = {"online_through_dead_gateway": 0, "not_online_with_session": 0,
                           "max_online_through_dead_gateway_s": 0.0,
                           "max_not_online_with_session_s": 0.0, "max_view_lag_s": 0.0}
        self.release_files = os.path.join(WORK, "releases")
        self.completed_releases = set()
        self.unwanted_releases = set()
        self.current_target = None
        self.agent_version = 0
        self.t0 = time.time()

    # ---- processes ------------------------------------------------------------------------
    def operator_procs(self):
        common = ["--kubeconfig", C["kubeconfig"], "--namespace", "lekiwi-system",
                  "--watch-namespace", NS]
        # Each robot a rollout writes, to tell when a robot was told its release; each list of
        # a watch (how long it took, what changed meanwhile).
        # Each status the Robot controller writes itself (a robot it marked gone) and each
        # phase change it sees.
        env = {"RUST_LOG": "warn,lekiwi_controllers::deployment::apply=debug,"
                           "lekiwi_controllers::robot=info,lekiwi_core::watch=info"}
        for c in ("ctl-a", "ctl-b"):
            self.ports[c] = free_port()
            self.procs[c] = Proc(c, [f"{BIN}/lekiwi-operator", "--role", "controller", *common,
                                     "--identity", c, "--http-addr",
                                     f"127.0.0.1:{self.ports[c]}"], env)
        self.gateways = [f"gw-{chr(97 + i)}" for i in range(C["gateways"])]
        for g in self.gateways:
            self.ports[g] = free_port()
            self.ports[g + "-http"] = free_port()
            self.procs[g] = Proc(g, [
                f"{BIN}/lekiwi-operator", "--role", "gateway", *common, "--identity", g,
                "--gateway-name", g, "--gateway-addr", f"127.0.0.1:{self.ports[g]}",
                "--http-addr", f"127.0.0.1:{self.ports[g + '-http']}",
                "--store-url", C["store_url"], "--blob-dir", os.path.join(WORK, "blobs"),
                "--max-unauthenticated-per-address", "0"],
                # The allocator's totals in the log when the gateway stops; a robot's refused
                # blob read (rare in a healthy fleet) named in the log, to tell a replica's lag;
                # each command sent, each desired release or agent handed to a session, and
                # each list of the Robot cache, to tell why a robot was not updated in time.
                dict(env, MIMALLOC_SHOW_STATS="1",
                     RUST_LOG="warn,lekiwi_gateway::blob_api::access=debug,"
                              "lekiwi_gateway::session::serve=info,"
                              "lekiwi_gateway::dispatch=debug,lekiwi_core::cache=info,"
                              "lekiwi_core::watch=info"))

    # Which HAProxy each client process connects through. A proxied connection holds two open
    # files in HAProxy (the robot's and the gateway's), and a process may hold at most the
    # machine's open-file limit: one proxy for the whole fleet would cap it near half that
    # limit, so the big simulator has a proxy of its own and the rest share another.
    LBS = {"sim": "lb-a", "sim-cut": "lb-b", "sim-skew": "lb-b", "fleet": "lb-b"}

    # The robots each client process runs.
    ROBOTS = {"sim": C["robots"] - C["stalled"], "sim-cut": C["stalled"], "sim-skew": 1,
              "fleet": C["agents"]}

    def lb_clients(self):
        """The robots each proxy carries."""
        out = {}
        for proc, lb in self.LBS.items():
            out[lb] = out.get(lb, 0) + self.ROBOTS[proc]
        return out

    def haproxy(self):
        servers = "\n".join(
            f"  server {g} 127.0.0.1:{self.ports[g]} check port {self.ports[g + '-http']} "
            "inter 1s fall 2 rise 2" for g in self.gateways)
        maxconn = (C["fds"] - 500) // 2
        for lb, clients in sorted(self.lb_clients().items()):
            if clients > maxconn:
                raise RuntimeError(
                    f"{lb} would carry {clients} robots, beyond the {maxconn} connections an "
                    f"open-file limit of {C['fds']} allows one proxy (two files a connection)")
            self.ports[lb] = free_port()
            cfg = os.path.join(WORK, f"haproxy-{lb}.cfg")
            with open(cfg, "w") as f:
                f.write(f"""global
  maxconn {maxconn}
defaults
  mode tcp
  timeout connect 5s
  timeout client 1h
  timeout server 1h
  timeout tunnel 1h
frontend agents
  bind 127.0.0.1:{self.ports[lb]}
  default_backend gateways
backend gateways
  balance roundrobin
  option httpchk GET /readyz
{servers}
""")
            self.procs[f"haproxy-{lb}"] = Proc(
                f"haproxy-{lb}", ["haproxy", "-db", "-f", cfg], nice=10)

    def fleet_procs(self):
        def lb(proc):
            return f"ws://127.0.0.1:{self.ports[self.LBS[proc]]}/v1/agent"
        token = open(os.path.join(WORK, "sim-token")).read().strip()
        common = ["--namespace", NS, "--report-every", "30",
                  "--events-per-minute", str(C["events_per_minute"]), "--drain-seconds", "60",
                  "--fail-health-share", "0.3", "--fail-health-versions", ",".join(self.failing),
                  "--health-check-seconds", "1", "--pre-switch-seconds", "0.5",
                  "--restart-seconds", "0.5",
                  # Not a version the rollouts push (1.0.0, 2.0.0, ...): a robot still on the
                  # release it started with is on no rolled-back release.
                  "--release-version", "0.9.0"]
        env = {"LEKIWI_ENROLLMENT_TOKEN": token, "RUST_LOG": "warn"}
        for name, prefix, extra in (
                ("sim", "sim", []), ("sim-cut", "cut", []),
                ("sim-skew", "skew", ["--clock-offset-seconds", "600"])):
            n = self.ROBOTS[name]
            self.procs[name] = Proc(name, [
                f"{BIN}/lekiwi-sim", "--gateway", lb(name), *common, "--robots", str(n),
                "--prefix", prefix,
                "--json", os.path.join(WORK, f"{name}.json"), *extra], env, nice=10)
        self.procs["fleet"] = Proc("fleet", [
            f"{BIN}/lekiwi-fleet", "--gateway", lb("fleet"), "--enrollment-token-file",
            os.path.join(WORK, "enroll-token"), "--namespace", NS, "--robots",
            str(self.ROBOTS["fleet"]), "--state-root", os.path.join(WORK, "agents"),
            "--health-command", "true", "--health-timeout-s", "5", "--backoff-max-ms", "5000",
            "--report-every", "30"], {"RUST_LOG": "warn"}, nice=10)

    def total_robots(self):
        return C["robots"] + 1 + C["agents"]

    # ---- metrics --------------------------------------------------------------------------
    def leader(self):
        for c in ("ctl-a", "ctl-b"):
            if not self.procs[c].alive():
                continue
            text = curl(f"http://127.0.0.1:{self.ports[c]}/metrics", 5)
            if metric(text, "lekiwi_leader_election_is_leader") == 1:
                return c, text
        return None, ""

    def phases(self):
        _, text = self.leader()
        out = {}
        for p in ("Online", "Offline", "Unknown", "Pending"):
            out[p] = metric(text, f'lekiwi_robots{{phase="{p}"}}') or 0
        return out

    def sessions(self):
        total = 0
        for g in self.gateways:
            if self.procs[g].alive():
                text = curl(f"http://127.0.0.1:{self.ports[g + '-http']}/metrics", 5)
                total += metric(text, "lekiwi_gateway_connections") or 0
        return total

    def apiserver_metrics(self):
        """The API server's /metrics text ("" when it does not answer)."""
        try:
            return subprocess.run(
                ["curl", "-fsS", "--max-time", "20", "--cacert", f"{C['cp_dir']}/pki/ca.crt",
                 "-H", f"Authorization: Bearer {open(C['cp_dir'] + '/admin-token').read().strip()}",
                 f"https://127.0.0.1:{C['apiserver_port']}/metrics"],
                capture_output=True, text=True, timeout=30).stdout
        except (OSError, subprocess.TimeoutExpired):
            return ""

    def apiserver_writes(self, text=None):
        """Write requests the API server has served so far, by resource."""
        if text is None:
            text = self.apiserver_metrics()
        writes = {}
        for line in text.splitlines():
            if not line.startswith("apiserver_request_total{"):
                continue
            labels = dict(kv.split("=", 1) for kv in line[line.index("{") + 1:line.index("}")]
                          .replace('"', "").split(","))
            if labels.get("verb") not in ("CREATE", "UPDATE", "PATCH", "DELETE", "APPLY"):
                continue
            key = labels.get("resource", "") + (f"/{labels['subresource']}"
                                                if labels.get("subresource") else "")
            writes[key] = writes.get(key, 0) + float(line.rsplit(" ", 1)[1])
        return writes

    def pids(self):
        out = {n: p.pid for n, p in self.procs.items()
               if p.alive() and (n.startswith(("gw-", "ctl-")))}
        for name in ("kube-apiserver", "etcd"):
            try:
                out[name] = int(open(f"{C['cp_dir']}/{name}.pid").read())
            except (OSError, ValueError):
                pass
        try:
            out["postgres"] = int(open(f"{C['pg_dir']}/data/postmaster.pid").readline())
        except (OSError, ValueError):
            pass
        return out

    def sample(self):
        now = time.time() - self.t0
        for name, pid in self.pids().items():
            try:
                status = open(f"/proc/{pid}/status").read()
                rss = int(next(l for l in status.splitlines() if l.startswith("VmRSS:")).split()[1])
                threads = int(next(l for l in status.splitlines()
                                   if l.startswith("Threads:")).split()[1])
                fds = len(os.listdir(f"/proc/{pid}/fd"))
            except (OSError, StopIteration, ValueError):
                continue
            sessions = 0
            if name.startswith(("gw-", "ctl-")):
                port = self.ports[name + "-http" if name.startswith("gw-") else name]
                text = curl(f"http://127.0.0.1:{port}/metrics", 5)
                sessions = int(metric(text, "lekiwi_gateway_connections") or 0)
                tasks = metric(text, "lekiwi_runtime_tasks")
                if tasks is not None:
                    self.samples.gauge(name, "tasks", pid, now, tasks, sessions)
            self.samples.add(name, pid, now, rss, fds, threads, sessions)
        self.check_robots(now)

    # ---- robots as the watch shows them ------------------------------------------------------
    def read_watch(self):
        path = os.path.join(WORK, "robots.log")
        if not os.path.exists(path):
            return
        with open(path) as f:
            f.seek(getattr(self, "watch_offset", 0))
            for line in f:
                if not line.endswith("\n"):
                    break
                parts = line.rstrip("\n").split("|")
                if len(parts) >= 7:
                    self.robot_state[parts[2]] = (parts[3], parts[4], parts[5] == "true")
                    if parts[6] and parts[1] == "MODIFIED":
                        written = float(parts[6])
                        self.view_time = max(self.view_time or written, written)
                        # Whole seconds: a write 0.9 s ago may read as 1.9 s.
                        self.max_view_lag = max(self.max_view_lag,
                                                float(parts[0]) - written - 1)
            self.watch_offset = f.tell()

    def down_at(self, t):
        """The gateways dead at time t."""
        return {g for g, killed, back in self.down if killed <= t and (back is None or t < back)}

    def stalled_at(self, t):
        return any(start <= t and (end is None or t < end) for start, end in self.stalls)

    def check_robots(self, now):
        """Counts robots shown in a state the documented graces do not allow, judged at the
        moment the watch's view shows (`view_time`), not the moment it arrived here: after an
        API server restart the watch runs minutes late while the server relists, and a view
        from then, judged now, would count a robot long Online again as still Unknown."""
        self.read_watch()
        now = min(now, self.view_time or now)
        dead = self.down_at(now)
        stalled = self.stalled_at(now)
        for name, (phase, gateway, _) in self.robot_state.items():
            if phase == "Online" and gateway in dead:
                since = self.online_dead_since.setdefault(name, now)
                d = now - since
                self.violations["max_online_through_dead_gateway_s"] = max(
                    self.violations["max_online_through_dead_gateway_s"], d)
            else:
                self.online_dead_since.pop(name, None)
            expected_online = not (stalled and name.startswith("cut-"))
            if phase != "Online" and expected_online:
                since = self.not_online_since.setdefault(name, now)
                self.violations["max_not_online_with_session_s"] = max(
                    self.violations["max_not_online_with_session_s"], now - since)
            else:
                self.not_online_since.pop(name, None)
        self.violations["online_through_dead_gateway"] = max(
            self.violations["online_through_dead_gateway"],
            sum(1 for n, s in self.online_dead_since.items() if now - s > GRACE_DEAD_GATEWAY))
        self.violations["not_online_with_session"] = max(
            self.violations["not_online_with_session"],
            sum(1 for n, s in self.not_online_since.items() if now - s > GRACE_NOT_ONLINE))
        self.violations["max_view_lag_s"] = round(self.max_view_lag, 1)

    # ---- releases and rollouts ----------------------------------------------------------------
    def make_release(self, version):
        """A release of 20 files of 16 KiB in two directories; each version changes one file."""
        d = os.path.join(self.release_files, version)
        base = os.path.join(self.release_files, "base")
        if not os.path.isdir(base):
            for i in range(20):
                path = os.path.join(base, f"dir{i % 2}", f"file{i:02}.bin")
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with open(path, "wb") as f:
                    f.write(random.randbytes(16384))
        shutil.copytree(base, d)
        with open(os.path.join(d, "dir0", "version.txt"), "w") as f:
            f.write(version + "\n")
        return d

    def live_gateway(self):
        return next(g for g in self.gateways if self.procs[g].alive())

    def server(self):
        return f"http://127.0.0.1:{self.ports[self.live_gateway()]}"

    def push_to_gateway(self, what, *args):
        """Runs `kubectl lekiwi <args> --server <a live gateway>` and returns the digest it
        prints. A gateway may be down or still starting (a fault of the soak): up to 5 tries,
        10 s apart, each at the gateway then alive."""
        for attempt in range(5):
            p = run(f"{BIN}/kubectl-lekiwi", "--kubeconfig", C["kubeconfig"], *args,
                    "--server", self.server(), "-n", NS, check=False, timeout=300)
            if p.returncode == 0:
                return p.stdout.strip().split()[-1]
            log(f"push of {what} failed (attempt {attempt + 1}): {p.stderr.strip()[-200:]}")
            time.sleep(10)
        raise RuntimeError(f"could not push {what}")

    def push(self, version):
        d = self.make_release(version)
        return self.push_to_gateway(f"release {version}", "release", "push", d,
                                    "--version", version)

    def push_agent(self, version):
        """A stand-in agent build (the simulated robots download and verify it, and restart as
        that version); one per architecture, as a RobotDeployment's spec.agent names them."""
        builds = []
        for arch in ("arm64", "amd64"):
            path = os.path.join(WORK, f"agent-{version}-{arch}")
            with open(path, "wb") as f:
                f.write(b"\x7fELF" + random.randbytes(200_000))
            digest = self.push_to_gateway(f"agent {version} ({arch})", "agent", "push", path,
                                          "--version", version, "--arch", arch)
            builds.append({"arch": arch, "digest": digest})
        return builds

    def apply(self, manifest):
        path = os.path.join(WORK, "apply.json")
        with open(path, "w") as f:
            json.dump(manifest, f)
        for attempt in range(10):
            p = run("kubectl", "apply", "--server-side", "--force-conflicts", "--field-manager",
                    "soak", "-f", path, check=False)
            if p.returncode == 0:
                return
            time.sleep(5)
        raise RuntimeError(f"apply failed: {p.stderr.strip()[-300:]}")

    def deployment(self, name):
        p = run("kubectl", "-n", NS, "get", "robotdeployment", name, "-o", "json", check=False,
                timeout=30)
        return json.loads(p.stdout) if p.returncode == 0 else None

    def kind_of(self, k):
        """The kind of the k-th rollout (from 1), in the rotation --rotation gives."""
        return C["rotation"][(k - 1) % len(C["rotation"])]

    def start_rollout(self, k):
        kind = self.kind_of(k)
        version = f"{k}.0.0"
        started = time.time()
        strategy = {"canary": 1, "batchSize": "10%", "successThreshold": 0.9,
                    "robotTimeoutSeconds": 180, "waitTimeoutSeconds": 120}
        if kind == "agent":
            self.agent_version += 1
            v = f"0.{self.agent_version + 100}.0"
            builds = self.push_agent(v)
            name = "soak-agent"
            spec = {"selector": {"matchExpressions": [
                {"key": "fleet.lekiwi.io/sim", "operator": "Exists"}]},
                "agent": {"version": v, "builds": builds}, "strategy": strategy}
            expected = "Completed"
        else:
            digest = self.push(version)
            name = "soak"
            spec = {"selector": {}, "release": {"version": version, "digest": digest},
                    "strategy": strategy}
            expected = {"ok": "Completed", "abort": "Aborted"}.get(kind, "RolledBack")
            if kind == "undo":
                # Slow enough to be undone mid-way whatever the fleet's size.
                strategy["pauseBetweenBatchesSeconds"] = 60
            if kind in ("fail", "undo"):
                self.unwanted_releases.add(version)
        self.apply({"apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "RobotDeployment",
                    "metadata": {"name": name, "namespace": NS}, "spec": spec})
        r = {"n": k, "kind": kind, "version": version if kind != "agent" else v,
             "deployment": name, "expected": expected, "phase": None, "started": started,
             "seconds": None, "undone": False, "aborted": False, "generation": None}
        self.rollouts.append(r)
        log(f"rollout {k} ({kind}): {r['version']} via {name}, expecting {expected}")
        return r

    def follow_rollout(self, r):
        """Moves a rollout on (undo or abort once robots switch); true once it ended."""
        if r.get("settle_until"):
            return self.settle_abort(r)
        d = self.deployment(r["deployment"])
        if not d:
            return False
        st = d.get("status") or {}
        if r["generation"] is None:
            r["generation"] = d["metadata"].get("generation")
        if st.get("observedGeneration") != d["metadata"].get("generation"):
            return False
        phase = st.get("phase")
        steer = {"undo": "undone", "abort": "aborted"}.get(r["kind"])
        # Undo once the canary switched; abort once the first batch after the canary is under
        # way, so robots are downloading when it comes.
        least = 2 if r["kind"] == "abort" else 1
        if steer and not r[steer] and phase == "Progressing" and st.get("updated", 0) >= least:
            p = run(f"{BIN}/kubectl-lekiwi", "--kubeconfig", C["kubeconfig"], "rollout",
                    r["kind"], r["deployment"], "-n", NS, check=False)
            if p.returncode == 0:
                r[steer] = True
                log(f"rollout {r['n']}: {r['kind']} after {st.get('updated')} robots updated")
            else:
                # The API server may be down (a fault of the soak): again on the next tick.
                log(f"rollout {r['n']}: {r['kind']} failed: {p.stderr.strip()[-200:]}")
        if phase in ("Completed", "RolledBack", "Failed", "Aborted") \
                and (not steer or r[steer] or phase != "Completed"):
            r["phase"] = phase
            r["seconds"] = round(time.time() - r["started"], 1)
            r["counts"] = {k: st.get(k) for k in ("targeted", "updated", "failed", "skipped")}
            if phase == "Completed" and r["kind"] != "agent":
                self.completed_releases.add(r["version"])
            log(f"rollout {r['n']} ended {phase} after {r['seconds']} s ({r['counts']})")
            if phase == "Aborted":
                # The next rollout waits until the fleet shows where the abort left it.
                r["settle_until"] = time.time() + ABORT_SETTLE
                return False
            return True
        return False

    def settle_abort(self, r):
        """After an abort: once the gateways' status writes run on time (and at least
        ABORT_SETTLE s on), counts the robots that run the aborted release. An abort starts no
        robot and lets no downloading robot switch, so that is the robots the rollout shows
        updated; one more is a robot that switched after it was told to stop."""
        if time.time() < r["settle_until"]:
            return False
        lag = self.status_lag()
        if (lag is None or lag > 5) and time.time() < r["settle_until"] + 300:
            return False
        st = (self.deployment(r["deployment"]) or {}).get("status") or {}
        r["counts"] = {k: st.get(k) for k in ("targeted", "updated", "failed", "skipped")}
        r["on_release"] = sum(1 for v in self.current_releases().values() if v == r["version"])
        log(f"rollout {r['n']}: {r['on_release']} robots run {r['version']} after the abort "
            f"(the rollout shows {r['counts']['updated']} updated)")
        r["settle_until"] = None
        return True

    # ---- faults ---------------------------------------------------------------------------------
    def fault_kinds(self):
        kinds = ["gateway", "leader", "apiserver", "postgres", "cut"]
        if C["as_postgres"]:
            kinds.append("disk")
        return kinds

    def fault(self, kind):
        f = {"kind": kind, "at": time.time(), "healed_s": None, "notes": ""}
        log(f"fault: {kind}")
        if kind == "gateway":
            g = self.gateways[len(self.faults) // len(self.fault_kinds()) % len(self.gateways)]
            f["sessions"] = self.sessions()
            f["writes_before"] = self.apiserver_writes()
            self.procs[g].kill()
            self.down.append([g, time.time(), None])
            f["notes"] = f"{g} SIGKILLed, restarted 30 s later"
            f["restart_at"] = time.time() + 30
            f["restart"] = g
        elif kind == "leader":
            leader, _ = self.leader()
            if leader:
                self.procs[leader].kill()
                f["notes"] = f"{leader} (leader) SIGKILLed, restarted at once"
                self.procs[leader].restart()
        elif kind == "apiserver":
            env = dict(os.environ, LEKIWI_CP_DIR=C["cp_dir"])
            script = os.path.join(C["root"], "scripts/testbed/control-plane.sh")
            subprocess.run(["bash", script, "kill"], env=env, capture_output=True, timeout=60)
            time.sleep(5)
            p = subprocess.run(["bash", script, "up"], env=env, capture_output=True, text=True,
                               timeout=300)
            f["notes"] = "etcd and kube-apiserver SIGKILLed, up again " + (
                "at once" if p.returncode == 0 else f"FAILED: {p.stderr[-200:]}")
        elif kind == "postgres":
            pg = [os.path.join(C["pg_bin"], "pg_ctl"), "-D", os.path.join(C["pg_dir"], "data"),
                  "-l", os.path.join(WORK, "postgres.log"), "-w", "-t", "120", "-m",
                  "immediate", "restart"]
            if C["as_postgres"]:
                pg = ["runuser", "-u", "postgres", "--"] + pg
            # The server's output goes to its log: a pipe here would stay open as long as it runs.
            p = subprocess.run(pg, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               timeout=180)
            f["notes"] = "PostgreSQL restarted (immediate)" + (
                "" if p.returncode == 0 else f" FAILED: {p.stderr[-200:]}")
        elif kind == "cut":
            os.kill(self.procs["sim-cut"].pid, signal.SIGSTOP)
            self.stall = (time.time(), time.time() + STALL_SECONDS)
            self.stalls.append([self.stall[0], None])
            f["notes"] = f"{C['stalled']} robots' connections stalled for {STALL_SECONDS} s"
        elif kind == "disk":
            st = os.statvfs(C["pg_dir"])
            free = st.f_bavail * st.f_frsize
            ballast = os.path.join(C["pg_dir"], "ballast")
            keep = 8 << 20
            subprocess.run(["fallocate", "-l", str(max(0, free - keep)), ballast], check=False)
            f["ballast"] = ballast
            f["release_at"] = time.time() + DISK_FULL_SECONDS
            f["notes"] = (f"event store's filesystem filled to its last 8 MiB for "
                          f"{DISK_FULL_SECONDS} s ({free >> 20} MiB were free)")
        self.faults.append(f)

    def follow_faults(self):
        now = time.time()
        for f in self.faults:
            if f.get("restart") and now >= f["restart_at"]:
                g = f.pop("restart")
                self.procs[g].restart()
                for d in self.down:
                    if d[0] == g and d[2] is None:
                        d[2] = time.time()
            if f.get("ballast") and now >= f["release_at"]:
                os.remove(f.pop("ballast"))
        if self.stall and now >= self.stall[1]:
            os.kill(self.procs["sim-cut"].pid, signal.SIGCONT)
            self.stall = None
            self.stalls[-1][1] = now
            cut = [f for f in self.faults if f["kind"] == "cut"][-1]
            cut["ended"] = now
        # A fault over (its process back, its disk freed, its robots let go) is healed once
        # every robot is Online and holds a session again: Online as the leader's store counts
        # them and as the API server shows them (this driver's own watch). The leader's count
        # alone is stale while its Robot watch lists again after an API server restart. The
        # cut-off robots' fault is healed once they are Online and connected as the API server
        # shows them: the cut touches no other robot, and an agent rollout under way restarts
        # robots all through the fleet (an hour's cut read as healed 417 s after its end, the
        # second the agent rollout that started during it ended).
        over = [f for f in self.faults if f["healed_s"] is None and not (
            f.get("restart") or f.get("ballast") or (f["kind"] == "cut" and self.stall))]
        if not over:
            return
        self.read_watch()
        cut = [(phase, connected) for n, (phase, _, connected) in self.robot_state.items()
               if n.startswith("cut-")]
        cut_back = bool(cut) and all(p == "Online" and c for p, c in cut)
        total = self.total_robots()
        watched = sum(1 for phase, _, _ in self.robot_state.values() if phase == "Online")
        counted = self.phases()
        fleet_back = (watched >= total and counted["Online"] >= total
                      and self.sessions() >= total)
        # The leader's kill touches no robot: it is healed once a controller leads again and its
        # Robot store holds every robot (its controllers run), however many robots an agent
        # rollout under way restarts meanwhile (an hour's leader heals read 151 s and 198 s,
        # each the end of such a rollout).
        led = sum(counted.values()) >= total
        for f in over:
            # What the driver's watch shows counts only once it shows a moment after the fault
            # ended: after an API server restart it ran minutes behind, and a cut read as healed
            # 0 s after its end from a view of before the cut.
            seen_after = (self.view_time or 0) >= f.get("ended", f["at"])
            if (seen_after and (fleet_back or (f["kind"] == "cut" and cut_back))) or (
                    f["kind"] == "leader" and led):
                f["healed_s"] = round(now - f.get("ended", f["at"]), 1)
                if f["kind"] == "gateway":
                    self.gateway_ratio(f, now)
                log(f"fault {f['kind']} healed after {f['healed_s']} s")

    def gateway_ratio(self, f, now):
        """The healing time against the API server's own limit: robots moved times status
        writes per move, divided by the write rate the API server sustained meanwhile."""
        after = self.apiserver_writes()
        before = f["writes_before"]
        robot_writes = sum(v - before.get(k, 0) for k, v in after.items() if k.startswith("robots"))
        moved = f["sessions"] / len(self.gateways)
        secs = max(now - f["at"], 1)
        rate = robot_writes / secs
        peak = max([w for t, w in self.samples.write_rates if t >= f["at"] - self.t0] or [rate])
        per_move = robot_writes / moved if moved else 0
        ideal = moved * per_move / peak if peak else None
        f["moved"] = int(moved)
        f["writes_per_move"] = round(per_move, 2)
        f["peak_write_rate"] = round(peak, 1)
        f["ratio"] = round(f["healed_s"] / ideal, 2) if ideal else None

    # ---- the run ----------------------------------------------------------------------------------
    def wait(self, what, timeout, check):
        deadline = time.time() + timeout
        while not check():
            for p in self.procs.values():
                if p.p is not None and p.p.poll() is not None and p.name != "driver":
                    raise RuntimeError(f"{p.name} exited: see {p.name}.log")
            if time.time() > deadline:
                raise RuntimeError(f"{what} not reached after {timeout} s")
            time.sleep(2)

    def ready(self, name, port):
        return self.procs[name].alive() and curl(f"http://127.0.0.1:{port}/readyz", 2) != ""

    def bring_up(self):
        self.operator_procs()
        for c in ("ctl-a", "ctl-b"):
            self.procs[c].start()
        for g in self.gateways:
            self.procs[g].start()
            self.wait(f"{g} ready", 90, lambda g=g: self.ready(g, self.ports[g + "-http"]))
        self.wait("a controller leader", 90, lambda: self.leader()[0] is not None)
        self.haproxy()
        for lb in sorted(self.lb_clients()):
            self.procs[f"haproxy-{lb}"].start()
        self.procs["watch"] = Proc("watch", [
            "python3", "-u", os.path.join(C["root"], "bench/recovery_watch.py"),
            f"https://127.0.0.1:{C['apiserver_port']}", f"{C['cp_dir']}/pki/ca.crt",
            f"{C['cp_dir']}/admin-token", NS, os.path.join(WORK, "robots.log")]).start()
        schedule = int(C["duration"] / C["release_every"]) + 2
        self.failing = [f"{k}.0.0" for k in range(1, schedule + 1) if self.kind_of(k) == "fail"]
        self.fleet_procs()
        for n in ("sim", "sim-cut", "sim-skew", "fleet"):
            self.procs[n].start()
        total = self.total_robots()
        t = time.time()
        self.wait(f"all {total} robots Online", total // 20 + 300,
                  lambda: self.phases()["Online"] >= total)
        log(f"all {total} robots Online after {time.time() - t:.0f} s")
        online = time.time() - t
        self.starting_release()
        return online

    def starting_release(self):
        """Gives the real agents the release the simulated robots start with (0.9.0), through a
        rollout of their own, as a lab's robots have a release before the next one comes. A
        robot with no earlier release keeps a failing one on rollback (it has nothing to go
        back to), so without this every real agent would stay on the first failing release.
        The soak's own deployment, newer, then owns these robots (this one shows them
        Superseded)."""
        digest = self.push("0.9.0")
        self.apply({"apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "RobotDeployment",
                    "metadata": {"name": "soak-start", "namespace": NS},
                    "spec": {"selector": {"matchExpressions": [
                        {"key": "fleet.lekiwi.io/sim", "operator": "DoesNotExist"}]},
                        "release": {"version": "0.9.0", "digest": digest},
                        "strategy": {"canary": 1, "batchSize": "25%",
                                     "robotTimeoutSeconds": 180}}})
        t = time.time()

        def completed():
            st = (self.deployment("soak-start") or {}).get("status") or {}
            if st.get("phase") in ("RolledBack", "Failed"):
                raise RuntimeError(f"the real agents' starting release ended {st.get('phase')}")
            self.start_counts = {k: st.get(k) for k in ("targeted", "updated", "skipped")}
            return st.get("phase") == "Completed"
        self.wait("the real agents on release 0.9.0", 600, completed)
        log(f"real agents' starting release Completed after {time.time() - t:.0f} s "
            f"({self.start_counts})")

    def status_lag(self):
        """The longest status-write lag among the live gateways (lekiwi_gateway_status_lag_seconds),
        or None when none answers."""
        lags = []
        for g in self.gateways:
            if self.procs[g].alive():
                text = curl(f"http://127.0.0.1:{self.ports[g + '-http']}/metrics", 5)
                lag = metric(text, "lekiwi_gateway_status_lag_seconds")
                if lag is not None:
                    lags.append(lag)
        return max(lags) if lags else None

    def wait_caught_up(self, bound=600):
        """Waits (sampling meanwhile) until every gateway's status writes run on time (lag at
        most 5 s, three samples in a row), at most `bound` seconds; returns the wait and whether
        they caught up. A fleet's connect burst leaves a backlog of writes that drains at the
        gateways' write rate: a window during the drain measures the backlog, not the steady
        rate."""
        t, calm = time.time(), 0
        while time.time() - t < bound:
            lag = self.status_lag()
            calm = calm + 1 if lag is not None and lag <= 5 else 0
            if calm >= 3:
                return time.time() - t, True
            time.sleep(10)
            self.sample()
        return time.time() - t, False

    def steady_window(self, label, seconds=120):
        waited, caught_up = self.wait_caught_up()
        log(f"status writes {'caught up' if caught_up else 'still late'} after {waited:.0f} s")
        label = (f"{label}, {waited:.0f} s later (status writes caught up)" if caught_up else
                 f"{label}, status writes still late after {waited:.0f} s")
        before, t = self.apiserver_writes(), time.time()
        end = t + seconds
        while time.time() < end:
            time.sleep(10)
            self.sample()
        after = self.apiserver_writes()
        w = sum(v - before.get(k, 0) for k, v in after.items() if k.startswith("robots"))
        rate = w / (time.time() - t)
        log(f"steady Robot writes/s ({label}): {rate:.1f}")
        return label, rate

    def etcd_port(self):
        """etcd's client port, read once from the control plane's ports.env (a restart keeps it)."""
        if not getattr(self, "_etcd_port", None):
            try:
                self._etcd_port = next(
                    l.split("=", 1)[1].strip() for l in open(f"{C['cp_dir']}/ports.env")
                    if l.startswith("ETCD_PORT="))
            except (OSError, StopIteration):
                return None
        return self._etcd_port

    def sample_control_plane(self, now, text):
        """What the API server and etcd hold, beside their RSS: the Go heap in use (live data and
        what the collector has not returned yet), the Kubernetes Events stored (they live for the
        API server's --event-ttl) and etcd's database size."""
        pids = self.pids()
        if "kube-apiserver" in pids and text:
            for name, series in (("heap", "go_memstats_heap_inuse_bytes"),
                                 ("events", 'etcd_object_counts{resource="events"}'),
                                 ("robots", 'etcd_object_counts{resource="robots.fleet.lekiwi.io"}')):
                v = metric(text, series)
                if v is not None:
                    self.samples.gauge("kube-apiserver", name, pids["kube-apiserver"], now, v)
        if "etcd" in pids and self.etcd_port():
            etcd = curl(f"http://127.0.0.1:{self.etcd_port()}/metrics", 5)
            for name, series in (("heap", "go_memstats_heap_inuse_bytes"),
                                 ("db", "etcd_mvcc_db_total_size_in_bytes")):
                v = metric(etcd, series)
                if v is not None:
                    self.samples.gauge("etcd", name, pids["etcd"], now, v)

    def tick(self):
        self.sample()
        text = self.apiserver_metrics()
        writes = self.apiserver_writes(text)
        robot = sum(v for k, v in writes.items() if k.startswith("robots"))
        now = time.time() - self.t0
        if writes and getattr(self, "last_writes", None):
            t0, w0 = self.last_writes
            # A restarted API server counts from 0 again.
            if now > t0 and robot >= w0:
                self.samples.write_rates.append((now, (robot - w0) / (now - t0)))
        if writes:
            self.last_writes = (now, robot)
        self.sample_control_plane(now, text)
        self.follow_faults()

    def soak(self):
        start = time.time()
        next_fault = start + C["fault_every"]
        next_release = start + 10
        kinds = self.fault_kinds()
        active, k = None, 0
        while time.time() < start + C["duration"]:
            self.tick()
            now = time.time()
            if now >= next_fault:
                self.fault(kinds[len(self.faults) % len(kinds)])
                next_fault += C["fault_every"]
            if active and self.follow_rollout(active):
                active = None
            elif active and now - active["started"] > ROLLOUT_LIMIT:
                active["phase"], active["seconds"] = "not ended", round(now - active["started"])
                log(f"rollout {active['n']} not ended after {ROLLOUT_LIMIT} s")
                active = None
            if not active and now >= next_release:
                k += 1
                active = self.start_rollout(k)
                next_release = max(now, next_release) + C["release_every"]
            time.sleep(max(0.0, 10 - (time.time() - now)))
        log("duration over: waiting for the last rollout and the last fault to end")
        deadline = time.time() + 900
        while time.time() < deadline:
            self.tick()
            if active and self.follow_rollout(active):
                active = None
            if not active and all(f["healed_s"] is not None for f in self.faults):
                break
            time.sleep(10)
        if active:
            active["phase"], active["seconds"] = "not ended", round(time.time() - active["started"])

    def current_releases(self):
        """Each robot's name and the release its status says it runs (None: none)."""
        p = run("kubectl", "-n", NS, "get", "robots", "-o", "json", timeout=300)
        return {r["metadata"]["name"]:
                ((r.get("status") or {}).get("currentRelease") or {}).get("version")
                for r in json.loads(p.stdout)["items"]}

    def unwanted_robots(self):
        bad = [f"{name}={cur}" for name, cur in self.current_releases().items()
               if cur in self.unwanted_releases]
        if bad:
            log(f"robots on unwanted releases: {bad[:20]}")
        return len(bad)

    def stop_fleet(self):
        for n in ("sim", "sim-cut", "sim-skew", "fleet"):
            if self.procs[n].alive():
                os.kill(self.procs[n].pid, signal.SIGCONT)
                os.kill(self.procs[n].pid, signal.SIGTERM)
        for n in ("sim", "sim-cut", "sim-skew", "fleet"):
            try:
                self.procs[n].p.wait(timeout=120)
            except subprocess.TimeoutExpired:
                self.procs[n].kill()

    def psql(self, sql):
        # The report's queries group every stored row: in memory, not in temporary files on the
        # database's volume, which the disk-full fault leaves nearly full (an hour's report
        # failed there with "No space left on device").
        pg = [os.path.join(C["pg_bin"], "psql"), "-X", "-q", "-At", "-h", "127.0.0.1", "-p",
              str(C["pg_port"]), "-U", "postgres", "-d", "lekiwi", "-c", "SET work_mem = '2GB'",
              "-c", sql]
        return subprocess.run(pg, capture_output=True, text=True, timeout=600, check=True).stdout

    def events(self):
        acked = unacked = 0
        for n in ("sim", "sim-cut", "sim-skew"):
            s = json.load(open(os.path.join(WORK, f"{n}.json")))
            a = s["events_acked"] + s.get("telemetry_batches_acked", 0)
            g = s["events_generated"] + s.get("telemetry_batches", 0)
            acked, unacked = acked + a, unacked + g - a
        rows = self.psql(
            "SELECT count(*), coalesce(sum(mx - cnt), 0) FROM (SELECT robot, count(*) cnt, "
            "max(seq) mx FROM seqs WHERE namespace = 'soak' AND robot NOT LIKE 'kiwi-%' "
            "GROUP BY robot) t").strip().split("|")
        stored = int(self.psql("SELECT count(*) FROM seqs WHERE namespace = 'soak' AND robot "
                               "NOT LIKE 'kiwi-%'").strip())
        gaps_all = int(self.psql(
            "SELECT coalesce(sum(mx - cnt), 0) FROM (SELECT robot, count(*) cnt, max(seq) mx "
            "FROM seqs WHERE namespace = 'soak' GROUP BY robot) t").strip())
        event_dupes = int(self.psql(
            "SELECT count(*) - count(DISTINCT (robot, seq)) FROM events "
            "WHERE namespace = 'soak'").strip())
        sample_dupes = int(self.psql(
            "SELECT count(*) FROM (SELECT 1 FROM samples WHERE namespace = 'soak' "
            "GROUP BY robot, seq, metric, ts_ms HAVING count(*) > 1) d").strip())
        log(f"store: {rows[0]} simulated robots hold {stored} durable messages; acked {acked}")
        return {"acked": acked, "stored": stored, "lost": max(0, acked - stored),
                "gaps": gaps_all, "event_dupes": event_dupes, "sample_dupes": sample_dupes,
                "unacked": unacked}

    def sizes(self, run_seconds):
        db = int(self.psql("SELECT pg_database_size('lekiwi')").strip()) / 2**20
        blob = sum(os.path.getsize(os.path.join(d, f))
                   for d, _, fs in os.walk(os.path.join(WORK, "blobs")) for f in fs) / 2**20
        per_hour = db / max(run_seconds, 1) * 3600
        return {"db_mib": db, "db_mib_per_hour": per_hour, "retention_days": 30,
                "db_at_retention_gib": per_hour * 24 * 30 / 1024, "blob_mib": blob,
                "releases": sum(1 for r in self.rollouts if r["kind"] != "agent"),
                "agent_builds": 2 * self.agent_version}

    def stop_all(self):
        for p in self.procs.values():
            if p.alive():
                try:
                    os.kill(p.pid, signal.SIGCONT)
                except OSError:
                    pass
                p.kill()


def main():
    s = Soak()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        online_s = s.bring_up()
        steady = [s.steady_window("before the first fault")]
        s.soak()
        steady.append(s.steady_window("after the last fault healed"))
        unwanted = s.unwanted_robots()
        run_seconds = time.time() - s.t0
        s.stop_fleet()
        events = s.events()
        sizes = s.sizes(run_seconds)
        facts = {
            "command": C["command"],
            "fleet": f"{C['robots']} simulated robots (lekiwi-sim; {C['stalled']} of them in the "
                     f"simulator that is cut off, one with its clock 10 minutes ahead) and "
                     f"{C['agents']} real agents (lekiwi-fleet)",
            "control plane": f"2 controller processes (leader election), {C['gateways']} gateways "
                             "behind HAProxy, PostgreSQL 15 event store, etcd + kube-apiserver",
            "run": f"{C['duration']} s, a fault every {C['fault_every']} s, a rollout every "
                   f"{C['release_every']} s (in turn: {', '.join(C['rotation'])}); all robots Online "
                   f"{online_s:.0f} s after start",
            "robots_total": s.total_robots(),
            "unwanted_robots": unwanted,
        }
        for line in open(os.path.join(WORK, "facts.env")):
            k, _, v = line.strip().partition("=")
            if k in ("date", "host", "source"):
                facts[k] = v
        text = report(facts, s.samples, s.rollouts, s.faults, s.violations, events, steady,
                      sizes, time.time() - s.t0)
        with open(os.path.join(WORK, "report.txt"), "w") as f:
            f.write(text)
        with open(os.path.join(WORK, "samples.json"), "w") as f:
            json.dump({"processes": s.samples.by_role, "write_rates": s.samples.write_rates,
                       "gauges": {f"{r} {n}": v for (r, n), v in s.samples.gauges.items()},
                       "faults": s.faults, "rollouts": s.rollouts}, f)
        return 0 if "Verdict: PASS" in text else 1
    finally:
        s.stop_all()


if __name__ == "__main__":
    sys.exit(main())
