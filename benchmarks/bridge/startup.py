"""`bench_bridge.py startup`: process start -> first HEARTBEAT and first ODOMETRY; import-time breakdown.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import select
import signal
import statistics
import subprocess
import sys
import time

from bridge.harness import (
    BRIDGE_COMP,
    DEFAULT_PROFILE,
    LOCAL,
    MSG_HEARTBEAT,
    MSG_ODOMETRY,
    REPO,
    Telemetry,
    msg_id,
    print_table,
    recv_stamped,
    udp_socket,
)

# ------------------------------------------------------------------------------------- 6. start-up

def bench_startup(args: argparse.Namespace) -> None:
    # As deployed: Python's bytecode cache in use. With PYTHONDONTWRITEBYTECODE set (some sandboxes and CI
    # images set it) every start would compile the bridge's own sources again, about 0.1-0.2 s here; one start
    # that is not timed writes the cache first.
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    if "PYTHONDONTWRITEBYTECODE" in os.environ:
        print("note: PYTHONDONTWRITEBYTECODE is set here; the bridges below run without it (as an install does)")
    times: list[float] = []
    odometry_times: list[float] = []
    for run in range(args.repeats + 1):
        sock, gcs = udp_socket(), udp_socket()
        sock.setblocking(False)
        t0 = time.monotonic()
        proc = subprocess.Popen(
            [sys.executable, "-m", "rover_bridge", "run", "--params", str(DEFAULT_PROFILE),
             "--autopilot", f"udpout:{LOCAL}:{sock.getsockname()[1]}", "--gcs",
             f"udpout:{LOCAL}:{gcs.getsockname()[1]}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO, env=env)
        got = odometry = None
        bridge_addr = None
        telemetry, next_send, last_heartbeat = Telemetry(), 0.0, -math.inf
        deadline = t0 + 60
        # After the bridge's first HEARTBEAT, the socket answers as an autopilot would (HEARTBEAT at 1 Hz,
        # WHEEL_DISTANCE and ATTITUDE at 50 Hz): the first ODOMETRY at the GCS is when the filter runs.
        while odometry is None and time.monotonic() < deadline:
            select.select([sock, gcs], [], [], 0.02)
            while True:
                try:
                    data, addr = sock.recvfrom(2048)
                except BlockingIOError:
                    break
                if got is None and msg_id(data) == MSG_HEARTBEAT and data[6] == BRIDGE_COMP:
                    got, bridge_addr = time.monotonic(), addr
            while (d := recv_stamped(gcs)) is not None:
                if got is not None and msg_id(d[0]) == MSG_ODOMETRY:
                    odometry = time.monotonic()
            now = time.monotonic()
            if got is not None and bridge_addr is not None and now >= next_send:
                t_s = now - got + 1.0
                kinds: tuple[str, ...] = ("WHEEL_DISTANCE", "ATTITUDE")
                if now - last_heartbeat >= 1.0:
                    kinds, last_heartbeat = ("HEARTBEAT", *kinds), now
                for kind in kinds:
                    sock.sendto(telemetry.frame(kind, t_s), bridge_addr)
                next_send = now + 0.02
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)
        sock.close()
        gcs.close()
        if got is not None and run > 0:  # run 0 only writes the bytecode cache
            times.append(got - t0)
            if odometry is not None:
                odometry_times.append(odometry - t0)
    # Import cost of what `rover_bridge run` imports, from python -X importtime: self time summed by
    # top-level package (these add up to the total), and the cumulative time of a few notable subtrees.
    imp = subprocess.run([sys.executable, "-X", "importtime", "-c",
                          "import rover_bridge.app.cli as c; c.build_parser()"],
                         capture_output=True, text=True, cwd=REPO, env=env)
    self_by_pkg: dict[str, int] = {}
    cumulative: dict[str, int] = {}
    for line in imp.stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|\s*(\S+)", line)
        if m:
            name = m.group(3)
            top = name.split(".")[0]
            self_by_pkg[top] = self_by_pkg.get(top, 0) + int(m.group(1))
            cumulative.setdefault(name, int(m.group(2)))
    total_us = sum(self_by_pkg.values())
    rows = [["process start -> first HEARTBEAT", len(times), statistics.median(times), min(times), max(times)],
            ["process start -> first ODOMETRY (filter built after the first pass)", len(odometry_times),
             statistics.median(odometry_times), min(odometry_times), max(odometry_times)]]
    print_table("6. start-up (seconds)", ["what", "runs", "median_s", "min_s", "max_s"], rows)
    top = sorted(self_by_pkg.items(), key=lambda kv: -kv[1])[:args.top]
    print_table(f"   import time by top-level package (python -X importtime, self times summed; total "
                f"{total_us / 1000.0:.0f} ms, one run)", ["package", "ms", "share"],
                [[k, v / 1000.0, f"{v / total_us:.0%}"] for k, v in top])
    # rover-bridge run imports filterpy (and scipy) when it builds the filter, after its first pass: off the
    # path to the first HEARTBEAT, on the one to the first ODOMETRY.
    later = subprocess.run([sys.executable, "-X", "importtime", "-c", "import filterpy.kalman"],
                           capture_output=True, text=True, cwd=REPO, env=env)
    later_us = sum(int(m.group(1)) for line in later.stderr.splitlines()
                   if (m := re.match(r"import time:\s+(\d+) \|", line)))
    print_table("   imported after the first pass, when the filter is built (rover_bridge.estimate.arc_ekf)",
                ["module", "ms"], [["filterpy.kalman (with scipy, numpy)", later_us / 1000.0]])
    notable = ["filterpy", "filterpy.stats", "scipy.stats", "scipy.linalg", "matplotlib", "numpy", "pymavlink.mavutil",
               "pymavlink.dialects.v20.ardupilotmega", "rover_bridge.estimate.ekf", "rover_bridge.app.commands.demo"]
    print_table("   cumulative import time of notable subtrees (ms; a subtree already imported elsewhere counts 0)",
                ["module", "ms"], [[n, cumulative[n] / 1000.0] for n in notable if n in cumulative])
