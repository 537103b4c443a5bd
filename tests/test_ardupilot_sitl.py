"""Against a real ArduPilot Rover SITL (optional): the stops that the emulator was taught from it.

Runs only when ROVER_BRIDGE_ARDUROVER names an `ardurover` binary (`build/sitl/bin/ardurover` of an
ArduPilot tree built with `./waf configure --board sitl && ./waf rover`); the tree's
Tools/autotest/default_params are found from there, or in ROVER_BRIDGE_ARDUPILOT_PARAMS. Not in CI:
building SITL takes about 10 minutes. Run with `python -m pytest -m ardupilot_sitl`.

ArduPilot runs the rover-skid model with per-wheel RC passthrough (SERVO1/3_FUNCTION = 51/53) and the
bridge on its SERIAL0 over TCP, which is where the stop used to be lost (ArduPilot parses a TCP
client's bytes in its main loop and drops what a closing client sent last). A second client on
SERIAL1 watches SERVO_OUTPUT_RAW at 40 Hz: the outputs themselves, not what the bridge says.
"""

from __future__ import annotations

import collections
import contextlib
import math
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from ardupilot_rig import BINARY, EARTH_RADIUS_M, EXTRA_PARAMS, REAL_SITL, default_params, north_east_m, stop_process
from lockstep import free_udp_port

from rover_bridge.mavlink.dialect import mavlink, mavutil

pytestmark = REAL_SITL

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "params" / "ardupilot-sitl-skid.toml"
INSTANCE = 4  # SITL's ports are 5760 + 10 * instance (SERIAL0) and 5762 + 10 * instance (SERIAL1)
SERIAL0, SERIAL1 = 5760 + 10 * INSTANCE, 5762 + 10 * INSTANCE
TRIM = 1500
HOLD, MANUAL = 4, 0  # Rover custom modes
GUIDED = 15
BODY_VELOCITY_MASK = 0b0000_0101_1100_0111


def _wait_port(port: int, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return
        time.sleep(0.2)
    raise AssertionError(f"ArduPilot SITL did not open port {port} in {timeout_s} s")


class Monitor:
    """A second client on SERIAL1: SERVO_OUTPUT_RAW (outputs 1 and 3) and the autopilot's mode."""

    def __init__(self) -> None:
        self.conn: Any = mavutil.mavlink_connection(f"tcp:127.0.0.1:{SERIAL1}", source_system=250,
                                                    source_component=191, dialect="ardupilotmega")
        self.servo: collections.deque[tuple[float, int, int]] = collections.deque(maxlen=20000)
        self.mode: int | None = None
        self.truth_deg: tuple[float, float] | None = None  # SIMSTATE lat, lon: where the rover really is
        self.alive = True
        self._threads = [threading.Thread(target=self._rx, daemon=True),
                         threading.Thread(target=self._tx, daemon=True)]
        for th in self._threads:
            th.start()

    def _tx(self) -> None:
        n = 0
        while self.alive:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            if n % 5 == 0:
                self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, 25_000, 0, 0, 0, 0, 0)
                self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                mavlink.MAVLINK_MSG_ID_SIMSTATE, 50_000, 0, 0, 0, 0, 0)
            n += 1
            time.sleep(1.0)

    def _rx(self) -> None:
        while self.alive:
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.5)
            except OSError:
                return
            if m is None:
                continue
            if m.get_type() == "SERVO_OUTPUT_RAW":
                self.servo.append((time.monotonic(), m.servo1_raw, m.servo3_raw))
            elif m.get_type() == "SIMSTATE":
                self.truth_deg = (m.lat * 1e-7, m.lng * 1e-7)
            elif m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1 and m.get_srcComponent() == 1:
                self.mode = m.custom_mode

    def arm(self) -> None:
        self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196, 0, 0, 0, 0, 0)

    def first(self, pred: Callable[[int, int], bool], since_s: float, timeout_s: float) -> float | None:
        """Time of the first output sample after `since_s` for which pred(servo1, servo3) holds."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for t, a, b in list(self.servo):
                if t > since_s and pred(a, b):
                    return t
            time.sleep(0.005)
        return None

    def samples(self, t0: float, t1: float) -> list[tuple[float, int, int]]:
        return [s for s in list(self.servo) if t0 <= s[0] <= t1]

    def close(self) -> None:
        self.alive = False
        self.conn.close()


@pytest.fixture(scope="module")
def ardupilot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Monitor]:
    params = default_params(BINARY)
    for name in ("rover.parm", "rover-skid.parm"):
        assert (params / name).is_file(), f"{params / name} not found: set ROVER_BRIDGE_ARDUPILOT_PARAMS"
    work = tmp_path_factory.mktemp("ardurover")
    (work / "extra.parm").write_text(EXTRA_PARAMS)
    defaults = ",".join(str(p) for p in (params / "rover.parm", params / "rover-skid.parm", work / "extra.parm"))
    with open(work / "ardurover.log", "wb") as log:
        proc = subprocess.Popen([BINARY, "--model", "rover-skid", "--defaults", defaults, "-I", str(INSTANCE),
                                 "--serial0", "tcp:0", "-w"], cwd=work, stdout=log, stderr=subprocess.STDOUT)
    try:
        _wait_port(SERIAL1, 60.0)
        monitor = Monitor()
        end = time.monotonic() + 60.0
        while (monitor.mode != MANUAL or not monitor.servo) and time.monotonic() < end:
            time.sleep(0.2)
        assert monitor.servo, "no SERVO_OUTPUT_RAW from ArduPilot SITL"
        yield monitor
        monitor.close()
    finally:
        stop_process(proc)


class Gcs:
    """A scripted ground station on the bridge's GCS link: heartbeat, body-frame velocity at 10 Hz."""

    def __init__(self, port: int) -> None:
        self.conn: Any = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255,
                                                    source_component=190, dialect="ardupilotmega")
        self.vx_mps: float | None = None
        self.alive = True
        self.position: Any = None  # the last GLOBAL_POSITION_INT the ground station saw
        self.reached = 0  # MISSION_ITEM_REACHED seen
        self._threads = [threading.Thread(target=self._tx, daemon=True), threading.Thread(target=self._rx, daemon=True)]
        for th in self._threads:
            th.start()

    def _rx(self) -> None:
        while self.alive:
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.2)
            except OSError:
                time.sleep(0.05)  # udpout before the bridge's first datagram back
                continue
            if m is None:
                continue
            if m.get_type() == "GLOBAL_POSITION_INT" and m.lat != 0:
                self.position = m
            elif m.get_type() == "MISSION_ITEM_REACHED":
                self.reached += 1

    def _tx(self) -> None:
        n = 0
        while self.alive:
            if n % 10 == 0:
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            vx = self.vx_mps
            if vx is not None:
                self.conn.mav.set_position_target_local_ned_send(
                    int(time.monotonic() * 1000) & 0xFFFFFFFF, 1, 1, mavlink.MAV_FRAME_BODY_NED,
                    BODY_VELOCITY_MASK, 0, 0, 0, vx, 0, 0, 0, 0, 0, 0, 0)
            n += 1
            time.sleep(0.1)

    def set_mode(self, custom_mode: int) -> None:
        self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, custom_mode, 0, 0, 0, 0, 0)

    def close(self) -> None:
        self.alive = False
        for th in self._threads:
            th.join(1.0)
        self.conn.close()


