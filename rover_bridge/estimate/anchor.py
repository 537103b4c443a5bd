"""Which frame ODOMETRY is in: the bridge's start pose, or the autopilot's own local frame (pure).

odometry.frame = 'autopilot' (what 'auto' picks when ODOMETRY goes to the autopilot): ArduPilot takes
ODOMETRY as external navigation, and with EK3_SRC1_YAW = 6 its yaw as north. A bridge that starts
(or restarts, mid-drive) at (0, 0, yaw 0) of a new frame would then be a jump ArduPilot rejects
while it goes on fusing the new frame's velocity, rotated by the new yaw: its position runs off and
does not come back. So the estimate's start frame is tied to the autopilot's before the first
ODOMETRY goes out:

- once wheel data and ATTITUDE flow, the bridge waits (odometry.anchor_timeout_s) for the autopilot's
  LOCAL_POSITION_NED; with one, its pose there (and ATTITUDE's heading) is where the estimate is: a
  restarted bridge continues exactly where the autopilot's own estimate is;
- without one by then (a cold start of both: ArduPilot has no position before external navigation
  arrives) the start pose is the origin, north-aligned by ATTITUDE's heading;
- without ATTITUDE either, the start frame itself (said, and ODOMETRY is not north-aligned).

The anchor is fixed once; ODOMETRY is held back until then. Both times are autopilot stamps: the
estimate's pose at a message's own stamp is matched with the message, so a rover already moving is
anchored where it was when the autopilot measured it. The last pose is deliberately not kept on
disk across restarts: the autopilot's estimate is the one that survived, and a file would be stale
whenever the rover moved while the bridge was down.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from rover_bridge.frames import LocalAnchor, NedPose
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing
from rover_bridge.odometry import Pose2D
from rover_bridge.params import OdometryParams

MAX_LOCAL_M = 1e6  # a LOCAL_POSITION_NED beyond this is corrupt, not a place
LOCAL_POSITION_MAX_AGE_S = 2.0  # older than the newest ATTITUDE by more than this: not used to anchor


class FrameAnchor:
    """Decides the anchor of the published frame (see the module docstring); None until decided."""

    def __init__(self, params: OdometryParams, reporter: Reporter) -> None:
        self.enabled = params.resolved_frame == "autopilot"
        self.timeout_s = params.anchor_timeout_s
        self.reporter = reporter
        self.anchor: LocalAnchor | None = None
        self.how = ""  # how it was anchored: local_position | origin | start
        self.local_position: tuple[float, float, float] | None = None  # (stamp_s, north_m, east_m)
        self.yaw: tuple[float, float] | None = None  # (stamp_s, yaw_cw_rad)
        self._waiting_since_s: float | None = None

    @property
    def ready(self) -> bool:
        """ODOMETRY may go out: the start frame is published, or the anchor is decided."""
        return not self.enabled or self.anchor is not None

    def on_local_position(self, stamp_s: float, north_m: float, east_m: float) -> None:
        if all(math.isfinite(v) and abs(v) <= MAX_LOCAL_M for v in (stamp_s, north_m, east_m)):
            self.local_position = (stamp_s, north_m, east_m)

    def on_attitude(self, stamp_s: float, yaw_cw_rad: float) -> None:
        if math.isfinite(stamp_s) and math.isfinite(yaw_cw_rad) and abs(yaw_cw_rad) <= 2.0 * math.pi:
            self.yaw = (stamp_s, yaw_cw_rad)

    def decide(self, now_s: float, pose_at: Callable[[float], Pose2D] | None) -> list[Outgoing]:
        """Anchor now if it can be; `pose_at(stamp_s)` is the estimate's pose at an autopilot stamp, None
        while the estimate has no wheel data yet. Returns the report of the decision (once)."""
        if not self.enabled or self.anchor is not None or pose_at is None:
            return []
        if self._waiting_since_s is None:
            self._waiting_since_s = now_s
        yaw = self.yaw
        local = self.local_position
        if yaw is not None and local is not None and local[0] >= yaw[0] - LOCAL_POSITION_MAX_AGE_S:
            ours_yaw = pose_at(yaw[0]).yaw_rad
            here = pose_at(local[0])
            self.anchor = LocalAnchor.matching(here.x_m, here.y_m, ours_yaw, NedPose(local[1], local[2], yaw[1]))
            return self._decided("local_position", "RB: odometry in autopilot frame (its position)", now_s)
        if now_s < self._waiting_since_s + self.timeout_s:
            return []
        if yaw is not None:
            ours_yaw = pose_at(yaw[0]).yaw_rad
            rotation = math.remainder(yaw[1] + ours_yaw, 2.0 * math.pi)  # theirs (cw) - ours (frd = -ccw)
            self.anchor = LocalAnchor(0.0, 0.0, rotation)
            return self._decided("origin", "RB: odometry at origin, north-aligned", now_s)
        self.anchor = LocalAnchor()
        return self._decided("start", "RB: no ATTITUDE: odometry in start frame", now_s,
                             mavlink.MAV_SEVERITY_WARNING)

    def _decided(self, how: str, text: str, now_s: float, severity: int = mavlink.MAV_SEVERITY_INFO
                 ) -> list[Outgoing]:
        self.how = how
        return self.reporter.statustext(severity, text, now_s, key="odometry frame")

    # ------------------------------------------------------------------ the published frame
    def published(self, pose: Pose2D) -> Pose2D:
        """An estimate pose (start frame) in the published frame, rover-bridge's convention (x, y left, CCW)."""
        if self.anchor is None:
            return pose
        ned = self.anchor.to_ned(pose.x_m, pose.y_m, pose.yaw_rad)
        return Pose2D(ned.north_m, -ned.east_m, -ned.yaw_cw_rad)

    def internal(self, pose: Pose2D) -> Pose2D:
        """The inverse of `published`."""
        if self.anchor is None:
            return pose
        x, y, yaw = self.anchor.from_ned(NedPose(pose.x_m, -pose.y_m, -pose.yaw_rad))
        return Pose2D(x, y, yaw)
