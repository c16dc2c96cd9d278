#!/usr/bin/env python3
"""Turns what bench/gateway.sh collected in its work directory into the one results table.

Inputs (all in WORK): facts.env (KEY=VALUE lines the script wrote as it went), the /metrics scrapes
taken at the start and the end of each steady-state window (apiserver-{a,b}.txt, gateway-{a,b}.txt,
controller-{a,b}.txt, echo-{a,b}.txt) and the simulator logs (sim-gateway.log, sim-echo.log).
Standard library only.
"""

import math
import re
import sys
from pathlib import Path

WRITE_VERBS = {"POST", "PUT", "PATCH", "APPLY", "DELETE", "DELETECOLLECTION"}
LABEL = re.compile(r'(\w+)="((?:[^"\\]|\\.)*)"')
SIM_LINE = re.compile(
    r"\[\s*([\d.]+)s\] connected (\d+)/(\d+)\s+heartbeats (\d+)\s+rtt p50 ([\d.]+) ms p99 ([\d.]+) ms"
    r" max ([\d.]+) ms\s+connect errors (\d+)\s+reconnects (\d+)\s+error frames (\d+)"
)


def parse_metrics(path):
    """{(name, frozenset(labels)): value} of a Prometheus/OpenMetrics text file."""
    out = {}
    if not path.exists():
        return out
    for line in path.read_text(errors="replace").splitlines():
        if not line or line.startswith("#"):
            continue
        if "{" in line:
            name, rest = line.split("{", 1)
            labels, _, value = rest.rpartition("} ")
            key = frozenset(LABEL.findall(labels))
        else:
            name, _, value = line.partition(" ")
            key = frozenset()
        try:
            out[(name, key)] = float(value.split()[0])
        except (ValueError, IndexError):
            continue
    return out


def total(metrics, name, **want):
    """Sum of the series `name` whose labels include `want`."""
    return sum(
        v
        for (n, labels), v in metrics.items()
        if n == name and all((k, val) in labels for k, val in want.items())
    )


def delta(a, b, name, **want):
    return total(b, name, **want) - total(a, name, **want)


def histogram(a, b, name):
    """[(upper bound, count in window)] from the cumulative `_bucket` series, sorted."""
    buckets = {}
    for (n, labels), v in b.items():
        if n != name + "_bucket":
            continue
        le = dict(labels)["le"]
        bound = math.inf if le == "+Inf" else float(le)
        buckets[bound] = v - a.get((n, labels), 0.0)
    return sorted(buckets.items())


def quantile(buckets, q):
    """histogram_quantile(): linear interpolation inside the bucket, seconds (None if empty)."""
    if not buckets or buckets[-1][1] <= 0:
        return None
    rank = q * buckets[-1][1]
    lower, below = 0.0, 0.0
    for bound, cumulative in buckets:
        if cumulative >= rank:
            if math.isinf(bound):
                return math.inf
            inside = cumulative - below
            return lower + (bound - lower) * ((rank - below) / inside if inside else 1.0)
        lower, below = bound, cumulative
    return math.inf


def share_at_most(buckets, bound):
    if not buckets or buckets[-1][1] <= 0:
        return None
    for b, cumulative in buckets:
        if b >= bound:
            return cumulative / buckets[-1][1]
    return 1.0


def max_bound(buckets):
    """Upper bound of the highest non-empty bucket."""
    for bound, cumulative in buckets:
        if cumulative >= buckets[-1][1]:
            return bound
    return math.inf


FIRST_BOUND = 0.0005


def ms(seconds, approx=True):
    if seconds is None:
        return "n/a"
    if math.isinf(seconds):
        return "> 4096"
    if approx and seconds <= FIRST_BOUND:
        # Inside the first bucket: interpolation would invent a number.
        return f"< {FIRST_BOUND * 1000:.2f}"
    return f"{'~' if approx else ''}{seconds * 1000:.2f}"


def requests(a, b, verbs=None):
    """{(resource[/subresource], verb): count} of apiserver_request_total between two scrapes."""
    out = {}
    for (n, labels), v in b.items():
        if n != "apiserver_request_total":
            continue
        d = dict(labels)
        if verbs is not None and d.get("verb") not in verbs:
            continue
        resource = d.get("resource", "?") + ("/" + d["subresource"] if d.get("subresource") else "")
        key = (resource, d.get("verb", "?"))
        out[key] = out.get(key, 0.0) + v - a.get((n, labels), 0.0)
    return {k: v for k, v in out.items() if v > 0}


