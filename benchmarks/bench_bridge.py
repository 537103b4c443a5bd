"""End-to-end benchmarks of the shipped bridge process (`python -m rover_bridge run`) over UDP loopback.

Subcommands (each prints a table and finishes in under 2 minutes; `all` runs them in turn):

  hotpath      CPU per message of Runner.step in-process, beside raw parse_buffer and BridgeCore.handle alone
  replay       BridgeCore alone on the cpu table's nominal traffic, in-process: ms of CPU per second of traffic
               and us per message kind (warm code, no sockets: the cores' own work, steadier than `cpu`)
  latency      GCS request datagram in -> RC_CHANNELS_OVERRIDE datagram out, next to a pymavlink UDP echo;
               value latency (the first override that shows the request); telemetry forwarding latency
  throughput   autopilot telemetry flood routed to a GCS: highest zero-loss rate, next to raw parse_buffer
  cpu          CPU % of one core at nominal load (50 Hz wheels / IMU / control, 30 Hz ODOMETRY), next to a
               plain pymavlink router; --parts: also the bridge with its cores stubbed (where the CPU goes);
               --without PART: also the bridge with that part of its filter costing nothing (as replay's)
  wakeup       CPU of a Python process that only wakes from select() (what a pass costs before any work)
  regularity   override period jitter at command.rate_hz = 50, quiet and under a 5000 msg/s GCS flood
  contention   the cpu table's nominal load while numpy keeps both cores busy, at normal priority and with the
               systemd unit's scheduling: override periods, deadlines seen from outside beside the bridge's own
               count, request -> override, watchdog ping gaps (2 x 63 s; not in `all`)
  memory       RSS over one million messages (in-process Runner + BridgeCore; --subprocess: the real process)
  startup      process start -> first HEARTBEAT sent; import-time breakdown

Run: python benchmarks/bench_bridge.py all [--base DIR]   (or one subcommand; --help for options)
  --base DIR          also measure the bridge of another source tree side by side, e.g. the previous
                      commit: mkdir /tmp/base && git archive HEAD~1 | tar -x -C /tmp/base
  BENCH_PREFIX=...    run the bridges (and the echo) under e.g. "chrt -f 10" or "nice -n -10"
  BENCH_CPROFILE=P    run this tree's bridge under cProfile (CPU time), stats to P
Not a test: numbers depend on the machine and its load; nothing here asserts on them. Comparisons
(bridge vs echo, bridge vs raw parse, quiet vs flood, this tree vs --base) are measured side by
side in the same run.

The harness fakes the autopilot and the GCS with plain UDP sockets and frames packed once by
pymavlink, so its own cost stays small next to the bridge's. Receive times are the kernel's
(SO_TIMESTAMPNS): on loopback that is when the sender's sendto() queued the datagram, so the
harness's own wake-up delay is not charged to the bridge (nor to the echo).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import logging
import math
import os
import random
import re
import select
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import load_profile

REPO = Path(__file__).resolve().parents[1]
DEFAULT_PROFILE = REPO / "params" / "default.toml"
LOCAL = "127.0.0.1"
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux value; Python does not export it
MSG_OVERRIDE = mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE
MSG_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
MSG_ODOMETRY = mavlink.MAVLINK_MSG_ID_ODOMETRY
MSG_COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK
AP_SYS, AP_COMP = 1, 1
GCS_SYS, GCS_COMP = 255, 190
BRIDGE_COMP = 191
BIG_RCVBUF = 4 * 1024 * 1024  # harness sockets must not be where datagrams are lost


# ------------------------------------------------------------------------------------- helpers

def free_udp_port() -> int:
    """A free port below the kernel's ephemeral range. Test suites running beside us pick ports the
    bind-to-0-and-close way; had we done the same, one of their emulators could be sending to a port
    it once chose and that is now our bridge's (it happened: thousands of foreign heartbeats a second)."""
    while True:
        port = random.randrange(20_000, 32_000)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((LOCAL, port))
            except OSError:
                continue
            return port


def udp_socket(timestamps: bool = False) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BIG_RCVBUF)
    if timestamps:
        s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    s.bind((LOCAL, 0))
    s.setblocking(False)
    return s


def msg_id(frame: bytes) -> int:
    """Message id of a MAVLink 2 frame (-1 for anything else)."""
    if len(frame) < 12 or frame[0] != 0xFD:
        return -1
    return frame[7] | frame[8] << 8 | frame[9] << 16


# Harness sockets that play the autopilot: they answer the bridge's SET_MESSAGE_INTERVAL requests as
# ArduPilot Rover 4.7 does (DENIED for WHEEL_DISTANCE, ACCEPTED otherwise). An autopilot that never
# answers leaves the bridge re-asking, which is a different (start-up) load than the one measured.
AUTOPILOT_SOCKETS: set[socket.socket] = set()
_ACK_PACKER: list[Any] = []


def answer_command(sock: socket.socket, frame: bytes, addr: Any) -> None:
    if sock not in AUTOPILOT_SOCKETS or msg_id(frame) != mavlink.MAVLINK_MSG_ID_COMMAND_LONG:
        return
    payload = frame[10:10 + frame[1]].ljust(33, b"\0")  # MAVLink 2 trims trailing zeros
    param1 = struct.unpack_from("<f", payload, 0)[0]
    command = struct.unpack_from("<H", payload, 28)[0]
    if command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
        return
    result = mavlink.MAV_RESULT_DENIED if int(param1) == 9000 else mavlink.MAV_RESULT_ACCEPTED
    if not _ACK_PACKER:
        _ACK_PACKER.append(Packer(AP_SYS, AP_COMP))
    ack = mavlink.MAVLink_command_ack_message(command, result, 0, 0, frame[5], frame[6])
    sock.sendto(_ACK_PACKER[0].pack(ack), addr)


def recv_stamped(sock: socket.socket) -> tuple[bytes, float] | None:
    """One datagram and its kernel receive time (time.time() seconds), or None if none is queued."""
    try:
        data, anc, _flags, addr = sock.recvmsg(2048, 64)
    except BlockingIOError:
        return None
    answer_command(sock, data, addr)
    for level, kind, payload in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = struct.unpack("qq", payload[:16])
            return data, sec + nsec * 1e-9
    return data, time.time()


def drain(sock: socket.socket) -> int:
    n = 0
    while True:
        try:
            data, addr = sock.recvfrom(4096)
        except BlockingIOError:
            return n
        answer_command(sock, data, addr)
        n += 1


def keep_stamped(sock: socket.socket, out: list[tuple[bytes, float]]) -> int:
    """Every datagram queued on `sock`, with its kernel stamp, appended to `out`; how many."""
    n = 0
    while (got := recv_stamped(sock)) is not None:
        out.append(got)
        n += 1
    return n


