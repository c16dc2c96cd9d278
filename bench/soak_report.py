"""The soak's samples and its report (bench/soak_driver.py uses it): slopes of memory, open files
and threads per process, and the table with PASS/FAIL. Standard library only."""
import statistics

# Seconds after a (re)start whose growth counts as warming up.
WARM_UP = 300
# Processes measured for information: the database engines, and thread counts of Go's runtime.
INFORMATIONAL = {"etcd", "postgres"}


class Samples:
    """Every 10 s: RSS (KiB), open files and threads of each process, by role and pid; and the
    API server's write rate to Robots."""

    def __init__(self):
        self.by_role = {}
        self.write_rates = []  # (t, robot writes per second over the last interval)
        self.gauges = {}  # (role, name) -> [(pid, t, value)]: what a process reports of itself

    def add(self, role, pid, t, rss, fds, threads, sessions=0):
        # A gateway's open files less its robots' sessions: what it holds besides them. Its
        # sessions are kept too: its memory is judged at a constant number of them.
        self.by_role.setdefault(role, []).append(
            (pid, t, rss, fds - sessions, threads, sessions))

    def gauge(self, role, name, pid, t, value, sessions=0):
        self.gauges.setdefault((role, name), []).append((pid, t, value, 0, 0, sessions))

    def gauge_drift(self, role, name, end):
        """As `drift`, of a gauge the process reports; a gateway's at a constant number of
        sessions."""
        return self._drift(role, self.gauges.get((role, name), []), 2, end, at_sessions=True)

    def drift(self, role, field, end):
        """(drift over the last two thirds, noise of the first third, samples used, mean) of
        `field` (2 rss, 3 fds, 4 threads) for the instance of `role` with the longest life in
        the last two thirds of the run, its first WARM_UP seconds left out; None when no
        instance lived long enough there to say."""
        return self._drift(role, self.by_role.get(role, []), field, end, at_sessions=True)

    def _drift(self, role, rows, field, end, at_sessions):
        if not rows:
            return None
        first_cut = end / 3
        # A process restarted by a fault warms its caches up for a while: not a leak. Of the
        # instances a fault restarted, the one with the longest steady life is judged: one
        # started a few minutes before the end is all warm-up.
        windows = []
        for pid in dict.fromkeys(r[0] for r in rows):
            born = min(r[1] for r in rows if r[0] == pid)
            start_late = max(first_cut, born + WARM_UP)
            late = [(r[1], r[field]) for r in rows if r[0] == pid and r[1] >= start_late]
            windows.append((late[-1][0] - late[0][0] if late else -1, pid, start_late, late))
        _, pid, start_late, late = max(windows, key=lambda w: w[0])
        early = [r[field] for r in rows if r[1] < first_cut and r[1] > min(120, end / 10)]
        # At least a third of the judged part of the run.
        if len(late) < 6 or late[-1][0] - late[0][0] < (end - first_cut) / 3:
            return None
        slope = _slope(late)
        if at_sessions and field == 2 and role.startswith("gw-"):
            # Robots move between gateways with the faults (a killed gateway's robots stay with
            # the survivor): the memory they bring is load, not a leak. The drift is the trend
            # of the RSS at a constant number of sessions.
            sessions = [r[5] if len(r) > 5 else 0 for r in rows if r[0] == pid
                        and r[1] >= start_late]
            slope = _slope_beside(late, sessions)
        drift = slope * (late[-1][0] - late[0][0])
        mean = statistics.fmean(v for _, v in late)
        noise = 3 * statistics.pstdev(early) if len(early) >= 3 else 0.0
        span = f"min {late[0][0] / 60:.0f}-{late[-1][0] / 60:.0f}"
        return drift, max(noise, 0.02 * mean, 1.0), f"{len(late)} samples, {span}", mean


