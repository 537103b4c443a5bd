"""Going to a point (pure): where a target is in the estimate's frame, and how a skid-steer gets there.

Where the rover is: the bridge's own estimate (the EKF, through `PoseSource`, which the composition
gives the command flow). A target is fixed in the estimate's frame when it arrives, so that it is
followed on one consistent estimate:

- LOCAL_NED (x north, y east): in the autopilot's local frame when the autopilot publishes
  LOCAL_POSITION_NED (fresh): the estimate's pose at that message's stamp is matched with it and
  ATTITUDE's heading, the target converted through that match; without it the origin is the bridge's
  start pose, aligned to north by ATTITUDE's heading (said which, once each).
- LOCAL_OFFSET_NED: a north/east offset from the pose now (north from ATTITUDE's heading).
- BODY_NED / BODY_OFFSET_NED: an offset forward/right from the pose now, rotated by its heading.
- global (lat/lon): needs the autopilot's GLOBAL_POSITION_INT no older than navigation.gps_timeout_s:
  the north/east offset from that fix (a local tangent plane: over the 200 m a target may be away,
  the flat-earth error is under 1 cm), applied to the estimate's pose at the fix's stamp. What remains
  is the GPS's own error at that moment (1-3 m for a plain receiver, centimetres with RTK) plus the
  estimate's drift over the leg (0.1-0.4 % of the distance, benchmarks/accuracy.py).

The controller, every output (time is the caller's): far off the target's bearing (more than
turn_in_place_deg) it turns in place, at a rate that stops the turn at the bearing within the angular
deceleration limit; otherwise it drives, steering by pure pursuit on the leg (start -> target: a
look-ahead point along the leg, lookahead_m or more with speed, so it converges back onto the line),
its speed the smaller of the cruise speed and the braking curve's (rover_bridge.command.approach: the
fastest speed from which it still stops on the target at the deceleration limit, after the lag of the
outputs and the wheels), scaled by the cosine of the heading error; the limiter ramps the speed up at the
acceleration limit. Inside the arrival radius it stops steering and closes the rest along its heading on
the same curve; the target is reached once that curve asks for no more than the limiter takes away in one
output (nearly stopped), then it turns to the final yaw if one was given. Everything it asks for still
goes through the limiter, the kinematics, the desaturation, the wheel speed loop and every safety path.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from rover_bridge.command.approach import StopProfile
from rover_bridge.command.targets import GlobalTarget, LocalTarget, Target
from rover_bridge.frames import LocalAnchor, NedPose, ne_from_lat_lon, yaw_frd_from_yaw_flu
from rover_bridge.kinematics import Twist2D
from rover_bridge.odometry import Pose2D, wrap_angle
from rover_bridge.params import LimitsParams, NavigationParams

LOCAL_POSITION_MAX_AGE_S = 2.0  # a LOCAL_POSITION_NED older than this (autopilot time) does not anchor
LOOKAHEAD_S = 1.0  # the look-ahead grows by this many seconds of the speed
# The frame's rotation from the track (fit_track): over the last minute of LOCAL_POSITION_NED fixes, used
# when its uncertainty is under half a degree (a rover that has moved a metre or two on a good fix);
# until then, and on a noisy GPS, ATTITUDE's heading.
FIT_WINDOW_S = 60.0
FIT_MIN_POINTS = 6
FIT_MAX_SIGMA_RAD = math.radians(0.5)
FIT_NOISE_FLOOR_M = 0.01  # no fix is better than this, however well a straight track fits


class PoseSource(Protocol):
    """What navigation needs of the estimate flow (the composition passes the EstimateCore)."""

    def nav_pose(self, now_s: float) -> Pose2D | None:
        """The estimate's pose now (x forward of the start pose, y left, yaw CCW); None if stale."""

    def nav_pose_at(self, stamp_s: float) -> Pose2D:
        """The estimate's pose at an autopilot stamp."""

    def autopilot_time_s(self, now_s: float) -> float: ...

    @property
    def position_fixes(self) -> Sequence[tuple[float, float, float, float, float, float]]:
        """Recent LOCAL_POSITION_NED fixes, oldest first, each beside the estimate's pose at its stamp:
        (autopilot stamp, x, y, yaw, north, east)."""

    @property
    def heading(self) -> tuple[float, float] | None:
        """(autopilot stamp, yaw clockwise from north) of the newest ATTITUDE."""

    @property
    def gps(self) -> tuple[float, float, float, float] | None:
        """(arrival time, autopilot stamp, lat deg, lon deg) of the newest GLOBAL_POSITION_INT."""

    @property
    def reset_counter(self) -> int:
        """Changes when the estimate's frame jumps (a pose reset, a reboot): targets in it are void."""