def forwarded_frames(buf: bytearray, size: int) -> int:
    """Flood frames in one datagram from the bridge (it packs several forwarded frames into one):
    frames from the emulated autopilot, not the COMMAND_ACKs the harness sent for stream requests."""
    n, i = 0, 0
    while i + 10 <= size and buf[i] == 0xFD:
        if buf[i + 5] == AP_SYS and buf[i + 6] == AP_COMP and buf[i + 7] != mavlink.MAVLINK_MSG_ID_COMMAND_ACK:
            n += 1
        i += 12 + buf[i + 1] + (13 if buf[i + 2] & 1 else 0)
    return n


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (q in 0..100)."""
    ordered = sorted(values)
    k = max(0, min(len(ordered) - 1, math.ceil(q / 100.0 * len(ordered)) - 1))
    return ordered[k]


class Packer:
    """Packs messages as one MAVLink 2 sender would (own ids, incrementing sequence)."""

    def __init__(self, sysid: int, compid: int) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    def pack(self, msg: Any) -> bytes:
        frame = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return frame


def write_profile(overrides: dict[str, str], directory: str) -> str:
    """A copy of params/default.toml with `section.key` values replaced (TOML text given verbatim)."""
    section = ""
    lines = []
    for line in DEFAULT_PROFILE.read_text(encoding="utf-8").splitlines():
        m = re.match(r"\s*\[(\w+)\]", line)
        if m:
            section = m.group(1)
        kv = re.match(r"\s*#?\s*(\w+)\s*=", line)
        if kv and f"{section}.{kv.group(1)}" in overrides:
            line = f"{kv.group(1)} = {overrides[section + '.' + kv.group(1)]}"
        lines.append(line)
    path = os.path.join(directory, "bench.toml")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# ------------------------------------------------------------------------------------- messages

def heartbeat_ap(armed: bool = True) -> Any:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             base, 0, mavlink.MAV_STATE_ACTIVE, 3)


def heartbeat_gcs() -> Any:
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)


def body_velocity_request(t_ms: int, vx: float, yaw_rate: float) -> Any:
    # MAV_FRAME_BODY_NED velocity + yaw rate: the request the bridge consumes and answers with an override.
    return mavlink.MAVLink_set_position_target_local_ned_message(
        t_ms, AP_SYS, AP_COMP, 8, 0b0000_0101_1100_0111, 0, 0, 0, vx, 0, 0, 0, 0, 0, 0, yaw_rate)


class Telemetry:
    """A consistent ArduPilot-like telemetry stream of a rover driving an arc (stamps from sim time)."""

    V_M_S, OMEGA_RAD_S, TRACK_M = 0.4, 0.2, 0.30

    def __init__(self) -> None:
        self.packer = Packer(AP_SYS, AP_COMP)

    def _state(self, t_s: float) -> tuple[float, float, float]:
        left = (self.V_M_S - self.OMEGA_RAD_S * self.TRACK_M / 2) * t_s
        right = (self.V_M_S + self.OMEGA_RAD_S * self.TRACK_M / 2) * t_s
        return left, right, self.OMEGA_RAD_S * t_s

    def frame(self, kind: str, t_s: float) -> bytes:
        left, right, yaw_ccw = self._state(t_s)
        ms, us = int(t_s * 1000), int(t_s * 1e6)
        yaw_cw = math.remainder(-yaw_ccw, 2 * math.pi)
        msg: Any
        if kind == "WHEEL_DISTANCE":
            msg = mavlink.MAVLink_wheel_distance_message(us, 2, [left, right] + [0.0] * 14)
        elif kind == "ATTITUDE":
            msg = mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, yaw_cw, 0.0, 0.0, -self.OMEGA_RAD_S)
        elif kind == "RAW_IMU":
            msg = mavlink.MAVLink_raw_imu_message(us, 0, 0, -1000, 0, 0, int(-self.OMEGA_RAD_S * 1000), 200, 0, 400)
        elif kind == "SYS_STATUS":
            msg = mavlink.MAVLink_sys_status_message(0x3F, 0x3F, 0x3F, 250, 12000, 150, 80, 0, 0, 0, 0, 0, 0)
        elif kind == "GPS_RAW_INT":
            msg = mavlink.MAVLink_gps_raw_int_message(us, 3, 473977420, 85455940, 100000, 90, 120, 40, 1800, 12)
        elif kind == "VFR_HUD":
            msg = mavlink.MAVLink_vfr_hud_message(self.V_M_S, self.V_M_S, int(math.degrees(yaw_cw)) % 360, 40,
                                                  100.0, 0.0)
        elif kind == "SERVO_OUTPUT_RAW":
            msg = mavlink.MAVLink_servo_output_raw_message(us & 0xFFFFFFFF, 0, 1600, 1500, 1640, 1500, 0, 0, 0, 0)
        elif kind == "GLOBAL_POSITION_INT":
            msg = mavlink.MAVLink_global_position_int_message(ms, 473977420, 85455940, 100000, 0, 40, 0, 0,
                                                              int(math.degrees(yaw_cw) * 100) % 36000)
        elif kind == "SYSTEM_TIME":
            msg = mavlink.MAVLink_system_time_message(int(time.time() * 1e6), ms)
        elif kind == "HEARTBEAT":
            msg = heartbeat_ap()
        else:  # pragma: no cover - programming error
            raise ValueError(kind)
        return self.packer.pack(msg)


FLOOD_MIX = ("ATTITUDE", "WHEEL_DISTANCE", "SYS_STATUS", "GPS_RAW_INT", "VFR_HUD", "SERVO_OUTPUT_RAW",
             "RAW_IMU", "GLOBAL_POSITION_INT", "SYSTEM_TIME", "HEARTBEAT")


def flood_frames(count: int, rate_hz: float, t0_s: float = 100.0) -> list[bytes]:
    """`count` frames of the mixed telemetry, stamped as if sent at `rate_hz`."""
    tel = Telemetry()
    return [tel.frame(FLOOD_MIX[i % len(FLOOD_MIX)], t0_s + i / rate_hz) for i in range(count)]


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
# `cpu --without PART`: this tree's bridge with one part of its filter costing nothing (_without), in the
# running process: what trimming that part could save at most where the code runs cold.
_WITHOUT_MAIN = """
import sys
sys.path.insert(0, {bench_dir!r})
from bench_bridge import _without
from rover_bridge.app.cli import main
_without({part!r})
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
        prof = os.environ.get("BENCH_CPROFILE") if root == REPO else None
        python = [sys.executable, *(["-c", _CPROFILE_MAIN.format(path=prof)] if prof else ["-m", "rover_bridge"])]
        if stub is not None:  # `cpu --parts`: one of STUBS
            python = [sys.executable, "-c", _STUB_MAIN.format(stub=stub)]
        if without is not None:  # `cpu --without`: one of WITHOUT
            python = [sys.executable, "-c", _WITHOUT_MAIN.format(bench_dir=str(Path(__file__).parent), part=without)]
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
        self.stats_path = os.path.join(workdir, "router-stats.json")
        self.log_path = os.path.join(workdir, "router.log")
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


def print_table(title: str, header: list[str], rows: list[list[Any]]) -> None:
    print(f"\n# {title}")
    cells = [header] + [[f"{c:.3f}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for r in cells:
        print("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))))


def self_cmd(*args: str) -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), *args]


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


# ------------------------------------------------------------------------------------- 1. latency

def wait_for(sock: socket.socket, want: Callable[[bytes], bool], timeout_s: float) -> float | None:
    """Kernel receive time of the first datagram on `sock` that `want`s, or None on timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        while (got := recv_stamped(sock)) is not None:
            if want(got[0]):
                return got[1]
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        select.select([sock], [], [], left)


def bench_latency(args: argparse.Namespace) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        under_test = bridges(args, str(DEFAULT_PROFILE), tmp)
        echo_port = free_udp_port()
        # The echo runs under the same BENCH_PREFIX as the bridges, so the comparison stays fair.
        echo = subprocess.Popen([*os.environ.get("BENCH_PREFIX", "").split(), *self_cmd("_echo", str(echo_port))],
                                stdout=subprocess.PIPE, cwd=REPO)
        socks = [(udp_socket(True), udp_socket()) for _ in under_test]
        echo_sock = udp_socket(True)
        stats: list[dict[str, Any]] = []
        is_override: Callable[[bytes], bool] = lambda f: msg_id(f) == MSG_OVERRIDE  # noqa: E731
        any_frame: Callable[[bytes], bool] = lambda f: True  # noqa: E731
        # (name, send socket, destination, receive socket, which frames count as the answer)
        paths = [(f"{br.name}: request -> override", gcs, br.gcs_addr, ap, is_override)
                 for br, (ap, gcs) in zip(under_test, socks, strict=True)]
        paths.append(("pymavlink echo: round trip", echo_sock, (LOCAL, echo_port), echo_sock, any_frame))
        samples: list[list[float]] = [[] for _ in paths]
        lost = [0] * len(paths)
        try:
            assert echo.stdout is not None
            echo.stdout.readline()
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                br.wait_up(ap, gcs)
            beats = [Heartbeats(ap, br, gcs) for br, (ap, gcs) in zip(under_test, socks, strict=True)]
            packer = Packer(GCS_SYS, GCS_COMP)
            next_slot = time.monotonic()
            for i in range(args.requests + 50):  # the first 50 warm up (caches, branch state)
                now = time.monotonic()
                for hb in beats:
                    hb.poll(now)
                for _ap, gcs in socks:
                    drain(gcs)
                frame = packer.pack(body_velocity_request(i, 0.3 + 0.1 * (i % 3), 0.0))
                k = i % len(paths)  # rotate who goes first: no systematic bias from the order
                for which in [*range(k, len(paths)), *range(k)]:
                    _name, tx, dest, rx, want = paths[which]
                    t0 = time.time()
                    tx.sendto(frame, dest)
                    t1 = wait_for(rx, want, 0.5)
                    if i < 50:
                        continue
                    if t1 is None:
                        lost[which] += 1
                    else:
                        samples[which].append((t1 - t0) * 1e6)
                next_slot += args.interval_ms / 1000.0
                pause = next_slot - time.monotonic()
                if pause > 0:
                    time.sleep(pause)
                for ap, _gcs in socks:
                    drain(ap)
        finally:
            echo.kill()
            echo.wait()
            stats = stop_all(under_test, [sock for pair in socks for sock in pair])
            echo_sock.close()
    rows = [[name, len(xs), n_lost, pct(xs, 50), pct(xs, 99), max(xs)]
            for (name, *_rest), xs, n_lost in zip(paths, samples, lost, strict=True)]
    print_table(f"1. latency, {args.requests} requests, one every {args.interval_ms} ms, microseconds "
                "(kernel receive stamps)", ["path", "n", "lost", "p50_us", "p99_us", "max_us"], rows)
    echo_p99 = pct(samples[-1], 99)
    for (name, *_rest), xs in zip(paths[:-1], samples[:-1], strict=True):
        p99 = pct(xs, 99)
        ratio = p99 / echo_p99
        print(f"{name.split(':')[0]}: p99 / echo p99 = {ratio:.2f}  (target: p99 <= 1000 us "
              f"[{'met' if p99 <= 1000 else 'MISSED'}], <= 3x echo [{'met' if ratio <= 3 else 'MISSED'}])")
    for br, st in zip(under_test, stats, strict=True):
        print(f"{br.name} counters: accepted {st.get('command', {}).get('requests.accepted')}, "
              f"outputs {st.get('command', {}).get('outputs.sent')}")
    value_latency(args)
    forward_latency(args)


def collect_overrides(sock: socket.socket, parser: Any, out: list[tuple[float, int]]) -> None:
    """Every RC_CHANNELS_OVERRIDE queued on `sock`: (kernel stamp, left PWM)."""
    while (got := recv_stamped(sock)) is not None:
        for m in parser.parse_buffer(got[0]) or []:
            if m.get_msgId() == MSG_OVERRIDE:
                out.append((got[1], int(m.chan1_raw)))


def straight_pwm(v_m_s: float) -> float:
    """The default profile's PWM for driving straight at v (its linear map, no speed curve)."""
    prof = load_profile(DEFAULT_PROFILE)
    trim, span = prof.output.pwm_trim, prof.output.pwm_max - prof.output.pwm_trim
    return trim + span * v_m_s / prof.robot.left_radius_m / prof.robot.max_wheel_rad_s


def value_latency(args: argparse.Namespace) -> None:
    """A GCS alternating 0.2 and 0.3 m/s every 35-65 ms (random spacing, fixed seed); every override
    captured with its kernel stamp. Per request: the first override after it (any value), and the first
    one that moved toward it (left PWM above / below the last override before the request); never
    reflected = no such override before the next request."""
    rng = random.Random(7)
    spacing = [rng.uniform(0.035, 0.065) for _ in range(args.value_requests)]
    with tempfile.TemporaryDirectory() as tmp:
        under_test = bridges(args, str(DEFAULT_PROFILE), tmp)
        rows = []
        for br in under_test:
            ap, gcs = udp_socket(True), udp_socket()
            parser = mavlink.MAVLink(None)
            overrides: list[tuple[float, int]] = []  # (kernel stamp, left PWM)
            requests: list[tuple[float, float]] = []  # (send time, v)
            try:
                br.wait_up(ap, gcs)
                hb = Heartbeats(ap, br, gcs)
                packer = Packer(GCS_SYS, GCS_COMP)

                start = time.monotonic() + 1.0  # the first second warms up
                t_next = start
                for i, gap in enumerate(spacing):
                    while (now := time.monotonic()) < t_next:
                        hb.poll(now)
                        collect_overrides(ap, parser, overrides)
                        select.select([ap], [], [], min(0.005, t_next - now))
                    v = 0.2 if i % 2 == 0 else 0.3
                    t_sent = time.time()
                    gcs.sendto(packer.pack(body_velocity_request(i, v, 0.0)), br.gcs_addr)
                    requests.append((t_sent, v))
                    t_next += gap
                end = time.monotonic() + 0.2
                while time.monotonic() < end:
                    collect_overrides(ap, parser, overrides)
                    time.sleep(0.005)
            finally:
                br.stop()
                ap.close()
                gcs.close()
            first, moved = [], []
            never = 0
            for k, (t_req, v) in enumerate(requests[1:], start=1):
                t_end = requests[k + 1][0] if k + 1 < len(requests) else math.inf
                before = [pwm for t, pwm in overrides if t < t_req]
                after = [(t, pwm) for t, pwm in overrides if t_req <= t < t_end]
                if not before or not after:
                    never += 1
                    continue
                first.append((after[0][0] - t_req) * 1e3)
                # Toward the request from where the wheels were (not from the previous request: the rover
                # may not have reached it); already there counts as shown at once.
                goal = straight_pwm(v)
                if abs(goal - before[-1]) < 1.0:
                    moved.append(first[-1])
                    continue
                up = goal > before[-1]
                hit = next((t for t, pwm in after if (pwm > before[-1]) == up and pwm != before[-1]), None)
                if hit is None:
                    never += 1
                else:
                    moved.append((hit - t_req) * 1e3)
            rows.append([br.name, len(requests) - 1, pct(first, 50), pct(first, 99), pct(moved, 50), pct(moved, 99),
                         never])
    print_table(f"1b. value latency: {args.value_requests} requests alternating 0.2 / 0.3 m/s every 35-65 ms; "
                "ms from the request to the first override, and to the first that moved toward it",
                ["bridge", "n", "first_p50_ms", "first_p99_ms", "moved_p50_ms", "moved_p99_ms", "never_reflected"],
                rows)


def collect_forwarded(sock: socket.socket, got: dict[int, float]) -> None:
    """The VFR_HUD frames of forward_latency queued on `sock`: their number (airspeed) -> kernel stamp."""
    while (item := recv_stamped(sock)) is not None:
        data, stamp = item
        i = 0
        while i + 10 <= len(data) and data[i] == 0xFD:  # every frame of the datagram
            if data[i + 7] == mavlink.MAVLINK_MSG_ID_VFR_HUD and data[i + 5] == AP_SYS:
                got.setdefault(round(struct.unpack_from("<f", data[i:i + 14].ljust(14, b"\0"), 10)[0]), stamp)
            i += 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)


