"""The bridge under test as a process: this tree's (`python -m rover_bridge run`, or under cProfile, with parts
of its cores stubbed, or with one part of its filter free), another tree's (--base), the plain pymavlink router
it is compared with; and the harness's own helper processes (bench_bridge.py's hidden subcommands).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bridge.harness import (
    AP_COMP,
    AP_SYS,
    AUTOPILOT_SOCKETS,
    GCS_COMP,
    GCS_SYS,
    LOCAL,
    REPO,
    Packer,
    drain,
    free_udp_port,
    heartbeat_ap,
    heartbeat_gcs,
    keep_stamped,
    self_cmd,
    udp_socket,
)
from rover_bridge.mavlink.dialect import mavlink

BENCHMARKS = Path(__file__).resolve().parents[1]  # on sys.path of a bridge under test that imports free_parts

# ------------------------------------------------------------------------------------- the bridge under test

_CPROFILE_MAIN = """
import cProfile, sys, time
from rover_bridge.app.cli import main
pr = cProfile.Profile(time.process_time)
pr.enable()
try:
    code = main(sys.argv[1:])
finally:
    pr.disable()
    pr.dump_stats({path!r})
sys.exit(code)
"""
# `cpu --without PART`: this tree's bridge with one part of its filter costing nothing (make_free), in the
# running process: what trimming that part could save at most where the code runs cold.
_WITHOUT_MAIN = """
import sys
sys.path.insert(0, {bench_dir!r})
from bridge.free_parts import make_free
from rover_bridge.app.cli import main
make_free({part!r})
sys.exit(main(sys.argv[1:]))
"""


# `cpu --parts`: this tree's bridge with parts of its cores replaced, to split its CPU. The shell, the
# links, the framer (and the decoding of what the cores read), the forwarding and the heartbeat stay
# the real ones in every variant:
#   routing            both cores stubbed: nothing consumed, only the heartbeats sent (HEARTBEAT still
#                      reaches the command core, which says whether the autopilot is there)
#   routing + outputs  as routing, plus constant RC_CHANNELS_OVERRIDE at 50 Hz to the autopilot and
#                      ODOMETRY at 30 Hz to the GCS (the nominal load's own outputs), on their own grids
#                      (ODOMETRY, as the real one, also early in a pass made anyway: OdometryPublisher)
#   command flow only  the real command core (requests, limiter, IK, overrides); the estimate core stubbed
#   estimate flow only the real estimate core (wheels, gyro, EKF, ODOMETRY); the command core stubbed
#   free estimator     the real command core, and an estimate core that costs nothing: what it reads is
#                      still decoded and handed to it, it answers with a constant ODOMETRY at 30 Hz (the
#                      bound for any faster estimator behind this shell, native code included)
STUBS: dict[str, str] = {"routing": "cores stubbed: routing", "outputs": "cores stubbed: routing + outputs",
                         "command": "command flow only", "estimate": "estimate flow only",
                         "free_estimator": "command flow + free estimator"}
_STUB_MAIN = """
import sys
from rover_bridge.app import composition
from rover_bridge.app.cli import main
from rover_bridge.command.core import CommandCore
from rover_bridge.estimate.core import EstimateCore
from rover_bridge.estimate.publish import EARLY_FRACTION
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import NOTHING, Link, Outgoing
STUB = {stub!r}
HB = mavlink.MAVLINK_MSG_ID_HEARTBEAT
def stub_core(cls, keep_heartbeat):
    handle = cls.handle
    cls.handle = ((lambda self, inc, now_s: handle(self, inc, now_s) if inc.msg.get_msgId() == HB else NOTHING)
                  if keep_heartbeat else (lambda self, inc, now_s: NOTHING))
    cls.tick = lambda self, now_s: []
    cls.next_deadline_s = lambda self, now_s: now_s + 1.0
