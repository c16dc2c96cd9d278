#!/usr/bin/env python3
"""Writes the status of every Robot of a namespace once, in one of several shapes, with a fixed
number of requests in flight, and prints one JSON line: writes, seconds, answers by code.

The shapes (bench/status-cost.sh compares what each costs the API server):
  ssa-full        server-side apply of the whole status a gateway writes (its facts, phase and
                  conditions), field manager lekiwi-gateway, forced: what a move writes today
  ssa-presence    server-side apply of the connection facts alone (connected, gateway, protocol,
                  lastHeartbeatTime, connectedSince, sessionEpoch), another field manager
  merge-full      JSON merge patch of the whole status
  merge-presence  JSON merge patch of the connection facts alone

Usage: status_cost.py API_URL CA_FILE TOKEN_FILE NAMESPACE SHAPE COUNT IN_FLIGHT ROUND
(names sim-00001 ... sim-COUNT; ROUND makes every write change something). Standard library only.
"""
import concurrent.futures
import http.client
import json
import ssl
import sys
import threading
import time
import urllib.parse
from collections import Counter

SHAPES = ("ssa-full", "ssa-presence", "merge-full", "merge-presence")


def presence(rnd, gateway):
    now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return {
        "connected": True,
        "gateway": gateway,
        "protocol": "websocket",
        "lastHeartbeatTime": now,
        "connectedSince": now,
        "sessionEpoch": 1_800_000_000_000_000 + rnd,
    }


def full(name, rnd, gateway):
    """A status as a gateway writes it for a robot that just connected (see presence/patch.rs)."""
    now = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    status = presence(rnd, gateway)

    def cond(kind, ok, reason, message):
        return {"type": kind, "status": "True" if ok else "False", "reason": reason,
                "message": message, "lastTransitionTime": now, "observedGeneration": 1}

    status.update({
        "phase": "Online",
        "observedGeneration": 1,
        "conditions": [
            cond("Connected", True, "Connected", f"connected through gateway {gateway}"),
            cond("Healthy", True, "Healthy", "the agent reports healthy"),
            cond("Teleoperating", False, "Idle", "not teleoperated"),
            cond("UpToDate", True, "NoReleaseRequested", "no release requested"),
        ],
        "agentVersion": "0.1.0",
        "agentDigest": "sha256:" + "ab" * 32,
        "currentRelease": {"version": "1.0.0", "digest": "sha256:" + "cd" * 32},
        "address": "10.0.0.1",
        "health": {"healthy": True},
        "teleoperation": {"active": False},
        "system": {"hostname": name, "os": "Debian GNU/Linux 12", "kernel": "6.1.0-rpi7",
                   "arch": "aarch64", "cpus": 4, "memoryBytes": 8_000_000_000},
        "telemetry": {"cpuPercent": 12.5 + rnd % 7, "memoryPercent": 40.0,
                      "temperatureCelsius": 51.0, "batteryPercent": 88.0},
    })
    return status


def request(shape, name, rnd):
    gateway = f"gw-{'ab'[rnd % 2]}"
    status = full(name, rnd, gateway) if shape.endswith("full") else presence(rnd, gateway)
    if shape.startswith("ssa"):
        body = {"apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot",
                "metadata": {"name": name}, "status": status}
        manager = "lekiwi-gateway" if shape == "ssa-full" else "lekiwi-gateway-presence"
        query = {"fieldManager": manager, "force": "true"}
        content = "application/apply-patch+yaml"
    else:
        body = {"status": status}
        query = {"fieldManager": "lekiwi-gateway-merge"}
        content = "application/merge-patch+json"
    return json.dumps(body), content, urllib.parse.urlencode(query)


def main():
    api, ca, token_file, namespace, shape, count, in_flight, rnd = sys.argv[1:9]
    if shape not in SHAPES:
        sys.exit(f"shape is one of {', '.join(SHAPES)}")
    count, in_flight, rnd = int(count), int(in_flight), int(rnd)
    url = urllib.parse.urlparse(api)
    token = open(token_file).read().strip()
    context = ssl.create_default_context(cafile=ca)
    local = threading.local()
    codes = Counter()
    lock = threading.Lock()

    def write(i):
        name = f"sim-{i:05d}"
        if not hasattr(local, "conn"):
            local.conn = http.client.HTTPSConnection(url.hostname, url.port, context=context,
                                                     timeout=60)
        body, content, query = request(shape, name, rnd)
        path = (f"/apis/fleet.lekiwi.io/v1alpha1/namespaces/{namespace}/robots/{name}/status"
                f"?{query}")
        try:
            local.conn.request("PATCH", path, body, {"Authorization": f"Bearer {token}",
                                                     "Content-Type": content})
            resp = local.conn.getresponse()
            resp.read()
            code = str(resp.status)
        except (OSError, http.client.HTTPException) as e:
            local.conn.close()
            del local.conn
            code = type(e).__name__
        with lock:
            codes[code] += 1

    started = time.monotonic()
    with concurrent.futures.ThreadPoolExecutor(max_workers=in_flight) as pool:
        list(pool.map(write, range(1, count + 1)))
    seconds = time.monotonic() - started
    print(json.dumps({"shape": shape, "writes": count, "seconds": round(seconds, 3),
                      "codes": dict(codes)}))


if __name__ == "__main__":
    main()
