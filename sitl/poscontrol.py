"""Rover's position controller and pivot turns, as behaviour (no code copied).

Read in ArduPilot (Rover 4.7): libraries/APM_Control/AR_PosControl.cpp (update, init, set_limits),
libraries/AC_PID/AC_P_2D.cpp + AP_Math/control.cpp (sqrt_controller), AC_PID_2D.cpp, and
libraries/AR_WPNav/AR_PivotTurn.cpp. What is kept:

- Position: velocity target = sqrt-shaped P (PSC_POS_P 0.2; linear up to accel/P^2, the error clamped
  to what the speed limit allows) on the target's position error, plus the target's own velocity,
  limited to the speed limit. Acceleration target = PSC_VEL_P (1.0) times the velocity error (filtered
  at 5 Hz) plus the target's acceleration. Desired speed = the forward part of the velocity target
  (unless stopping, never below the speed the vehicle turns at: sqrt(ATC_TURN_MAX_G * g / 2 *
  TURN_RADIUS), and 0 for a skid-steering rover, which can pivot), acceleration-limited; desired turn
  rate = the lateral part of the acceleration target / max(speed, 1 m/s). Idle for 100 ms: it starts
  again from where the vehicle is.
- Pivot (skid-steering only, WP_PIVOT_ANGLE > 5): starts when the heading error to the next leg is
  more than WP_PIVOT_ANGLE; the vehicle first slows to zero, then turns on the spot towards the leg at
  up to WP_PIVOT_RATE (through the heading controller ATC_STR_ANG_P); it ends within 5 deg of the leg
  and WP_PIVOT_DELAY seconds after that.
"""

from __future__ import annotations

import math

from sitl.control import AttitudeControl, NavState, ParamGetter, filter_alpha

TIMEOUT_MS = 100  # AR_POSCON_TIMEOUT_MS and AR_PIVOT_TIMEOUT_MS
POS_P = 0.2  # AR_POSCON_POS_P (PSC_POS_P)
VEL_P = 1.0  # AR_POSCON_VEL_P (PSC_VEL_P)
VEL_FILT_HZ = 5.0
PIVOT_ACCURACY_DEG = 5.0

Vec = tuple[float, float]


def _sub(a: Vec, b: Vec) -> Vec:
    return a[0] - b[0], a[1] - b[1]


def _norm(a: Vec) -> float:
    return math.hypot(a[0], a[1])


def _limit(a: Vec, length: float) -> Vec:
    n = _norm(a)
    return a if n <= length or n == 0.0 else (a[0] * length / n, a[1] * length / n)


