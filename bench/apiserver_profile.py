#!/usr/bin/env python3
"""Sums a kube-apiserver CPU profile (its /debug/pprof/profile) by what the API server was doing,
and prints one Markdown table: CPU seconds, mean cores and share per kind of work.

Every sampled stack is put in the first kind whose marker one of its frames contains, so the
shares add up to 100 %. Writes run in a goroutine of their own (the request's timeout), so a
write is told by its handler's inner functions, not by the HTTP filters above them.

Usage: apiserver_profile.py PROFILE (needs `go tool pprof`). Standard library otherwise.
"""
import re
import subprocess
import sys
from collections import Counter

# (kind, markers): the first kind with a marker in the stack takes the sample.
KINDS = (
    ("garbage collection in the background", ("runtime.gcBgMarkWorker",)),
    ("PATCH: Robot status writes (and the Leases' apply)", ("(*patcher).patchResource",)),
    ("POST: creates (Events)", ("handlers.createHandler",)),
    ("PUT: updates", ("handlers.UpdateResource",)),
    ("DELETE", ("handlers.DeleteResource", "handlers.DeleteCollection")),
    ("watch: encoding and sending events to watchers",
     ("(*WatchServer).ServeHTTP", "(*cacheWatcher)")),
    ("watch cache: events read from etcd and dispatched",
     ("(*watchChan)", "(*Cacher).dispatchEvent", "(*Cacher).processEvent", "(*watchCache)")),
    ("GET and LIST", ("handlers.ListResource", "handlers.GetResource", "(*Cacher).GetToList")),
    ("HTTP, TLS, authentication and filters (not in a handler above)",
     ("net/http.", "crypto/tls.", "endpoints/filters.", "server/filters.")),
)
OTHER = "other"
UNITS = {"ns": 1e-9, "us": 1e-6, "ms": 1e-3, "s": 1.0, "min": 60.0, "hrs": 3600.0}


def seconds(text):
    m = re.fullmatch(r"([0-9.]+)(ns|us|ms|s|min|hrs)", text)
    return float(m.group(1)) * UNITS[m.group(2)] if m else 0.0


def classify(frames):
    for kind, markers in KINDS:
        if any(marker in frame for frame in frames for marker in markers):
            return kind
    return OTHER


def main():
    path = sys.argv[1]
    out = subprocess.run(["go", "tool", "pprof", "-traces", path], check=True,
                         capture_output=True, text=True).stdout
    duration = 0.0
    m = re.search(r"Duration: ([0-9.]+\w+)", out)
    if m:
        duration = seconds(m.group(1))
    by_kind = Counter()
    value, frames = 0.0, []
    for line in out.splitlines() + ["-----------+"]:
        if line.startswith("-----------+"):
            if frames:
                by_kind[classify(frames)] += value
            value, frames = 0.0, []
            continue
        m = re.match(r"\s+([0-9.]+(?:ns|us|ms|s|min|hrs))\s+(\S.*)$", line)
        if m and not frames:
            value, frames = seconds(m.group(1)), [m.group(2)]
        elif frames:
            frames.append(line.strip())
    total = sum(by_kind.values())
    if total == 0:
        sys.exit(f"{path}: no samples")
    print(f"API server CPU profile over {duration:.0f} s from the kill: {total:.1f} CPU seconds, "
          f"{total / max(duration, 1e-9):.2f} cores on average")
    print()
    print("| what the API server did | CPU seconds | cores | share |")
    print("|---|---|---|---|")
    for kind, _ in KINDS + ((OTHER, ()),):
        s = by_kind.get(kind, 0.0)
        print(f"| {kind} | {s:.1f} | {s / max(duration, 1e-9):.2f} | {100 * s / total:.0f} % |")


if __name__ == "__main__":
    main()
