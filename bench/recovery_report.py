#!/usr/bin/env python3
"""Turns what bench/recovery.sh collected in its work directory into the one results table.

Inputs (all in WORK): facts.env, robots.log (every Robot change, stamped on arrival by
recovery_watch.py), the API server's /metrics before the kill, after the recovery window and after
the restart window, survivor-metrics/ (the survivor's /metrics every 10 s from the kill), sim.json
(the simulator's summary), stored.txt and gaps.txt (what PostgreSQL holds). Standard library
only; the metric parsing is bench/report.py's.
"""

import json
import os
import sys
from collections import Counter, defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report import WRITE_VERBS, histogram, parse_metrics, quantile  # noqa: E402

KILLED, SURVIVOR = "gw-a", "gw-b"
# The gateways' routine status refresh period (their --status-refresh-seconds default, which the
# benchmark keeps): N/300 writes a second are the fleet's cost with no kill at all.
REFRESH_PERIOD_S = 300.0


def facts(work):
    out = {}
    for line in (work / "facts.env").read_text().splitlines():
        key, _, value = line.partition("=")
        out[key] = value
    return out


def watch(work):
    """[(time, name, phase, gateway, connected)] in arrival order."""
    rows = []
    for line in (work / "robots.log").read_text(errors="replace").splitlines():
        parts = line.split("|")
        if len(parts) != 7 or parts[1] not in ("ADDED", "MODIFIED"):
            continue
        t, _, name, phase, gateway, connected, _ = parts
        rows.append((float(t), name, phase, gateway, connected == "true"))
    return rows


def percentile(values, p):
    if not values:
        return float("nan")
    values = sorted(values)
    return values[min(len(values) - 1, round((len(values) - 1) * p))]


def writes(a, b):
    """API-server write requests between two scrapes: {resource: count}, and {code: count}."""
    by_resource, by_code = Counter(), Counter()
    for (name, labels), value in b.items():
        if name != "apiserver_request_total":
            continue
        labels = dict(labels)
        if labels.get("verb") not in WRITE_VERBS:
            continue
        n = value - a.get((name, frozenset(labels.items())), 0.0)
        if n > 0:
            resource = labels.get("resource", "?")
            if labels.get("subresource"):
                resource += "/" + labels["subresource"]
            by_resource[resource] += n
            by_code[labels.get("code", "?")] += n
    return by_resource, by_code


def all_requests_by_code(a, b):
    """Every API-server request (reads too) between two scrapes, by code."""
    out = Counter()
    for (name, labels), value in b.items():
        if name == "apiserver_request_total":
            out[dict(labels).get("code", "?")] += value - a.get((name, labels), 0.0)
    return out


def moves(rows, t_kill, t_end):
    """Per robot: where it was at the kill, when it was Online on the survivor, and whether it
    showed anything but Online after that (or, for robots on the survivor, at all)."""
    state, recovered, wrong, dipped = {}, {}, set(), set()
    for t, name, phase, gateway, connected in rows:
        if t < t_kill:
            state[name] = (phase, gateway, connected)
            continue
        if t > t_end:
            break
        was = state.get(name, ("", "", False))
        on_killed = was[1] == KILLED
        if name in recovered or not on_killed:
            if phase != "Online":
                wrong.add(name)
            continue
        if phase == "Online" and gateway == SURVIVOR and connected:
            recovered[name] = t - t_kill
        elif phase in ("Unknown", "Offline"):
            dipped.add(name)
    on_killed = {n for n, (p, g, c) in state.items() if g == KILLED and p == "Online" and c}
    return state, on_killed, recovered, wrong, dipped


def robot_watches(a, b):
    """Between two scrapes: watches of Robots begun, and single reads and lists of Robots
    served. Kubernetes 1.20 counts a GET of one custom resource as verb LIST, so the metric
    cannot tell them apart; `--audit` (bench/audit_report.py) can, by client."""
    begun = read = 0.0
    for (name, labels), value in b.items():
        d = dict(labels)
        if name == "apiserver_request_total" and d.get("resource") == "robots":
            if d.get("verb") == "WATCH":
                begun += value - a.get((name, labels), 0.0)
            elif d.get("verb") in ("LIST", "GET"):
                read += value - a.get((name, labels), 0.0)
    return f"{int(begun)} / {int(read)}"