@contextlib.contextmanager
def bridge(profile: Path, workdir: Path) -> Iterator[tuple[subprocess.Popen[bytes], Gcs, Path]]:
    gcs_port = free_udp_port()
    log_path = workdir / "bridge.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "rover_bridge", "-v", "run", "--params", str(profile),
                                 "--autopilot", f"tcp:127.0.0.1:{SERIAL0}", "--gcs", f"udpin:127.0.0.1:{gcs_port}"],
                                cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    gcs = Gcs(gcs_port)
    try:
        end = time.monotonic() + 20.0
        while b"rover-bridge running" not in log_path.read_bytes():
            assert proc.poll() is None and time.monotonic() < end, log_path.read_text()[-2000:]
            time.sleep(0.05)
        yield proc, gcs, log_path
    finally:
        gcs.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _profile(tmp_path: Path, output_mode: str) -> Path:
    text = PROFILE.read_text()
    assert 'mode = "rc_override"' in text
    path = tmp_path / f"sitl-{output_mode}.toml"
    path.write_text(text.replace('mode = "rc_override"', f'mode = "{output_mode}"', 1))
    return path


def _drive(monitor: Monitor, gcs: Gcs, log_path: Path) -> None:
    monitor.arm()  # the profile's require_armed: the bridge holds neutral while the autopilot is disarmed
    gcs.vx_mps = 1.0
    started = time.monotonic()
    assert monitor.first(lambda a, b: a >= 1600 and b >= 1600, started, 10.0) is not None, \
        f"the rover did not drive: {monitor.servo[-1] if monitor.servo else None}\n{log_path.read_text()[-2000:]}"
    time.sleep(1.0)


def _at_trim(a: int, b: int) -> bool:
    return a == TRIM and b == TRIM