grid = [0.0, 0.0]
odometry = mavlink.MAVLink_odometry_message(0, 1, 8, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                                            0.0, 0.0, 0.0, [0.0] * 21, [0.0] * 21, 0, 0, 100)
EARLY_S = EARLY_FRACTION / 30.0
def odometry_tick(now_s):  # as OdometryPublisher: on a 30 Hz grid, sent early in a pass made anyway
    if now_s < grid[1] - EARLY_S:
        return []
    grid[1] = max(grid[1] + 1.0 / 30.0, now_s)
    return [Outgoing(Link.GCS, odometry, 1, 197)]
def odometry_stub():
    EstimateCore.odometry_due = lambda self, now_s: odometry_tick(now_s)
    EstimateCore.next_early_s = lambda self, now_s: grid[1] - EARLY_S
if STUB == "command":
    stub_core(EstimateCore, False)
elif STUB == "free_estimator":
    stub_core(EstimateCore, False)
    odometry_stub()
    EstimateCore.tick = lambda self, now_s: odometry_tick(now_s)
    EstimateCore.next_deadline_s = lambda self, now_s: grid[1]
elif STUB == "estimate":
    stub_core(CommandCore, True)
else:
    stub_core(EstimateCore, False)
    stub_core(CommandCore, True)
    override = mavlink.MAVLink_rc_channels_override_message(1, 1, 1500, 65535, 1500, *([65535] * 15))
    def outputs_tick(self, now_s):
        out = []
        if now_s >= grid[0]:
            grid[0] = max(grid[0] + 0.02, now_s)
            out.append(Outgoing(Link.AUTOPILOT, override, 255, 190))
        return out + odometry_tick(now_s)
    if STUB == "outputs":
        odometry_stub()
        CommandCore.tick = outputs_tick
        CommandCore.next_deadline_s = lambda self, now_s: min(grid)
