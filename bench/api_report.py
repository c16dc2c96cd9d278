#!/usr/bin/env python3
"""Turns what bench/api.sh collected in its work directory into the one results table.

Inputs (in WORK): facts.env (KEY=VALUE lines the script wrote), the output of each wrk run,
wrk-<server>-<one|list>-<lat|rps>.txt (`wrk --latency`), and fanout.json (graphql-fanout's one
line) when the fan-out ran. Arguments: WORK ROBOTS DURATION
CONNECTIONS PROFILE COMMAND. Standard library only.
"""

import json
import re
import sys
from pathlib import Path

UNIT_MS = {"us": 0.001, "ms": 1.0, "s": 1000.0, "m": 60_000.0}
PERCENTILE = re.compile(r"^\s*(50|99)(?:\.000)?%\s+([\d.]+)(us|ms|s|m)\s*$")
RPS = re.compile(r"^Requests/sec:\s+([\d.]+)")
ERRORS = re.compile(r"Non-2xx or 3xx responses:\s+(\d+)|Socket errors: (.*)")
TARGET_P99_MS = 1.0
TARGET_RPS = 10_000
TARGET_FANOUT_P99_MS = 100.0


def parse_wrk(path):
    """{'p50': ms, 'p99': ms, 'rps': float, 'errors': str} of one wrk output."""
    out = {"errors": ""}
    for line in path.read_text(errors="replace").splitlines():
        m = PERCENTILE.match(line)
        if m:
            out["p" + m.group(1)] = float(m.group(2)) * UNIT_MS[m.group(3)]
        m = RPS.match(line)
        if m:
            out["rps"] = float(m.group(1))
        m = ERRORS.search(line)
        if m:
            out["errors"] += (m.group(0) + "; ")
    if out.get("rps", 0) == 0:
        # Nothing answered within wrk's timeout: no latency to report.
        out = {"rps": 0.0, "errors": out["errors"] + "no answer within the run; "}
    return out


def facts(work):
    out = {}
    path = work / "facts.env"
    if path.exists():
        for line in path.read_text().splitlines():
            key, _, value = line.partition("=")
            out[key] = value
    return out


def main():
    work, robots, duration, connections, profile, command = sys.argv[1:7]
    work = Path(work)
    f = facts(work)
    rows = []
    for what, label in (("one", "one robot"), ("list", "list of 100 (labelSelector)")):
        for server, name in (("fleet", "Fleet API"), ("kube", "API server")):
            lat = parse_wrk(work / f"wrk-{server}-{what}-lat.txt")
            rps = parse_wrk(work / f"wrk-{server}-{what}-rps.txt")
            verdict = ""
            if server == "fleet":
                ok = lat.get("p99", 1e9) < TARGET_P99_MS and rps.get("rps", 0) >= TARGET_RPS
                verdict = "PASS" if ok else "FAIL"
            errors = (lat["errors"] + rps["errors"]).strip("; ") or "none"
            rows.append((label, name, lat.get("p50"), lat.get("p99"), rps.get("p99"),
                         rps.get("rps"), verdict, errors))
    fmt = lambda v, spec: "-" if v is None else format(v, spec)
    print(f"Fleet API benchmark: {robots} Robots, wrk {duration}s per run ({f.get('source', '?')})")
    if profile != "release":
        print(f"!! {profile} build: a smoke test of bench/api.sh, NOT a measurement")
    print(f"command: {command}")
    print(f"Robots created in {f.get('create_seconds', '?')} s; gateway cache filled in "
          f"{f.get('cache_seconds', '?')} s; gateway RSS {f.get('gateway_rss_mib', '?')} MiB")
    print()
    head = ("request", "server", "p50 ms (1 conn)", "p99 ms (1 conn)",
            f"p99 ms ({connections} conn)", f"req/s ({connections} conn)",
            f"target p99<{TARGET_P99_MS:g} ms, >={TARGET_RPS} req/s", "errors")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for label, name, p50, p99, p99_load, rps, verdict, errors in rows:
        print(f"| {label} | {name} | {fmt(p50, '.3f')} | {fmt(p99, '.3f')} | "
              f"{fmt(p99_load, '.3f')} | {fmt(rps, '.0f')} | {verdict} | {errors} |")
    print()
    for row in fanout_rows(work):
        print(row)
    print("Same ServiceAccount token (a viewer role) for both servers; the API server's answers are")
    print("what `kubectl get robot NAME -o json` and `kubectl get robots -l room=rK --chunk-size=100`")
    print("request. wrk, the gateway and the API server share the machine's cores.")


def fanout_rows(work):
    """The fan-out result as a line and a blank, or nothing when it did not run."""
    path = work / "fanout.json"
    if not path.exists() or not path.read_text().strip():
        return []
    r = json.loads(path.read_text())
    ok = r["missed"] == 0 and r["p99_ms"] < TARGET_FANOUT_P99_MS
    return [
        f"Subscription fan-out: {r['subscribers']} GraphQL subscribers x {r['rounds']} phase "
        f"changes: write -> receipt p50 {r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms, max "
        f"{r['max_ms']:.1f} ms, {r['missed']} missed (target p99 < {TARGET_FANOUT_P99_MS:g} ms: "
        f"{'PASS' if ok else 'FAIL'})",
        "",
    ]


if __name__ == "__main__":
    main()
