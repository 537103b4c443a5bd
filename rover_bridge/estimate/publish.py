"""ODOMETRY (331) from the filter's state and covariance, on a fixed rate grid (pure).

- time_usec: the caller's stamp on the autopilot's boot clock (rover_bridge.estimate.clock).
- frame_id MAV_FRAME_LOCAL_FRD, child_frame_id MAV_FRAME_BODY_FRD (the only frames ArduPilot takes as
  external navigation). The pose is in the start frame (x forward of the start pose, y right) or, with
  an anchor (rover_bridge.estimate.anchor), in the autopilot's local frame (x north, y east, yaw from
  north: an FRD frame whose forward axis is north); z = 0; q from the clockwise yaw; vx forward,
  vy = 0, vz = 0, yawspeed CW+ (body frame either way).
- covariances: the filter's x, y, yaw, v, yaw-rate blocks with the FRD sign flips
  (frames.covariance_frd_from_flu); vy has a finite variance (LATERAL_SIGMA_* below: the wheels do
  not side-slip much, but not never); z, roll, pitch and their rates are unobserved: each gets
  [odometry] unobserved_variance (unset: 1e4 m^2 or rad^2 for ground stations, sigma 100: "unknown",
  as a number rather than the NaN-first-element convention, which many receivers mishandle; 0.01
  when ODOMETRY goes to the autopilot, which folds z into its one position error and roll and pitch
  into its one angle error). With an anchor the x, y block is rotated into the published frame.
- estimator_type MAV_ESTIMATOR_TYPE_UNKNOWN: the enum has no wheel/inertial dead-reckoning member;
  NAIVE claims no covariance (PX4 then ignores the covariance) and VIO claims a camera, both false.
- quality: 100 / (1 + sigma_xy / QUALITY_POS_M + sigma_yaw / QUALITY_YAW_RAD), rounded, clamped to
  1..100 (sigma_xy: the larger principal standard deviation of x, y); 0 when the wheels are stale
  (the estimate is then a blind extrapolation).
"""

# Kalman-filter notation (P for a covariance) reads better than pep8 names here.
# ruff: noqa: N803
from __future__ import annotations

import math

from rover_bridge import frames
from rover_bridge.estimate.models import IV, IW, IX, IY, IYAW, Floats, Rows
from rover_bridge.frames import LocalAnchor
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.wire import FLOAT32_MAX, Link, f32, uint
from rover_bridge.params import OdometryParams

LATERAL_SIGMA_M_S = 0.02  # vy: skid-steer side slip, plus ...
LATERAL_SIGMA_PER_M_S = 0.05  # ... a fraction of the forward speed ...
LATERAL_SIGMA_PER_RAD_S = 0.05  # ... and of the yaw rate (m/s per rad/s)
QUALITY_POS_M = 0.5
QUALITY_YAW_RAD = math.radians(5.0)

TARGET_LINKS: dict[str, tuple[Link, ...]] = {
    "gcs": (Link.GCS,),
    "autopilot": (Link.AUTOPILOT,),
    "both": (Link.GCS, Link.AUTOPILOT),
    "none": (),
}


def upper_triangle_21(cov: list[list[float]]) -> list[float]:
    """The 21 numbers MAVLink carries for a symmetric 6x6: row-major upper triangle incl. diagonal."""
    return [float(cov[i][j]) for i in range(6) for j in range(i, 6)]


def sigma_xy(P: Rows) -> float:
    """Larger principal standard deviation of the x, y block (closed form for a 2x2)."""
    a, b, c = float(P[IX][IX]), float(P[IX][IY]), float(P[IY][IY])
    half_tr = 0.5 * (a + c)
    lam = half_tr + math.sqrt(max(0.0, 0.25 * (a - c) ** 2 + b * b))
    return math.sqrt(max(0.0, lam))


def quality(P: Rows, wheels_fresh: bool) -> int:
    """ODOMETRY.quality (see the module docstring)."""
    if not wheels_fresh:
        return 0
    sigma_yaw = math.sqrt(max(0.0, float(P[IYAW][IYAW])))
    q = 100.0 / (1.0 + sigma_xy(P) / QUALITY_POS_M + sigma_yaw / QUALITY_YAW_RAD)
    return max(1, min(100, round(q)))


