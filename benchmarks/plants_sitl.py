"""benchmarks/plants.py's drive on a real ArduPilot Rover SITL, through the bridge process, on the wall clock: what
the emulated skid plant stands in for (`python benchmarks/bench_plants.py --ardupilot BINARY`, about 90 s).

ardurover --model rover-skid with the defaults of its tree (rover.parm, rover-skid.parm) plus per-wheel
passthrough (SERVO1/3_FUNCTION 51/53) and SITL's encoders with the profile's track (WENC_TYPE 10, WENC_POS_Y
+-0.8185), ARMING_CHECK 0; `rover-bridge run` on SERIAL0 with bench_profile(); the requests from a ground station
at 10 Hz; the truth from SIM_STATE at 40 Hz on SERIAL1 (speed along the heading, zgyro, position integrated from
vn/ve), ODOMETRY as the ground station receives it. The phases are timed on the wall clock, so a loaded machine
shifts them a little. Everything runs in a fresh temporary folder (SITL writes eeprom.bin and logs there).
"""

from __future__ import annotations

import math
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import plants
from pymavlink import mavutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from ardupilot_rig import EXTRA_PARAMS, stop_process

from rover_bridge.app.demo import free_udp_port
from rover_bridge.params import profile_to_toml

mavlink = mavutil.mavlink
BODY_VELOCITY_MASK = 0b0000_0101_1100_0111
SIM_STATE_ID = 108
BOOT_S = 20.0  # GPS and EKF settle (ARMING_CHECK 0 arms at once, but the estimate needs its start)


class _Links:
    """The truth monitor on SERIAL1 and the ground station on the bridge, each with its own threads."""

    def __init__(self, serial1: int, gcs_port: int, trace: plants.Trace) -> None:
        self.mon: Any = _connect(f"tcp:127.0.0.1:{serial1}", 250, 191)
        self.gcs: Any = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=255,
                                                   source_component=190)
        self.trace = trace
        self.request: tuple[float, float] | None = None  # (v m/s, omega rad/s counter-clockwise)
        self.alive = True
        self._truth: tuple[float, float, float] | None = None  # (t, x, y)
        self._threads = [threading.Thread(target=f, daemon=True)
                         for f in (self._truth_rx, self._truth_tx, self._gcs_tx, self._gcs_rx)]
        for th in self._threads:
            th.start()

    def _truth_rx(self) -> None:
        while self.alive:
            m = self.mon.recv_match(type="SIM_STATE", blocking=True, timeout=0.5)
            if m is None:
                continue
            now = time.monotonic()
            t, x, y = self._truth if self._truth is not None else (now, 0.0, 0.0)
            self._truth = (now, x + m.vn * (now - t), y + m.ve * (now - t))
            self.trace.t_s.append(now)
            self.trace.v_m_s.append(m.vn * math.cos(m.yaw) + m.ve * math.sin(m.yaw))
            self.trace.yaw_rate_ccw_rad_s.append(-m.zgyro)  # SITL's gyro z is clockwise positive
            self.trace.xy_m.append(self._truth[1:])

    def _truth_tx(self) -> None:
        while self.alive:
            self.mon.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self.mon.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, SIM_STATE_ID, 25_000,
                                           0, 0, 0, 0, 0)
            time.sleep(1.0)

    def _gcs_tx(self) -> None:
        n = 0
        while self.alive:
            if n % 10 == 0:
                self.gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            if self.request is not None:
                v, omega = self.request
                self.gcs.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_BODY_NED,
                                                                BODY_VELOCITY_MASK, 0, 0, 0, v, 0, 0, 0, 0, 0, 0,
                                                                -omega)
            n += 1
            time.sleep(0.1)

    def _gcs_rx(self) -> None:
        while self.alive:
            try:
                m = self.gcs.recv_match(type="ODOMETRY", blocking=True, timeout=0.2)
            except OSError:  # udpout before the bridge's first datagram back
                time.sleep(0.05)
                continue
            if m is not None:
                self.trace.odometry.setdefault(m.time_usec, (time.monotonic(), m.x, m.y))

    def phase(self, name: str, seconds: float, v_m_s: float, omega_rad_s: float = 0.0) -> None:
        self.request = (v_m_s, omega_rad_s)
        start = time.monotonic()
        time.sleep(seconds)
        self.trace.phases[name] = (start, time.monotonic())

    def close(self) -> None:
        self.alive = False
        for th in self._threads:
            th.join(1.0)
        self.mon.close()
        self.gcs.close()


def _connect(url: str, system: int, component: int, timeout_s: float = 60.0) -> Any:
    end = time.monotonic() + timeout_s
    while True:
        try:
            return mavutil.mavlink_connection(url, source_system=system, source_component=component)
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.5)


INSTANCE = 13  # SITL's ports 5760/5762 + 10 x instance: not the tests' 4, 5 and 6, which may be running


def drive_ardupilot(binary: str, instance: int = INSTANCE) -> plants.Trace:
    """plants.drive's requests on a real SITL (module docstring); SITL's ports 5760/5762 + 10 x instance."""
    defaults = Path(binary).resolve().parents[3] / "Tools" / "autotest" / "default_params"
    serial0, serial1 = 5760 + 10 * instance, 5762 + 10 * instance
    trace = plants.Trace()
    with tempfile.TemporaryDirectory(prefix="bench-plants-") as tmp:
        work = Path(tmp)
        (work / "extra.parm").write_text(EXTRA_PARAMS)
        (work / "bench.toml").write_text(profile_to_toml(plants.bench_profile()))
        parms = ",".join(str(p) for p in (defaults / "rover.parm", defaults / "rover-skid.parm", work / "extra.parm"))
        with open(work / "ardurover.log", "wb") as log:
            sitl = subprocess.Popen([binary, "--model", "rover-skid", "--defaults", parms, "-I", str(instance),
                                     "--serial0", "tcp:0", "-w"], cwd=work, stdout=log, stderr=subprocess.STDOUT)
        procs = [sitl]
        links: _Links | None = None
        try:
            time.sleep(2.0)
            gcs_port = free_udp_port()
            with open(work / "bridge.log", "wb") as log:
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "rover_bridge", "run", "--params", str(work / "bench.toml"),
                     "--autopilot", f"tcp:127.0.0.1:{serial0}", "--gcs", f"udpin:127.0.0.1:{gcs_port}"],
                    cwd=work, stdout=log, stderr=subprocess.STDOUT))
            links = _Links(serial1, gcs_port, trace)
            time.sleep(BOOT_S)
            links.mon.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196, 0, 0, 0, 0, 0)
            time.sleep(4.0)  # as plants.drive's start()
            for v in plants.STEPS_M_S:
                links.phase(f"step {v}", plants.HOLD_S, v)
            links.phase("stop", plants.STOP_S, 0.0)
            links.phase("arc", plants.TURN_S, *plants.ARC)
            links.phase("after arc", plants.AFTER_ARC_S, plants.ARC[0])
            links.phase("arc stop", 2.0, 0.0)
            links.phase("spin", plants.TURN_S, 0.0, plants.SPIN_RAD_S)
            links.phase("spin stop", 2.0, 0.0)
        finally:
            if links is not None:
                links.close()
            for proc in reversed(procs):
                stop_process(proc)
    if not trace.t_s or not trace.odometry:
        raise RuntimeError(f"no truth ({len(trace.t_s)}) or no ODOMETRY ({len(trace.odometry)}) from the real SITL")
    return trace
