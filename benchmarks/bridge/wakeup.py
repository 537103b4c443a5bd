"""`bench_bridge.py wakeup`: the CPU of a Python process that only wakes from select().
"""

from __future__ import annotations

import argparse
import contextlib
import select
import time

from bridge.harness import print_table, udp_socket

# ------------------------------------------------------------------------------------- wake-up cost

def bench_wakeup(args: argparse.Namespace) -> None:
    """What one wake-up costs before any work: this process sleeps in select() on a timer at the rate of
    the bridge's passes at nominal load and, per wake-up, does nothing or tries a non-blocking read on
    two idle sockets (what a pass does on links with nothing more to read)."""
    socks = [udp_socket() for _ in range(2)]
    for sock in socks:
        sock.setblocking(False)
    rows = []
    try:
        for reads in (0, 2):
            wakes = 0
            period = 1.0 / args.rate_hz
            cpu0, start = time.process_time(), time.monotonic()
            deadline = start
            while (now := time.monotonic()) < start + args.seconds:
                deadline += period
                if deadline > now:
                    select.select(socks[:1], [], [], deadline - now)
                wakes += 1
                for sock in socks[:reads]:
                    with contextlib.suppress(BlockingIOError):
                        sock.recv(4096)
            cpu_s = time.process_time() - cpu0
            wall_s = time.monotonic() - start
            rows.append([f"{args.rate_hz:.0f}", reads, wakes, f"{cpu_s / wakes * 1e6:.0f}",
                         f"{cpu_s / wall_s * 100.0:.2f}"])
    finally:
        for sock in socks:
            sock.close()
    print_table("7. The cost of a wake-up: a Python process that only sleeps in select() on a timer (CPU time, "
                "user + system)", ["wakeups_per_s", "reads_per_wakeup", "wakeups", "cpu_us_per_wakeup",
                                   "cpu_%_core"], rows)
