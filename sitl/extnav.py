"""ArduPilot's use of ODOMETRY as external navigation (VISO_TYPE = 1, EK3_SRC1_* = 6): behaviour only.

Read in ArduPilot's source (GCS_Common.cpp handle_odometry, AP_VisualOdom_MAV.cpp, AP_NavEKF3
writeExtNavData / SelectVelPosFusion / FuseVelPosNED / fuseEulerYaw) and measured on a real Rover 4.7:

- Only frame_id MAV_FRAME_LOCAL_FRD (20) with child_frame_id MAV_FRAME_BODY_FRD (12) is used; other
  frames are dropped silently. Frames closer than 20 ms apart are dropped (EKF3 takes 50 Hz at most).
- The pose covariance is folded into one position error, cbrt(var_x^2 + var_y^2 + var_z^2), and one
  angle error, cbrt(var_roll^2 + var_pitch^2 + var_yaw^2), clamped to [VISO_POS_M_NSE, 100 m] and
  [VISO_YAW_M_NSE, 1.5 rad]; yaw is never trusted better than 5 deg. The velocity covariance is
  ignored (VISO_VEL_M_NSE is used).
- Velocity (body FRD) is rotated into the local frame by the frame's own quaternion and fused.
- Position: innovation test with EK3_POS_I_GATE (500 = 5 sigma); a rejected position is retried and,
  after 10 s of rejections with velocity aiding, the position is reset to the external one.
  A changed reset_counter resets the north/east position to the new one at once (not the yaw).
- Yaw (EK3_SRC1_YAW = 6): innovation test with EK3_YAW_I_GATE (300 = 3 sigma); a rejected yaw is not
  used, and the estimate's north stays what the first frames made it.
- The EKF starts using the data about 2 s after the first frame ("EKF3 IMU0 is using external nav
  data"); before that the autopilot has no position (LOCAL_POSITION_NED is not sent).

The model is the autopilot's position estimate, not a copy of EKF3: position and yaw with one
variance each; velocity predicted with the IMU (the body's acceleration, rotated by the estimate's
own yaw) and pulled toward each frame's velocity; yaw predicted with the gyro. So when the frames
stop the estimate dead-reckons on the IMU, as the EKF does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.mav import MAVLinkMessage

FRAME_LOCAL_FRD = 20
FRAME_BODY_FRD = 12
MIN_INTERVAL_US = 20_000
POS_ERR_MAX_M = 100.0
ANG_ERR_MAX_RAD = 1.5
YAW_ERR_MIN_RAD = math.radians(5.0)
POS_RETRY_WITH_VEL_US = 10_000_000
START_DELAY_US = 2_000_000
USING_TEXT = "EKF3 IMU0 is using external nav data"
VEL_GAIN = 0.5  # share of a frame's velocity innovation fused


@dataclass(frozen=True)
class ExtNavSettings:
    """The ArduPilot parameters that matter here (their defaults)."""

    pos_noise_m: float = 0.2  # VISO_POS_M_NSE
    yaw_noise_rad: float = 0.2  # VISO_YAW_M_NSE
    vel_noise_m_s: float = 0.1  # VISO_VEL_M_NSE
    pos_gate: float = 5.0  # EK3_POS_I_GATE / 100
    yaw_gate: float = 3.0  # EK3_YAW_I_GATE / 100
    use_yaw: bool = True  # EK3_SRC1_YAW = 6


def _yaw_of(q: list[float]) -> float:
    """Yaw (clockwise from north, FRD/NED) of a quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def folded_errors(pose_covariance: list[float]) -> tuple[float, float]:
    """(position error m, angle error rad) as ArduPilot folds the 21-element pose covariance, before clamping."""
    c = [float(v) for v in pose_covariance]
    if math.isnan(c[0]):
        return 0.0, 0.0
    return (math.cbrt(c[0] ** 2 + c[6] ** 2 + c[11] ** 2), math.cbrt(c[15] ** 2 + c[18] ** 2 + c[20] ** 2))


