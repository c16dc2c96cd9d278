#!/usr/bin/env python3
"""The Python half of bench/analysis-writes.sh: drives each rollout against the kube API and
counts, from the API server's audit log, what the rollout and the time after it cost in Robot
writes.

Subcommands (the private control plane and namespace come from the environment
bench/analysis-writes.sh exports: LEKIWI_CP_DIR, APISERVER_PORT, BENCH_NS, BENCH_ROBOTS):

  rollout VERSION DIGEST WINDOW BATCH OUT   create (first) or patch the RobotDeployment `fleet` to
                                            VERSION, with spec.analysis.windowSeconds WINDOW (0:
                                            no analysis), batchSize BATCH; waits for its end and
                                            writes the send and end times (unix seconds) to OUT
  report WORK                               the table, from WORK/facts.env, WORK/rollout-*.json
                                            and WORK/audit.log

A status write is a `patch` of `robots/status` (server-side apply), counted when it was received,
by the process that sent it (the operator runs as two processes, `--role controller` and `--role
gateway`, whose User-Agents name their role). Standard library only.
"""

import json
import os
import sys
import time
from collections import Counter
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from rollout_report import GROUP, Kube, env, log  # noqa: E402

ROUTINE_REFRESH = 300
"""The gateway's --status-refresh-seconds, which the benchmark leaves at its default."""

ENDED = ("Completed", "RolledBack", "Failed")


def rollout(version, digest, window, batch, out):
    kube, ns = Kube(), env("BENCH_NS")
    path = f"{GROUP}/namespaces/{ns}/robotdeployments"
    analysis = {"windowSeconds": int(window)} if int(window) > 0 else None
    spec = {
        "selector": {},
        "release": {"version": version, "digest": digest},
        "strategy": {"batchSize": batch, "canary": 0, "successThreshold": 0.8,
                     "pauseBetweenBatchesSeconds": 0},
        "analysis": analysis,
    }
    sent = time.time()
    try:
        kube.deployment(ns, "fleet")
        d = kube.request("PATCH", f"{path}/fleet", {"spec": spec},
                         content_type="application/merge-patch+json")
    except RuntimeError:
        body = {"apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "RobotDeployment",
                "metadata": {"name": "fleet"},
                "spec": {k: v for k, v in spec.items() if v is not None}}
        d = kube.request("POST", path, body)
    generation = d["metadata"]["generation"]
    timeout = float(os.environ.get("BENCH_ROLLOUT_TIMEOUT", "900"))
    last = 0.0
    while True:
        time.sleep(1)
        st = kube.deployment(ns, "fleet").get("status") or {}
        phase = st.get("phase")
        if st.get("observedGeneration") == generation and phase in ENDED:
            break
        if time.time() - sent > timeout:
            sys.exit(f"rollout of {version} did not end within {timeout:.0f} s: {phase}")
        if time.time() - last > 15:
            last = time.time()
            log(f"  {version}: {phase}, updated {st.get('updated', 0)} of {st.get('targeted', '?')}")
    ended = time.time()
    summary = {k: st.get(k) for k in ("phase", "targeted", "updated", "failed", "skipped")}
    with open(out, "w") as f:
        json.dump({"version": version, "window": int(window), "batch": batch, "sent": sent,
                   "ended": ended, "status": summary}, f)
    log(f"  {version}: {phase} after {ended - sent:.1f} s")


def seconds(stamp):
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def writes(audit, spans):
    """Robot writes received in each of `spans` ((start, end) unix seconds): per span a Counter
    of (kind, writer) -> requests, kind `status` or `robot` (the object itself: spec,
    annotations), writer `gateway` or `controller` (any other client by its name)."""
    counts = [Counter() for _ in spans]
    with open(audit) as log_file:
        for line in log_file:
            try:
                event = json.loads(line)
            except ValueError:
                continue
            if event.get("stage") != "ResponseComplete" or event.get("verb") not in ("patch", "update"):
                continue
            ref = event.get("objectRef") or {}
            if ref.get("resource") != "robots":
                continue
            received = seconds(event["requestReceivedTimestamp"])
            agent = event.get("userAgent", "")
            if agent.startswith("lekiwi-operator") and "(" in agent:
                who = agent[agent.index("(") + 1:].split(";")[0].rstrip(")")
            else:
                who = agent.split("/")[0]
            kind = "status" if ref.get("subresource") == "status" else "robot"
            refused = (event.get("responseStatus") or {}).get("code") == 409
            for i, (start, end) in enumerate(spans):
                if start <= received < end:
                    counts[i][(kind, who)] += 1
                    if refused:
                        counts[i][("refused", kind)] += 1
                        if kind == "status":
                            counts[i][("refused", who)] += 1
    return counts