def survivor_writes(work, t_kill):
    """The survivor's own status-write counts sampled every ~10 s from the kill: a table of its
    writes per 20 s by queue (gone = moved robots shown Unknown/Offline, move, high = other
    transitions, low = routine refreshes), and the totals by queue and result; nothing when the
    samples are missing."""
    samples = []
    for path in sorted((work / "survivor-metrics").glob("*.txt"), key=lambda p: float(p.stem)):
        counts = Counter()
        for (name, labels), value in parse_metrics(path).items():
            if name == "lekiwi_gateway_status_writes_total":
                labels = dict(labels)
                counts[(labels.get("priority", "?"), labels.get("result", "?"))] = value
        samples.append((float(path.stem) - t_kill, counts))
    if len(samples) < 2:
        return
    queues = ("gone", "move", "high", "low")
    print()
    print("The survivor's status writes by queue (its own metrics, sampled every 10 s from the kill; "
          "gone = moved robots shown Unknown or Offline, high = other transitions, low = routine "
          "refreshes):")
    print()
    print("| from | gone | move | high | low | not written (any queue) |")
    print("|---|---|---|---|---|---|")
    base = samples[0]
    for i, (t, counts) in enumerate(samples[1:], start=1):
        if t - base[0] < 19.5 and i < len(samples) - 1:
            continue
        delta = {k: counts[k] - base[1].get(k, 0.0) for k in counts}
        by_queue = [sum(v for (q, r), v in delta.items() if q == queue and r == "ok")
                    for queue in queues]
        failed = sum(v for (q, r), v in delta.items() if r != "ok")
        print(f"| {base[0]:.0f}–{t:.0f} s | " + " | ".join(f"{int(v)}" for v in by_queue)
              + f" | {int(failed)} |")
        base = (t, counts)
    first, last = samples[0][1], samples[-1][1]
    total = Counter({k: last[k] - first.get(k, 0.0) for k in last})
    print()
    print(f"Totals from {samples[0][0]:.0f} s to {samples[-1][0]:.0f} s after the kill: "
          + ", ".join(f"{q}/{r} {int(v)}" for (q, r), v in sorted(total.items()) if v > 0))


def row(what, value, goal=""):
    print(f"| {what} | {value} | {goal} |")


def header(f, what):
    print(f"# Recovery benchmark ({what}), {f.get('date', '?')}")
    print()
    print(f"- source: {f.get('source', '?')}; command: `{f.get('command', '?')}`")
    print(f"- host: {f.get('host', '?')}")
    print(f"- transport: {f.get('transport', 'plain ws:// on loopback')}")
    nice = f.get("world_nice", "0")
    print(f"- simulated robots and HAProxy at CPU niceness {nice}"
          + (" (the control plane first)" if nice != "0" else " (as the control plane)"))
    cp_nice = f.get("control_plane_nice", "0")
    if cp_nice != "0":
        print(f"- etcd and the API server at CPU niceness {cp_nice} (the operator, PostgreSQL at 0)")


def report_first_boot(work, f):
    """The first-boot scenario: incumbents Online, then the new fleet enrolls at once."""
    robots, incumbents, t0 = int(f["robots"]), int(f["incumbents"]), float(f["boot_time"])
    rows = watch(work)
    online_at, wrong, state = {}, set(), {}
    for t, name, phase, gateway, connected in rows:
        if name.startswith("sim-"):
            if t >= t0 and state.get(name) == "Online" and phase != "Online":
                wrong.add(name)
            state[name] = phase
        elif phase == "Online" and name not in online_at:
            online_at[name] = t - t0
    times = list(online_at.values())
    refused = Counter()
    for g in ("gw-a", "gw-b"):
        for (name, labels), value in parse_metrics(work / f"{g}-after-boot.txt").items():
            if name.startswith("lekiwi_gateway_refused"):
                refused[dict(labels).get("kind", dict(labels).get("reason", "?"))] += value
    codes = all_requests_by_code(parse_metrics(work / "apiserver-before-boot.txt"),
                                 parse_metrics(work / "apiserver-after-boot.txt"))
    sim = json.loads((work / "sim-new.json").read_text()) if (work / "sim-new.json").exists() else {}
    header(f, "first boot")
    print(f"- {incumbents} incumbent robots Online, then {robots} new robots enroll at once through "
          "HAProxy over two gateways (no connect-rate limit in the simulator)")
    print()
    print("| measure | value | goal |")
    print("|---|---|---|")
    row("new robots Online (watch)", f"{len(times)} / {robots}", f"{robots}")
    row("time until all enrolled and Online", f"{f.get('all_enrolled_online_seconds')} s")
    row("per-robot enrolment to Online p50 / p99 / max",
        f"{percentile(times, 0.5):.1f} s / {percentile(times, 0.99):.1f} s / {percentile(times, 1.0):.1f} s")
    row("incumbent robots that left Online meanwhile", len(wrong), "0")
    row("gateway refusals before upgrade, by reason",
        ", ".join(f"{r} {int(v)}" for r, v in refused.most_common()) or "0")
    row("gateway open files, max (gw-a / gw-b)", f.get("gateway_fds_max", "?"))
    row("API answers 429 / 5xx", f"{int(codes.get('429', 0))} / "
        f"{int(sum(v for c, v in codes.items() if c.startswith('5')))}", "0 / 0")
    if sim:
        row("simulator connect errors / reconnects", f"{sim['connect_errors']} / {sim['reconnects']}")