def _slope(points):
    """The Theil-Sen slope: the median of the slopes between every two samples. A process's
    RSS moves in the allocator's steps (pages committed and purged by the MiB); a least-squares
    line through a few such steps reads a trend where the level only went down and up again (a
    standby controller's 28.8-30.9 MiB read as +1.3 MiB over 40 minutes), while a steady growth
    moves the median of the pairwise slopes as much as it moves a fitted line."""
    slopes = [(v2 - v1) / (t2 - t1)
              for i, (t1, v1) in enumerate(points) for t2, v2 in points[i + 1:] if t2 != t1]
    return statistics.median(slopes) if slopes else 0.0


def _slope_beside(points, other):
    """The time coefficient of `v ~ t + other` (least squares with two regressors): the trend of
    v with `other` held constant; the plain slope when `other` does not vary apart from t."""
    n = len(points)
    mt = sum(t for t, _ in points) / n
    mv = sum(v for _, v in points) / n
    mo = sum(other) / n
    stt = sum((t - mt) ** 2 for t, _ in points)
    soo = sum((o - mo) ** 2 for o in other)
    sto = sum((t - mt) * (o - mo) for (t, _), o in zip(points, other))
    stv = sum((t - mt) * (v - mv) for t, v in points)
    sov = sum((o - mo) * (v - mv) for (_, v), o in zip(points, other))
    det = stt * soo - sto ** 2
    if soo == 0 or det <= 1e-9 * stt * soo:
        return _slope(points)
    return (soo * stv - sto * sov) / det


# A leak, a queue that only grows, a store that fills: each shows as growth. Growth beyond the
# noise fails; a fall beyond it (memory an allocator gave back after a fault's burst) is shown
# in the row, not failed.
GROWTH_GOAL = "at most +{:.1f} (noise of the first third)"


def growth(drift, noise):
    """The drift as the table shows it: a fall beyond the noise says so."""
    return f"{drift:+.1f}" + (" (fell)" if drift < -noise else "")