@dataclass(frozen=True, slots=True)
class NavTarget:
    """A target fixed in the estimate's frame, with what it needs for feedback."""

    x_m: float
    y_m: float
    start_x_m: float  # the leg's start (the pose when the target arrived): cross-track error
    start_y_m: float
    yaw_rad: float | None  # the heading to turn to on arrival (estimate frame, CCW)
    speed_m_s: float
    anchor: LocalAnchor  # estimate frame -> NED (for bearings and POSITION_TARGET_LOCAL_NED)
    global_target: GlobalTarget | None = None
    frame_note: str = ""  # how a LOCAL_NED target was tied to the estimate ("autopilot" | "start")


@dataclass(frozen=True, slots=True)
class Unresolved:
    """Why a target cannot be followed: `text` is short (it goes into a STATUSTEXT); `temporary` when a
    moment later it might be (no GPS fix yet), not when the target itself is wrong (too far)."""

    text: str
    temporary: bool = True


@dataclass(frozen=True, slots=True)
class NavStatus:
    distance_m: float
    bearing_cw_rad: float  # to the target, clockwise from north
    crosstrack_m: float
    phase: str  # drive | turn (in place, toward the target) | yaw (arrived, turning to its yaw) | done


def heading_anchor(source: PoseSource, now_s: float, max_age_s: float) -> LocalAnchor | None:
    """Rotation only: the estimate's axes against north, from ATTITUDE's heading (None without a fresh one)."""
    heading = source.heading
    if heading is None or source.autopilot_time_s(now_s) - heading[0] > max_age_s:
        return None
    stamp, yaw_cw = heading
    ours = source.nav_pose_at(stamp)
    return LocalAnchor(0.0, 0.0, math.remainder(yaw_cw - yaw_frd_from_yaw_flu(ours.yaw_rad), 2.0 * math.pi))


@dataclass(frozen=True, slots=True)
class TrackFit:
    """The rotation from the estimate's axes to the autopilot's NED, fitted to the positions of a track."""

    rotation_cw_rad: float
    sigma_rad: float  # its 1-sigma uncertainty, from the fit's own residuals
    spread_m: float  # RMS distance of the track's points from their centroid
    points: int


def fit_track(fixes: Sequence[tuple[float, float, float, float, float, float]], since_s: float) -> TrackFit | None:
    """Least-squares rotation (2-D Kabsch) between our positions and the autopilot's over the fixes since
    `since_s`; None for fewer than FIT_MIN_POINTS. Positions carry the frame's rotation far better than one
    heading does once the rover has moved: an autopilot's heading is good to a few degrees (a compass, or
    a gyro drifting between fixes), and every degree puts a target 1.7 cm per metre of leg off."""
    pts = [(x, -y, n, e) for t, x, y, _, n, e in fixes if t >= since_s]  # ours as (forward, right)
    count = len(pts)
    if count < FIT_MIN_POINTS:
        return None
    px = sum(p[0] for p in pts) / count
    py = sum(p[1] for p in pts) / count
    qx = sum(p[2] for p in pts) / count
    qy = sum(p[3] for p in pts) / count
    dot = cross = spread2 = 0.0
    for a, b, c, d in pts:
        a, b, c, d = a - px, b - py, c - qx, d - qy
        dot += a * c + b * d
        cross += a * d - b * c
        spread2 += a * a + b * b
    if spread2 <= 0.0:
        return None
    rotation = math.atan2(cross, dot)
    cos_r, sin_r = math.cos(rotation), math.sin(rotation)
    residual2 = 0.0
    for a, b, c, d in pts:
        a, b = a - px, b - py
        residual2 += (c - qx - (cos_r * a - sin_r * b)) ** 2 + (d - qy - (sin_r * a + cos_r * b)) ** 2
    noise_m = math.sqrt(residual2 / max(1, 2 * count - 3))
    return TrackFit(rotation, max(noise_m, FIT_NOISE_FLOOR_M) / math.sqrt(spread2), math.sqrt(spread2 / count),
                    count)


def north_anchor(source: PoseSource, now_s: float, heading_max_age_s: float) -> tuple[LocalAnchor | None, str]:
    """Rotation only: our axes against north, and where it came from ("track" or "heading")."""
    fixes = source.position_fixes
    if fixes:
        fit = fit_track(fixes, source.autopilot_time_s(now_s) - FIT_WINDOW_S)
        if fit is not None and fit.sigma_rad <= FIT_MAX_SIGMA_RAD:
            return LocalAnchor(0.0, 0.0, fit.rotation_cw_rad), "track"
    return heading_anchor(source, now_s, heading_max_age_s), "heading"