@pytest.mark.parametrize("output_mode", ["rc_override", "servo"])
def test_sigterm_over_tcp_stops_the_real_autopilot(ardupilot: Monitor, tmp_path: Path, output_mode: str) -> None:
    """SIGTERM while driving: ArduPilot's outputs reach trim within the 200 ms exit budget and stay
    there past RC_OVERRIDE_TIME (3 s). Before the confirmed stop, rc_override lost it for about 3 s
    and servo mode for good."""
    assert ardupilot.first(_at_trim, time.monotonic() - 1.0, 10.0) is not None, "outputs not at trim before"
    with bridge(_profile(tmp_path, output_mode), tmp_path) as (proc, gcs, log_path):
        _drive(ardupilot, gcs, log_path)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        gcs.vx_mps = None
        assert proc.wait(5.0) == 0
        exited_s = time.monotonic() - t0
        t_trim = ardupilot.first(_at_trim, t0, 5.0)
        time.sleep(max(0.0, t0 + 4.0 - time.monotonic()))
        log = log_path.read_text()
    assert t_trim is not None, f"outputs never came back to trim: {ardupilot.servo[-1]}\n{log[-2000:]}"
    # 200 ms exit budget plus one SERVO_OUTPUT_RAW period (25 ms) of the monitor's own stream.
    assert t_trim - t0 < 0.225, f"trim {1000 * (t_trim - t0):.0f} ms after SIGTERM"
    assert exited_s < 0.5
    after = ardupilot.samples(t_trim, t0 + 4.0)
    assert after and all(_at_trim(a, b) for _, a, b in after), "outputs left trim again after the stop"
    assert "stop confirmed" in log, log[-2000:]


def test_hold_on_the_autopilot_stops_the_rover(ardupilot: Monitor, tmp_path: Path) -> None:
    """RC passthrough ignores the mode; the bridge must brake when the autopilot reports HOLD, and
    drive again only on a fresh request after the mode has left HOLD."""
    with bridge(PROFILE, tmp_path) as (proc, gcs, log_path):
        _drive(ardupilot, gcs, log_path)
        t0 = time.monotonic()
        gcs.set_mode(HOLD)
        t_trim = ardupilot.first(_at_trim, t0, 5.0)
        assert t_trim is not None, f"still driving in HOLD: {ardupilot.servo[-1]}\n{log_path.read_text()[-2000:]}"
        assert t_trim - t0 < 2.0  # the limiter's braking from 1 m/s, plus the mode report
        assert ardupilot.mode == HOLD
        time.sleep(1.0)
        held = ardupilot.samples(t_trim, time.monotonic())
        assert all(_at_trim(a, b) for _, a, b in held), "drove while the autopilot was in HOLD"
        gcs.vx_mps = None
        gcs.set_mode(MANUAL)
        end = time.monotonic() + 5.0
        while ardupilot.mode != MANUAL and time.monotonic() < end:
            time.sleep(0.05)
        assert ardupilot.mode == MANUAL
        _drive(ardupilot, gcs, log_path)  # a fresh request after HOLD drives again
        gcs.vx_mps = None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(5.0) == 0
    assert ardupilot.first(_at_trim, time.monotonic() - 0.5, 3.0) is not None


def test_go_to_a_point_on_the_real_autopilot(ardupilot: Monitor, tmp_path: Path) -> None:
    """GUIDED through the bridge, then a MISSION_ITEM_INT (current = 2) 4 m north of the autopilot's
    position: the bridge drives there on its own estimate and says MISSION_ITEM_REACHED; judged by the
    simulator's truth (SIMSTATE), not by what either side estimates."""
    with bridge(PROFILE, tmp_path) as (proc, gcs, log_path):
        ardupilot.arm()
        # ArduPilot refuses GUIDED ("Flight mode change failed") until its EKF has a position: ~25 s.
        end = time.monotonic() + 90.0
        while ardupilot.mode != GUIDED and time.monotonic() < end:
            gcs.set_mode(GUIDED)
            time.sleep(1.0)
        assert ardupilot.mode == GUIDED, log_path.read_text()[-2000:]
        end = time.monotonic() + 20.0
        while (gcs.position is None or ardupilot.truth_deg is None) and time.monotonic() < end:
            time.sleep(0.1)
        assert gcs.position is not None, "the ground station saw no GLOBAL_POSITION_INT through the bridge"
        assert ardupilot.truth_deg is not None, "no SIMSTATE from ArduPilot SITL"
        time.sleep(1.0)  # standing still in GUIDED before the target
        start_truth = ardupilot.truth_deg
        here = (gcs.position.lat * 1e-7, gcs.position.lon * 1e-7)
        north_m = 4.0
        target = (here[0] + math.degrees(north_m / EARTH_RADIUS_M), here[1])
        gcs.conn.mav.mission_item_int_send(1, 1, 0, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                           mavlink.MAV_CMD_NAV_WAYPOINT, 2, 0, 0, 0, 0, 0,
                                           round(target[0] * 1e7), round(target[1] * 1e7), 0)
        t0 = time.monotonic()
        while gcs.reached == 0 and time.monotonic() - t0 < 40.0:
            time.sleep(0.05)
        assert gcs.reached >= 1, f"no MISSION_ITEM_REACHED in 40 s\n{log_path.read_text()[-2000:]}"
        time.sleep(2.0)  # stopped, and staying
        n, e = north_east_m(start_truth, *ardupilot.truth_deg)
        gcs.set_mode(MANUAL)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(5.0) == 0
    # The GPS's own error is in the target (it was placed from GLOBAL_POSITION_INT): measured 0.08-0.15 m.
    assert math.hypot(n - north_m, e) < 0.5, f"stopped at north {n:.2f} m, east {e:.2f} m (target 4 m north)"
