"""A real ArduPilot Rover SITL rig, shared by tests/test_ardupilot_sitl_nav.py and benchmarks/bench_sitl_control.py.

- `Link`: a pymavlink connection read by a thread (every message kept, bounded), a heartbeat at 1 Hz while
  `beating`, and `each` called every 0.1 s (a ground station's requests).
- `Sitl`: one `ardurover` (rover-skid, rover.parm + rover-skid.parm + the given .parm files + `extra`) in its own
  folder, with a monitor on SERIAL1 that asks for the simulator's truth and the outputs (`streams`).
- `Bridge`: `rover-bridge run` on the SITL's SERIAL0 (TCP), a ground station `Link` on its UDP port.
- `alone` / `bridged`: one run's SITL with a ground station, ArduPilot alone (the GCS on its SERIAL0) or through the
  bridge (the shipped .parm and profile), closed however the run ends.

SITL's ports are 5760 + 10 * instance (SERIAL0, TCP, one client) and 5762 + 10 * instance (SERIAL1). The
binary's tree gives the default parameter files (<tree>/build/sitl/bin/ardurover ->
<tree>/Tools/autotest/default_params), or ROVER_BRIDGE_ARDUPILOT_PARAMS.
"""

from __future__ import annotations

import collections
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import pytest
from navmetrics import Point

from rover_bridge.app.demo import free_udp_port
from rover_bridge.mavlink.dialect import mavlink, mavutil

T = TypeVar("T")
BINARY = os.environ.get("ROVER_BRIDGE_ARDUROVER", "")
# Every real-SITL test module's marks (`pytestmark = REAL_SITL`): CI's real-SITL set selects them by the marker, and
# without the binary they are skipped, saying why.
REAL_SITL = [
    pytest.mark.ardupilot_sitl,
    pytest.mark.skipif(not BINARY, reason="ROVER_BRIDGE_ARDUROVER does not name an ardurover binary"),
]

REPO = Path(__file__).resolve().parents[1]
PROFILE = REPO / "params" / "ardupilot-sitl-skid.toml"
PARM = REPO / "deploy" / "ardupilot-rover.parm"
EARTH_RADIUS_M = 6378137.0
# Per-wheel passthrough, SITL's wheel encoders with the profile's effective track (see its comments), no arming
# checks, MAVLink on SERIAL1 (the truth monitor).
EXTRA_PARAMS = """SERVO1_FUNCTION 51
SERVO3_FUNCTION 53
ARMING_CHECK 0
SERIAL1_PROTOCOL 2
WENC_TYPE 10
WENC2_TYPE 10
WENC_POS_Y 0.8185
WENC2_POS_Y -0.8185
"""
# The monitor's streams by default: the simulator's truth (position, attitude) at 20 Hz, the outputs at 40 Hz.
STREAMS = {mavlink.MAVLINK_MSG_ID_SIMSTATE: 50_000, mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 25_000}


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM, then SIGKILL if it has not gone within 10 s."""
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def north_east_m(origin_deg: tuple[float, float], lat_deg: float, lon_deg: float) -> Point:
    """A lat/lon's north/east of the origin (the test's own flat earth: not the bridge's code under test)."""
    lat0, lon0 = origin_deg
    return (math.radians(lat_deg - lat0) * EARTH_RADIUS_M,
            math.radians(lon_deg - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0)))


def default_params(binary: str) -> Path:
    given = os.environ.get("ROVER_BRIDGE_ARDUPILOT_PARAMS")
    return Path(given) if given else Path(binary).resolve().parents[3] / "Tools" / "autotest" / "default_params"