def forward_latency(args: argparse.Namespace) -> None:
    """Telemetry alone (VFR_HUD, forwarded raw) every 15-25 ms (random spacing, fixed seed) and nothing
    else: no request wakes the bridge, so a frame waits for the batch (mavlink.autopilot_batch_ms) at
    most. Per frame: its send time to the kernel stamp of the datagram that brought it to the GCS."""
    rng = random.Random(11)
    spacing = [rng.uniform(0.015, 0.025) for _ in range(args.forward_frames)]
    mav = mavlink.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
    frames = []
    for i in range(len(spacing)):
        frames.append(bytes(mavlink.MAVLink_vfr_hud_message(float(i + 1), 0.0, 0, 0, 0.0, 0.0).pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    with tempfile.TemporaryDirectory() as tmp:
        under_test = bridges(args, str(DEFAULT_PROFILE), tmp)
        rows = []
        for br in under_test:
            ap, gcs = udp_socket(), udp_socket(True)
            sent: dict[int, float] = {}
            got: dict[int, float] = {}
            try:
                br.wait_up(ap, gcs)
                hb = Heartbeats(ap, br, gcs)
                t_next = time.monotonic() + 1.0
                for i, gap in enumerate(spacing):
                    while (now := time.monotonic()) < t_next:
                        hb.poll(now)
                        collect_forwarded(gcs, got)
                        drain(ap)
                        select.select([gcs], [], [], min(0.005, t_next - now))
                    sent[i + 1] = time.time()
                    ap.sendto(frames[i], br.ap_addr)
                    t_next += gap
                end = time.monotonic() + 0.3
                while time.monotonic() < end:
                    collect_forwarded(gcs, got)
                    time.sleep(0.005)
            finally:
                br.stop()
                ap.close()
                gcs.close()
            lat = [(got[k] - t) * 1e3 for k, t in sent.items() if k in got]
            rows.append([br.name, len(sent), len(sent) - len(lat), pct(lat, 50), pct(lat, 99), max(lat)])
    print_table(f"1c. telemetry forwarding: {args.forward_frames} autopilot frames every 15-25 ms and nothing "
                "else; ms from the send to the GCS's kernel stamp", ["bridge", "n", "lost", "p50_ms", "p99_ms",
                                                                   "max_ms"], rows)


# ------------------------------------------------------------------------------------- 2. throughput

def offer(bridge: Bridge, ap: socket.socket, gcs: socket.socket, frames: list[bytes],
          rate_hz: float | None) -> tuple[int, int, float, float]:
    """Send `frames` to the bridge at `rate_hz` (None: as fast as possible) in 1 ms slots; count
    the forwarded ones arriving at the GCS socket. Returns (sent, received, seconds spent sending,
    CPU seconds the bridge used meanwhile)."""
    dest = bridge.ap_addr
    received = 0
    n = len(frames)
    sent = 0
    buf = bytearray(2048)

    def collect() -> int:
        got = 0
        while True:
            try:
                k = gcs.recv_into(buf)
            except BlockingIOError:
                return got
            # Forwarded flood frames only (not the harness's COMMAND_ACKs to the bridge's stream requests).
            got += forwarded_frames(buf, k)
    cpu0 = bridge.cpu_s()
    start = time.monotonic()
    if rate_hz is None:
        for f in frames:
            ap.sendto(f, dest)
            sent += 1
            if sent % 64 == 0:
                received += collect()
    else:
        while sent < n:
            due = min(n, int((time.monotonic() - start) * rate_hz) + 1)
            while sent < due:
                ap.sendto(frames[sent], dest)
                sent += 1
            received += collect()
            time.sleep(0.0005)
    spent = time.monotonic() - start
    quiet_until = time.monotonic() + 0.3
    while time.monotonic() < quiet_until:
        select.select([gcs], [], [], 0.05)
        got = collect()
        if got:
            received += got
            quiet_until = time.monotonic() + 0.3
    drain(ap)
    return sent, received, spent, bridge.cpu_s() - cpu0


def parse_rate(frames: list[bytes]) -> float:
    """pymavlink's own parse_buffer, one datagram at a time (as a UDP receiver must), messages per
    CPU second (CPU, not wall, time: the bridge's cost below is CPU time too)."""
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True  # as the bridge's links parse
    t0 = time.process_time()
    n = 0
    for f in frames:
        got = mav.parse_buffer(f)
        n += len(got) if got else 0
    return n / max(1e-9, time.process_time() - t0)


def zero_loss_search(bridge: Bridge, ap: socket.socket, gcs: socket.socket, args: argparse.Namespace,
                     frames_for: Callable[[float], list[bytes]], rows: list[list[Any]]) -> float:
    """Raise the offered rate by 1.5x until something is lost, then bisect; the best rate without loss."""
    best_ok, lo, hi = 0.0, 0.0, None
    rate = args.start_hz
    for _ in range(args.max_steps):
        sent, received, spent, cpu = offer(bridge, ap, gcs, frames_for(rate), rate)
        rows.append([bridge.name, f"{rate:.0f}", sent, received, sent - received, sent / spent,
                     cpu / max(1, received) * 1e6])
        if received >= sent:
            best_ok, lo = rate, rate
        else:
            hi = rate
        if hi is None:
            rate *= 1.5
        elif hi - lo <= max(250.0, 0.05 * hi):
            break
        else:
            rate = (lo + hi) / 2
    return best_ok


def bench_throughput(args: argparse.Namespace) -> None:
    step_s = args.step_s
    rows: list[list[Any]] = []
    parse_rates: list[float] = []
    best: dict[str, list[float]] = {}
    stats: list[dict[str, Any]] = []

    def frames_for(rate: float) -> list[bytes]:
        frames = flood_frames(int(rate * step_s), rate)
        parse_rates.append(parse_rate(frames))  # the raw rate, on these very bytes, between bridge runs
        return frames

    with tempfile.TemporaryDirectory() as tmp:
        under_test = [*bridges(args, str(DEFAULT_PROFILE), tmp), PlainRouter(tmp)]
        socks = [(udp_socket(), udp_socket()) for _ in under_test]
        try:
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                br.wait_up(ap, gcs)
                offer(br, ap, gcs, flood_frames(2000, 2000.0), 2000.0)  # warm up
            for _rep in range(args.repeats):
                for br, (ap, gcs) in zip(under_test, socks, strict=True):
                    best.setdefault(br.name, []).append(zero_loss_search(br, ap, gcs, args, frames_for, rows))
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                frames = frames_for(60_000.0)
                sent, received, spent, cpu = offer(br, ap, gcs, frames, None)
                rows.append([br.name, "max", sent, received, sent - received, sent / spent,
                             cpu / max(1, received) * 1e6])
        finally:
            stats = stop_all(under_test, [sock for pair in socks for sock in pair])
    print_table(f"2. throughput: mixed autopilot telemetry ({len(FLOOD_MIX)} types, one per datagram) -> bridge -> "
                f"GCS, {step_s:.0f} s per step",
                ["bridge", "offered_hz", "sent", "received", "lost", "achieved_send_hz", "bridge_cpu_us_per_msg"], rows)
    raw = statistics.median(parse_rates)
    print(f"pymavlink parse_buffer (same frames, same run): median {raw:,.0f} msg/s "
          f"(min {min(parse_rates):,.0f}, max {max(parse_rates):,.0f}, {len(parse_rates)} runs)")
    for name in best:
        # Loaded steps only: at low rates the fixed cost of timers and wake-ups dominates the per-message figure.
        cpu_us = statistics.median([r[6] for r in rows if r[0] == name and (r[1] == "max" or float(r[1]) >= 3000)])
        print(f"{name}: median bridge CPU per forwarded message {cpu_us:.1f} us = capacity {1e6 / cpu_us:,.0f} msg/s "
              f"per CPU second = {1e6 / cpu_us / raw:.0%} of raw parse (raw parse: {1e6 / raw:.1f} us/msg)")
    for name, rates in best.items():
        share = statistics.median(rates) / raw
        print(f"{name}: highest zero-loss rate, median of {len(rates)}: {statistics.median(rates):,.0f} msg/s "
              f"({', '.join(f'{r:,.0f}' for r in rates)}) = {share:.0%} of raw parse "
              f"(target >= 40% [{'met' if share >= 0.4 else 'MISSED'}])")
    for br, st in zip(under_test, stats, strict=True):
        if st.get("links"):
            print(f"{br.name} link counters:", json.dumps(st["links"]))


# ------------------------------------------------------------------------------------- 3. cpu

NOMINAL_AP = (("WHEEL_DISTANCE", 50.0), ("ATTITUDE", 50.0), ("RAW_IMU", 50.0), ("VFR_HUD", 10.0),
              ("GLOBAL_POSITION_INT", 10.0), ("SERVO_OUTPUT_RAW", 10.0), ("GPS_RAW_INT", 5.0),
              ("SYS_STATUS", 2.0), ("SYSTEM_TIME", 2.0), ("HEARTBEAT", 1.0))


def nominal_schedule(seconds: float, t0_s: float) -> Iterator[tuple[float, str]]:
    """(time offset, what) events of the nominal load, in time order."""
    events: list[tuple[float, str]] = []
    for kind, hz in NOMINAL_AP:
        events += [(k / hz, kind) for k in range(int(seconds * hz))]
    events += [(k / 50.0 + 0.003, "REQUEST") for k in range(int(seconds * 50))]
    events += [(k / 1.0 + 0.5, "GCS_HEARTBEAT") for k in range(int(seconds))]
    events += [(k / 5.0 + 0.1, "GCS_TIMESYNC") for k in range(int(seconds * 5))]
    events.sort()
    yield from events


def bench_cpu(args: argparse.Namespace) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        profile = write_profile({"command.rate_hz": "50.0"}, tmp)
        parts = [Bridge(profile, tmp, name, stub=stub) for stub, name in STUBS.items()] if args.parts else []
        parts += [Bridge(profile, tmp, f"bridge, {part} free", without=part) for part in args.without or ()]
        under_test = [*bridges(args, profile, tmp), *parts, PlainRouter(tmp)]
        socks = [(udp_socket(), udp_socket()) for _ in under_test]
        samples: list[list[tuple[float, float, float]]] = [[] for _ in under_test]
        stats: list[dict[str, Any]] = []
        all_socks = [s for pair in socks for s in pair]
        try:
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                br.wait_up(ap, gcs)
            total = args.warmup_s + args.seconds
            traffic = replay_frames(total)  # built before the clock starts
            start = time.monotonic()
            measure_at = start + args.warmup_s
            measuring = False
            # Who gets an instant's frames first turns with every instant: the first process sent to wakes
            # first and sees its burst whole more often (measured: about 15 % fewer passes, 0.05-0.15x of the
            # router less CPU for the same tree listed first), so a fixed order favours it.
            pairs = list(zip(under_test, socks, strict=True))
            turn, last_offset = 0, None
            for offset, _what, to_gcs_port, frame in traffic:
                if offset != last_offset:
                    turn, last_offset = (turn + 1) % len(pairs), offset
                target = start + offset
                while (now := time.monotonic()) < target:
                    select.select(all_socks, [], [], target - now)
                    for sock in all_socks:
                        drain(sock)
                if not measuring and now >= measure_at:
                    for br, smp in zip(under_test, samples, strict=True):
                        smp.append((time.monotonic(), *br.cpu_split_s()))
                    measuring = True
                # The same bytes go to every bridge under test (sent one after the other).
                for br, (ap, gcs) in pairs[turn:] + pairs[:turn]:
                    if to_gcs_port:
                        gcs.sendto(frame, br.gcs_addr)
                    else:
                        ap.sendto(frame, br.ap_addr)
            for br, smp in zip(under_test, samples, strict=True):
                smp.append((time.monotonic(), *br.cpu_split_s()))
        finally:
            stats = stop_all(under_test, all_socks)
    cpu: list[tuple[float, float, float]] = []  # wall, user, sys over the measured window
    for smp in samples:
        (t0, u0, s0), (t1, u1, s1) = smp[0], smp[-1]
        cpu.append((t1 - t0, u1 - u0, s1 - s0))
    router_pct = (cpu[-1][1] + cpu[-1][2]) / cpu[-1][0] * 100.0  # the PlainRouter is always last
    rows = []
    for br, (wall, user, sys_), st in zip(under_test, cpu, stats, strict=True):
        cpu_pct = (user + sys_) / wall * 100.0
        ratio = cpu_pct / router_pct if router_pct > 0 else math.inf
        is_router = isinstance(br, PlainRouter)
        est, cmd = st.get("estimate", {}), st.get("command", {})
        rows.append([br.name, f"{wall:.1f}", f"{user:.2f}", f"{sys_:.2f}", f"{cpu_pct:.2f}", f"{ratio:.2f}",
                     "-" if is_router else ("met" if ratio <= 1.5 else "MISSED"),
                     est.get("odometry_sent"), cmd.get("outputs.sent"), cmd.get("requests.accepted"),
                     st.get("runner", {}).get("forwarded"), st.get("runner", {}).get("ticks"),
                     st.get("runner", {}).get("passes", "-")])
    print_table("3. CPU at nominal load: WHEEL_DISTANCE, ATTITUDE, RAW_IMU 50 Hz; requests 50 Hz, command.rate_hz 50; "
                "ODOMETRY 30 Hz; other telemetry ~40 Hz; GCS 6 Hz. Target: <= 1.5x the plain pymavlink router "
                "in the same run (x_router)",
                ["bridge", "wall_s", "user_s", "sys_s", "cpu_%_core", "x_router", "target", "odometry", "outputs",
                 "accepted", "forwarded", "ticks", "passes"],
                rows)


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


# ------------------------------------------------------------------------------------- 4b. contention

UNIT = REPO / "deploy" / "rover-bridge.service"
CHRT_POLICY = {"fifo": "-f", "rr": "-r", "batch": "-b", "idle": "-i", "other": "-o"}


def unit_settings() -> dict[str, str]:
    """The [Service] keys of the shipped systemd unit (comments and continuations skipped)."""
    return dict(line.split("=", 1) for line in UNIT.read_text().splitlines()
                if "=" in line and not line.startswith(("#", " ")))


def unit_prefix(settings: dict[str, str]) -> list[str]:
    """The command prefix that runs a process as the unit's scheduling does (CPUSchedulingPolicy=,
    CPUSchedulingPriority=, Nice=)."""
    prefix: list[str] = []
    if "Nice" in settings:
        prefix += ["nice", "-n", settings["Nice"]]
    policy = settings.get("CPUSchedulingPolicy")
    if policy:
        prefix += ["chrt", CHRT_POLICY[policy], settings.get("CPUSchedulingPriority", "0")]
    return prefix


def burn_main(seconds: float, threads: int) -> None:
    """Keep `threads` cores busy for `seconds` with numpy (matrix products release the GIL); prints the
    products done. Started with one BLAS thread each (OPENBLAS_NUM_THREADS=1 and the like)."""
    import threading

    import numpy as np

    a = np.random.default_rng(0).random((192, 192))
    done = [0] * threads
    end = time.monotonic() + seconds

    def work(k: int) -> None:
        while time.monotonic() < end:
            a @ a
            done[k] += 1

    workers = [threading.Thread(target=work, args=(k,)) for k in range(threads)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    print(sum(done), flush=True)


def cpu_idle_fraction(before: list[int], after: list[int]) -> float:
    """The machine's idle share between two /proc/stat 'cpu' lines (idle + iowait over all)."""
    delta = [b - a for a, b in zip(before, after, strict=True)]
    return (delta[3] + delta[4]) / max(1, sum(delta))


def proc_stat_cpu() -> list[int]:
    return [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]


@contextlib.contextmanager
def realtime_harness(priority: int) -> Iterator[bool]:
    """The harness (autopilot and ground station) at a real-time priority above the bridge's while it
    measures: it stands for hardware outside this computer, its traffic and stamps stay on time. False
    (and nothing changed) where the process may not."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, AttributeError, OSError):
        yield False
        return
    try:
        yield True
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def outside_deadlines(stamps: list[float], period_s: float) -> tuple[Any, list[tuple[float, float]]]:
    """The overrides as the autopilot saw them (kernel stamps), accounted by the bridge's own definition
    (rover_bridge.app.deadlines: only written times count, so arrival times find the same ones late):
    the accounting, and (stamp, time past its grid point) of each on-grid override."""
    from rover_bridge.app.deadlines import OVERRIDES, OutputTiming, Schedule
    from rover_bridge.params import Profile

    t = Profile().timing
    out = OutputTiming(Schedule(OVERRIDES, period_s), t.budget_fraction, t.deadline_fraction)
    on_grid = []
    for at in stamps:
        past = out.record(at, at)
        if past is not None:
            on_grid.append((at, past))
    return out, on_grid


def contention_run(name: str, prefix: list[str], profile: str, tmp: str, args: argparse.Namespace,
                   watchdog_usec: int) -> list[Any]:
    """One bridge at the cpu table's nominal load for warm-up + seconds, both cores kept busy by numpy."""
    notify_path = os.path.join(tmp, f"notify-{name}.sock")
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(notify_path)
    notify.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    notify.setblocking(False)
    br = Bridge(profile, tmp, f"bridge-{name}", prefix=prefix,
                env_extra={"NOTIFY_SOCKET": notify_path, "WATCHDOG_USEC": str(watchdog_usec)})
    ap, gcs = udp_socket(True), udp_socket()
    ap_frames: list[tuple[bytes, float]] = []
    pings: list[float] = []
    requests: list[float] = []
    total = args.warmup_s + args.seconds
    burner = None
    try:
        br.wait_up(ap, gcs, ap_frames=ap_frames)
        blas_one = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
        burner = subprocess.Popen(self_cmd("_burn", str(total + 1.0), "2"), stdout=subprocess.PIPE, cwd=REPO,
                                  env={**os.environ, **blas_one})
        traffic = replay_frames(total)
        # The socket queues only net.unix.max_dgram_qlen (10) pings, and nothing read it while the bridge came
        # up: the bridge's later pings were refused meanwhile. Gaps count from here.
        _notify_messages(notify)
        with realtime_harness(args.harness_priority) as rt:
            idle0 = proc_stat_cpu()
            start, traffic_start = time.monotonic(), time.time()
            for offset, what, to_gcs, frame in traffic:
                target = start + offset
                while (now := time.monotonic()) < target:
                    select.select([ap, gcs, notify], [], [], target - now)
                    keep_stamped(ap, ap_frames)
                    drain(gcs)
                    pings += [stamp for data, stamp in _notify_messages(notify) if data == b"WATCHDOG=1"]
                if what == "REQUEST":
                    requests.append(time.time())
                (gcs if to_gcs else ap).sendto(frame, br.gcs_addr if to_gcs else br.ap_addr)
            idle = cpu_idle_fraction(idle0, proc_stat_cpu())
        settle = time.monotonic() + 0.2
        while (now := time.monotonic()) < settle:
            select.select([ap, notify], [], [], settle - now)
            keep_stamped(ap, ap_frames)
            pings += [stamp for data, stamp in _notify_messages(notify) if data == b"WATCHDOG=1"]
    finally:
        stats = br.stop()
        keep_stamped(ap, ap_frames)
        burned = burner.communicate(timeout=30)[0].decode().strip() if burner is not None else "-"
        for sock in (ap, gcs, notify):
            sock.close()
    parser = mavlink.MAVLink(None)
    overrides: list[tuple[float, int]] = []  # (kernel stamp, left channel)
    for data, stamp in ap_frames:
        for m in parser.parse_buffer(data) or []:
            if m.get_msgId() == MSG_OVERRIDE:
                overrides.append((stamp, int(m.chan1_raw)))
    # The stop on SIGTERM (neutral, then release: not periodic outputs, the bridge does not count them).
    first_release = next((i for i, (_, ch) in enumerate(overrides) if ch == 0), len(overrides))
    stamps = [t for t, _ in overrides[:max(0, first_release - 1)]]
    period = 1.0 / args.rate_hz
    outside, on_grid = outside_deadlines(stamps, period)  # the whole run: what the bridge's counters cover
    inside = stats.get("timing", {}).get("overrides", {})
    measured_from = traffic_start + args.warmup_s  # the target's window: after the warm-up
    window = [t for t in stamps if t >= measured_from]
    window_past = [(t, past) for t, past in on_grid if t >= measured_from]
    window_late = [t for t, past in window_past if past > outside.deadline_s]
    periods_ms = [(b - a) * 1e3 for a, b in itertools.pairwise(window)]
    latency_ms: list[float] = []
    k = 0
    for t_req in requests:
        while k < len(stamps) and stamps[k] < t_req:
            k += 1
        if k < len(stamps) and t_req >= measured_from:
            latency_ms.append((stamps[k] - t_req) * 1e3)
    gaps_ms = [(b - a) * 1e3 for a, b in itertools.pairwise(pings)]
    late_pct = 100.0 * len(window_late) / max(1, len(window))
    if window_late:
        print(f"{name}: late overrides at " + ", ".join(f"{t - traffic_start:.2f}" for t in window_late[:20])
              + f" s into the run{' ...' if len(window_late) > 20 else ''}")
    worst_ms = max((past for _, past in window_past), default=0.0) * 1e3
    return [name, " ".join(prefix) or "-", "yes" if rt else "no", f"{100 * (1 - idle):.0f}", burned, len(window),
            f"{pct(periods_ms, 99):.2f}", f"{max(periods_ms):.1f}", len(window_late), f"{late_pct:.3f}",
            f"{worst_ms:.1f}", outside.late, inside.get("late", "-"), inside.get("over_budget", "-"),
            f"{pct(latency_ms, 50):.2f}", f"{pct(latency_ms, 99):.2f}", f"{max(latency_ms):.1f}", len(pings),
            f"{max(gaps_ms):.0f}" if gaps_ms else "-", br.proc.returncode]


def _notify_messages(sock: socket.socket) -> list[tuple[bytes, float]]:
    out: list[tuple[bytes, float]] = []
    keep_stamped(sock, out)
    return out


@contextlib.contextmanager
def autogroup_nice(nice: int | None) -> Iterator[str]:
    """With `nice`, this session's scheduler autogroup (the bench, the bridge and the numpy load share it)
    at that nice while it runs: on a machine shared with other sessions, whose autogroups otherwise split
    the CPU with this one, -20 approximates a machine where only the numpy load competes. Says what held."""
    path = Path("/proc/self/autogroup")
    if nice is None or not path.exists():
        yield path.read_text().strip() if path.exists() else "no autogroup"
        return
    before = path.read_text().split()[-1]
    try:
        path.write_text(str(nice))
    except OSError as exc:
        yield f"autogroup nice not set ({exc.strerror})"
        return
    try:
        yield path.read_text().strip()
    finally:
        path.write_text(before)


def bench_contention(args: argparse.Namespace) -> None:
    settings = unit_settings()
    watchdog_usec = round(float(settings.get("WatchdogSec", "1")) * 1e6)
    modes = [("normal", []), ("unit", unit_prefix(settings))]
    rows = []
    with tempfile.TemporaryDirectory() as tmp, autogroup_nice(args.autogroup_nice) as group:
        profile = write_profile({"command.rate_hz": f"{args.rate_hz}"}, tmp)
        for name, prefix in modes if not args.unit_first else modes[::-1]:
            rows.append(contention_run(name, prefix, profile, tmp, args, watchdog_usec))
    load = os.getloadavg()
    print_table(f"4b. held under load: the cpu table's nominal traffic ({args.rate_hz:.0f} Hz overrides) for "
                f"{args.warmup_s:.0f} + {args.seconds:.0f} s per run while numpy keeps both cores busy (2 threads, "
                f"normal priority); WatchdogSec={watchdog_usec / 1e6:g}. Overrides as the autopilot received them "
                f"(kernel stamps) over the last {args.seconds:.0f} s: period, late (past 95 % of the period after the "
                "grid point, rover_bridge.app.deadlines), request -> the first override after it; over the whole "
                "run (start-up included): late seen from outside beside the bridge's own count (--stats-json); "
                f"machine load average {load[0]:.1f} / {load[1]:.1f} at the end; scheduler group {group}",
                ["sched", "prefix", "harness_rt", "busy_%", "products", "overrides", "period_p99_ms",
                 "period_max_ms", "late", "late_%", "worst_past_ms", "run_late_seen", "run_late_counted",
                 "over_budget", "req_p50_ms", "req_p99_ms", "req_max_ms", "pings", "ping_gap_max_ms", "exit"], rows)
    for row in rows:
        name, late_pct, seen, counted, gap = row[0], float(row[9]), row[11], row[12], row[18]
        agree = "agree" if str(seen) == str(counted) else "DISAGREE"
        target = (f"late {late_pct:.3f} % (target <= 0.1 % [{'met' if late_pct <= 0.1 else 'MISSED'}])"
                  if name == "unit" else f"late {late_pct:.3f} % (reported beside the unit's)")
        gap_ok = gap != "-" and float(gap) <= watchdog_usec / 2e3
        print(f"{name}: {target}; whole run, bridge and bench {agree} ({counted} / {seen}); longest watchdog gap "
              f"{gap} ms (target <= {watchdog_usec / 2e3:.0f} ms [{'met' if gap_ok else 'MISSED'}])")
        if row[19] != 0:  # SIGTERM'd bridges exit 0; 1 is the stop guard's (the loop stood for loop_watchdog_s)
            print(f"{name}: the bridge exited {row[19]} before the end (its log says why): no counters of its own")


# ------------------------------------------------------------------------------------- 5. memory

CHEAP_MIX = ("SYS_STATUS", "GPS_RAW_INT", "VFR_HUD", "SERVO_OUTPUT_RAW", "GLOBAL_POSITION_INT", "HEARTBEAT")


def self_rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def bench_memory(args: argparse.Namespace) -> None:
    if args.subprocess:
        bench_memory_subprocess(args)
    else:
        bench_memory_inprocess(args)


def bench_memory_inprocess(args: argparse.Namespace) -> None:
    """The shipped shell and core in this process (Runner over real UDP endpoints, the same
    read / handle / forward path as the process, minus select()): batches of datagrams are queued
    on the bridge's sockets, then one Runner.step takes them. Fast enough for a million messages
    in under two minutes; the harness allocates everything it sends before the first RSS reading."""
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.app.loop import Runner
    from rover_bridge.mavlink.links import Endpoint
    from rover_bridge.mavlink.wire import Link
    from rover_bridge.params import load_profile

    total = args.warmup + args.messages
    batch = 500
    ap_port, gcs_port = free_udp_port(), free_udp_port()
    ap_ep = Endpoint(f"udpin:{LOCAL}:{ap_port}", Link.AUTOPILOT)
    gcs_ep = Endpoint(f"udpin:{LOCAL}:{gcs_port}", Link.GCS)
    runner = Runner(BridgeCore(load_profile(str(DEFAULT_PROFILE))), ap_ep, [gcs_ep])
    ap, gcs = udp_socket(), udp_socket()
    tel = Telemetry()
    gcs_packer = Packer(GCS_SYS, GCS_COMP)
    gcs.sendto(gcs_packer.pack(heartbeat_gcs()), (LOCAL, gcs_port))
    # Forwarded-only telemetry is prepacked and cycled (the core ignores its stamps); the estimator's
    # inputs are packed as they go, stamped on the simulated clock handed to the runner (3 kHz), so
    # the estimator runs its normal path (stamps never jump back: no "reboots").
    cycle = [tel.frame(CHEAP_MIX[i % len(CHEAP_MIX)], 100.0 + i / 3000.0) for i in range(1200)]
    ekf_kinds = ("WHEEL_DISTANCE", "ATTITUDE", "SYSTEM_TIME")
    requests = [gcs_packer.pack(body_velocity_request(k, 0.1 * k, 0.05 * k)) for k in range(10)]
    rss: list[tuple[int, float, int]] = []
    checkpoints = sorted({args.warmup, *(args.warmup + k * args.messages // 4 for k in range(1, 5))})
    sent = 0
    t_s = 100.0
    start = time.monotonic()
    try:
        while sent < total:
            for i in range(batch):
                n = sent + i
                if n % 50 == 0:
                    gcs.sendto(requests[(n // 50) % 10], (LOCAL, gcs_port))
                elif n % 12 == 1:  # 1/12 of the stream: wheels, attitude, time in turn
                    ap.sendto(tel.frame(ekf_kinds[(n // 12) % 3], t_s + i / 3000.0), (LOCAL, ap_port))
                else:
                    ap.sendto(cycle[n % len(cycle)], (LOCAL, ap_port))
            sent += batch
            t_s += batch / 3000.0
            runner.step(t_s)
            drain(gcs)
            drain(ap)
            if checkpoints and sent >= checkpoints[0]:
                checkpoints.pop(0)
                rss.append((sent, time.monotonic() - start, self_rss_kb()))
    finally:
        runner.close()
        ap.close()
        gcs.close()
    rx = ap_ep.rx_frames + gcs_ep.rx_frames
    base_kb = rss[0][2]
    rows = [[n, f"{t:.1f}", kb / 1024.0, (kb - base_kb) / 1024.0] for n, t, kb in rss]
    print_table(f"5. memory: VmRSS of the Runner + BridgeCore (in-process, real UDP endpoints), 90% forwarded-only "
                f"telemetry, 8% WHEEL_DISTANCE/ATTITUDE/SYSTEM_TIME, 2% requests; first row after {args.warmup:,} "
                "warm-up messages",
                ["messages_sent", "elapsed_s", "rss_mb", "growth_mb"], rows)
    growth = (rss[-1][2] - base_kb) / 1024.0
    measured = rss[-1][0] - rss[0][0]
    print(f"growth over {measured:,} messages after warm-up: {growth:.2f} MB (target < 5 MB "
          f"[{'met' if growth < 5 else 'MISSED'}]); runner received {rx:,} frames "
          f"(rx_bad {ap_ep.rx_bad + gcs_ep.rx_bad}), forwarded {runner.forwarded:,}, consumed {runner.consumed:,}")


def bench_memory_subprocess(args: argparse.Namespace) -> None:
    """Closed loop: at most `window` forwarded frames in flight, so the bridge runs flat out and
    nothing is dropped; the mix is 90% forwarded telemetry (prepacked), 8% WHEEL_DISTANCE / ATTITUDE
    stamped with the real elapsed time (the estimator runs its normal path), 2% velocity requests."""
    total = args.warmup + args.messages
    with tempfile.TemporaryDirectory() as tmp:
        bridge = Bridge(str(DEFAULT_PROFILE), tmp)
        ap, gcs = udp_socket(), udp_socket()
        tel = Telemetry()
        gcs_packer = Packer(GCS_SYS, GCS_COMP)
        cheap = [tel.frame(CHEAP_MIX[i % len(CHEAP_MIX)], 100.0 + i * 0.01) for i in range(1200)]
        requests = [gcs_packer.pack(body_velocity_request(k, 0.1 * k, 0.05 * k)) for k in range(10)]
        rss: list[tuple[int, float, int]] = []
        buf = bytearray(2048)
        sent = fwd_sent = received = lost = 0
        checkpoints = sorted({args.warmup, *(args.warmup + k * args.messages // 4 for k in range(1, 5))})
        try:
            bridge.wait_up(ap, gcs)
            start = time.monotonic()
            last_progress = start
            while sent < total and time.monotonic() - start < args.max_s:
                while sent < total and fwd_sent - received - lost < args.window:
                    if sent % 50 == 0:
                        gcs.sendto(requests[(sent // 50) % 10], bridge.gcs_addr)  # consumed, not forwarded
                    else:
                        if sent % 12 == 1:
                            kind = "WHEEL_DISTANCE" if sent % 24 == 1 else "ATTITUDE"
                            frame = tel.frame(kind, 100.0 + time.monotonic() - start)
                        else:
                            frame = cheap[sent % len(cheap)]
                        ap.sendto(frame, bridge.ap_addr)
                        fwd_sent += 1
                    sent += 1
                    if checkpoints and sent >= checkpoints[0]:
                        checkpoints.pop(0)
                        time.sleep(0.2)  # let it catch up before reading its RSS
                        rss.append((sent, time.monotonic() - start, bridge.rss_kb()))
                select.select([gcs], [], [], 0.05)
                got = 0
                while True:
                    try:
                        k = gcs.recv_into(buf)
                    except BlockingIOError:
                        break
                    got += forwarded_frames(buf, k)
                received += got
                drain(ap)
                now = time.monotonic()
                if got:
                    last_progress = now
                elif now - last_progress > 1.0:  # nothing back for a second: what is in flight is lost
                    lost += fwd_sent - received - lost
                    last_progress = now
            if not rss or rss[-1][0] != sent:
                time.sleep(0.2)
                rss.append((sent, time.monotonic() - start, bridge.rss_kb()))
        finally:
            stats = bridge.stop()
            ap.close()
            gcs.close()
    links = stats.get("links", {})
    rx = sum(v.get("rx", 0) for v in links.values())
    base_kb = rss[0][2]
    rows = [[n, f"{t:.1f}", kb / 1024.0, (kb - base_kb) / 1024.0] for n, t, kb in rss]
    print_table(f"5. memory: bridge VmRSS, closed loop (<= {args.window} in flight), 90% forwarded telemetry, 8% "
                f"WHEEL_DISTANCE/ATTITUDE, 2% requests; first row after {args.warmup:,} warm-up messages",
                ["messages_sent", "elapsed_s", "rss_mb", "growth_mb"], rows)
    growth = (rss[-1][2] - base_kb) / 1024.0
    measured = rss[-1][0] - rss[0][0]
    print(f"growth over {measured:,} messages after warm-up: {growth:.2f} MB (target < 5 MB over 1,000,000 "
          f"[{'met' if growth < 5 and measured >= 1_000_000 else 'MISSED' if growth >= 5 else 'not reached'}]); "
          f"bridge received {rx:,} frames, rx_bad {sum(v.get('rx_bad', 0) for v in links.values())}, "
          f"lost in flight {lost:,}")


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


# ------------------------------------------------------------------------------------- hot path (in-process)

def _load_tree_modules(root: Path) -> tuple[Any, Any]:
    """links and runner modules of another source tree (the rest of the package is this tree's)."""
    import importlib.util
    mods = []
    for name, places in (("links", ("mavlink/links", "links")), ("runner", ("app/loop", "runner"))):
        # This tree's layout (packages by flow) or an older flat one.
        path = next(p for p in (root / "rover_bridge" / f"{place}.py" for place in places) if p.exists())
        spec = importlib.util.spec_from_file_location(f"_base_{name}", path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # dataclasses look their module up there
        spec.loader.exec_module(mod)
        mods.append(mod)
    links_mod, runner_mod = mods
    for shared in ("Endpoint", "RawFrame"):  # the other tree's runner must see its own links' types
        if hasattr(runner_mod, shared) and hasattr(links_mod, shared):
            setattr(runner_mod, shared, getattr(links_mod, shared))
    return links_mod, runner_mod


def bench_hotpath(args: argparse.Namespace) -> None:
    """CPU per message of one Runner.step over datagrams already queued on its UDP socket (no
    scheduling, no wake-ups: the code path alone), beside pymavlink's parse_buffer and BridgeCore.handle
    alone on the same frames; with --base, the shell (links.py + runner.py) of another tree too."""
    from rover_bridge.app import loop as this_runner
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.mavlink import links as this_links
    from rover_bridge.mavlink.wire import Incoming, Link
    from rover_bridge.params import load_profile

    profile = load_profile(str(DEFAULT_PROFILE))
    shells: dict[str, tuple[Any, Any]] = {"bridge": (this_links, this_runner)}
    if args.base:
        shells["base"] = _load_tree_modules(Path(args.base).resolve())
    rigs: dict[str, tuple[Any, socket.socket, socket.socket, tuple[str, int]]] = {}
    for name, (links_mod, runner_mod) in shells.items():
        ap_port, gcs_port = free_udp_port(), free_udp_port()
        ap_ep = links_mod.Endpoint(f"udpin:{LOCAL}:{ap_port}", Link.AUTOPILOT)
        gcs_ep = links_mod.Endpoint(f"udpin:{LOCAL}:{gcs_port}", Link.GCS)
        for ep in (ap_ep, gcs_ep):  # the whole batch must fit, whatever either tree asks for
            ep.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BIG_RCVBUF)
        runner = runner_mod.Runner(BridgeCore(profile), ap_ep, [gcs_ep])
        ap, gcs = udp_socket(), udp_socket()
        gcs.sendto(Packer(GCS_SYS, GCS_COMP).pack(heartbeat_gcs()), (LOCAL, gcs_port))  # the GCS is a peer
        rigs[name] = (runner, ap, gcs, (LOCAL, ap_port))
    batch = args.batch
    frames_all = flood_frames(batch * args.repeats, 3000.0)
    results: dict[str, list[float]] = {"parse": [], "core": [], **{name: [] for name in rigs}}
    core_only = BridgeCore(profile)
    clock = {name: 100.0 for name in rigs}
    for rep in range(args.repeats):
        frames = frames_all[rep * batch:(rep + 1) * batch]
        mav = mavlink.MAVLink(None)
        mav.robust_parsing = True
        c0 = time.process_time()
        msgs = [m for f in frames for m in (mav.parse_buffer(f) or [])]
        results["parse"].append((time.process_time() - c0) / batch * 1e6)
        c0 = time.process_time()
        for i, m in enumerate(msgs):
            core_only.handle(Incoming(Link.AUTOPILOT, m), 100.0 + rep * 0.5 + i / 3000.0)
        results["core"].append((time.process_time() - c0) / batch * 1e6)
        names = list(rigs) if rep % 2 == 0 else list(rigs)[::-1]
        for name in names:
            runner, ap, gcs, dest = rigs[name]
            for f in frames:
                ap.sendto(f, dest)
            clock[name] += 0.5
            c0 = time.process_time()
            runner.step(clock[name])
            results[name].append((time.process_time() - c0) / batch * 1e6)
            drain(gcs)
            drain(ap)
    for runner, ap, gcs, _dest in rigs.values():
        runner.close()
        ap.close()
        gcs.close()
    parse_us = statistics.median(results["parse"])
    rows = [["pymavlink parse_buffer (raw parse)", statistics.median(results["parse"]), min(results["parse"]), "100%"],
            ["BridgeCore.handle alone (decoded messages)", statistics.median(results["core"]),
             min(results["core"]), "-"]]
    for name in rigs:
        med = statistics.median(results[name])
        rows.append([f"{name}: Runner.step (read, handle, forward)", med, min(results[name]), f"{parse_us / med:.0%}"])
        shell = med - statistics.median(results["core"])
        rows.append([f"{name}: the same minus BridgeCore.handle (parse + shell)", shell, "-",
                     f"{parse_us / shell:.0%}"])
    print_table(f"hot path: CPU microseconds per message, {args.repeats} batches of {batch} queued datagrams of the "
                f"throughput mix, in-process", ["what", "median_us", "min_us", "rate_vs_raw_parse"], rows)


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


# ------------------------------------------------------------------------------------- CLI

def replay_frames(seconds: float) -> list[tuple[float, str, bool, bytes]]:
    """(offset, kind, from the GCS, frame) of the cpu table's nominal traffic (nominal_schedule)."""
    tel, gcs = Telemetry(), Packer(GCS_SYS, GCS_COMP)
    out = []
    for offset, what in nominal_schedule(seconds, 0.0):
        if what == "REQUEST":
            frame = gcs.pack(body_velocity_request(int(offset * 1000), 0.4, 0.2 * math.sin(offset)))
        elif what == "GCS_HEARTBEAT":
            frame = gcs.pack(heartbeat_gcs())
        elif what == "GCS_TIMESYNC":
            frame = gcs.pack(mavlink.MAVLink_timesync_message(0, int(offset * 1e9)))
        else:
            frame = tel.frame(what, 100.0 + offset)
        out.append((offset, what, what.startswith("GCS_") or what == "REQUEST", frame))
    return out


WITHOUT = ("judge", "update", "predict", "filterpy")  # replay/cpu --without: the filter's parts that can be made free


def _without(part: str) -> None:
    """Make one part of the filter cost nothing in this process (replay and cpu --without): what trimming it could
    buy at most. judge: the first 50 wheel intervals are judged, every later one gets the 50th's verdict;
    update / predict: filterpy's update / prediction (with the models it runs) are skipped; filterpy: only
    filterpy's own predict and update are (the models still run, the state stays where it started)."""
    from rover_bridge.estimate import arc_ekf, wheel_judge

    if part == "judge":
        real = wheel_judge.WheelJudge.judge
        memo: list[Any] = []

        def judge(self: Any, t_s: float, w: Any, x: Any, P: Any) -> Any:  # noqa: N803
            if len(memo) < 50:
                memo.append(real(self, t_s, w, x, P))
            return memo[-1]
        wheel_judge.WheelJudge.judge = judge  # type: ignore[method-assign]
    elif part == "update":
        arc_ekf.ArcKalmanFilter.update_rows = lambda self, *a, **k: None  # type: ignore[method-assign]
    elif part == "predict":
        arc_ekf.ArcKalmanFilter.predict_arc = lambda self, dt_s: None  # type: ignore[method-assign]
    elif part == "filterpy":
        from filterpy.kalman import KalmanFilter

        KalmanFilter.predict = lambda self, *a, **k: None
        KalmanFilter.update = lambda self, *a, **k: None


def replay_main(seconds: float, repeats: int, without: str | None = None) -> dict[str, Any]:
    """The replay of one tree (the rover_bridge this process imports): what bench_replay prints.

    Passes as the running bridge makes them at this load: the autopilot's frames are read in the pass of
    the next ground-station frame (its link rests between reads, mavlink.autopilot_batch_ms), each handled
    at its own arrival time; then what is due (tick) and what may leave early (ODOMETRY), as Runner.step
    does; a deadline before the next frame is a pass of its own.

    After each pass pymavlink decodes that pass's frames again, timed on its own: the reference. The
    machine's speed can swing 1.5x within a minute here; the cores' time over the reference's (x_ref)
    cancels that, as the cpu table's router does."""
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.mavlink import fastcodec
    from rover_bridge.mavlink.wire import Incoming, Link

    if without is not None:
        _without(without)
    parser = mavlink.MAVLink(None)
    passes: list[tuple[float, list[tuple[float, str, Any, Any, int]], list[bytes]]] = []
    batch: list[tuple[float, str, Any, Any, int]] = []
    raw: list[bytes] = []
    for off, kind, gcs, f in replay_frames(seconds):
        msg = fastcodec.decode(f) or parser.decode(bytearray(f))
        batch.append((1000.0 + off, kind, Link.GCS if gcs else Link.AUTOPILOT, msg, msg_id(f)))
        raw.append(bytes(f))
        if gcs:
            passes.append((1000.0 + off, batch, raw))
            batch, raw = [], []
    totals: list[float] = []
    refs: list[float] = []
    per_kind: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        profile = load_profile(write_profile({"command.rate_hz": "50.0"}, tmp))
    logging.disable(logging.WARNING)  # the cores' STATUSTEXT log lines (no encoders yet, ...)
    warm_s = 1000.0 + seconds / 4
    clock = time.process_time
    for _ in range(repeats):
        core = BridgeCore(profile)
        kind_s: dict[str, float] = {}
        counts: dict[str, int] = {}

        def add(what: str, dt: float, now: float, kind_s: dict[str, float] = kind_s,
                counts: dict[str, int] = counts) -> None:
            if now >= warm_s:
                kind_s[what] = kind_s.get(what, 0.0) + dt
                counts[what] = counts.get(what, 0) + 1

        def due(now: float, core: Any = core) -> None:
            c0 = clock()
            if now >= core.next_deadline_s(now):
                core.tick(now)
                add("tick", clock() - c0, now)
                c0 = clock()
            if now >= core.next_early_s(now):
                core.early_tick(now)
                add("early tick", clock() - c0, now)

        t = 1000.0
        ref_s = 0.0
        for pass_s, frames, datagrams in passes:
            while (deadline := core.next_deadline_s(t)) < pass_s:  # the loop woke for it
                t = max(t, deadline)
                due(t)
            for now, kind, link, msg, mid in frames:
                c0 = clock()
                reads = core.reads(link)
                if reads is None or mid in reads:  # as the shell: undecoded frames never reach the core
                    core.handle(Incoming(link, msg), now)
                add(kind, clock() - c0, now)
            t = pass_s
            due(t)
            c0 = clock()
            for datagram in datagrams:
                parser.decode(bytearray(datagram))
            if t >= warm_s:
                ref_s += clock() - c0
        totals.append(sum(kind_s.values()) / (seconds * 0.75) * 1e3)
        refs.append(sum(kind_s.values()) / ref_s)
        for k, v in kind_s.items():
            per_kind.setdefault(k, []).append(v / counts[k] * 1e6)
    logging.disable(logging.NOTSET)
    return {"ms_per_s": statistics.median(totals), "runs": totals, "x_ref": statistics.median(refs),
            "us": {k: statistics.median(v) for k, v in per_kind.items()}}


def bench_replay(args: argparse.Namespace) -> None:
    # Each run in a fresh process, the trees taking turns (measured: the same tree read about 10 % cheaper in
    # this process than in a child, so both are children).
    roots = {"bridge": REPO, **({"base": Path(args.base).resolve()} if args.base else {})}
    extra: dict[str, list[str]] = {name: [] for name in roots}
    for part in args.without or ():
        roots[f"bridge, {part} free"] = REPO
        extra[f"bridge, {part} free"] = ["--without", part]
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in roots}
    for rep in range(args.repeats):
        for name in list(roots) if rep % 2 == 0 else list(roots)[::-1]:
            done = subprocess.run(self_cmd("_replay", str(args.seconds), "1", *extra[name]), capture_output=True,
                                  text=True, cwd=REPO, env=bridge_env(roots[name]), check=True)
            runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
    kinds = sorted({k for rs in runs.values() for r in rs for k in r["us"]})
    rows = []
    for name, rs in runs.items():
        totals, ratios = [r["ms_per_s"] for r in rs], [r["x_ref"] for r in rs]
        rows.append([name, f"{statistics.median(ratios):.3f}", " / ".join(f"{x:.3f}" for x in ratios),
                     f"{statistics.median(totals):.2f}",
                     *[f"{statistics.median(r['us'].get(k, 0.0) for r in rs):.1f}" for k in kinds]])
    print_table(f"replay: BridgeCore alone on {args.seconds:.0f} s of the cpu table's nominal traffic, in-process "
                f"(the last three quarters measured; median of {args.repeats} processes per tree); x_ref: the cores' "
                "CPU over pymavlink's decode of the same frames, timed between the passes; ms of CPU per second of "
                "traffic; us per message kind, per tick (command output, heartbeat, deadlines) and per early tick "
                "(ODOMETRY)", ["tree", "x_ref", "runs", "ms_per_s", *kinds], rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("latency")
    p.add_argument("--requests", type=int, default=5000)
    p.add_argument("--value-requests", type=int, default=600, help="requests of the value-latency run")
    p.add_argument("--interval-ms", type=float, default=2.0, help="time between requests (default %(default)s)")
    p.add_argument("--forward-frames", type=int, default=500, help="frames of the telemetry-forwarding run")
    p = sub.add_parser("throughput")
    p.add_argument("--start-hz", type=float, default=4000.0)
    p.add_argument("--step-s", type=float, default=1.5)
    p.add_argument("--max-steps", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p = sub.add_parser("cpu")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--warmup-s", type=float, default=3.0)
    p.add_argument("--parts", action="store_true",
                   help="also run this tree's bridge with parts of its cores stubbed (routing; routing + "
                        "outputs; one flow only; the command flow with an estimator that costs nothing): "
                        "where its CPU goes")
    p.add_argument("--without", action="append", choices=WITHOUT,
                   help="also run this tree's bridge with that part of the filter costing nothing (repeatable; "
                        "as replay --without, in the running process)")
    p = sub.add_parser("regularity")
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--flood-hz", type=float, default=5000.0)
    p = sub.add_parser("contention")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--warmup-s", type=float, default=3.0)
    p.add_argument("--rate-hz", type=float, default=50.0, help="command.rate_hz (the cpu table's: %(default)s)")
    p.add_argument("--harness-priority", type=int, default=20,
                   help="SCHED_FIFO priority of the harness while it measures (above the unit's)")
    p.add_argument("--unit-first", action="store_true", help="run the unit's scheduling first")
    p.add_argument("--autogroup-nice", type=int, default=None, metavar="N",
                   help="run this session's scheduler autogroup at nice N (-20: as if only the numpy load "
                        "competed on a machine other sessions share; needs root)")
    p = sub.add_parser("memory")
    p.add_argument("--messages", type=int, default=1_000_000)
    p.add_argument("--warmup", type=int, default=20_000)
    p.add_argument("--window", type=int, default=256, help="forwarded frames in flight at most")
    p.add_argument("--max-s", type=float, default=110.0, help="stop sending after this long (default %(default)s)")
    p.add_argument("--subprocess", action="store_true",
                   help="measure the real process, closed loop (slower: fewer messages in the time limit)")
    p = sub.add_parser("startup")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--top", type=int, default=10)
    p = sub.add_parser("wakeup")
    p.add_argument("--rate-hz", type=float, default=110.0, help="wake-ups a second (the bridge's passes at nominal "
                   "load: about 110)")
    p.add_argument("--seconds", type=float, default=10.0)
    p = sub.add_parser("hotpath")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--batch", type=int, default=1500)
    p = sub.add_parser("replay")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--without", action="append", choices=WITHOUT,
                   help="also replay this tree with that part of the filter costing nothing (repeatable): the most "
                        "that trimming it could save")
    all_p = sub.add_parser("all")
    for sp in (sub.choices["latency"], sub.choices["throughput"], sub.choices["cpu"], sub.choices["regularity"],
               sub.choices["hotpath"], sub.choices["replay"], all_p):
        sp.add_argument("--base", metavar="DIR", help="also measure the bridge of another source tree, side by side")
    p = sub.add_parser("_echo")
    p.add_argument("port", type=int)
    p = sub.add_parser("_router")
    p.add_argument("ap_port", type=int)
    p.add_argument("gcs_port", type=int)
    p.add_argument("stats_path")
    p = sub.add_parser("_flood")
    p.add_argument("port", type=int)
    p.add_argument("rate", type=float)
    p.add_argument("seconds", type=float)
    p = sub.add_parser("_burn")
    p.add_argument("seconds", type=float)
    p.add_argument("threads", type=int)
    p = sub.add_parser("_replay")
    p.add_argument("seconds", type=float)
    p.add_argument("repeats", type=int)
    p.add_argument("--without", choices=WITHOUT)
    args = parser.parse_args(argv)
    if args.cmd == "_echo":
        echo_main(args.port)
    elif args.cmd == "_router":
        router_main(args.ap_port, args.gcs_port, args.stats_path)
    elif args.cmd == "_flood":
        flood_main(args.port, args.rate, args.seconds)
    elif args.cmd == "_burn":
        burn_main(args.seconds, args.threads)
    elif args.cmd == "_replay":
        print(json.dumps(replay_main(args.seconds, args.repeats, args.without)))
    elif args.cmd == "all":
        with_base = ("hotpath", "replay", "latency", "throughput", "cpu", "regularity")
        for name in ("hotpath", "replay", "latency", "throughput", "cpu", "wakeup", "regularity", "memory", "startup"):
            main([name, "--base", args.base] if args.base and name in with_base else [name])
    else:
        {"latency": bench_latency, "throughput": bench_throughput, "cpu": bench_cpu, "regularity": bench_regularity,
         "memory": bench_memory, "startup": bench_startup, "hotpath": bench_hotpath, "replay": bench_replay,
         "wakeup": bench_wakeup, "contention": bench_contention}[args.cmd](args)


if __name__ == "__main__":
    main()
