"""The bridge between a pymavlink GCS and the emulator, set up as a rover owner would (tests/test_nav_e2e.py,
tests/test_gcs_failsafe_e2e.py): the shipped profile params/ardupilot-sitl-skid.toml and the shipped
deploy/ardupilot-rover.parm loaded into the emulator's bridge setup (sitl/vehicles/ardupilot-skid-bridge.toml:
rover-skid, motors on passthrough 51/53, SERVO5/6 = 73/74). Lockstep, UDP loopback (tests/lockstep.py)."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from pathlib import Path

from lockstep import Lockstep
from navmetrics import Point, RouteFigures, route_figures
from pymavlink.mavparm import MAVParmDict

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import Profile, load_profile
from sitl import Emulator, VehicleConfig, load_vehicle
from sitl.geo import lat_lon_of
from sitl.modes import MODE_AUTO

REPO = Path(__file__).resolve().parents[1]
ANCHOR = load_vehicle(REPO / "sitl" / "vehicles" / "ardupilot-skid-anchor.toml")
BRIDGE = load_vehicle(REPO / "sitl" / "vehicles" / "ardupilot-skid-bridge.toml")
P = mavlink
WAYPOINTS: list[Point] = [(10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]  # 10 m apart, two 90 deg corners


def shipped_profile() -> Profile:
    """The shipped SITL profile; the emulator reports its wheels as 0 = left, 1 = right (ArduPilot's SITL
    encoders the other way round, which the profile is written for)."""
    p = load_profile(REPO / "params" / "ardupilot-sitl-skid.toml")
    return dataclasses.replace(p, encoders=dataclasses.replace(p.encoders, left_index=0, right_index=1))


@functools.cache
def shipped_parm() -> dict[str, float]:
    parm = MAVParmDict()
    parm.load(str(REPO / "deploy" / "ardupilot-rover.parm"), check=False)
    return {name: float(value) for name, value in parm.items()}


class BridgeRig:
    """The bridge between a pymavlink GCS and the emulator, the shipped .parm loaded; the true track kept."""

    def __init__(self, profile: Profile | None = None, vehicle: VehicleConfig = BRIDGE, seed: int = 29,
                 **params: float) -> None:
        self.ls = Lockstep(profile or shipped_profile(), vehicle, seed=seed, start_armed=True)
        for name, value in {**shipped_parm(), **params}.items():
            self.ls.emu.set_param(name, value)
        self.track: list[Point] = []
        self.gcs_alive = True  # False: the GCS sends nothing at all (no heartbeat either)
        self.ls.run_for(2.0)  # heartbeats, streams

    @property
    def emu(self) -> Emulator:
        return self.ls.emu

    def _record(self) -> None:
        self.track.append((self.emu.truth.x_m, self.emu.truth.y_m))

    def run(self, seconds: float, send: Callable[[], None] | None = None) -> None:
        if self.gcs_alive:
            self.ls.run_for(seconds, send=send, after_step=self._record)
            return
        for _ in range(round(seconds / self.ls.dt_s)):
            self.ls.step()
            self._record()

    def run_until(self, done: Callable[[], bool], timeout_s: float, send: Callable[[], None] | None = None) -> bool:
        end = self.ls.t_s + timeout_s
        while self.ls.t_s < end:
            if done():
                return True
            self.run(0.1, send)
        return done()

    def set_mode(self, mode: int) -> None:
        self.ls.gcs.mav.command_long_send(1, 1, P.MAV_CMD_DO_SET_MODE, 0, P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode,
                                          0, 0, 0, 0, 0)
        self.run(0.3)
        assert self.emu.mode == mode

    def upload(self, points: list[Point]) -> int:
        """A GCS's mission upload (MISSION_COUNT, an item per MISSION_REQUEST, MISSION_ACK) through the bridge;
        item 0 is home. Returns the MISSION_ACK's type."""
        v, gcs, answered = self.emu.vehicle, self.ls.gcs, set()
        items = [(0.0, 0.0), *points]
        start = len(self.ls.view.of("MISSION_ACK"))
        gcs.mav.mission_count_send(1, 1, len(items), P.MAV_MISSION_TYPE_MISSION)
        for _ in range(300):
            self.ls.step()
            for _t, m in self.ls.view.of("MISSION_REQUEST") + self.ls.view.of("MISSION_REQUEST_INT"):
                if m.seq not in answered:
                    answered.add(m.seq)
                    lat, lon = lat_lon_of(*items[m.seq], v.origin_lat_deg, v.origin_lon_deg)
                    gcs.mav.mission_item_int_send(1, 1, m.seq, P.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                  P.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                                  round(lat * 1e7), round(lon * 1e7), 0, P.MAV_MISSION_TYPE_MISSION)
            acks = self.ls.view.of("MISSION_ACK")[start:]
            if acks:
                return int(acks[-1][1].type)
        raise AssertionError("no MISSION_ACK through the bridge")

    def fly_mission(self, points: list[Point], timeout_s: float = 90.0) -> RouteFigures:
        """Upload `points` through the bridge, fly them in AUTO until the last is reached: the figures from the
        true track (timed from the mode change; NaN time if the last waypoint was never reached)."""
        assert self.upload(points) == P.MAV_MISSION_ACCEPTED
        since = len(self.ls.view.of("MISSION_ITEM_REACHED"))
        self.set_mode(MODE_AUTO)
        start, at, first = self.ls.t_s - 0.3, self.track[-1], len(self.track)
        done = self.run_until(lambda: len(self.ls.view.of("MISSION_ITEM_REACHED")) - since >= len(points), timeout_s)
        return route_figures(self.track[first:], at, points, self.ls.t_s - start if done else math.nan)

    def reached(self) -> list[int]:
        return [m.seq for _t, m in self.ls.view.of("MISSION_ITEM_REACHED")]

    def texts(self) -> list[str]:
        return [m.text for _t, m in self.ls.view.of("STATUSTEXT")]

    def drive(self, v_m_s: float, yaw_rate_cw_rad_s: float = 0.0) -> Callable[[], None]:
        return lambda: self.ls.send_body_velocity(v_m_s, yaw_rate_cw_rad_s)

    def from_home_m(self) -> float:
        return math.hypot(self.emu.truth.x_m, self.emu.truth.y_m)

    def stopped(self) -> bool:
        return abs(self.emu.truth.v_m_s) < 0.01 and abs(self.emu.truth.yaw_rate_rad_s) < 0.01

    def close(self) -> None:
        self.ls.close()
