"""What the demo's ground station sends: a route as phases, each one velocity request repeated at 10 Hz.

Kept apart from rover_bridge.app.demo so that a scenario's own route (rover_bridge.app.demo_obstacles) can be
written without importing the demo that drives it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.frames import mavlink_yaw_rate_from_omega
from rover_bridge.mavlink.dialect import mavlink

BODY_MASK = 0b0000_0101_1100_0111  # velocity + yaw rate used; position, accel, yaw ignored
EARTH_MASK = 0b0000_1101_1100_0111  # velocity used; yaw and yaw rate ignored
EARTH_YAW_MASK = 0b0000_1001_1100_0111  # velocity and yaw used: drive at that speed facing that heading


@dataclass(frozen=True)
class Request:
    """One SET_POSITION_TARGET_LOCAL_NED the GCS repeats at 10 Hz during a phase."""

    frame: int
    vx_m_s: float
    vy_m_s: float
    yaw_rate_cw_rad_s: float
    type_mask: int
    yaw_cw_rad: float = 0.0  # used only with EARTH_YAW_MASK

    @property
    def speed_m_s(self) -> float:
        """The speed asked for: forward + (a body request may reverse; an earth one is a heading and a speed)."""
        return self.vx_m_s if self.frame == mavlink.MAV_FRAME_BODY_NED else math.hypot(self.vx_m_s, self.vy_m_s)


def body(v_m_s: float, omega_ccw_rad_s: float) -> Request:
    return Request(mavlink.MAV_FRAME_BODY_NED, v_m_s, 0.0, mavlink_yaw_rate_from_omega(omega_ccw_rad_s), BODY_MASK)


def earth(v_north_m_s: float, v_east_m_s: float) -> Request:
    return Request(mavlink.MAV_FRAME_LOCAL_NED, v_north_m_s, v_east_m_s, 0.0, EARTH_MASK)


def toward(speed_m_s: float) -> Request:
    """An earth-frame request at ``speed_m_s`` whose heading a Phase's ``aim_ne`` fills in (``aimed``)."""
    return Request(mavlink.MAV_FRAME_LOCAL_NED, speed_m_s, 0.0, 0.0, EARTH_YAW_MASK)


def aimed(request: Request, from_ne: tuple[float, float], to_ne: tuple[float, float]) -> Request:
    """``request`` facing from one point to the other (north, east): a heading and the speed along it.
    Speed 0 turns the rover in place to face it (the heading controller)."""
    bearing = math.atan2(to_ne[1] - from_ne[1], to_ne[0] - from_ne[0])
    speed = request.speed_m_s
    return Request(mavlink.MAV_FRAME_LOCAL_NED, speed * math.cos(bearing), speed * math.sin(bearing), 0.0,
                   EARTH_YAW_MASK, bearing)


@dataclass(frozen=True)
class Phase:
    name: str
    duration_s: float
    request: Request | None  # None: send nothing (the bridge's timeout brakes the rover)
    # Aim the request at this point (north, east, m) from where the rover is when the phase starts: a ground
    # station pointing the rover at something it sees on its map.
    aim_ne: tuple[float, float] | None = None