class ExtNavConsumer:
    """The autopilot's position and yaw estimate when it navigates on ODOMETRY (see the module doc)."""

    def __init__(self, settings: ExtNavSettings | None = None) -> None:
        self.settings = settings or ExtNavSettings()
        self.started_us: int | None = None
        self.using = False
        self.north_m = self.east_m = 0.0
        self.pos_var = 0.0
        self.yaw_cw_rad = 0.0
        self.yaw_var = 0.0
        self.vel_n_m_s = self.vel_e_m_s = 0.0
        self._last_us: int | None = None
        self._last_reset_counter: int | None = None
        self._rejected_since_us: int | None = None
        self.counters = {"frames": 0, "dropped_frame": 0, "dropped_rate": 0, "pos_fused": 0, "pos_rejected": 0,
                         "pos_resets": 0, "pos_timeout_resets": 0, "yaw_fused": 0, "yaw_rejected": 0}
        self.last_errors: tuple[float, float] = (0.0, 0.0)  # clamped (position m, angle rad) of the last frame

    def position(self) -> tuple[float, float] | None:
        """North, east of the autopilot's estimate; None before it uses external navigation."""
        return (self.north_m, self.east_m) if self.using else None

    def update(self, now_us: int) -> str | None:
        """The autopilot's loop: the text it says when it starts using the data (once)."""
        if not self.using and self.started_us is not None and now_us >= self.started_us + START_DELAY_US:
            self.using = True
            return USING_TEXT
        return None

    def predict(self, dt_s: float, gyro_cw_rad_s: float, accel_fwd_m_s2: float = 0.0,
                accel_right_m_s2: float = 0.0) -> None:
        """The EKF's prediction: the IMU's body acceleration (FRD) rotated by its yaw, the gyro."""
        if self.started_us is None or dt_s <= 0.0:
            return
        c, s = math.cos(self.yaw_cw_rad), math.sin(self.yaw_cw_rad)
        self.vel_n_m_s += (c * accel_fwd_m_s2 - s * accel_right_m_s2) * dt_s
        self.vel_e_m_s += (s * accel_fwd_m_s2 + c * accel_right_m_s2) * dt_s
        self.north_m += self.vel_n_m_s * dt_s
        self.east_m += self.vel_e_m_s * dt_s
        self.pos_var += (self.settings.vel_noise_m_s * dt_s) ** 2 + 1e-4 * dt_s
        self.yaw_cw_rad = math.remainder(self.yaw_cw_rad + gyro_cw_rad_s * dt_s, 2.0 * math.pi)
        self.yaw_var += 1e-5 * dt_s

    def odometry(self, msg: MAVLinkMessage, now_us: int, ahrs_yaw_cw_rad: float) -> None:
        """One ODOMETRY frame from the companion."""
        st = self.settings
        if int(msg.frame_id) != FRAME_LOCAL_FRD or int(msg.child_frame_id) != FRAME_BODY_FRD:
            self.counters["dropped_frame"] += 1
            return
        if self._last_us is not None and now_us - self._last_us < MIN_INTERVAL_US:
            self.counters["dropped_rate"] += 1
            return
        values = (float(msg.x), float(msg.y), float(msg.vx), float(msg.vy), *(float(v) for v in msg.q))
        if not all(math.isfinite(v) for v in values):
            self.counters["dropped_frame"] += 1
            return
        self._last_us = now_us
        self.counters["frames"] += 1
        pos_err, ang_err = folded_errors(list(msg.pose_covariance))
        pos_err = min(max(pos_err, st.pos_noise_m), POS_ERR_MAX_M)
        ang_err = min(max(ang_err, st.yaw_noise_rad), ANG_ERR_MAX_RAD)
        self.last_errors = (pos_err, ang_err)
        yaw = _yaw_of(list(msg.q))
        vx, vy = float(msg.vx), float(msg.vy)
        c, s = math.cos(yaw), math.sin(yaw)
        vn, ve = c * vx - s * vy, s * vx + c * vy  # rotated by the frame's own quaternion
        # VISO_VEL_M_NSE (0.1 m/s) is tight: each frame pulls the velocity most of the way to its own.
        self.vel_n_m_s += VEL_GAIN * (vn - self.vel_n_m_s)
        self.vel_e_m_s += VEL_GAIN * (ve - self.vel_e_m_s)
        r_pos = pos_err * pos_err
        yaw_err = max(ang_err, YAW_ERR_MIN_RAD)
        reset = self._last_reset_counter is not None and int(msg.reset_counter) != self._last_reset_counter
        self._last_reset_counter = int(msg.reset_counter)
        if self.started_us is None:  # first frame: the estimate starts here
            self.started_us = now_us
            self.north_m, self.east_m, self.pos_var = float(msg.x), float(msg.y), r_pos
            self.yaw_cw_rad = yaw if st.use_yaw else ahrs_yaw_cw_rad
            self.yaw_var = yaw_err * yaw_err
            return
        dn, de = float(msg.x) - self.north_m, float(msg.y) - self.east_m
        if reset:
            self.north_m, self.east_m, self.pos_var = float(msg.x), float(msg.y), r_pos
            self._rejected_since_us = None
            self.counters["pos_resets"] += 1
        else:
            var = self.pos_var + r_pos
            if (dn * dn + de * de) / (st.pos_gate * st.pos_gate * 2.0 * var) <= 1.0:
                k = self.pos_var / var
                self.north_m += k * dn
                self.east_m += k * de
                self.pos_var *= 1.0 - k
                self._rejected_since_us = None
                self.counters["pos_fused"] += 1
            else:
                self.counters["pos_rejected"] += 1
                if self._rejected_since_us is None:
                    self._rejected_since_us = now_us
                elif now_us - self._rejected_since_us > POS_RETRY_WITH_VEL_US:
                    self.north_m, self.east_m, self.pos_var = float(msg.x), float(msg.y), r_pos
                    self._rejected_since_us = None
                    self.counters["pos_timeout_resets"] += 1
        if st.use_yaw:
            innov = math.remainder(yaw - self.yaw_cw_rad, 2.0 * math.pi)
            var_yaw = self.yaw_var + yaw_err * yaw_err
            if innov * innov <= st.yaw_gate * st.yaw_gate * var_yaw:
                k = self.yaw_var / var_yaw
                self.yaw_cw_rad = math.remainder(self.yaw_cw_rad + k * innov, 2.0 * math.pi)
                self.yaw_var *= 1.0 - k
                self.counters["yaw_fused"] += 1
            else:
                self.counters["yaw_rejected"] += 1
