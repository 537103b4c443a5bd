"""The real process with its autopilot link fed decoded-message fuzz for 30 s: it keeps overriding.

The test is the autopilot: a UDP socket that sends a valid armed HEARTBEAT every second and, between
them, about 250 messages a second of every type the bridge reads from an autopilot, each field drawn
from 0, its type's extremes, NaN, infinities, UNIX-epoch and boot-time stamps and random values, in
sequence (stamps jump back and forth). A ground station streams 0.3 m/s. Every second of the run
must carry at least 80 % of command.rate_hz overrides, and after the fuzz a fresh request must drive.
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from test_process_faults import Gcs

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import Profile

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]
FUZZ_S = 30.0
FUZZ_HZ = 250.0  # fuzz frames a second into the autopilot link
RATE_HZ = Profile().command.rate_hz
INT_LIMITS = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
              "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1), "uint64_t": (0, 2**64 - 1),
              "int64_t": (-2**63, 2**63 - 1)}
FLOAT_SPECIAL = [0.0, math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e-38, 1.0, -1.0]
TYPES = [mavlink.MAVLink_heartbeat_message, mavlink.MAVLink_attitude_message, mavlink.MAVLink_scaled_imu_message,
         mavlink.MAVLink_raw_imu_message, mavlink.MAVLink_wheel_distance_message, mavlink.MAVLink_system_time_message,
         mavlink.MAVLink_command_ack_message, mavlink.MAVLink_local_position_ned_message,
         mavlink.MAVLink_timesync_message, mavlink.MAVLink_command_long_message]


def fuzz_value(rng: random.Random, name: str, kind: str, t_s: float) -> Any:
    if kind in ("float", "double"):
        return rng.choice(FLOAT_SPECIAL) if rng.random() < 0.5 else rng.uniform(-1e3, 1e3)
    lo, hi = INT_LIMITS[kind]
    if name in ("time_usec", "time_boot_ms") and rng.random() < 0.5:
        # boot time now, a UNIX-epoch stamp, or far away: stamps jump back and forth
        scale = 1e6 if name == "time_usec" else 1e3
        choice = rng.choice([t_s * scale, 1.733e15 + t_s * 1e6, rng.uniform(0, t_s * scale), hi])
        return max(lo, min(hi, round(choice)))
    return rng.choice([lo, hi, 0, 1]) if rng.random() < 0.5 else rng.randint(lo, hi)


def fuzz_message(rng: random.Random, t_s: float) -> Any:
    cls = rng.choice(TYPES)
    kwargs: dict[str, Any] = {}
    for name, kind, length in zip(cls.fieldnames, cls.fieldtypes, cls.array_lengths, strict=True):
        if kind == "char":
            kwargs[name] = b""
        elif length:
            kwargs[name] = [fuzz_value(rng, name, kind, t_s) for _ in range(length)]
        else:
            kwargs[name] = fuzz_value(rng, name, kind, t_s)
    return cls(**kwargs)


class FakeAutopilot:
    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.peer: tuple[str, int] | None = None
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.overrides: list[tuple[float, int, int]] = []  # (time, ch1, ch3)

    def send(self, msg: Any) -> None:
        if self.peer is None:
            return
        # A value the wire cannot carry cannot reach the bridge either: skipped.
        with contextlib.suppress(OSError, ValueError, OverflowError, TypeError):
            self.sock.sendto(msg.pack(self.mav), self.peer)

    def heartbeat(self) -> None:
        self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                    mavlink.MAV_MODE_FLAG_SAFETY_ARMED | 1, 15, 4, 3))

    def receive(self) -> None:
        while True:
            try:
                data, peer = self.sock.recvfrom(65535)
            except BlockingIOError:
                return
            self.peer = peer
            for msg in self.parser.parse_buffer(data) or []:
                if msg.get_type() == "RC_CHANNELS_OVERRIDE":
                    self.overrides.append((time.monotonic(), msg.chan1_raw, msg.chan3_raw))


def test_thirty_seconds_of_autopilot_fuzz_keep_the_overrides_coming_and_a_fresh_request_drives() -> None:
    rng = random.Random(20261201)
    ap = FakeAutopilot()
    gcs = Gcs()
    proc = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "run", "--params", str(REPO / "params" / "default.toml"),
         "--autopilot", f"udpout:127.0.0.1:{ap.port}", "--gcs", f"udpout:127.0.0.1:{gcs.port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        t0 = time.monotonic()
        next_hb = next_req = 0.0
        while not ap.overrides:  # the bridge's first frames tell the autopilot where it is
            assert time.monotonic() - t0 < 60.0, "no override from the bridge"
            ap.receive()
            if ap.peer is not None and time.monotonic() >= next_hb:
                ap.heartbeat()
                next_hb = time.monotonic() + 1.0
            gcs.heartbeat()
            gcs.forward(0.3)
            time.sleep(0.05)
        start = time.monotonic()
        sent = 0
        while (now := time.monotonic()) < start + FUZZ_S:
            ap.receive()
            if now >= next_hb:
                ap.heartbeat()
                next_hb = now + 1.0
            if now >= next_req:
                gcs.heartbeat()
                gcs.forward(0.3)
                next_req = now + 0.1
            # 250 frames a second of fuzz whatever the load: a late turn of this loop sends what it owes.
            while sent < FUZZ_HZ * (now - start):
                ap.send(fuzz_message(rng, now - t0))
                sent += 1
            gcs.drain()
            time.sleep(0.02)
        assert proc.poll() is None, "the bridge died under the fuzz"
        per_second = [sum(1 for t, _, _ in ap.overrides if start + k <= t < start + k + 1) for k in range(int(FUZZ_S))]
        assert sent > 5000
        assert min(per_second) >= 0.8 * RATE_HZ, per_second
        # Afterwards: clean telemetry, a fresh request drives.
        fresh_from = time.monotonic()
        while time.monotonic() < fresh_from + 2.0:
            ap.receive()
            ap.heartbeat()
            gcs.heartbeat()
            gcs.forward(0.3)
            time.sleep(0.1)
        ap.receive()
        driving = [o for o in ap.overrides if o[0] > fresh_from and o[1] > 1500 and o[2] > 1500]
        assert driving, ap.overrides[-5:]
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
        if proc.stdout:
            proc.stdout.close()
        gcs.close()
        ap.sock.close()