def report(work):
    work = Path(work)
    facts = dict(l.rstrip("\n").split("=", 1) for l in open(work / "facts.env") if "=" in l)
    robots = int(facts["robots"])
    after = float(facts["after_seconds"])
    runs = [json.load(open(work / f"rollout-{name}.json")) for name in ("plain", "analysis")]
    spans = []
    for r in runs:
        spans += [(r["sent"], r["ended"]), (r["ended"], r["ended"] + after)]
    counts = writes(work / "audit.log", spans)
    print(f"LeKiwi analysis-writes benchmark, {facts['date']}")
    for key in ("host", "source", "command", "binaries", "operator", "fleet", "release",
                "strategy"):
        print(f"{key}: {facts.get(key, '?')}")
    print("counted: Robot writes (patches) received by the API server, from its audit log, "
          "refused ones included (a 409 is a fenced write that met a newer version); status = "
          "robots/status, robot = the object (spec.release, marks, annotations)")
    print()
    routine = robots / ROUTINE_REFRESH
    rows = [("phase", "seconds", "status writes (gateway + controller)", "refused (409)",
             "per robot", "status writes/s", "robot writes")]
    verdicts = []
    for i, r in enumerate(runs):
        label = "with spec.analysis" if r["window"] else "without analysis"
        if r["window"]:
            label += f" (windowSeconds {r['window']})"
        for j, phase in enumerate(("rollout", f"{after:.0f} s after it")):
            c = counts[2 * i + j]
            start, end = spans[2 * i + j]
            status = sum(n for (kind, _), n in c.items() if kind == "status")
            gw, ctrl = c[("status", "gateway")], c[("status", "controller")]
            robot = sum(n for (kind, _), n in c.items() if kind == "robot")
            per = status / robots
            rate = status / (end - start)
            what = f"{label}: {phase}" + (f" ({r['status']['phase']}, {r['version']})" if j == 0 else "")
            rows.append((what, f"{end - start:.0f}", f"{status} ({gw} + {ctrl})",
                         str(c[("refused", "status")]), f"{per:.2f}", f"{rate:.2f}", str(robot)))
            if j == 0:
                # The rollout's own writes: each robot's routine refreshes in it aside.
                routine_share = (end - start) / ROUTINE_REFRESH
                refused = c[("refused", "status")] / robots
                own = gw / robots - c[("refused", "gateway")] / robots - routine_share
                verdicts.append((f"{label}: the gateway's accepted status writes per robot for "
                                 f"the rollout, less its routine refreshes ({routine_share:.2f})",
                                 f"{own:.2f}", "<= 2", round(own, 2) <= 2))
                total = per - routine_share
                verdicts.append((f"{label}: every status write per robot for the rollout, less "
                                 f"its routine refreshes", f"{total:.2f} (controller "
                                 f"{ctrl / robots:.2f}, refused {refused:.2f})", "<= 2",
                                 round(total, 2) <= 2))
            else:
                verdicts.append((f"{label}: status writes/s after the rollout",
                                 f"{rate:.2f}", f"<= 1.5 x N/{ROUTINE_REFRESH} = {1.5 * routine:.2f}",
                                 rate <= 1.5 * routine))
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
    print()
    print(f"routine refresh: N / {ROUTINE_REFRESH} s = {routine:.2f} status writes/s "
          f"({after / ROUTINE_REFRESH:.2f} per robot in {after:.0f} s)")
    for what, got, goal, ok in verdicts:
        print(f"{what}: {got}  (goal {goal})  {'PASS' if ok else 'FAIL'}")
    other = Counter()
    for c in counts:
        for (kind, who), n in c.items():
            if kind != "refused" and who not in ("gateway", "controller"):
                other[(kind, who)] += n
    if other:
        print("other clients' Robot writes: " + ", ".join(f"{k}/{w} {n}" for (k, w), n in sorted(other.items())))


def main():
    cmd, args = sys.argv[1], sys.argv[2:]
    if cmd == "rollout":
        rollout(*args)
    elif cmd == "report":
        report(*args)
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