def _to_body(a: Vec, yaw: float) -> Vec:
    """NED (north, east) -> body (forward, right)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return a[0] * c + a[1] * s, -a[0] * s + a[1] * c


def sqrt_controller(error: float, p: float, accel_max: float) -> float:
    """Linear near zero, then the speed from which ``accel_max`` stops within the error."""
    if accel_max <= 0.0:
        return error * p
    linear = accel_max / (p * p)
    if error > linear:
        return math.sqrt(2.0 * accel_max * (error - linear / 2.0))
    if error < -linear:
        return -math.sqrt(2.0 * accel_max * (-error - linear / 2.0))
    return error * p


def inv_sqrt_controller(output: float, p: float, accel_max: float) -> float:
    if accel_max <= 0.0:
        return output / p
    if abs(output) < accel_max / p:
        return output / p
    linear = accel_max / (p * p)
    return output * output / (2.0 * accel_max) + linear / 2.0


class PosControl:
    """AR_PosControl (see the module docstring); the target comes from set_target each loop."""

    def __init__(self, atc: AttitudeControl) -> None:
        self._atc = atc
        self.speed_max = self.accel_max = self.lat_accel_max = self.jerk_max = 0.0
        self.turn_radius_m = 0.0  # 0 for a skid-steering rover (it can pivot), else TURN_RADIUS
        self.pos_target: Vec = (0.0, 0.0)
        self.vel_desired: Vec = (0.0, 0.0)
        self.accel_desired: Vec = (0.0, 0.0)
        self._vel_error: Vec | None = None  # filtered; None = reset
        self._last_ms: int | None = None
        self.desired_speed = 0.0
        self.turn_rate_rad_s = 0.0
        self.lat_accel = 0.0

    def set_limits(self, speed_max: float, accel_max: float, lat_accel_max: float, jerk_max: float) -> None:
        self.speed_max, self.accel_max = max(speed_max, 0.0), max(accel_max, 0.0)
        self.lat_accel_max, self.jerk_max = max(lat_accel_max, 0.0), max(jerk_max, 0.0)

    def active(self, now_ms: int) -> bool:
        return self._last_ms is not None and now_ms - self._last_ms < TIMEOUT_MS

    def init(self, nav: NavState) -> None:
        self.pos_target = (nav.north_m, nav.east_m)
        self.vel_desired = (nav.vel_n_m_s, nav.vel_e_m_s)
        self.accel_desired = (0.0, 0.0)

    def set_target(self, pos: Vec, vel: Vec, accel: Vec) -> None:
        self.pos_target, self.vel_desired, self.accel_desired = pos, vel, accel

    def pos_error(self, nav: NavState, now_ms: int) -> Vec:
        if not self.active(now_ms):
            return 0.0, 0.0
        return _sub(self.pos_target, (nav.north_m, nav.east_m))

    def _d1_max(self) -> float:
        d1 = min(self.accel_max, self.lat_accel_max)
        if self.jerk_max > 0.0:
            d1 = min(d1, self.jerk_max / POS_P)
        return d1

    def update(self, nav: NavState, now_ms: int, dt_s: float) -> None:
        if not self.active(now_ms):
            self._vel_error = None
        self._last_ms = now_ms
        error = _sub(self.pos_target, (nav.north_m, nav.east_m))
        d1 = self._d1_max()
        if self.speed_max > 0.0:
            error = _limit(error, inv_sqrt_controller(self.speed_max, POS_P, d1))
        n = _norm(error)
        scale = sqrt_controller(n, POS_P, d1) / n if n > 0.0 else 0.0
        vel_target: Vec = (error[0] * scale + self.vel_desired[0], error[1] * scale + self.vel_desired[1])
        stopping = self.vel_desired == (0.0, 0.0)
        vel_target = _limit(vel_target, self.speed_max)
        raw = _sub(vel_target, (nav.vel_n_m_s, nav.vel_e_m_s))
        if self._vel_error is None:
            self._vel_error = raw
        else:
            k = filter_alpha(dt_s, VEL_FILT_HZ)
            e = self._vel_error
            self._vel_error = (e[0] + k * (raw[0] - e[0]), e[1] + k * (raw[1] - e[1]))
        accel = (self._vel_error[0] * VEL_P + self.accel_desired[0], self._vel_error[1] * VEL_P + self.accel_desired[1])
        speed = _to_body(vel_target, nav.yaw_rad)[0]
        if not stopping:  # never slower than the vehicle can turn at (0 when it can pivot)
            turn_speed_min = math.sqrt(max(0.0, self._atc.turn_lat_accel_max * 0.5 * self.turn_radius_m))
            speed = max(min(_norm(vel_target), turn_speed_min), speed)
        self.desired_speed = self._atc.desired_speed_accel_limited(speed, dt_s)
        self.lat_accel = 0.0 if stopping else _to_body(accel, nav.yaw_rad)[1]
        self.turn_rate_rad_s = self._atc.turn_rate_from_lat_accel(self.lat_accel, self.desired_speed)


class PivotTurn:
    """AR_PivotTurn (see the module docstring)."""

    def __init__(self, param: ParamGetter, atc: AttitudeControl) -> None:
        self._param = param
        self._atc = atc
        self.enabled = False
        self._active = False
        self._delay_start_ms: int | None = None

    @property
    def active(self) -> bool:
        return self.enabled and self._active

    def deactivate(self) -> None:
        self._active = False

    def _usable(self) -> bool:
        return self.enabled and self._param("WP_PIVOT_ANGLE") > PIVOT_ACCURACY_DEG

    def check_activation(self, heading_deg: float, yaw_deg: float, now_ms: int, force: bool = False) -> None:
        if not self._usable():
            self._active = False
            return
        error = abs(math.remainder(heading_deg - yaw_deg, 360.0))
        if error > self._param("WP_PIVOT_ANGLE") or force:
            self._active, self._delay_start_ms = True, None
            return
        if self._active and error < PIVOT_ACCURACY_DEG and self._delay_start_ms is None:
            self._delay_start_ms = now_ms
        delay_ms = max(0.0, min(60.0, self._param("WP_PIVOT_DELAY"))) * 1000.0
        if self._delay_start_ms is not None and now_ms - self._delay_start_ms >= delay_ms:
            self._active, self._delay_start_ms = False, None

    def would_activate(self, yaw_change_deg: float) -> bool:
        return self._usable() and abs(math.remainder(yaw_change_deg, 360.0)) > self._param("WP_PIVOT_ANGLE")

    def turn_rate_rad_s(self, heading_deg: float, yaw_deg: float, now_ms: int) -> float:
        rate = self._atc.turn_rate_from_heading(math.radians(heading_deg), math.radians(self._param("WP_PIVOT_RATE")))
        self.check_activation(heading_deg, yaw_deg, now_ms)
        return rate
