"""Discontinuities of the published estimate: pose resets and autopilot reboots (pure).

ODOMETRY.reset_counter rises by one on every pose reset (MAVLink command or CLI) and on every
autopilot reboot detected in the wheel distances (the odometry re-bases there: exactly once per
reboot), so a receiver knows a jump is not motion.

Pose reset: COMMAND_LONG MAV_CMD_USER_1 (31010) addressed to the bridge (target_system = the
vehicle, target_component = [mavlink] component_id): param1 x (m, forward of the start pose),
param2 y (m, right), param3 yaw (deg, clockwise); NaN leaves that coordinate as it is. A pose
beyond POSE_RESET_MAX_M / POSE_RESET_MAX_YAW_DEG is garbage (a corrupted frame, degrees for
metres), not a place: denied.
"""

from __future__ import annotations

import math

from rover_bridge import frames
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing
from rover_bridge.odometry import Pose2D

POSE_RESET_COMMAND = mavlink.MAV_CMD_USER_1
POSE_RESET_MAX_M = 1e6
POSE_RESET_MAX_YAW_DEG = 360.0


def requested_pose(msg: MAVLinkMessage, current: Pose2D) -> Pose2D | None:
    """The pose a MAV_CMD_USER_1 asks for (rover-bridge's FLU convention), or None if it is garbage."""
    # FRD in the command (x forward, y right, yaw clockwise in degrees); NaN keeps the coordinate.
    x_m = current.x_m if math.isnan(msg.param1) else float(msg.param1)
    y_m = current.y_m if math.isnan(msg.param2) else frames.y_frd_from_y_flu(float(msg.param2))
    yaw = (
        current.yaw_rad
        if math.isnan(msg.param3)
        else frames.yaw_frd_from_yaw_flu(math.radians(float(msg.param3)))
    )
    in_range = (abs(x_m) <= POSE_RESET_MAX_M and abs(y_m) <= POSE_RESET_MAX_M
                and (math.isnan(msg.param3) or abs(float(msg.param3)) <= POSE_RESET_MAX_YAW_DEG))
    if not (all(math.isfinite(v) for v in (x_m, y_m, yaw)) and in_range):
        return None
    return Pose2D(x_m, y_m, yaw)


class ResetCounter:
    """ODOMETRY.reset_counter and the reports that go with each discontinuity."""

    def __init__(self, reporter: Reporter) -> None:
        self.reporter = reporter
        self.value = 0
        self.counters = {"reboots": 0, "pose_resets": 0, "pose_resets_denied": 0}

    def _bump(self) -> None:
        self.value = (self.value + 1) % 256

    def reboot(self, reason: str, now_s: float) -> list[Outgoing]:
        """The autopilot rebooted: the odometry re-based once."""
        self._bump()
        self.counters["reboots"] += 1
        return self.reporter.statustext(
            mavlink.MAV_SEVERITY_WARNING, f"autopilot reboot: odometry re-based ({reason})"[:50], now_s, key="reboot")

    def pose_reset(self, pose: Pose2D, now_s: float) -> list[Outgoing]:
        """The pose was put somewhere (x forward, y left, yaw CCW)."""
        self._bump()
        self.counters["pose_resets"] += 1
        return self.reporter.statustext(
            mavlink.MAV_SEVERITY_INFO,
            f"pose reset x {pose.x_m:.2f} y {frames.y_frd_from_y_flu(pose.y_m):.2f} "
            f"yaw {math.degrees(frames.yaw_frd_from_yaw_flu(pose.yaw_rad)):.1f}",
            now_s,
            key="pose reset",
        )

    def denied(self) -> None:
        self.counters["pose_resets_denied"] += 1