def report_steady(work, f):
    """The steady scenario: one row per fleet size."""
    header(f, "steady state as the fleet grows")
    gateways = f.get("gateways", "gw-a gw-b").split()
    names = " / ".join(gateways)
    print(f"- {len(gateways)} gateways, robots spread over them by the simulator's URL list; heartbeat "
          f"every {f.get('interval')} s; status refresh every 300 s (the default)")
    print()
    print(f"| robots | provisioned in / Online after | heartbeat RTT p50 / p99 (goal p99 < 10 ms) | gateway RSS per "
          f"connection {names} (goal ≤ 16 KiB) | API writes/s (N/300) | CPU {names} / apiserver (cores) "
          "| CPU simulators / machine (cores of 2) | fewest Online in the window | largest declared status lag |")
    print("|---|---|---|---|---|---|---|---|---|")
    for size in f["steady_sizes"].split(","):
        buckets = {}
        for g in gateways:
            a, b = (parse_metrics(work / f"{g}-{size}-{x}.txt") for x in "ab")
            for bound, n in histogram(a, b, "lekiwi_gateway_heartbeat_rtt_seconds"):
                buckets[bound] = buckets.get(bound, 0.0) + n
        rtt = sorted(buckets.items())
        per_conn = []
        for g in gateways:
            grown = int(f[f"rss_{size}_{g}"]) - int(f[f"rss_base_{g}"])
            per_conn.append(f"{grown / max(int(f[f'connections_{size}_{g}']), 1):.1f} KiB")
        api_a, api_b = (parse_metrics(work / f"apiserver-{size}-{x}.txt") for x in "ab")
        window = float(f[f"window_{size}_seconds"])
        api_writes = sum(writes(api_a, api_b)[0].values()) / window
        cpu = " / ".join(f.get(f"cpu_{size}_window_{n}", "?") for n in [*gateways, "apiserver"])
        sims = sum(float(v) for k, v in f.items() if k.startswith(f"cpu_{size}_window_sim-"))
        machine = f.get(f"cpu_{size}_window_machine", "?")
        p50, p99 = (quantile(rtt, q) for q in (0.5, 0.99))
        rtt_cell = "no heartbeats" if p50 is None else f"{p50 * 1000:.2f} / {p99 * 1000:.2f} ms"
        print(f"| {size} | {f.get(f'steady_{size}_provision_seconds', '?')} s / "
              f"{f.get(f'steady_{size}_online_seconds')} s | {rtt_cell} | "
              f"{' / '.join(per_conn)} | {api_writes:.1f} ({int(size) / 300:.1f}) | {cpu} | "
              f"{sims:.2f} / {machine} | "
              f"{f.get(f'steady_{size}_fewest_online', '?')} | "
              f"{f.get(f'steady_{size}_max_status_lag', '?')} s |")
    print()
    for size in f["steady_sizes"].split(","):
        api_a, api_b = (parse_metrics(work / f"apiserver-{size}-{x}.txt") for x in "ab")
        print(f"- {size} robots, in the window: watches of Robots begun / Robot reads "
              f"(GET or LIST) served: {robot_watches(api_a, api_b)}")


def main():
    work = Path(sys.argv[1])
    f = facts(work)
    scenario = f.get("scenario")
    if scenario == "first-boot":
        report_first_boot(work, f)
    elif scenario == "steady":
        report_steady(work, f)
    else:
        report_kill(work, f)


