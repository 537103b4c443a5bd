"""MAVSDK-Python 4.x (the C++ library, in-process), a real ground-station client, through the bridge.

The emulator runs in wall-clock time in a thread, the bridge as the real `rover-bridge run` process,
MAVSDK listens on the bridge's ground-station port as QGroundControl would.
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from lockstep import step_wall
from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk

from sitl import Emulator, VehicleConfig

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class WallClock(threading.Thread):
    """Steps the emulator on the wall clock until stopped (the autopilot 'powered off')."""

    def __init__(self, emu: Emulator) -> None:
        super().__init__(daemon=True)
        self.emu = emu
        self.running = threading.Event()
        self.running.set()
        self.lock = threading.Lock()

    def run(self) -> None:
        last = time.monotonic()
        while self.running.is_set():
            now = time.monotonic()
            with self.lock:
                step_wall(self.emu, now - last)
            last = now
            time.sleep(0.005)


@dataclass
class Setup:
    emu: Emulator
    clock: WallClock
    bridge: subprocess.Popen[bytes]
    mavsdk: Mavsdk


@pytest.fixture
def setup(tmp_path: Path) -> Iterator[Setup]:
    gcs_port = free_port()
    emu = Emulator(VehicleConfig(start_armed=True), seed=4)
    emu.open("udpin:127.0.0.1:0")
    clock = WallClock(emu)
    clock.start()
    bridge = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "run", "--params", str(REPO / "params" / "default.toml"),
         "--autopilot", f"udpout:127.0.0.1:{emu.local_address[1]}", "--gcs", f"udpout:127.0.0.1:{gcs_port}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    assert mavsdk.add_any_connection(f"udpin://127.0.0.1:{gcs_port}") == ConnectionResult.SUCCESS
    try:
        yield Setup(emu, clock, bridge, mavsdk)
    finally:
        clock.running.clear()
        clock.join(timeout=5.0)
        bridge.terminate()
        try:
            bridge.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            bridge.kill()
        mavsdk.destroy()
        emu.close()


def wait_for(cond: object, timeout_s: float) -> float | None:
    """Seconds until cond() is true, or None after timeout_s."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        if cond():  # type: ignore[operator]
            return time.monotonic() - start
        time.sleep(0.1)
    return None


def test_mavsdk_sees_the_vehicle_go_when_the_autopilot_stops(setup: Setup) -> None:
    # MAVSDK counts a system as connected while any heartbeat of its system id arrived in the last 3 s;
    # the bridge's heartbeat carries the vehicle's id, so it stops sending it to the GCS when the
    # autopilot's heartbeat is lost (safety.heartbeat_timeout_s, 3 s).
    system = setup.mavsdk.first_autopilot(30.0)
    assert system is not None and system.get_system_id() == 1
    assert wait_for(system.is_connected, 10.0) is not None
    time.sleep(2.0)
    assert system.is_connected()
    setup.clock.running.clear()  # the autopilot stops: no heartbeat, no telemetry
    setup.clock.join(timeout=5.0)
    gone_after = wait_for(lambda: not system.is_connected(), 15.0)
    assert gone_after is not None, "MAVSDK still shows the vehicle connected 15 s after its autopilot stopped"
    assert 3.0 < gone_after < 9.0  # the bridge's 3 s, then MAVSDK's own 3 s
    assert setup.bridge.poll() is None  # the bridge itself is still running (and says why on STATUSTEXT)


def test_mavsdk_goto_location_drives_the_rover_to_the_point(setup: Setup) -> None:
    # Action.goto_location on ArduPilot: DO_SET_MODE (Offboard = GUIDED for a rover), then on its ACK a
    # COMMAND_INT DO_REPOSITION with CHANGE_MODE, the yaw in radians; MAVSDK waits for the ACK from the
    # autopilot's ids. The bridge answers for the autopilot and drives there, then turns to the yaw.
    from mavsdk.plugins.action import Action, ActionResult

    system = setup.mavsdk.first_autopilot(30.0)
    assert system is not None
    assert wait_for(system.is_connected, 10.0) is not None
    time.sleep(3.0)  # the bridge's streams up, the gyro settled
    earth = 6378137.0
    vehicle = VehicleConfig()
    north, east = 1.5, -1.0
    lat = vehicle.origin_lat_deg + math.degrees(north / earth)
    lon = vehicle.origin_lon_deg + math.degrees(east / (earth * math.cos(math.radians(vehicle.origin_lat_deg))))
    action = Action(system)
    assert action.goto_location(lat, lon, 584.0, 90.0) == ActionResult.SUCCESS
    assert setup.emu.mode == 15

    def arrived() -> bool:
        with setup.clock.lock:
            truth = setup.emu.truth
        return (math.hypot(truth.x_m - north, truth.y_m - east) <= 0.15 and abs(truth.v_m_s) < 1e-3
                and abs(truth.yaw_rate_rad_s) < 1e-3)

    assert wait_for(arrived, 30.0) is not None, f"not reached: {setup.emu.truth}"
    with setup.clock.lock:
        truth = setup.emu.truth
    assert abs(math.degrees(math.remainder(truth.yaw_rad - math.pi / 2, 2 * math.pi))) <= 5.0  # facing east
