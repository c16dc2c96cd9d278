#!/usr/bin/env python3
"""Who asked the API server what about Robots, from its audit log (bench/recovery.sh --audit).

Reads the kube-apiserver's audit log (JSON lines, level Metadata, Robots only) and prints, for
requests received in [FROM, TO) (unix seconds), a Markdown table of requests by client (the
User-Agent: the operator names its role and identity in it), verb, subresource and answer code,
and one of the Robot watches each client began and how long the ended ones lasted. The operator's
replicas, the controller and the benchmark's own watch (curl) are thus told apart: a 409 is
charged to whoever was refused, a list of every Robot to whoever asked for it.

It splits the Robot status writes received in the window into those to the moved robots (per
moved robot, by gateways and by the controller; the issue's "at most one status write per robot
moving") and those to the others (mostly routine refreshes), and tabulates the gateways' status
writes per 20 s: how many a second, how fast they were answered, and how many were in flight on
average (the writer's cap is --status-concurrency): answers slowing while fewer than the cap
are in flight say the API server, not the writer, sets the pace.

It also times the recovery by the API server's own clock: for each robot a gateway other than
the one that wrote it last before FROM writes after it (a moved robot), when that write was
answered; and, given the benchmark's watch log, how much later the watch saw that robot on its
new gateway (the watch's lag, which the watch-based recovery times include). Moved robots the
controller wrote before their new gateway did (marked `Unknown`) are timed the same way: how
long each showed that.

Usage: audit_report.py AUDIT_LOG FROM TO [WATCH_LOG]"""
import json
import sys
from collections import Counter, defaultdict
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from recovery_report import percentile  # noqa: E402


PACE_BUCKET = 20
"""Seconds per row of the status-write pace table."""

REFRESH_PERIOD = 300
"""The gateways' routine refresh period (--status-refresh-seconds, which the benchmark leaves at
its default): a robot written on its new gateway gets (window end - then) / period routine
refreshes in the window on average."""


def seconds(stamp):
    """Unix seconds of an RFC 3339 time stamp with microseconds, as the audit log writes them."""
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def client(agent):
    """A short name for a User-Agent: the part in parentheses for the operator, else the product."""
    if "(" in agent and agent.endswith(")"):
        return agent[agent.index("(") + 1:-1]
    return agent.split(" ")[0] or "(none)"


def gateway(agent):
    """The gateway identity in an operator's User-Agent, or None for other clients."""
    who = client(agent)
    return who.split("; ", 1)[1] if who.startswith("gateway; ") else None