def report_kill(work, f):
    """The kill scenario: one gateway SIGKILLed under a steady fleet."""
    robots = int(f["robots"])
    t_kill, t_restart = float(f["kill_time"]), float(f["restart_time"])
    rows = watch(work)
    t_end = t_restart + float(f.get("after_restart_seconds", "0"))
    if not any(t > t_kill for t, *_ in rows):
        sys.exit("the Robot watch recorded nothing after the kill: no valid result (see watch.log)")
    state, on_killed, recovered, wrong, dipped = moves(rows, t_kill, t_end)
    times = [recovered[n] for n in on_killed if n in recovered]
    never = len(on_killed) - len(times)

    before = parse_metrics(work / "apiserver-before-kill.txt")
    after = parse_metrics(work / "apiserver-after-recovery.txt")
    restart = parse_metrics(work / "apiserver-after-restart.txt")
    ready = parse_metrics(work / "apiserver-restart-ready.txt")
    rec_writes, rec_codes = writes(before, after)
    rst_writes, rst_codes = writes(ready, restart)
    codes = all_requests_by_code(before, restart)
    moved = max(len(on_killed), 1)
    robot_writes = sum(v for r, v in rec_writes.items() if r.startswith(("robots", "events")))

    sim = json.loads((work / "sim.json").read_text())
    stored, distinct, robots_with_events, _ = (int(x) for x in (work / "stored.txt").read_text().split("|"))
    gaps = int((work / "gaps.txt").read_text().strip() or 0)
    lost = sim["events_acked"] - min(stored, sim["events_acked"])

    header(f, "a gateway killed")
    print(f"- {robots} robots, heartbeat every {f.get('interval')} s, {f.get('events_per_minute')} "
          "events/min each; two gateways behind HAProxy (TCP, round robin, /readyz checks every 1 s); "
          "event store PostgreSQL 15 shared by both")
    print(f"- all Online after {f.get('all_online_seconds')} s; sessions before the kill: "
          f"gw-a {f.get('sessions_before_gw-a')}, gw-b {f.get('sessions_before_gw-b')}")
    print()
    print("| measure | value | goal |")
    print("|---|---|---|")
    row("robots on the killed gateway (moved)", len(on_killed))
    row("recovery, all moved robots Online on the survivor",
        f"{max(times):.1f} s" if times and not never else f"{never} never recovered", "≤ 30 s")
    row("per-robot recovery p50 / p99", f"{percentile(times, 0.5):.1f} s / {percentile(times, 0.99):.1f} s")
    row("moved robots that showed Unknown/Offline before recovering", len(dipped))
    row("robots wrongly not Online after recovering (or on the survivor)", len(wrong), "0")
    row("sessions moved (survivor sessions = N, controller Online = N)",
        f"{f['sessions_moved_seconds']} s" if "sessions_moved_seconds" in f else "not reached")
    row("every robot Online through the survivor in the watch (the write window ends 30 s later)",
        f"{f['recovered_seconds_by_watch']} s" if "recovered_seconds_by_watch" in f else "not reached")
    row(f"API writes in the {float(f['recovery_window_seconds']):.0f} s after the kill",
        ", ".join(f"{r} {int(v)}" for r, v in rec_writes.most_common()) or "0")
    row("  of them Robot + Event writes per robot moved", f"{robot_writes / moved:.2f}", "≤ 1.2")
    routine = robots * float(f["recovery_window_seconds"]) / REFRESH_PERIOD_S
    row(f"  the same above the fleet's routine refreshes (N/{REFRESH_PERIOD_S:.0f} × window = {routine:.0f})",
        f"{(robot_writes - routine) / moved:.2f}", "≤ 1.2")
    row("API answers 429 / 5xx (kill to end of restart window)",
        f"{int(sum(v for c, v in codes.items() if c == '429'))} / "
        f"{int(sum(v for c, v in codes.items() if c.startswith('5')))}", "0 / 0")
    row("restarted gw-a ready (/readyz) after", f"{f.get('restart_ready_seconds', '?')} s")
    row(f"API writes in the {float(f['after_restart_seconds']):.0f} s after the restarted gw-a was ready",
        ", ".join(f"{r} {int(v)}" for r, v in rst_writes.most_common()) or "0")
    row("sessions after the restart window (gw-a / gw-b)",
        f"{f.get('sessions_after_restart_gw-a')} / {f.get('sessions_after_restart_gw-b')}")
    row("events generated / acknowledged (simulator)", f"{sim['events_generated']} / {sim['events_acked']}")
    row("events stored (distinct robot+seq) / robots with gaps in seq", f"{stored} ({distinct}) / {gaps}")
    row("events lost (acknowledged, not stored)", lost, "0")
    row("events still unacknowledged when the simulator stopped",
        sim["events_generated"] - sim["events_acked"], "0")
    row("events stored twice", stored - distinct, "0")
    row("events resent after reconnects", sim["events_resent"])
    row("simulator reconnects / connect errors", f"{sim['reconnects']} / {sim['connect_errors']}")
    row("API write codes in the recovery window", dict(rec_codes) or "-")
    row("watches of Robots begun / Robot reads (GET or LIST) served in the recovery window",
        robot_watches(before, after))
    cpu = sorted(((k.removeprefix("cpu_recovery_window_"), float(v)) for k, v in f.items()
                  if k.startswith("cpu_recovery_window_")), key=lambda kv: -kv[1])
    row(f"CPU in the {float(f['recovery_window_seconds']):.0f} s after the kill (cores; "
        f"{os.cpu_count()} in the machine)", ", ".join(f"{k} {v:.2f}" for k, v in cpu) or "-")
    survivor_writes(work, t_kill)


if __name__ == "__main__":
    main()