sys.exit(main(sys.argv[1:]))
"""


class Bridge:
    """`python -m rover_bridge run` with both links `udpin:` so the harness sockets are its peers."""

    def __init__(self, profile_path: str, workdir: str, name: str = "bridge", root: Path = REPO,
                 stub: str | None = None, prefix: list[str] | None = None,
                 env_extra: dict[str, str] | None = None, without: str | None = None) -> None:
        self.name = name
        self.ap_port, self.gcs_port = free_udp_port(), free_udp_port()
        self.ap_addr, self.gcs_addr = (LOCAL, self.ap_port), (LOCAL, self.gcs_port)
        self.stats_path = os.path.join(workdir, f"{name}-stats.json")
        self.log_path = os.path.join(workdir, f"{name}.log")
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop()
        # BENCH_CPROFILE=PATH runs the bridge of this tree under cProfile timed in CPU time (not wall
        # time, which on a busy machine charges other processes' time slices to whatever was running).
        # Another of this tree's bridges in the same run (cpu --sectors) writes to PATH.<its name>.
        prof = os.environ.get("BENCH_CPROFILE") if root == REPO else None
        if prof and name != "bridge":
            prof = f"{prof}.{re.sub(r'[^A-Za-z0-9]+', '_', name).strip('_')}"
        python = [sys.executable, *(["-c", _CPROFILE_MAIN.format(path=prof)] if prof else ["-m", "rover_bridge"])]
        if stub is not None:  # `cpu --parts`: one of STUBS
            python = [sys.executable, "-c", _STUB_MAIN.format(stub=stub)]
        if without is not None:  # `cpu --without`: one of free_parts.WITHOUT
            python = [sys.executable, "-c", _WITHOUT_MAIN.format(bench_dir=str(BENCHMARKS), part=without)]
        # BENCH_PREFIX="chrt -f 10" (or "nice -n -10") runs every bridge under test that way: what a
        # real-time priority (e.g. systemd's CPUSchedulingPolicy=) buys on a busy machine.
        # `prefix` (contention: the unit's scheduling) replaces BENCH_PREFIX.
        python = [*(os.environ.get("BENCH_PREFIX", "").split() if prefix is None else prefix), *python]
        self.proc = subprocess.Popen(
            [*python, "run", "--params", profile_path,
             "--autopilot", f"udpin:{LOCAL}:{self.ap_port}", "--gcs", f"udpin:{LOCAL}:{self.gcs_port}",
             "--stats-json", self.stats_path],
            stdout=self._log, stderr=subprocess.STDOUT, cwd=root, env={**bridge_env(root), **(env_extra or {})})

    def wait_up(self, ap: socket.socket, gcs: socket.socket, timeout_s: float = 60.0,
                ap_frames: list[tuple[bytes, float]] | None = None) -> None:
        """Introduce both harness sockets (udpin learns its peers) until the bridge talks to both.
        With `ap_frames`, what the bridge sends the autopilot meanwhile is kept (datagram, kernel stamp)."""
        AUTOPILOT_SOCKETS.add(ap)
        hb_ap, hb_gcs = Packer(AP_SYS, AP_COMP), Packer(GCS_SYS, GCS_COMP)
        deadline = time.monotonic() + timeout_s
        got_ap = got_gcs = False
        next_hb = 0.0
        while not (got_ap and got_gcs):
            now = time.monotonic()
            if now > deadline or self.proc.poll() is not None:
                raise RuntimeError(f"bridge did not come up; see {self.log_path}")
            # Paced by the clock, not by replies: the bridge forwards each GCS heartbeat to the
            # autopilot socket, and answering every wake-up with another pair feeds a ping-pong.
            if now >= next_hb:
                ap.sendto(hb_ap.pack(heartbeat_ap()), self.ap_addr)
                gcs.sendto(hb_gcs.pack(heartbeat_gcs()), self.gcs_addr)
                next_hb = now + 0.1
            select.select([ap, gcs], [], [], 0.1)
            got_ap = got_ap or (drain(ap) if ap_frames is None else keep_stamped(ap, ap_frames)) > 0
            got_gcs = got_gcs or drain(gcs) > 0
        settle = time.monotonic() + 0.5  # let it work off what start-up queued
        while (now := time.monotonic()) < settle:
            select.select([ap, gcs], [], [], settle - now)
            if ap_frames is None:
                drain(ap)
            else:
                keep_stamped(ap, ap_frames)
            drain(gcs)

    def cpu_s(self) -> float:
        """utime + stime of the bridge process so far, seconds."""
        user, system = self.cpu_split_s()
        return user + system

    def cpu_split_s(self) -> tuple[float, float]:
        """(utime, stime) of the bridge process so far, seconds."""
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        tick = os.sysconf("SC_CLK_TCK")
        return int(fields[11]) / tick, int(fields[12]) / tick

    def rss_kb(self) -> int:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise RuntimeError("no VmRSS")

    def stop(self) -> dict[str, Any]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._log.close()
        try:
            stats: dict[str, Any] = json.loads(Path(self.stats_path).read_text())
        except (OSError, ValueError):
            stats = {}
        return stats


def bridge_env(root: Path) -> dict[str, str]:
    """Environment that makes `python -m rover_bridge` import the package under `root` (for --base)."""
    env = dict(os.environ)
    if root != REPO:
        env["PYTHONPATH"] = str(root)
    return env


class PlainRouter(Bridge):
    """Reference: the least a pymavlink program can do with the same traffic - decode every frame
    (recv_msg) and forward it to the other side - and nothing else (no control, no estimator)."""

    def __init__(self, workdir: str, name: str = "pymavlink router") -> None:
        self.name = name
        self.ap_port, self.gcs_port = free_udp_port(), free_udp_port()
        self.ap_addr, self.gcs_addr = (LOCAL, self.ap_port), (LOCAL, self.gcs_port)
        self.stats_path = os.path.join(workdir, f"{name}-stats.json")  # two routers with --sectors
        self.log_path = os.path.join(workdir, f"{name}.log")
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([*os.environ.get("BENCH_PREFIX", "").split(),
                                      *self_cmd("_router", str(self.ap_port), str(self.gcs_port), self.stats_path)],
                                     stdout=self._log, stderr=subprocess.STDOUT, cwd=REPO)


def bridges(args: argparse.Namespace, profile_path: str, workdir: str) -> list[Bridge]:
    """The bridge of this tree, and with --base DIR the one of another tree (e.g. a `git archive` of
    the previous commit) measured alongside it in the same run."""
    out = [Bridge(profile_path, workdir, "bridge")]
    if getattr(args, "base", None):
        out.append(Bridge(profile_path, workdir, "base", root=Path(args.base).resolve()))
    return out


class Heartbeats:
    """Keeps the fake autopilot's (and GCS's) 1 Hz heartbeat going from inside a measuring loop."""

    def __init__(self, ap: socket.socket, bridge: Bridge, gcs: socket.socket | None = None) -> None:
        self.ap, self.gcs, self.bridge = ap, gcs, bridge
        self.ap_packer, self.gcs_packer = Packer(AP_SYS, AP_COMP), Packer(GCS_SYS, GCS_COMP)
        self.next_s = 0.0

    def poll(self, now_s: float) -> None:
        if now_s >= self.next_s:
            self.ap.sendto(self.ap_packer.pack(heartbeat_ap()), self.bridge.ap_addr)
            if self.gcs is not None:
                self.gcs.sendto(self.gcs_packer.pack(heartbeat_gcs()), self.bridge.gcs_addr)
            self.next_s = now_s + 0.5


def stop_all(bridges: Sequence[Any], socks: Sequence[socket.socket]) -> list[Any]:
    """Stop every bridge under test (collecting its stats) and close the harness's sockets."""
    stats = [br.stop() for br in bridges]
    for sock in socks:
        sock.close()
    return stats