def last_sim_line(path):
    if not path.exists():
        return None
    last = None
    for line in path.read_text(errors="replace").splitlines():
        m = SIM_LINE.search(line)
        if m:
            last = m
    return last


def read_facts(work):
    facts = {}
    for line in (work / "facts.env").read_text().splitlines():
        key, sep, value = line.partition("=")
        if sep:
            facts[key] = value
    return facts


def num(facts, key, default=None):
    try:
        return float(facts[key])
    except (KeyError, ValueError):
        return default


CPU_ORDER = ["gateway", "echo", "sim", "apiserver", "etcd", "controller"]


def other_cpu(facts, phase):
    """Cores used by processes the benchmark did not start, over a phase."""
    prefix = f"cpu_{phase}_window_"
    cpu = {k[len(prefix) :]: num(facts, k) for k in facts if k.startswith(prefix)}
    machine = cpu.pop("machine", None)
    return None if machine is None else max(machine - sum(cpu.values()), 0)


def cpu_cell(facts, phase):
    """Cores used per process over a phase, and what the rest of the machine used meanwhile."""
    prefix = f"cpu_{phase}_window_"
    cpu = {k[len(prefix) :]: num(facts, k) for k in facts if k.startswith(prefix)}
    machine = cpu.pop("machine", None)
    parts = [f"{k} {cpu[k]:.2f}" for k in CPU_ORDER if k in cpu]
    if machine is not None:
        parts.append(f"other processes {other_cpu(facts, phase):.2f}")
        parts.append(f"machine {machine:.2f} of {facts.get('cpus', '?')}")
    return ", ".join(parts) or "n/a"


