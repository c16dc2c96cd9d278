#!/usr/bin/env python3
"""Turns what bench/hostile.sh collected in its work directory into its results table.

Inputs (in WORK): facts.env, /metrics scrapes of the gateway and the API server at both ends of
the quiet and the attack window (gateway-{quiet,attack}-{a,b}.txt, apiserver-...), attack.json
(the attacker's own counts). Reuses the parsing helpers of bench/report.py. Standard library only.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from report import histogram, ms, num, parse_metrics, quantile, read_facts, requests  # noqa: E402

RTT = "lekiwi_gateway_heartbeat_rtt_seconds"


def window(work, facts, phase):
    """The figures of one window."""
    gw_a = parse_metrics(work / f"gateway-{phase}-a.txt")
    gw_b = parse_metrics(work / f"gateway-{phase}-b.txt")
    api_a = parse_metrics(work / f"apiserver-{phase}-a.txt")
    api_b = parse_metrics(work / f"apiserver-{phase}-b.txt")
    seconds = num(facts, f"{phase}_seconds", 1.0) or 1.0
    h = histogram(gw_a, gw_b, RTT)
    reqs = requests(api_a, api_b)
    by_resource = {}
    for (resource, _verb), n in reqs.items():
        by_resource[resource] = by_resource.get(resource, 0.0) + n
    return {
        "p50": quantile(h, 0.5),
        "p99": quantile(h, 0.99),
        "samples": h[-1][1] if h else 0,
        "rss_mib": (num(facts, f"{phase}_rss_max_kib", 0) or 0) / 1024,
        "api_rate": sum(reqs.values()) / seconds,
        "api_top": sorted(by_resource.items(), key=lambda kv: -kv[1])[:4],
        "not_online": int(num(facts, f"{phase}_not_online_max", -1)),
        "reconnects": int(num(facts, f"{phase}_sim_reconnects", -1)),
        "healthz": facts.get(f"{phase}_healthz", "?"),
        "seconds": seconds,
    }


def ratio(quiet, attack):
    if quiet is None or attack is None or quiet <= 0:
        return None
    return attack / quiet


def verdict(r, limit=2.0):
    if r is None:
        return "n/a"
    return f"{r:.2f}x {'PASS' if r <= limit else 'FAIL'}"


def main():
    work = Path(sys.argv[1])
    facts = read_facts(work)
    q = window(work, facts, "quiet")
    a = window(work, facts, "attack")
    try:
        attack = json.loads((work / "attack.json").read_text())
    except (OSError, ValueError):
        attack = {}

    rows = [
        ("heartbeat RTT p50 (ms)", ms(q["p50"]), ms(a["p50"]), verdict(ratio(q["p50"], a["p50"]))),
        ("heartbeat RTT p99 (ms)", ms(q["p99"]), ms(a["p99"]), verdict(ratio(q["p99"], a["p99"]))),
        ("RTT samples", f"{q['samples']:.0f}", f"{a['samples']:.0f}", ""),
        ("gateway RSS max (MiB)", f"{q['rss_mib']:.1f}", f"{a['rss_mib']:.1f}",
         verdict(ratio(q["rss_mib"], a["rss_mib"]))),
        ("API server requests/s", f"{q['api_rate']:.2f}", f"{a['api_rate']:.2f}",
         verdict(ratio(q["api_rate"], a["api_rate"]))),
        ("robots not Online (max of 5 s samples)", str(q["not_online"]), str(a["not_online"]),
         "PASS" if a["not_online"] == 0 and q["not_online"] == 0 else "FAIL"),
        ("simulator reconnects", str(q["reconnects"]), str(a["reconnects"]),
         "PASS" if a["reconnects"] == 0 else "FAIL"),
        ("/healthz at window end", q["healthz"], a["healthz"], ""),
    ]
    for proc in ("gateway", "apiserver", "controller", "sim", "attacker", "machine"):
        qc = facts.get(f"cpu_quiet_window_{proc}")
        ac = facts.get(f"cpu_attack_window_{proc}")
        if qc is not None or ac is not None:
            rows.append((f"CPU of {proc} (cores)", qc or "-", ac or "-", ""))
    width = max(len(r[0]) for r in rows)
    lines = [
        f"LeKiwi gateway under attack — {facts.get('date', '?')}",
        f"host: {facts.get('host', '?')}",
        f"source: {facts.get('source', '?')}; command: {facts.get('command', '?')}",
        f"robots: {facts.get('robots', '?')}, heartbeat every {facts.get('interval', '?')} s; "
        f"windows of {q['seconds']:.0f} s; attack: {facts.get('attack', '?')}",
        f"CPU pinning: {facts.get('pinning', '?')}",
        "",
        f"{'':<{width}} | {'quiet':>14} | {'under attack':>14} | attack/quiet (goal <= 2x)",
        f"{'-' * width}-+-{'-' * 14}-+-{'-' * 14}-+-{'-' * 26}",
    ]
    for name, qv, av, v in rows:
        lines.append(f"{name:<{width}} | {qv:>14} | {av:>14} | {v}")
    lines.append("")
    lines.append("API server requests by resource in the attack window: "
                 + ", ".join(f"{r} {n:.0f}" for r, n in a["api_top"]))
    lines.append(f"after the attack: robots not Online {facts.get('after_not_online', '?')}, "
                 f"gateway RSS {int(facts.get('after_rss_kib', '0')) / 1024:.1f} MiB")
    if attack:
        lines.append("")
        lines.append("What the attacker did and how the gateway answered (attack.json):")
        flood = attack.pop("flood_answers", {})
        for key in sorted(attack):
            lines.append(f"  {key}: {attack[key]}")
        if flood:
            lines.append("  flood answers: " + ", ".join(f"{k} {v}" for k, v in sorted(flood.items())))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