def resolve(target: Target, source: PoseSource, now_s: float, params: NavigationParams, max_speed_m_s: float,
            cruise_m_s: float | None = None, heading_max_age_s: float = 1.0) -> NavTarget | Unresolved:
    """The target in the estimate's frame, or why it cannot be followed (short: it goes into a STATUSTEXT).
    The cruise speed: the target's own, else `cruise_m_s` (DO_CHANGE_SPEED), else navigation.speed_m_s."""
    pose = source.nav_pose(now_s)
    if pose is None:
        return Unresolved("no position estimate")
    north, _ = north_anchor(source, now_s, heading_max_age_s)
    speed = min(target.speed_m_s or cruise_m_s or params.speed_m_s, max_speed_m_s)
    frame_note = ""
    if isinstance(target, LocalTarget) and target.frame == "body":
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        fwd, left = target.x_m, -target.y_m
        x, y = pose.x_m + c * fwd - s * left, pose.y_m + s * fwd + c * left
        anchor = north or LocalAnchor()
        yaw = None if target.yaw_cw_rad is None else wrap_angle(pose.yaw_rad - target.yaw_cw_rad)
    else:
        if north is None:
            return Unresolved("no heading (ATTITUDE)")
        anchor = north
        if isinstance(target, GlobalTarget):
            gps = source.gps
            if gps is None or now_s - gps[0] > params.gps_timeout_s:
                return Unresolved("no GPS (GLOBAL_POSITION_INT)")
            _, stamp, lat0, lon0 = gps
            dn, de = ne_from_lat_lon(lat0, lon0, target.lat_deg, target.lon_deg)
            at = source.nav_pose_at(stamp)
            here = north.to_ned(at.x_m, at.y_m, at.yaw_rad)
            x, y, _ = north.from_ned(NedPose(here.north_m + dn, here.east_m + de, 0.0))
        elif target.frame == "offset":
            here = north.to_ned(pose.x_m, pose.y_m, pose.yaw_rad)
            x, y, _ = north.from_ned(NedPose(here.north_m + target.x_m, here.east_m + target.y_m, 0.0))
        else:  # LOCAL_NED: the autopilot's frame if it publishes one, else the start pose, north-aligned
            fixes = source.position_fixes
            newest = fixes[-1] if fixes else None
            if newest is not None and source.autopilot_time_s(now_s) - newest[0] <= LOCAL_POSITION_MAX_AGE_S:
                # Our pose at the newest fix onto it, with the rotation above.
                _, fx, fy, fyaw, fn, fe = newest
                ned_yaw = north.to_ned(fx, fy, fyaw).yaw_cw_rad
                anchor = LocalAnchor.matching(fx, fy, fyaw, NedPose(fn, fe, ned_yaw))
                frame_note = "autopilot"
            else:
                frame_note = "start"
            x, y, _ = anchor.from_ned(NedPose(target.x_m, target.y_m, 0.0))
        yaw = None
        if target.yaw_cw_rad is not None:
            yaw = anchor.from_ned(NedPose(0.0, 0.0, target.yaw_cw_rad))[2]
    distance = math.hypot(x - pose.x_m, y - pose.y_m)
    if distance > params.max_distance_m:
        return Unresolved(f"{distance:.0f} m away, max {params.max_distance_m:.0f} m", temporary=False)
    return NavTarget(x, y, pose.x_m, pose.y_m, yaw, speed, anchor,
                     target if isinstance(target, GlobalTarget) else None, frame_note)