class Link:
    """A pymavlink connection read by a thread: every message kept (bounded), a heartbeat sent at 1 Hz while
    `beating`, and `each` (if set) called every 0.1 s (a GCS's velocity requests or sticks)."""

    def __init__(self, url: str, sysid: int, compid: int, beating: bool = True) -> None:
        self.conn: Any = mavutil.mavlink_connection(url, source_system=sysid, source_component=compid,
                                                    dialect="ardupilotmega")
        self.beating = beating
        self.each: Callable[[], None] | None = None
        self.messages: collections.deque[tuple[float, Any]] = collections.deque(maxlen=200_000)
        self.lock = threading.Lock()
        self.alive = True
        self._threads = [threading.Thread(target=self._rx, daemon=True), threading.Thread(target=self._tx, daemon=True)]
        for th in self._threads:
            th.start()

    def _rx(self) -> None:
        while self.alive:
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.2)
            except OSError:
                time.sleep(0.05)
                continue
            if m is not None and m.get_type() != "BAD_DATA":
                self.messages.append((time.monotonic(), m))

    def _tx(self) -> None:
        n = 0
        while self.alive:
            with self.lock:
                if self.beating and n % 10 == 0:
                    self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                if self.each is not None:
                    self.each()
            n += 1
            time.sleep(0.1)

    def of(self, kind: str, since: float = 0.0) -> list[Any]:
        return [m for t, m in list(self.messages) if t >= since and m.get_type() == kind]

    def texts(self, since: float = 0.0) -> list[str]:
        return [m.text for m in self.of("STATUSTEXT", since)]

    def wait(self, done: Callable[[], bool], timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if done():
                return True
            time.sleep(0.02)
        return done()

    def command(self, command: int, *params: float) -> int | None:
        p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
        since = time.monotonic()
        with self.lock:
            self.conn.mav.command_long_send(1, 1, command, 0, *p)
        ok = self.wait(lambda: any(m.command == command for m in self.of("COMMAND_ACK", since)), 3.0)
        return [m.result for m in self.of("COMMAND_ACK", since) if m.command == command][-1] if ok else None

    def set_param(self, name: str, value: float) -> None:
        since = time.monotonic()
        with self.lock:
            self.conn.mav.param_set_send(1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)
        assert self.wait(lambda: any(m.param_id == name for m in self.of("PARAM_VALUE", since)), 5.0), name

    def get_param(self, name: str) -> float:
        since = time.monotonic()
        with self.lock:
            self.conn.mav.param_request_read_send(1, 1, name.encode(), -1)
        assert self.wait(lambda: any(m.param_id == name for m in self.of("PARAM_VALUE", since)), 5.0), name
        return float([m for m in self.of("PARAM_VALUE", since) if m.param_id == name][-1].param_value)

    def close(self) -> None:
        self.alive = False
        for th in self._threads:
            th.join(1.0)
        self.conn.close()


class Sitl:
    """One ardurover and its monitor on SERIAL1: truth (north, east from where it booted), mode, outputs."""

    def __init__(self, binary: str, instance: int, extra: str, workdir: Path, parm_files: tuple[Path, ...] = (),
                 streams: dict[int, int] | None = None) -> None:
        self.instance = instance
        self.serial0 = 5760 + 10 * instance
        workdir.mkdir(parents=True, exist_ok=True)
        (workdir / "extra.parm").write_text(extra)
        params = default_params(binary)
        defaults = ",".join(str(p) for p in (params / "rover.parm", params / "rover-skid.parm", *parm_files,
                                             workdir / "extra.parm"))
        self.log = open(workdir / "ardurover.log", "wb")  # noqa: SIM115
        self.proc = subprocess.Popen([binary, "--model", "rover-skid", "--defaults", defaults, "-I", str(instance),
                                      "--serial0", "tcp:0", "-w"], cwd=workdir, stdout=self.log,
                                     stderr=subprocess.STDOUT)
        self.monitor = self._connect(self.serial0 + 2, 250, 191)
        self.monitor.beating = False  # not the GCS: its heartbeat is no GCS for ArduPilot's failsafe anyway
        self.origin_deg: tuple[float, float] | None = None
        for _ in range(3):
            for message_id, interval_us in (STREAMS if streams is None else streams).items():
                self.monitor.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, interval_us)
            if self.monitor.wait(lambda: len(self.monitor.of("SIMSTATE")) > 5, 2.0):
                break
        last = self.monitor.of("SIMSTATE")[-1]
        self.origin_deg = (last.lat * 1e-7, last.lng * 1e-7)

    @staticmethod
    def _connect(port: int, sysid: int, compid: int) -> Link:
        end = time.monotonic() + 90.0
        while True:
            try:
                return Link(f"tcp:127.0.0.1:{port}", sysid, compid)
            except OSError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.5)

    def gcs_on_serial0(self) -> Link:
        return self._connect(self.serial0, 255, 190)

    def truth(self) -> Point:
        m = self.monitor.of("SIMSTATE", time.monotonic() - 1.0)[-1]
        assert self.origin_deg is not None
        return north_east_m(self.origin_deg, m.lat * 1e-7, m.lng * 1e-7)

    def track(self, since: float, until: float = math.inf) -> list[Point]:
        assert self.origin_deg is not None
        return [north_east_m(self.origin_deg, m.lat * 1e-7, m.lng * 1e-7)
                for t, m in list(self.monitor.messages) if since <= t <= until and m.get_type() == "SIMSTATE"]

    def mode(self) -> int | None:
        beats = [m for m in self.monitor.of("HEARTBEAT", time.monotonic() - 2.0) if m.get_srcSystem() == 1
                 and m.get_srcComponent() == 1]
        return int(beats[-1].custom_mode) if beats else None

    def _speed_from_track(self) -> float:
        now = time.monotonic()
        pts = [(t, m) for t, m in list(self.monitor.messages) if t >= now - 0.5 and m.get_type() == "SIMSTATE"]
        if len(pts) < 2:
            return math.inf
        (t0, a), (t1, b) = pts[0], pts[-1]
        d = math.hypot((b.lat - a.lat) * 1e-7 * 111_320.0,
                       (b.lng - a.lng) * 1e-7 * 111_320.0 * math.cos(math.radians(a.lat * 1e-7)))
        return d / max(t1 - t0, 1e-3)

    def stopped(self) -> bool:
        return self._speed_from_track() < 0.05

    def home_here(self) -> None:
        """Truth coordinates from here on (ArduPilot sets home at arming: call it right after arming)."""
        m = self.monitor.of("SIMSTATE")[-1]
        self.origin_deg = (m.lat * 1e-7, m.lng * 1e-7)

    def home_from_autopilot(self) -> tuple[float, float]:
        """Truth coordinates from the autopilot's home on (HOME_POSITION, asked for; its latitude, longitude in deg).

        Home is the EKF's position where it was set (at arming if not locked), so distances from it are what the
        autopilot's circle fence measures, less the EKF's error against the truth."""
        since = time.monotonic()
        for _ in range(3):
            self.monitor.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION)
            if self.monitor.wait(lambda: bool(self.monitor.of("HOME_POSITION", since)), 2.0):
                break
        homes = self.monitor.of("HOME_POSITION", since)
        assert homes, f"no HOME_POSITION ({self.monitor.texts()[-5:]})"
        self.origin_deg = (homes[-1].latitude * 1e-7, homes[-1].longitude * 1e-7)
        return self.origin_deg

    def lat_lon_e7(self, north_m: float, east_m: float) -> tuple[int, int]:
        assert self.origin_deg is not None
        lat0, lon0 = self.origin_deg
        return (round((lat0 + math.degrees(north_m / EARTH_RADIUS_M)) * 1e7),
                round((lon0 + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))) * 1e7))

    def close(self) -> None:
        self.monitor.close()
        stop_process(self.proc)
        self.log.close()