def main():
    work = Path(sys.argv[1])
    f = read_facts(work)
    robots = int(num(f, "robots", 0))
    interval = num(f, "interval", 0)
    refresh = num(f, "status_refresh", 300)
    window_gw = num(f, "window_gateway_seconds", 0) or math.nan
    window_echo = num(f, "window_echo_seconds", 0) or math.nan

    api_a, api_b = parse_metrics(work / "apiserver-a.txt"), parse_metrics(work / "apiserver-b.txt")
    gw_a, gw_b = parse_metrics(work / "gateway-a.txt"), parse_metrics(work / "gateway-b.txt")
    ct_a, ct_b = parse_metrics(work / "controller-a.txt"), parse_metrics(work / "controller-b.txt")
    ec_a, ec_b = parse_metrics(work / "echo-a.txt"), parse_metrics(work / "echo-b.txt")
    gw_end = parse_metrics(work / "gateway-b.txt")

    # --- round trips (agent-reported, previous heartbeat), steady-state window only ------------
    gw_h = histogram(gw_a, gw_b, "lekiwi_gateway_heartbeat_rtt_seconds")
    ec_h = histogram(ec_a, ec_b, "lekiwi_bench_echo_heartbeat_rtt_seconds")
    gw_p50, gw_p99 = quantile(gw_h, 0.5), quantile(gw_h, 0.99)
    ec_p50, ec_p99 = quantile(ec_h, 0.5), quantile(ec_h, 0.99)
    gw_n = gw_h[-1][1] if gw_h else 0
    ec_n = ec_h[-1][1] if ec_h else 0
    le8, le16 = share_at_most(gw_h, 0.008), share_at_most(gw_h, 0.016)
    if le8 is None:
        rtt_result = "NO DATA"
    elif le8 >= 0.99:
        rtt_result = "PASS"
    elif le16 < 0.99:
        rtt_result = "FAIL"
    else:
        rtt_result = "PASS (interpolated)" if gw_p99 < 0.010 else "FAIL (interpolated)"

    def ratio(a, b):
        if a is None or b is None or b <= 0 or math.isinf(a) or math.isinf(b):
            return "n/a"
        if a <= FIRST_BOUND and b <= FIRST_BOUND:
            return "n/a (both < 0.5 ms)"
        return f"{a / b:.1f}x"

    sim_gw, sim_ec = last_sim_line(work / "sim-gateway.log"), last_sim_line(work / "sim-echo.log")

    # --- memory -----------------------------------------------------------------------------
    rss_before, rss_after = num(f, "gateway_rss_before_kib"), num(f, "gateway_rss_after_kib")
    rss_max = num(f, "gateway_rss_max_kib")
    conns = num(f, "gateway_connections_end", robots) or robots
    per_conn = (rss_after - rss_before) / conns if rss_before and rss_after and conns else None
    e_before, e_after = num(f, "echo_rss_before_kib"), num(f, "echo_rss_after_kib")
    e_conns = num(f, "echo_connections_end", robots) or robots
    e_per_conn = (e_after - e_before) / e_conns if e_before and e_after and e_conns else None

    # --- API server writes in the gateway window -----------------------------------------------
    writes = requests(api_a, api_b, WRITE_VERBS)
    all_writes = sum(writes.values())
    lease_writes = sum(v for (r, _), v in writes.items() if r == "leases")
    robot_writes = all_writes - lease_writes
    transitions = delta(ct_a, ct_b, "lekiwi_robot_phase_transitions_total")
    high_writes = delta(gw_a, gw_b, "lekiwi_gateway_status_writes_total", priority="high")
    low_writes = delta(gw_a, gw_b, "lekiwi_gateway_status_writes_total", priority="low")
    # Each phase transition costs one controller status write and one Event; each gateway
    # transition (connect, disconnect, change) one status write.
    allowed = robots / refresh + (2 * transitions + high_writes) / window_gw
    writes_result = "PASS" if robot_writes / window_gw <= allowed + 1e-9 else "FAIL"
    status_total = total(gw_end, "lekiwi_gateway_status_writes_total")
    status_errors = total(gw_end, "lekiwi_gateway_status_writes_total", result="error")

    t_online = num(f, "time_all_online_seconds")
    t_conn = num(f, "time_all_sessions_seconds")
    t_echo_conn = num(f, "echo_time_all_sessions_seconds")

    rows = []

    def row(name, value, target="", result=""):
        rows.append((name, value, target, result))

    def rtt_cell(p50, p99, h, n):
        mx = max_bound(h) if h else None
        return f"{ms(p50)} / {ms(p99)} / <= {ms(mx, False)} ms  (n={int(n)})"

    row("robots", f"{robots}")
    row("heartbeat interval", f"{interval:g} s")
    row(
        "RTT via gateway p50 / p99 / max",
        rtt_cell(gw_p50, gw_p99, gw_h, gw_n),
        "p99 < 10 ms",
        rtt_result,
    )
    if le8 is not None:
        row("  heartbeats <= 8 ms / <= 16 ms", f"{le8 * 100:.2f} % / {le16 * 100:.2f} %")
    row("RTT via echo floor p50 / p99 / max", rtt_cell(ec_p50, ec_p99, ec_h, ec_n))
    row("RTT ratio gateway/echo p50 / p99", f"{ratio(gw_p50, ec_p50)} / {ratio(gw_p99, ec_p99)}")
    for label, m in (("gateway", sim_gw), ("echo", sim_ec)):
        if m:
            row(
                f"  sim exact, whole run incl. ramp, {label}",
                f"{float(m.group(5)):.2f} / {float(m.group(6)):.2f} / {float(m.group(7)):.2f} ms",
            )
    if rss_before and rss_after:
        row(
            "gateway RSS before / after (max)",
            f"{rss_before / 1024:.1f} / {rss_after / 1024:.1f} ({(rss_max or rss_after) / 1024:.1f}) MiB",
        )
    rss_prov = num(f, "gateway_rss_provisioned_kib")
    if rss_prov and rss_before and robots:
        row(
            "  of which token Secret cache (provisioning)",
            f"{(rss_prov - rss_before) / 1024:.1f} MiB, {(rss_prov - rss_before) / robots:.1f} KiB/robot",
        )
    row(
        "gateway RSS per connection",
        f"{per_conn:.1f} KiB" if per_conn is not None else "n/a",
        "< 32 KiB",
        "n/a" if per_conn is None else ("PASS" if per_conn < 32 else "FAIL"),
    )
    if e_per_conn is not None:
        row(
            "  echo floor RSS before / after, per conn",
            f"{e_before / 1024:.1f} / {e_after / 1024:.1f} MiB, {e_per_conn:.1f} KiB",
        )
    row(
        "time until all Online"
        + (" (known robots)" if f.get("mode") == "provision" else " (incl. enrollment)"),
        f"{t_online:.1f} s" if t_online is not None else "not reached",
        "",
        "" if t_online is not None else "FAIL",
    )
    row(
        "  all sessions open (gateway gauge)",
        f"{t_conn:.1f} s" if t_conn is not None else "not reached",
    )
    ramp_a, ramp_b = (
        parse_metrics(work / "apiserver-start.txt"),
        parse_metrics(work / "apiserver-online.txt"),
    )
    if ramp_a and ramp_b and robots:
        ramp_all = requests(ramp_a, ramp_b)
        ramp_writes = {k: v for k, v in ramp_all.items() if k[1] in WRITE_VERBS}
        row(
            "  API requests per robot during ramp",
            f"{sum(ramp_all.values()) / robots:.1f} ({sum(ramp_writes.values()) / robots:.1f} writes); "
            + ", ".join(
                f"{verb} {res} {v / robots:.2f}"
                for (res, verb), v in sorted(ramp_all.items(), key=lambda kv: -kv[1])[:4]
            ),
        )
        if t_online:
            row(
                "  API requests/s during ramp",
                f"{sum(ramp_all.values()) / t_online:.0f} ({sum(ramp_writes.values()) / t_online:.0f} writes)",
            )
    if any(k.startswith("cpu_ramp_window_") for k in f):
        row("  CPU during ramp (cores)", cpu_cell(f, "ramp"))
    if t_echo_conn is not None:
        row("  all sessions open, echo floor", f"{t_echo_conn:.1f} s")
    row(
        "API server writes/s, steady state",
        f"{all_writes / window_gw:.2f} /s ({robot_writes / window_gw:.2f} without Leases)",
        f"<= {allowed:.2f} /s",
        writes_result,
    )
    row(
        "  target = N/refresh + transitions",
        f"{robots}/{refresh:g} + (2x{int(transitions)} phase + {int(high_writes)} gateway)/{window_gw:.0f} s",
    )
    for (resource, verb), v in sorted(writes.items(), key=lambda kv: -kv[1]):
        row(f"  {verb} {resource}", f"{v / window_gw:.2f} /s ({int(v)})")
    if window_gw < refresh:
        row(
            "  note",
            f"window {window_gw:.0f} s < statusRefreshSeconds {refresh:g} s: refreshes not sampled",
        )
    row(
        "gateway status writes total / window",
        f"{int(status_total)} / {int(high_writes + low_writes)} "
        f"(high {int(high_writes)}, low {int(low_writes)}, errors {int(status_errors)} total)",
    )
    if sim_gw:
        row(
            "errors: sim connect errors / reconnects / error frames",
            f"gateway {sim_gw.group(8)} / {sim_gw.group(9)} / {sim_gw.group(10)}"
            + (f"; echo {sim_ec.group(8)} / {sim_ec.group(9)} / {sim_ec.group(10)}" if sim_ec else ""),
        )
    refused = total(gw_end, "lekiwi_gateway_refused_total")
    ended = {
        dict(labels).get("kind"): v
        for (n, labels), v in gw_end.items()
        if n == "lekiwi_gateway_sessions_ended_total" and v > 0
    }
    row(
        "gateway refused / sessions ended",
        f"{int(refused)} / " + (", ".join(f"{k} {int(v)}" for k, v in sorted(ended.items())) or "0"),
    )
    row("CPU in gateway window (cores)", cpu_cell(f, "gateway"))
    row("CPU in echo window (cores)", cpu_cell(f, "echo"))
    for phase in ("ramp", "gateway", "echo"):
        other = other_cpu(f, phase)
        if other is not None and other > 0.3:
            row(
                "  WARNING",
                f"other processes used {other:.2f} cores during the {phase} window: "
                "its numbers are disturbed, rerun on a quieter machine",
            )
    if f.get("gateway_env"):
        row("gateway environment", f["gateway_env"])

    width = [max(len(r[i]) for r in rows) for i in range(4)]
    header = [
        f"LeKiwi gateway benchmark, {f.get('date', '?')}",
        f"host: {f.get('host', '?')}",
        f"source: {f.get('source', '?')}",
        f"command: {f.get('command', '?')}",
        f"simulator: {robots} robots, heartbeat {interval:g} s, new robots {f.get('connect_rates', '?')}",
        "robots: "
        + (
            "provisioned first (Robots + token Secrets created by the benchmark in "
            f"{num(f, 'provision_seconds', 0):.0f} s), so they connect as known robots"
            if f.get("mode") == "provision"
            else "enroll on first connect with the fleet enrollment token (Robot + token Secret each)"
        ),
        f"gateway: {f.get('gateway_flags', '?')}",
        f"transport: {f.get('tls', 'none (plain ws:// on loopback)')}",
        f"windows: gateway {window_gw:.0f} s, echo {window_echo:.0f} s of steady state;"
        " RTT = agent-reported heartbeat round trip, read from the server's histogram"
        " (bounds 0.5 ms x 2^k; ~ = interpolated inside a bucket)",
        "",
    ]
    lines = header + [
        f"{r[0]:<{width[0]}}  {r[1]:<{width[1]}}  {r[2]:<{width[2]}}  {r[3]}".rstrip() for r in rows
    ]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