# ------------------------------------------------------------------------------------- helper processes

def echo_main(port: int) -> None:
    """A plain pymavlink UDP echo: parse every datagram with pymavlink and send the frame back."""
    from rover_bridge.mavlink.dialect import mavutil
    conn: Any = mavutil.mavlink_connection(f"udpin:{LOCAL}:{port}", dialect="ardupilotmega")
    print("ready", flush=True)
    while True:
        select.select([conn.fd], [], [], 1.0)
        while (m := conn.recv_msg()) is not None:
            conn.write(m.get_msgbuf())


def router_main(ap_port: int, gcs_port: int, stats_path: str) -> None:
    """PlainRouter's process: two pymavlink udpin links, every frame decoded and sent to the other.
    On SIGTERM it writes how often it woke up (as the bridge's `passes`) to `stats_path`."""
    from rover_bridge.mavlink.dialect import mavutil
    ap: Any = mavutil.mavlink_connection(f"udpin:{LOCAL}:{ap_port}", dialect="ardupilotmega")
    gcs: Any = mavutil.mavlink_connection(f"udpin:{LOCAL}:{gcs_port}", dialect="ardupilotmega")
    wakes = 0

    def stop(*_: Any) -> None:
        Path(stats_path).write_text(json.dumps({"runner": {"passes": wakes}}))
        os._exit(0)

    signal.signal(signal.SIGTERM, stop)
    peers = {ap.fd: (ap, gcs), gcs.fd: (gcs, ap)}
    while True:
        readable, _, _ = select.select(list(peers), [], [], 1.0)
        wakes += 1
        for fd in readable:
            src, dst = peers[fd]
            while (m := src.recv_msg()) is not None:
                if m.get_type() != "BAD_DATA":
                    dst.write(m.get_msgbuf())


def flood_main(port: int, rate_hz: float, seconds: float) -> None:
    """A GCS sending `rate_hz` non-request messages (forwarded by the bridge) in 1 ms slots."""
    packer = Packer(GCS_SYS, GCS_COMP)
    kinds = [
        mavlink.MAVLink_param_request_read_message(AP_SYS, AP_COMP, b"WP_SPEED", -1),
        mavlink.MAVLink_timesync_message(0, 12345),
        mavlink.MAVLink_system_time_message(int(time.time() * 1e6), 0),
        mavlink.MAVLink_named_value_float_message(0, b"gcs", 1.0),
    ]
    frames = [packer.pack(kinds[i % len(kinds)]) for i in range(1024)]
    sock = udp_socket()
    dest = (LOCAL, port)
    start = time.monotonic()
    sent = 0
    while (now := time.monotonic()) < start + seconds:
        due = int((now - start) * rate_hz)
        while sent < due:
            sock.sendto(frames[sent % len(frames)], dest)
            sent += 1
        time.sleep(0.001)
    print(sent, flush=True)