class Bridge:
    """`rover-bridge run` on the SITL's SERIAL0, a ground station on its UDP port."""

    def __init__(self, sitl: Sitl, workdir: Path, profile: Path = PROFILE, autopilot: str | None = None,
                 extra_args: Sequence[str] = ()) -> None:
        port = free_udp_port()
        self.log_path = workdir / "bridge.log"
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "rover_bridge", "-v", "run", "--params", str(profile),
                                          "--autopilot", autopilot or f"tcp:127.0.0.1:{sitl.serial0}",
                                          "--gcs", f"udpin:127.0.0.1:{port}", *extra_args], cwd=REPO, stdout=log,
                                         stderr=subprocess.STDOUT)
        end = time.monotonic() + 30.0
        while b"rover-bridge running" not in self.log_path.read_bytes():
            assert self.proc.poll() is None and time.monotonic() < end, self.log_path.read_text()[-2000:]
            time.sleep(0.05)
        self.gcs = Link(f"udpout:127.0.0.1:{port}", 255, 190)

    def stop(self) -> float:
        """SIGTERM; the time it was sent."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        assert self.proc.wait(10.0) == 0
        return t0

    def close(self) -> None:
        self.gcs.close()
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@contextmanager
def alone(binary: str, instance: int, extra: str, workdir: Path,
          streams: dict[int, int] | None = None) -> Iterator[tuple[Sitl, Link]]:
    """ArduPilot alone (rover-skid.parm's SERVO1/3_FUNCTION 73/74: its own skid mixer) and a GCS on its SERIAL0."""
    sitl = Sitl(binary, instance, extra, workdir / "alone-sitl", (), streams)
    gcs: Link | None = None
    try:
        gcs = sitl.gcs_on_serial0()
        yield sitl, gcs
    finally:
        if gcs is not None:
            gcs.close()
        sitl.close()


@contextmanager
def bridged(binary: str, instance: int, extra: str, workdir: Path, streams: dict[int, int] | None = None,
            extra_args: Sequence[str] = ()) -> Iterator[tuple[Sitl, Bridge]]:
    """The bridge setup: the shipped .parm (per-wheel passthrough) and `rover-bridge run` with the shipped profile."""
    sitl = Sitl(binary, instance, extra, workdir / "bridge-sitl", (PARM,), streams)
    bridge: Bridge | None = None
    try:
        bridge = Bridge(sitl, workdir, PROFILE, extra_args=extra_args)
        yield sitl, bridge
    finally:
        if bridge is not None:
            bridge.gcs.each = None
            bridge.close()
        sitl.close()


def through_bridge(binary: str, instance: int, extra: str, workdir: Path, streams: dict[int, int] | None,
                   drive: Callable[[Sitl, Bridge], T]) -> tuple[T, dict[str, int]]:
    """`drive` on a `bridged` SITL, then the bridge stopped: what drive returned and the bridge's `command` counters
    (its --stats-json)."""
    stats = workdir / "stats.json"
    with bridged(binary, instance, extra, workdir, streams, ("--stats-json", str(stats))) as (sitl, bridge):
        result = drive(sitl, bridge)
        bridge.stop()
        return result, json.loads(stats.read_text())["command"]


WALL_AHEAD_M, BEHIND_M, HALF_WIDTH_M = 10.0, 30.0, 10.0  # wall_ahead's rectangle: 40 m along the heading, 20 m across


def upload_fence(link: Link, vertices_e7: list[tuple[int, int]]) -> None:
    """An inclusion polygon by the mission protocol (mission type FENCE): MISSION_COUNT, each MISSION_REQUEST(_INT)
    answered with a MISSION_ITEM_INT (MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, param1 = vertex count), then
    ArduPilot's MISSION_ACK."""
    fence = mavlink.MAV_MISSION_TYPE_FENCE
    since = time.monotonic()
    with link.lock:
        link.conn.mav.mission_count_send(1, 1, len(vertices_e7), fence)
    sent: set[int] = set()
    end = time.monotonic() + 15.0
    while time.monotonic() < end:
        acks = [m for m in link.of("MISSION_ACK", since) if m.mission_type == fence]
        if acks:
            assert acks[-1].type == mavlink.MAV_MISSION_ACCEPTED, acks[-1]
            assert sent == set(range(len(vertices_e7))), sent
            return
        asked = [m for kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST") for m in link.of(kind, since)
                 if m.mission_type == fence]
        for seq in sorted({int(m.seq) for m in asked} - sent):
            lat, lon = vertices_e7[seq]
            with link.lock:
                link.conn.mav.mission_item_int_send(
                    1, 1, seq, mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 0, 1,
                    len(vertices_e7), 0, 0, 0, lat, lon, 0, fence)
            sent.add(seq)
        time.sleep(0.02)
    raise AssertionError(f"fence upload: no MISSION_ACK (sent {sorted(sent)}; {link.texts()[-5:]})")


def wall_ahead(sitl: Sitl) -> tuple[float, float, float]:
    """Upload the rectangle around the rover, its near wall WALL_AHEAD_M ahead; (north, east, yaw) of the start."""
    sitl.home_here()
    yaw = float(sitl.monitor.of("SIM_STATE", time.monotonic() - 1.0)[-1].yaw)
    fwd, right = (math.cos(yaw), math.sin(yaw)), (-math.sin(yaw), math.cos(yaw))
    corners = [(WALL_AHEAD_M, -HALF_WIDTH_M), (WALL_AHEAD_M, HALF_WIDTH_M), (-BEHIND_M, HALF_WIDTH_M),
               (-BEHIND_M, -HALF_WIDTH_M)]
    upload_fence(sitl.monitor, [sitl.lat_lon_e7(a * fwd[0] + r * right[0], a * fwd[1] + r * right[1])
                                for a, r in corners])
    n0, e0 = sitl.truth()
    return n0, e0, yaw
