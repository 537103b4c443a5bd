"""A pose source for navigation tests: a unicycle the test moves, with the autopilot's heading, local
position fixes and GPS as the estimate flow would hand them over (rover_bridge.command.navigation.PoseSource).

The estimate's frame is the start pose (x forward, y left, yaw CCW); the autopilot's NED frame is that
frame turned by `north_rotation_cw_rad` (the start heading from north) and moved by (north0, east0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from rover_bridge.frames import LocalAnchor
from rover_bridge.kinematics import Twist2D
from rover_bridge.odometry import Pose2D, arc_step

EARTH_RADIUS_M = 6378137.0
LAT0, LON0 = -35.363261, 149.165230


@dataclass
class FakeSource:
    pose: Pose2D = field(default_factory=Pose2D)
    north_rotation_cw_rad: float = 0.0
    north0_m: float = 0.0
    east0_m: float = 0.0
    heading_error_rad: float = 0.0  # ATTITUDE's heading minus the true one
    fresh: bool = True
    has_heading: bool = True
    fixes_on: bool = True
    gps_on: bool = True
    gps_age_s: float = 0.0
    reset_counter: int = 0
    now_s: float = 0.0
    fixes: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)

    @property
    def anchor(self) -> LocalAnchor:
        return LocalAnchor(self.north0_m, self.east0_m, self.north_rotation_cw_rad)

    # -- PoseSource
    def nav_pose(self, now_s: float) -> Pose2D | None:
        return self.pose if self.fresh else None

    def nav_pose_at(self, stamp_s: float) -> Pose2D:
        return self.pose

    def autopilot_time_s(self, now_s: float) -> float:
        return now_s

    @property
    def heading(self) -> tuple[float, float] | None:
        if not self.has_heading:
            return None
        return self.now_s, self.anchor.to_ned(self.pose.x_m, self.pose.y_m, self.pose.yaw_rad).yaw_cw_rad \
            + self.heading_error_rad

    @property
    def position_fixes(self) -> list[tuple[float, float, float, float, float, float]]:
        return self.fixes if self.fixes_on else []

    @property
    def gps(self) -> tuple[float, float, float, float] | None:
        if not self.gps_on:
            return None
        ned = self.anchor.to_ned(self.pose.x_m, self.pose.y_m, self.pose.yaw_rad)
        return self.now_s - self.gps_age_s, self.now_s, *lat_lon(ned.north_m, ned.east_m)

    # -- the test's side
    def fix(self, now_s: float) -> None:
        """The autopilot's LOCAL_POSITION_NED now (exact), beside our pose."""
        self.now_s = now_s
        ned = self.anchor.to_ned(self.pose.x_m, self.pose.y_m, self.pose.yaw_rad)
        self.fixes.append((now_s, self.pose.x_m, self.pose.y_m, self.pose.yaw_rad, ned.north_m, ned.east_m))

    def move(self, twist: Twist2D, dt_s: float) -> None:
        self.pose = arc_step(self.pose, twist.v_m_s * dt_s, twist.omega_rad_s * dt_s)
        self.now_s += dt_s

    def ned(self) -> tuple[float, float]:
        ned = self.anchor.to_ned(self.pose.x_m, self.pose.y_m, self.pose.yaw_rad)
        return ned.north_m, ned.east_m


def lat_lon(north_m: float, east_m: float) -> tuple[float, float]:
    return (LAT0 + math.degrees(north_m / EARTH_RADIUS_M),
            LON0 + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(LAT0)))))
