#!/usr/bin/env python3
"""Turns what bench/agent.sh collected in its work directory into the one results table.

Inputs (all in WORK): facts.env (KEY=VALUE lines the script wrote as it went), samples.tsv (both
processes' VmRSS and CPU ticks every 10 s, plus the operator, the control plane and the whole
machine), the agent's /status at the start, after the warm-up and at the end
(status-{start,warmup,end}.json), smaps_rollup of both processes at the end, agent.log and
agent-warnings.txt. Standard library only.
"""

import json
import re
import sys
from pathlib import Path

MB = 1e6  # the target is in MB; sizes here are decimal megabytes
TARGET_RSS_MB = 10.0
LABEL_WIDTH = 46
COLUMN = 16


def read_facts(work):
    facts = {}
    for line in (work / "facts.env").read_text().splitlines():
        key, _, value = line.partition("=")
        facts[key] = value
    return facts


def read_samples(work):
    lines = (work / "samples.tsv").read_text().split("\n")
    header = lines[0].split()
    return [dict(zip(header, map(float, line.split()))) for line in lines[1:] if line.strip()]


def read_json(path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def smaps(path):
    """{field: kB} of a smaps_rollup file."""
    out = {}
    if not path.exists():
        return out
    for line in path.read_text().splitlines():
        m = re.match(r"(\w+):\s+(\d+) kB", line)
        if m:
            out[m.group(1)] = int(m.group(2))
    return out


def biggest_mappings(path, n=4):
    """The n mappings of a full smaps file with the most Rss: [(kB, name)], names merged."""
    if not path.exists():
        return []
    by_name, name = {}, None
    for line in path.read_text().splitlines():
        head = re.match(r"[0-9a-f]+-[0-9a-f]+ \S+ \S+ \S+ \S+\s*(.*)$", line)
        if head:
            name = head.group(1) or "[anonymous]"
            continue
        m = re.match(r"Rss:\s+(\d+) kB", line)
        if m and name is not None:
            by_name[name] = by_name.get(name, 0) + int(m.group(1))
    return sorted(((kb, Path(k).name if k.startswith("/") else k) for k, kb in by_name.items()),
                  reverse=True)[:n]


def mb(kib):
    return kib * 1024 / MB


def row(label, agent, reference="", target="", verdict=""):
    text = f"{label:<{LABEL_WIDTH}}{agent:<{COLUMN + 8}}{reference:<{COLUMN + 4}}"
    if target:
        text += f"{target:<16}{verdict}"
    return text.rstrip()


def main():
    work = Path(sys.argv[1])
    facts = read_facts(work)
    samples = read_samples(work)
    hz = float(facts["clk_tck"])
    duration = int(facts["duration"])
    warmup = int(facts["warmup"])
    first, last = samples[0], samples[-1]
    # The rate window: from the first sample at or after the warm-up to the last one.
    start = next(s for s in samples if s["t"] >= warmup)
    window = last["t"] - start["t"]

    def per_hour(key):
        return (last[key] - start[key]) / hz / window * 3600 if window > 0 else float("nan")

    def cores(key):
        return (last[key] - start[key]) / hz / window if window > 0 else float("nan")

    agent_rss, ne_rss = last["agent_rss_kib"], last["ne_rss_kib"]
    agent_max = max(s["agent_rss_kib"] for s in samples)
    ne_max = max(s["ne_rss_kib"] for s in samples)
    agent_cpu_h, ne_cpu_h = per_hour("agent_ticks"), per_hour("ne_ticks")

    st_start = read_json(work / "status-start.json")
    st_warm = read_json(work / "status-warmup.json")
    st_end = read_json(work / "status-end.json")
    t_warm, t_end = float(facts["t_warmup"]), float(facts["t_end"])
    sent_warm, sent_end = st_warm.get("bytesSent", 0), st_end.get("bytesSent", 0)
    bytes_h = (sent_end - sent_warm) / (t_end - t_warm) * 3600 if t_end > t_warm else float("nan")

    tcp_w = facts.get("tcp_sent_warmup", "").split()
    tcp_e = facts.get("tcp_sent_end", "").split()

    log = (work / "agent.log").read_text(errors="replace") if (work / "agent.log").exists() else ""
    log = re.sub(r"\x1b\[[0-9;]*m", "", log)
    sessions = len(re.findall(r"\bconnected\b.*heartbeat_s=|heartbeat_s=.*\bconnected$", log, re.M))
    heartbeat = re.search(r"heartbeat_s=(\d+)", log)
    warnings = (work / "agent-warnings.txt").read_text().splitlines() \
        if (work / "agent-warnings.txt").exists() else []

    sm_a, sm_n = smaps(work / "smaps-agent.txt"), smaps(work / "smaps-node-exporter.txt")

    out = []
    out.append(f"LeKiwi agent benchmark, {facts['date']}")
    out.append(f"host: {facts['host']}")
    out.append(f"source: {facts['source']}")
    out.append(f"command: {facts['command']}")
    env = f", environment {facts['agent_env']}" if facts.get("agent_env") else ""
    out.append(
        f"agent: lekiwi-agent {facts['agent_version']} (agent profile: opt-level s, LTO), default settings: telemetry "
        f"intervals {facts['agent_intervals']}; heartbeat {heartbeat.group(1) if heartbeat else '?'} s "
        f"(the gateway's default); status endpoint on 127.0.0.1{env}"
    )
    out.append(f"gateway: lekiwi-operator {facts['operator_flags']}")
    out.append(
        f"reference: prometheus-node-exporter {facts['node_exporter_version']}, default collectors, "
        f"a plain child process like the agent, /metrics ({int(facts['node_exporter_scrape_bytes']) / 1e3:.0f} kB) "
        f"scraped every 60 s"
    )
    out.append(
        f"run: {duration} s from both processes' start, RSS and CPU sampled every 10 s; rates over "
        f"{start['t']:.0f}-{last['t']:.0f} s ({window:.0f} s, the first {warmup} s left out), "
        f"extrapolated to one hour; MB = 10^6 bytes"
    )
    out.append("")
    out.append(row("", "agent", "node-exporter", "target"))
    rss_ok = mb(agent_rss) < TARGET_RSS_MB and mb(agent_max) < TARGET_RSS_MB
    out.append(row(f"RSS at the end ({last['t']:.0f} s)", f"{mb(agent_rss):.2f} MB", f"{mb(ne_rss):.2f} MB",
                   f"agent < {TARGET_RSS_MB:.0f} MB", "PASS" if rss_ok else "FAIL"))
    out.append(row("RSS max (of the 10 s samples)", f"{mb(agent_max):.2f} MB", f"{mb(ne_max):.2f} MB"))
    out.append(row("RSS after start-up (first sample)", f"{mb(first['agent_rss_kib']):.2f} MB",
                   f"{mb(first['ne_rss_kib']):.2f} MB"))
    out.append(row("RSS ratio agent / node-exporter", f"{agent_rss / ne_rss:.2f}x" if ne_rss else "n/a"))
    if sm_a and sm_n:
        out.append(row("  anonymous / file-backed (smaps_rollup)",
                       f"{mb(sm_a.get('Anonymous', 0)):.2f} / {mb(sm_a.get('Rss', 0) - sm_a.get('Anonymous', 0)):.2f} MB",
                       f"{mb(sm_n.get('Anonymous', 0)):.2f} / {mb(sm_n.get('Rss', 0) - sm_n.get('Anonymous', 0)):.2f} MB"))
        out.append(row("  private / shared (smaps_rollup)",
                       f"{mb(sm_a.get('Private_Clean', 0) + sm_a.get('Private_Dirty', 0)):.2f} / "
                       f"{mb(sm_a.get('Shared_Clean', 0) + sm_a.get('Shared_Dirty', 0)):.2f} MB",
                       f"{mb(sm_n.get('Private_Clean', 0) + sm_n.get('Private_Dirty', 0)):.2f} / "
                       f"{mb(sm_n.get('Shared_Clean', 0) + sm_n.get('Shared_Dirty', 0)):.2f} MB"))
    big = biggest_mappings(work / "smaps-agent-full.txt")
    if big:
        out.append(row("  agent's largest mappings (Rss)",
                       ", ".join(f"{name} {mb(kb):.2f}" for kb, name in big) + " MB"))
    out.append(row("threads at the end", f"{last['agent_threads']:.0f}", f"{last['ne_threads']:.0f}"))
    out.append(row("CPU per hour", f"{agent_cpu_h:.1f} s ({agent_cpu_h / 36:.3f} %)",
                   f"{ne_cpu_h:.1f} s ({ne_cpu_h / 36:.3f} %)"))
    out.append(row("  CPU over the whole run", f"{(last['agent_ticks']) / hz:.2f} s",
                   f"{(last['ne_ticks']) / hz:.2f} s"))
    out.append(row("bytes sent per hour (WebSocket, /status)", f"{bytes_h / 1e3:.1f} kB"))
    out.append(row("  bytes sent in the whole run", f"{sent_end / 1e3:.1f} kB in {t_end:.0f} s"))
    if len(tcp_w) == 2 and len(tcp_e) == 2 and t_end > t_warm:
        tcp_h = (int(tcp_e[0]) - int(tcp_w[0])) / (t_end - t_warm) * 3600
        # 20 bytes IPv4 + 32 bytes TCP with timestamps per segment; link-layer framing not counted.
        wire_h = tcp_h + (int(tcp_e[1]) - int(tcp_w[1])) / (t_end - t_warm) * 3600 * 52
        out.append(row("  TCP payload / + TCP/IPv4 headers per hour", f"{tcp_h / 1e3:.1f} / {wire_h / 1e3:.1f} kB"))
    out.append(row("outbox pending at the end", f"{st_end.get('outboxPending', '?')}", "", "0",
                   "PASS" if st_end.get("outboxPending") == 0 else "FAIL"))
    out.append(row("connected at the end / sessions in the run",
                   f"{st_end.get('connected')} / {sessions}", "", "1 session",
                   "PASS" if st_end.get("connected") and sessions == 1 else "FAIL"))
    out.append(row("  connected after start", f"{float(facts['agent_connected_after_seconds']):.1f} s"))
    out.append(row("gateway store", facts.get("store", "?")))
    out.append(row("Robot phase at the end", facts.get("robot_phase", "?")))
    out.append(row("binary size (as built / stripped)",
                   f"{int(facts['agent_binary_bytes']) / MB:.2f} / {int(facts['agent_stripped_bytes']) / MB:.2f} MB",
                   f"{int(facts['node_exporter_binary_bytes']) / MB:.2f} MB"))
    out.append(row("agent log warnings / errors",
                   f"{sum(' WARN ' in w for w in warnings)} / {sum(' ERROR ' in w for w in warnings)}"))
    seen = []
    for w in warnings:
        text = re.sub(r"^\S+\s+", "", w)
        if text not in seen:
            seen.append(text)
    for text in seen[:5]:
        out.append(f"  {text[:150]}")
    if len(seen) > 5:
        out.append(f"  ... and {len(seen) - 5} more distinct lines (agent.log in the work directory)")

    machine = cores("machine_ticks")
    ours = {k: cores(f"{k}_ticks") for k in ("agent", "ne", "operator", "apiserver", "etcd")}
    other = machine - sum(ours.values())
    out.append(row("CPU in the window (cores)",
                   f"agent {ours['agent']:.4f}, node-exporter {ours['ne']:.4f}, operator {ours['operator']:.3f}, "
                   f"apiserver {ours['apiserver']:.3f}, etcd {ours['etcd']:.3f}, other processes {other:.2f}, "
                   f"machine {machine:.2f} of {facts['host'].split()[0]}"))
    if other > 0.3:
        out.append(
            f"WARNING: other processes used {other:.2f} cores during the window; CPU figures may be "
            "inflated by contention (RSS and bytes are not affected)"
        )
    print("\n".join(out))


if __name__ == "__main__":
    main()
