"""The one place where MAVLink's sign and frame conventions meet rover-bridge's.

MAVLink: NED / FRD, yaw and yaw rates clockwise positive (seen from above), body y to the
right. rover-bridge inside: x forward, y left, yaw and omega counter-clockwise positive.
Most bugs in this field are sign bugs; every conversion lives here and is tested with a
spin in place and a right turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def omega_from_mavlink_yaw_rate(yaw_rate_cw_rad_s: float) -> float:
    """MAVLink yaw rate (clockwise +, a right turn) -> omega (counter-clockwise +)."""
    return -yaw_rate_cw_rad_s


def mavlink_yaw_rate_from_omega(omega_ccw_rad_s: float) -> float:
    """omega (counter-clockwise +) -> MAVLink yaw rate (clockwise +)."""
    return -omega_ccw_rad_s


def yaw_frd_from_yaw_flu(yaw_ccw_rad: float) -> float:
    """Heading in our x-forward/y-left frame -> heading in the matching FRD frame (clockwise +)."""
    return -yaw_ccw_rad


def yaw_flu_from_yaw_frd(yaw_cw_rad: float) -> float:
    """A heading or bearing clockwise + (FRD, NED, MAVLink sensor orientations) -> ours (counter-clockwise +)."""
    return -yaw_cw_rad


def y_frd_from_y_flu(y_left_m: float) -> float:
    """Lateral coordinate: y left (ours) -> y right (FRD)."""
    return -y_left_m


def quaternion_from_yaw(yaw_rad: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a pure rotation about the down (FRD/NED) axis by `yaw_rad` (clockwise +)."""
    half = 0.5 * yaw_rad
    return (math.cos(half), 0.0, 0.0, math.sin(half))


def ned_heading_rad(v_north_m_s: float, v_east_m_s: float) -> float:
    """Direction of a horizontal NED velocity, clockwise from north (as ATTITUDE.yaw)."""
    return math.atan2(v_east_m_s, v_north_m_s)


def heading_error_rad(target_cw_rad: float, current_cw_rad: float) -> float:
    """Signed shortest turn from current to target, clockwise + (positive = turn right), in [-pi, pi]."""
    return math.remainder(target_cw_rad - current_cw_rad, 2.0 * math.pi)


def heading_from_body_yaw_rad(current_cw_rad: float, body_yaw_cw_rad: float) -> float:
    """A yaw given in a body frame (relative, clockwise +) -> absolute heading from north, in [-pi, pi]."""
    return math.remainder(current_cw_rad + body_yaw_cw_rad, 2.0 * math.pi)


def omega_toward_heading(target_cw_rad: float, current_cw_rad: float, kp_1_s: float,
                         max_rad_s: float) -> float:
    """Proportional heading controller: omega (counter-clockwise +) that turns toward `target_cw_rad`.

    A positive (clockwise) heading error is a right turn, which is a negative omega here.
    """
    yaw_rate_cw = kp_1_s * heading_error_rad(target_cw_rad, current_cw_rad)
    yaw_rate_cw = max(-max_rad_s, min(max_rad_s, yaw_rate_cw))
    return omega_from_mavlink_yaw_rate(yaw_rate_cw)


# Sign of each axis of (x, y, z, roll, pitch, yaw) - or of their rates - from x-forward/y-left/z-up
# to FRD: a half turn about x, so y, z, pitch and yaw change sign, x and roll do not.
EARTH_RADIUS_M = 6378137.0  # WGS-84 equatorial, as ArduPilot's Location uses


def ne_from_lat_lon(origin_lat_deg: float, origin_lon_deg: float, lat_deg: float,
                    lon_deg: float) -> tuple[float, float]:
    """(north m, east m) of a lat/lon from the origin, on the flat patch about the origin (over the few hundred
    metres a target or a fence spans, the error is under a centimetre)."""
    north = math.radians(lat_deg - origin_lat_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - origin_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(origin_lat_deg))
    return north, east


FLU_TO_FRD_SIGNS = (1.0, -1.0, -1.0, 1.0, -1.0, -1.0)


def covariance_frd_from_flu(cov_flu: list[list[float]]) -> list[list[float]]:
    """6x6 covariance of (x, y, z, roll, pitch, yaw) or of their rates: FLU -> FRD.

    C_frd = S C_flu S with S = diag(FLU_TO_FRD_SIGNS): variances keep their values, cross terms
    between one flipped and one unflipped axis change sign (e.g. x-y, x-yaw), others do not (y-yaw).
    """
    s = FLU_TO_FRD_SIGNS
    return [[s[i] * s[j] * float(cov_flu[i][j]) for j in range(6)] for i in range(6)]


# ------------------------------------------------------------------ the autopilot's local frame

@dataclass(frozen=True, slots=True)
class NedPose:
    """A pose in a local NED frame (the autopilot's LOCAL_POSITION_NED frame): north, east, yaw clockwise
    from north (as ATTITUDE.yaw)."""

    north_m: float = 0.0
    east_m: float = 0.0
    yaw_cw_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class LocalAnchor:
    """Where the bridge's own frame (x forward of the start pose, y left, yaw CCW) lies in a NED frame.

    A point of the start frame, taken as FRD (x forward, y right), is rotated clockwise by
    `rotation_cw_rad` (the start pose's heading from north) and moved by (north_m, east_m). The
    identity anchor is the start frame itself (x as 'north', y right as 'east').
    """

    north_m: float = 0.0
    east_m: float = 0.0
    rotation_cw_rad: float = 0.0

    @classmethod
    def matching(cls, ours_x_m: float, ours_y_m: float, ours_yaw_rad: float, theirs: NedPose) -> LocalAnchor:
        """The anchor that puts our pose (x, y left, yaw CCW) exactly onto `theirs`."""
        rotation = math.remainder(theirs.yaw_cw_rad - yaw_frd_from_yaw_flu(ours_yaw_rad), 2.0 * math.pi)
        c, s = math.cos(rotation), math.sin(rotation)
        fwd, right = ours_x_m, y_frd_from_y_flu(ours_y_m)
        return cls(theirs.north_m - (c * fwd - s * right), theirs.east_m - (s * fwd + c * right), rotation)

    def to_ned(self, x_m: float, y_m: float, yaw_rad: float) -> NedPose:
        """Our pose (x forward of the start pose, y left, yaw CCW) in the NED frame."""
        c, s = math.cos(self.rotation_cw_rad), math.sin(self.rotation_cw_rad)
        fwd, right = x_m, y_frd_from_y_flu(y_m)
        return NedPose(self.north_m + c * fwd - s * right, self.east_m + s * fwd + c * right,
                       math.remainder(yaw_frd_from_yaw_flu(yaw_rad) + self.rotation_cw_rad, 2.0 * math.pi))

    def from_ned(self, ned: NedPose) -> tuple[float, float, float]:
        """A NED pose in our frame: (x forward of the start pose, y left, yaw CCW)."""
        c, s = math.cos(self.rotation_cw_rad), math.sin(self.rotation_cw_rad)
        dn, de = ned.north_m - self.north_m, ned.east_m - self.east_m
        fwd, right = c * dn + s * de, -s * dn + c * de
        return fwd, -right, -math.remainder(ned.yaw_cw_rad - self.rotation_cw_rad, 2.0 * math.pi)