def _rotate_xy(cov: list[list[float]], angle_rad: float) -> list[list[float]]:
    """T C T' with T the rotation of the first two axes by angle_rad (x toward y), others unchanged."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    t = [[1.0 if i == j else 0.0 for j in range(6)] for i in range(6)]
    t[0][0], t[0][1], t[1][0], t[1][1] = c, -s, s, c
    tc = [[sum(t[i][k] * cov[k][j] for k in range(6)) for j in range(6)] for i in range(6)]
    return [[sum(tc[i][k] * t[j][k] for k in range(6)) for j in range(6)] for i in range(6)]


# ODOMETRY may leave up to this fraction of its period before its grid point, in a pass the bridge
# makes anyway (a message arrived, another output was due): a wake-up of its own costs more than the
# message. The grid stays, so the rate is exact on average; an early one is also at least this
# fraction of a period after the one before (one that left late does not bring it closer).
EARLY_FRACTION = 0.5
# ... but when it goes to the autopilot, never closer than this to the one before: ArduPilot's EKF3
# drops external navigation that comes less than 20 ms after the previous sample (AP_NavEKF3.h,
# extNavIntervalMin_ms).
EARLY_MIN_INTERVAL_S = 0.021


class OdometryPublisher:
    """Where ODOMETRY goes, when the next one is due, and how one is packed."""

    def __init__(self, params: OdometryParams) -> None:
        self.links = TARGET_LINKS[params.targets]
        self.unobserved_variance = params.resolved_unobserved_variance
        self.period_s = 1.0 / params.rate_hz
        self.early_s = EARLY_FRACTION * self.period_s
        # An early one is never closer than the window to the one before (nor, to the autopilot, than its EKF takes).
        self.min_interval_s = max(self.early_s, EARLY_MIN_INTERVAL_S if Link.AUTOPILOT in self.links else 0.0)
        self.next_s: float | None = None
        self._last_s = -math.inf  # when the last one left
        self.sent = 0

    def due(self, now_s: float, early: bool = False) -> bool:
        """True (and the grid moved on) when an ODOMETRY is due at now_s; with `early`, also from
        early_deadline_s on (see EARLY_FRACTION)."""
        last = self.next_s
        if not self.links or not (last is None or now_s >= (self._early_from(last) if early else last)):
            return False
        # Keep the grid; after a stall restart it instead of bursting the missed messages.
        base = now_s if last is None or now_s - last > self.period_s else last
        self.next_s = base + self.period_s
        self._last_s = now_s
        return True

    def _early_from(self, next_s: float) -> float:
        # The window before the grid point, but never within min_interval_s of the last one (to the
        # autopilot from about 48 Hz on: never early). On the grid point itself it is due either way.
        return min(next_s, max(next_s - self.early_s, self._last_s + self.min_interval_s))

    def deadline_s(self, now_s: float) -> float | None:
        """When the next ODOMETRY must leave (None: it goes nowhere)."""
        if not self.links:
            return None
        return now_s if self.next_s is None else self.next_s

    def early_deadline_s(self, now_s: float) -> float | None:
        """From when the next ODOMETRY may leave with a pass made anyway (due(early=True))."""
        if not self.links:
            return None
        return now_s if self.next_s is None else self._early_from(self.next_s)

    def message(self, x: Floats, P: Rows, time_usec: int, reset_counter: int, quality_0_100: int,
                anchor: LocalAnchor | None = None) -> MAVLinkMessage:
        """ODOMETRY for state x with covariance P (rover-bridge's FLU convention) at time_usec, in the start
        frame or, with `anchor`, in the autopilot's local frame.

        It runs at odometry.rate_hz, so the covariances are written out in closed form (the few entries
        the state has, FRD signs applied, rotated into the anchor's frame), not built as 6x6 matrices;
        `reference_covariances` is the general construction it is tested against."""
        big = self.unobserved_variance
        xs = [float(v) for v in x]
        p = P
        v, w = xs[IV], xs[IW]
        # FRD signs (x, -y, -yaw): x-y and x-yaw change sign, y-yaw does not.
        cxx, cxy, cyy = p[IX][IX], -p[IX][IY], p[IY][IY]
        cxw, cyw, cww = -p[IX][IYAW], p[IY][IYAW], p[IYAW][IYAW]
        if anchor is None:
            px, py, yaw_frd = xs[IX], -xs[IY], -xs[IYAW]
            # Zero entries keep the signs S C S gives them (-0.0 where one axis of the pair flips).
            pose_cov = [cxx, cxy, -0.0, 0.0, -0.0, cxw, cyy, 0.0, -0.0, 0.0, cyw, big, -0.0, 0.0, 0.0, big, -0.0,
                        -0.0, big, 0.0, cww]
        else:
            ned = anchor.to_ned(xs[IX], xs[IY], xs[IYAW])
            px, py, yaw_frd = ned.north_m, ned.east_m, ned.yaw_cw_rad
            c, s_ = math.cos(anchor.rotation_cw_rad), math.sin(anchor.rotation_cw_rad)
            t00, t01 = c * cxx - s_ * cxy, c * cxy - s_ * cyy  # R C, then (R C) R'
            t10, t11 = s_ * cxx + c * cxy, s_ * cxy + c * cyy
            pose_cov = [t00 * c - t01 * s_, t00 * s_ + t01 * c, 0.0, 0.0, 0.0, c * cxw - s_ * cyw,
                        t10 * s_ + t11 * c, 0.0, 0.0, 0.0, s_ * cxw + c * cyw, big, 0.0, 0.0, 0.0, big, 0.0, 0.0,
                        big, 0.0, cww]
        lateral = LATERAL_SIGMA_M_S + LATERAL_SIGMA_PER_M_S * abs(v) + LATERAL_SIGMA_PER_RAD_S * abs(w)
        vel_cov = [p[IV][IV], -0.0, -0.0, 0.0, -0.0, -p[IV][IW], lateral * lateral, 0.0, -0.0, 0.0, 0.0, big, -0.0,
                   0.0, 0.0, big, -0.0, -0.0, big, 0.0, p[IW][IW]]
        self.sent += 1
        half = 0.5 * yaw_frd if math.isfinite(yaw_frd) else math.nan
        # Clamped to the wire types: the estimate is fed by the autopilot, and a packing error must
        # never escape the loop (pymavlink raises on a float beyond float32 or an integer out of range).
        return mavlink.MAVLink_odometry_message(
            time_usec=uint(time_usec, 64),
            frame_id=mavlink.MAV_FRAME_LOCAL_FRD,
            child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
            x=f32(px),
            y=f32(py),
            z=0.0,
            q=[math.cos(half), 0.0, 0.0, math.sin(half)],
            vx=f32(v),
            vy=0.0,
            vz=0.0,
            rollspeed=0.0,
            pitchspeed=0.0,
            yawspeed=f32(-w),  # MAVLink's yaw rate is clockwise positive
            pose_covariance=[c if -FLOAT32_MAX <= c <= FLOAT32_MAX else f32(c) for c in pose_cov],
            velocity_covariance=[c if -FLOAT32_MAX <= c <= FLOAT32_MAX else f32(c) for c in vel_cov],
            reset_counter=uint(reset_counter, 8),
            estimator_type=mavlink.MAV_ESTIMATOR_TYPE_UNKNOWN,
            quality=min(100, uint(quality_0_100, 8)),  # int8_t on the wire: -1 (failure) to 100
        )


def reference_covariances(x: Floats, P: Rows, big: float, anchor: LocalAnchor | None = None
                          ) -> tuple[list[float], list[float]]:
    """ODOMETRY's (pose, velocity) covariances built the general way: 6x6 FLU matrices, S C S into FRD,
    rotated into the anchor's frame, upper triangles. The reference OdometryPublisher.message is
    tested against (tests/test_estimate_parts.py)."""
    v, w = float(x[IV]), float(x[IW])
    pose_flu = [[0.0] * 6 for _ in range(6)]
    vel_flu = [[0.0] * 6 for _ in range(6)]
    for a, ia in ((0, IX), (1, IY), (5, IYAW)):
        for b, ib in ((0, IX), (1, IY), (5, IYAW)):
            pose_flu[a][b] = float(P[ia][ib])
    for a, ia in ((0, IV), (5, IW)):
        for b, ib in ((0, IV), (5, IW)):
            vel_flu[a][b] = float(P[ia][ib])
    for k in (2, 3, 4):
        pose_flu[k][k] = vel_flu[k][k] = big
    lateral = LATERAL_SIGMA_M_S + LATERAL_SIGMA_PER_M_S * abs(v) + LATERAL_SIGMA_PER_RAD_S * abs(w)
    vel_flu[1][1] = lateral * lateral
    pose_frd = frames.covariance_frd_from_flu(pose_flu)
    if anchor is not None:
        pose_frd = _rotate_xy(pose_frd, anchor.rotation_cw_rad)
    return upper_triangle_21(pose_frd), upper_triangle_21(frames.covariance_frd_from_flu(vel_flu))