def report(facts, samples, rollouts, faults, violations, events, steady, sizes, end):
    """The table, as text."""
    lines, fails = [], []

    def row(what, measured, goal="", ok=None):
        verdict = "" if ok is None else ("PASS" if ok else "FAIL")
        if ok is False:
            fails.append(what)
        lines.append(f"| {what} | {measured} | {goal} | {verdict} |")

    lines.append("| check | measured | goal | |")
    lines.append("|---|---|---|---|")
    for role in sorted(samples.by_role):
        files = "open files besides sessions" if role.startswith("gw-") else "open files"
        for field, name, unit in ((2, "RSS", "MiB"), (3, files, ""), (4, "threads", "")):
            d = samples.drift(role, field, end)
            if d is None:
                row(f"{role} {name} drift, last 2/3 of the run", "no instance lived long enough: n/a")
                continue
            drift, noise, n, mean = d
            scale = 1024 if unit == "MiB" else 1
            judged = role not in INFORMATIONAL and not (role == "kube-apiserver" and field == 4)
            what = f"{name} at constant sessions" if role.startswith("gw-") and field == 2 else name
            row(f"{role} {what} drift, last 2/3 of the run ({n}, mean "
                f"{mean / scale:.1f}{' ' + unit if unit else ''})",
                growth(drift / scale, noise / scale), GROWTH_GOAL.format(noise / scale),
                drift <= noise if judged else None)
        d = samples.gauge_drift(role, "tasks", end)
        if d is not None:
            drift, noise, n, mean = d
            what = "tasks at constant sessions" if role.startswith("gw-") else "tasks"
            row(f"{role} {what} drift, last 2/3 of the run ({n}, mean {mean:.0f})",
                growth(drift, noise), GROWTH_GOAL.format(noise), drift <= noise)
    row("events lost (acknowledged to a robot, not in the store)", events["lost"], "0",
        events["lost"] == 0)
    row("gaps in a robot's stored sequence numbers", events["gaps"], "0", events["gaps"] == 0)
    row("events stored twice", events["event_dupes"], "0", events["event_dupes"] == 0)
    row("telemetry samples stored twice", events["sample_dupes"], "0",
        events["sample_dupes"] == 0)
    row("durable messages acknowledged / stored", f"{events['acked']} / {events['stored']}")
    row("durable messages unacknowledged when the robots stopped", events["unacked"], "0",
        events["unacked"] == 0)
    for r in rollouts:
        ok = r["phase"] == r["expected"]
        measured = f"{r['phase']} in {r['seconds']} s, {r.get('counts')}"
        goal = r["expected"]
        if r["kind"] == "abort":
            # An abort starts no robot and lets no downloading robot switch.
            on = r.get("on_release")
            updated = (r.get("counts") or {}).get("updated")
            measured += f"; {on} robots run it after the abort"
            goal += ", robots on it = updated"
            ok = ok and on is not None and on == updated
        row(f"rollout {r['n']} ({r['kind']}, {r['version']})", measured, goal, ok)
    row("robots on a release no deployment asked for (rolled back or undone)",
        facts["unwanted_robots"], "0", facts["unwanted_robots"] == 0)
    row("robots Online through a dead gateway past its Lease + 30 s (most at once)",
        violations["online_through_dead_gateway"], "0",
        violations["online_through_dead_gateway"] == 0)
    row("longest a robot was shown Online through a dead gateway, s",
        f"{violations['max_online_through_dead_gateway_s']:.0f}")
    row("robots with a session not Online for over 300 s (most at once)",
        violations["not_online_with_session"], "0", violations["not_online_with_session"] == 0)
    row("longest a robot with a session was not Online, s",
        f"{violations['max_not_online_with_session_s']:.0f}")
    row("the driver's watch behind the API server's writes at most, s (robot states are judged "
        "at the time the watch shows)", f"{violations.get('max_view_lag_s', 0):.0f}")
    for f in faults:
        healed = f["healed_s"]
        extra = ""
        if f["kind"] == "gateway" and f.get("ratio") is not None:
            extra = (f"; {f['moved']} robots moved, {f['writes_per_move']} Robot writes each, "
                     f"API server at up to {f['peak_write_rate']} writes/s: "
                     f"{f['ratio']}x its own limit")
        row(f"fault {f['kind']}: {f['notes']}",
            f"healed in {healed} s{extra}" if healed is not None else "NOT healed",
            "healed", healed is not None)
    for role, name, what, scale, unit in (
            ("kube-apiserver", "heap", "Go heap in use", 1 << 20, "MiB"),
            ("kube-apiserver", "events", "Kubernetes Events stored", 1, ""),
            ("kube-apiserver", "robots", "Robots stored", 1, ""),
            ("etcd", "heap", "Go heap in use", 1 << 20, "MiB"),
            ("etcd", "db", "database size", 1 << 20, "MiB")):
        d = samples.gauge_drift(role, name, end)
        if d is None:
            continue
        drift, noise, n, mean = d
        u = " " + unit if unit else ""
        row(f"{role} {what} drift, last 2/3 of the run ({n}, mean {mean / scale:.1f}{u})",
            f"{drift / scale:+.1f}", f"within ±{noise / scale:.1f} (noise of the first third)")
    for label, w in steady:
        goal = facts["robots_total"] / 300
        row(f"steady Robot writes/s, {label}", f"{w:.1f}",
            f"≈ N/300 = {goal:.1f} (+ transitions)", w <= 2 * goal + 1)
    row("event store size (PostgreSQL database)", f"{sizes['db_mib']:.0f} MiB, growing "
        f"{sizes['db_mib_per_hour']:.0f} MiB/h: {sizes['db_at_retention_gib']:.1f} GiB at "
        f"{sizes['retention_days']} days' retention")
    row("blob store size", f"{sizes['blob_mib']:.1f} MiB for {sizes['releases']} releases "
        f"and {sizes['agent_builds']} agent builds")
    head = [f"- {k}: {v}" for k, v in facts.items() if k != "unwanted_robots"]
    verdict = "PASS" if not fails else f"FAIL ({len(fails)}): " + "; ".join(fails)
    return "\n".join(["# Soak", ""] + head + ["", f"Verdict: {verdict}", ""] + lines) + "\n"
