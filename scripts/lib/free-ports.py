#!/usr/bin/env python3
"""Prints N distinct free TCP ports on 127.0.0.1, one per line (default 1), for the test control
plane and the benchmarks. They are picked outside the kernel's ephemeral range, so client sockets
(the fleet simulator opens 10,000) can never take them between this pick and the server's bind.

Usage: python3 scripts/lib/free-ports.py [N]
"""
import random
import socket
import sys


def main():
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 1
    with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
        ephemeral_lo = int(f.read().split()[0])
    lo, hi = (10000, ephemeral_lo - 1) if ephemeral_lo > 20000 else (61000, 65000)
    held, ports = [], []
    while len(ports) < count:
        port = random.randint(lo, hi)
        s = socket.socket()
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            s.close()
            continue
        held.append(s)  # held until all are picked, so the N ports differ
        ports.append(port)
    print("\n".join(map(str, ports)))


if __name__ == "__main__":
    main()