def read(path, start, end):
    """Completed requests received in [start, end), the watches begun in it (with their
    duration if they ended), the moved robots' first writes after `start`: name ->
    (new gateway, seconds after `start` it was answered), and the status writes received in
    the window: (name, "gateway" or the client) -> seconds after `start` each was received; and
    the controller's first status write after `start` of each robot it wrote."""
    requests = Counter()
    status_writes = defaultdict(list)
    answers = defaultdict(list)
    watches = defaultdict(list)
    last_writer, moved, marked = {}, {}, {}
    with open(path) as log:
        for line in log:
            try:
                event = json.loads(line)
            except ValueError:
                continue
            received = seconds(event["requestReceivedTimestamp"])
            note_write(event, start, last_writer, moved, marked)
            if not start <= received < end:
                continue
            ref = event.get("objectRef") or {}
            who = client(event.get("userAgent", ""))
            verb = event.get("verb", "?")
            if verb == "watch":
                if event.get("stage") == "ResponseStarted":
                    watches[who].append(None)
                elif event.get("stage") == "ResponseComplete":
                    watches[who].append(seconds(event["stageTimestamp"]) - received)
                continue
            if event.get("stage") != "ResponseComplete":
                continue
            code = (event.get("responseStatus") or {}).get("code", "?")
            requests[(who, verb, ref.get("subresource", ""), code)] += 1
            if verb == "patch" and ref.get("subresource") == "status":
                kind = "gateway" if who.startswith("gateway; ") else who.split(";")[0]
                status_writes[(ref.get("name"), kind)].append(received - start)
                if kind == "gateway":
                    took = seconds(event["stageTimestamp"]) - received
                    answers[int((received - start) // PACE_BUCKET)].append(took)
    return requests, watches, moved, status_writes, answers, marked


def note_write(event, start, last_writer, moved, marked):
    """Follows which gateway wrote each Robot's status last before `start`, and records the
    first successful write after it by another gateway, and the controller's first successful
    status write after it (`marked`: name -> seconds after `start`)."""
    if event.get("verb") != "patch" or event.get("stage") != "ResponseComplete":
        return
    if (event.get("responseStatus") or {}).get("code") != 200:
        return
    writer = gateway(event.get("userAgent", ""))
    name = (event.get("objectRef") or {}).get("name")
    if name is None:
        return
    answered = seconds(event["stageTimestamp"])
    if writer is None:
        if client(event.get("userAgent", "")).startswith("controller") and answered >= start:
            marked.setdefault(name, answered - start)
        return
    if answered < start:
        last_writer[name] = writer
    elif name not in moved and last_writer.get(name, writer) != writer:
        moved[name] = (writer, answered - start)


def quantiles(values):
    """p50 / p99 / max of `values`, one decimal."""
    return " / ".join(f"{percentile(values, p):.1f} s" for p in (0.5, 0.99, 1.0))


def watch_lag(path, start, moved):
    """For each moved robot, seconds from its new gateway's write being answered until the
    watch log shows it on that gateway."""
    seen = {}
    with open(path) as log:
        for line in log:
            fields = line.rstrip("\n").split("|")
            if len(fields) < 6 or fields[2] in seen or fields[2] not in moved:
                continue
            arrived = float(fields[0]) - start
            writer, answered = moved[fields[2]]
            # The watch may show the write a moment before the API server finished answering it.
            if fields[4] == writer and arrived >= answered - 1:
                seen[fields[2]] = arrived - answered
    return list(seen.values())


def print_pace(answers):
    """The gateways' status writes per PACE_BUCKET seconds: rate, answer times, in flight."""
    print(f"\nGateways' Robot status writes per {PACE_BUCKET} s from the kill or first boot (audit log):\n")
    print("| from | writes/s | answered p50 / p90 / max | in flight, mean |")
    print("|---|---|---|---|")
    for bucket in sorted(answers):
        took = answers[bucket]
        times = " / ".join(f"{percentile(took, p):.2f}" for p in (0.5, 0.9, 1.0))
        print(f"| {bucket * PACE_BUCKET} s | {len(took) / PACE_BUCKET:.1f} | {times} s | "
              f"{sum(took) / PACE_BUCKET:.1f} |")


def print_status_writes(status_writes, moved, window):
    """The window's Robot status writes (any answer), to moved robots and to the others; those
    to moved robots split at each one's first write on its new gateway."""
    to_moved, to_others = Counter(), Counter()
    upto, after = 0, 0
    for (name, kind), times in status_writes.items():
        (to_moved if name in moved else to_others)[kind] += len(times)
        if name in moved:
            written = moved[name][1]
            # Received after the move write was answered: a later write, not one of the move's.
            late = sum(1 for t in times if t > written)
            after += late
            upto += len(times) - late
    n = len(moved)
    expected = sum(max(window - t, 0) for _, t in moved.values()) / REFRESH_PERIOD
    by_kind = ", ".join(f"{k} {v}" for k, v in to_moved.most_common())
    print(f"Robot status writes received in the window (any answer): to the {n} moved "
          f"robots {sum(to_moved.values())}, {sum(to_moved.values()) / n:.2f} per robot "
          f"({by_kind}); to the other robots {sum(to_others.values())}")
    print(f"  to moved robots up to each one's first write on its new gateway (the move itself, "
          f"refused tries and the controller's writes before it): {upto}, {upto / n:.2f} per robot; "
          f"after it, to the window's end: {after}, {after / n:.2f} per robot (routine refreshes "
          f"at each robot's point of the {REFRESH_PERIOD} s period, expected "
          f"{expected:.0f} = {expected / n:.2f} per robot; transitions; the controller's)")


def print_shown_gone(moved, marked):
    """Moved robots the controller wrote after the kill before their new gateway did (it marks a
    dead gateway's unclaimed robots `Unknown`): how long each showed that, by the API server's
    clock (a watch's times include its lag)."""
    shown = [(marked[n], t) for n, (_, t) in moved.items() if n in marked and marked[n] < t]
    if not shown:
        return
    marks, writes = [m for m, _ in shown], [t for _, t in shown]
    spans = [t - m for m, t in shown]
    print(f"Moved robots the controller wrote before their new gateway did (shown Unknown): "
          f"{len(shown)}; shown so for p50 / max {percentile(spans, 0.5):.1f} / {max(spans):.1f} s "
          f"(controller's writes answered {min(marks):.1f}-{max(marks):.1f} s after the kill, the "
          f"new gateway's {min(writes):.1f}-{max(writes):.1f} s)")


def main():
    path, start, end = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
    requests, watches, moved, status_writes, answers, marked = read(path, start, end)
    print(f"Robot requests received in the {end - start:.0f} s from the kill or first boot (audit log):\n")
    print("| client | verb | subresource | code | requests |")
    print("|---|---|---|---|---|")
    for (who, verb, sub, code), n in sorted(requests.items()):
        print(f"| {who} | {verb} | {sub or '-'} | {code} | {n} |")
    print("\n| client | Robot watches begun | ended in the window | their length p50 / max |")
    print("|---|---|---|---|")
    for who, stages in sorted(watches.items()):
        ended = [d for d in stages if d is not None]
        length = " / ".join(f"{percentile(ended, p):.1f} s" for p in (0.5, 1.0)) if ended else "-"
        print(f"| {who} | {len(stages) - len(ended)} | {len(ended)} | {length} |")
    failed = Counter()
    for (who, _, _, code), n in requests.items():
        if isinstance(code, int) and code >= 500:
            failed[who] += n
    if failed:
        print("\n5xx answers by client: " + ", ".join(f"{w} {n}" for w, n in sorted(failed.items()))
              + " (a client killed mid-request is answered 500 in the API server's books)")
    if moved:
        times = [t for _, t in moved.values()]
        print(f"\nRobots moved to another gateway and written there: {len(moved)}; their first "
              f"write answered after the kill, p50 / p99 / all: {quantiles(times)}")
    if moved:
        print_shown_gone(moved, marked)
        print_status_writes(status_writes, moved, end - start)
    if answers:
        print_pace(answers)
    if moved and len(sys.argv) > 4:
        lags = watch_lag(sys.argv[4], start, moved)
        if lags:
            print(f"The benchmark's Robot watch saw {len(lags)} of them on their new gateway "
                  f"this much after the write, p50 / p99 / max: {quantiles(lags)}")


if __name__ == "__main__":
    main()
