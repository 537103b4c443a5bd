"""`bench_bridge.py regularity`: override period jitter at command.rate_hz = 50, quiet and under a GCS flood.
"""

from __future__ import annotations

import argparse
import itertools
import select
import socket
import statistics
import subprocess
import tempfile
import time
from typing import Any

from bridge.harness import (
    MSG_OVERRIDE,
    REPO,
    drain,
    msg_id,
    pct,
    print_table,
    recv_stamped,
    self_cmd,
    udp_socket,
    write_profile,
)
from bridge.process import Bridge, Heartbeats, bridges, stop_all

# ------------------------------------------------------------------------------------- 4. regularity

def override_periods(bridge: Bridge, ap: socket.socket, gcs: socket.socket, seconds: float) -> list[float]:
    beats = Heartbeats(ap, bridge, gcs)
    stamps: list[float] = []
    end = time.monotonic() + seconds
    while (now := time.monotonic()) < end:
        beats.poll(now)
        select.select([ap], [], [], 0.05)
        while (got := recv_stamped(ap)) is not None:
            if msg_id(got[0]) == MSG_OVERRIDE:
                stamps.append(got[1])
        drain(gcs)
    return [b - a for a, b in itertools.pairwise(stamps)]


def bench_regularity(args: argparse.Namespace) -> None:
    rate_hz = 50.0
    period = 1.0 / rate_hz
    rows: list[list[Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        profile = write_profile({"command.rate_hz": f"{rate_hz}"}, tmp)
        under_test = bridges(args, profile, tmp)
        socks = [(udp_socket(True), udp_socket()) for _ in under_test]
        stats: list[dict[str, Any]] = []
        try:
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                br.wait_up(ap, gcs)
            for rep in range(args.repeats):
                for flood in (False, True):
                    # Bridges take turns (one measured at a time, the other idle), in alternating order.
                    order = list(zip(under_test, socks, strict=True))
                    for br, (ap, gcs) in order if rep % 2 == 0 else order[::-1]:
                        flooder = None
                        if flood:
                            flooder = subprocess.Popen(
                                self_cmd("_flood", str(br.gcs_port), str(args.flood_hz), str(args.seconds + 0.5)),
                                stdout=subprocess.PIPE, cwd=REPO)
                        override_periods(br, ap, gcs, 0.3)  # flooder starting; not measured
                        periods = override_periods(br, ap, gcs, args.seconds)
                        flood_sent = "-"
                        if flooder is not None:
                            out, _ = flooder.communicate(timeout=30)
                            flood_sent = f"{int(out.decode().strip() or 0) / (args.seconds + 0.5):.0f}"
                        dev_ms = [abs(p - period) * 1e3 for p in periods]
                        rows.append([br.name, rep + 1, "flood" if flood else "quiet", flood_sent, len(periods),
                                     statistics.mean(periods) * 1e3, pct(dev_ms, 50), pct(dev_ms, 99), max(dev_ms)])
        finally:
            stats = stop_all(under_test, [sock for pair in socks for sock in pair])
    print_table(f"4. override period at command.rate_hz = {rate_hz:.0f} (nominal {period * 1e3:.0f} ms), idle "
                f"(neutral refresh), {args.seconds:.0f} s per run; deviation = |period - {period * 1e3:.0f} ms|",
                ["bridge", "run", "gcs", "flood_msg_s", "periods", "mean_ms", "p50_dev_ms", "p99_dev_ms",
                 "max_dev_ms"], rows)
    for br, st in zip(under_test, stats, strict=True):
        for cond in ("quiet", "flood"):
            p99s: list[float] = [r[7] for r in rows if r[0] == br.name and r[2] == cond]
            med = statistics.median(p99s)
            verdict = "met" if med < 2 else "MISSED"
            print(f"{br.name} {cond}: median of p99 deviation {med:.3f} ms (target < 2 ms [{verdict}])")
        print(f"{br.name} forwarded {st.get('runner', {}).get('forwarded')} frames")