class GotoController:
    """Turn in place, regulated pure pursuit on a braking curve, a stop inside the radius, the final yaw
    (module docstring).

    One instance follows one target at a time (`reset` for a new one): it remembers whether it is turning
    in place (hysteresis: it turns until the heading error is below yaw_tolerance_deg, then drives, so it
    does not start each leg on an arc), whether it is inside the radius (inside once is inside: it does
    not chase the point again, nor turn back to it, because the stop drifted) and whether it has stopped.
    """

    def __init__(self, params: NavigationParams, limits: LimitsParams, stop: StopProfile) -> None:
        self.radius_m = params.arrival_radius_m
        self.turn_in_place_rad = math.radians(params.turn_in_place_deg)
        self.lookahead_m = params.lookahead_m
        self.yaw_tolerance_rad = math.radians(params.yaw_tolerance_deg)
        self.max_omega = limits.max_angular_rad_s
        self.alpha = limits.max_angular_accel_rad_s2
        self.stop = stop
        self.arrived = False  # inside the radius
        self.stopped = False  # and the curve asks for (nearly) nothing more
        self.turning = False

    def reset(self) -> None:
        self.arrived = self.stopped = self.turning = False

    def turn_rate(self, error_rad: float) -> float:
        """CCW rate toward a heading error, slowing so that the turn stops on it within the angular limit:
        at sqrt(alpha * |error|) a turn stops in half the error; the linear part settles the last degrees."""
        rate = min(self.max_omega, math.sqrt(self.alpha * abs(error_rad)), 4.0 * abs(error_rad))
        return math.copysign(rate, error_rad)

    def status(self, pose: Pose2D, t: NavTarget) -> NavStatus:
        dx, dy = t.x_m - pose.x_m, t.y_m - pose.y_m
        lx, ly = t.x_m - t.start_x_m, t.y_m - t.start_y_m
        leg = math.hypot(lx, ly)
        # Signed distance from the leg (start -> target), positive to the right of it, as ArduPilot's.
        cross = 0.0 if leg < 1e-6 else ((pose.x_m - t.start_x_m) * ly - (pose.y_m - t.start_y_m) * lx) / leg
        bearing_cw = math.remainder(t.anchor.rotation_cw_rad + yaw_frd_from_yaw_flu(math.atan2(dy, dx)),
                                    2.0 * math.pi)
        phase = "yaw" if self.stopped else "turn" if self.turning else "drive"
        return NavStatus(math.hypot(dx, dy), bearing_cw, cross, phase)

    def twist(self, pose: Pose2D, t: NavTarget) -> tuple[Twist2D, NavStatus]:
        """What to drive now; the status's phase is "done" once the target (and its yaw) is reached."""
        dx, dy = t.x_m - pose.x_m, t.y_m - pose.y_m
        distance = math.hypot(dx, dy)
        if not self.arrived and distance <= self.radius_m:
            self.arrived = True
        status = self.status(pose, t)
        done = NavStatus(status.distance_m, status.bearing_cw_rad, status.crosstrack_m, "done")
        if self.arrived and not self.stopped:
            # What is left along the heading, on the same curve, no steering: a point a few centimetres
            # aside is not chased (it would swing the heading), one just passed is not turned back to.
            along = dx * math.cos(pose.yaw_rad) + dy * math.sin(pose.yaw_rad)
            speed = min(t.speed_m_s, self.stop.speed_m_s(along))
            if speed > self.stop.settle_m_s:
                return Twist2D(speed, 0.0), status
            self.stopped = True
            status = self.status(pose, t)
        if self.stopped:
            if t.yaw_rad is None:
                return Twist2D(), done
            error = wrap_angle(t.yaw_rad - pose.yaw_rad)
            if abs(error) <= self.yaw_tolerance_rad:
                return Twist2D(), done
            return Twist2D(0.0, self.turn_rate(error)), status
        error = wrap_angle(math.atan2(dy, dx) - pose.yaw_rad)
        if abs(error) > self.turn_in_place_rad:
            self.turning = True
        elif abs(error) <= self.yaw_tolerance_rad:
            self.turning = False
        if self.turning:
            return Twist2D(0.0, self.turn_rate(error)), self.status(pose, t)
        speed = min(t.speed_m_s, self.stop.speed_m_s(distance)) * max(0.0, math.cos(error))
        # Pure pursuit on the leg: the point a look-ahead ahead of the rover's projection onto it.
        lx, ly = t.x_m - t.start_x_m, t.y_m - t.start_y_m
        leg = math.hypot(lx, ly)
        ahead = max(self.lookahead_m, LOOKAHEAD_S * speed)
        if leg < 1e-6 or distance <= ahead:
            px, py = t.x_m, t.y_m
        else:
            along = ((pose.x_m - t.start_x_m) * lx + (pose.y_m - t.start_y_m) * ly) / leg
            s = min(leg, max(0.0, along) + ahead)
            px, py = t.start_x_m + lx * s / leg, t.start_y_m + ly * s / leg
        alpha = wrap_angle(math.atan2(py - pose.y_m, px - pose.x_m) - pose.yaw_rad)
        chord = max(1e-6, math.hypot(px - pose.x_m, py - pose.y_m))
        omega = 2.0 * math.sin(alpha) / chord * speed
        if abs(omega) > self.max_omega:  # regulated: slow down rather than cut the curvature
            speed *= self.max_omega / abs(omega)
            omega = math.copysign(self.max_omega, omega)
        return Twist2D(speed, omega), status
