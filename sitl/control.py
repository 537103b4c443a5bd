"""Rover's speed and turn-rate controllers, as behaviour (no code copied).

Read in ArduPilot (Rover 4.7): libraries/APM_Control/AR_AttitudeControl.cpp (get_steering_out_rate,
get_turn_rate_from_heading, get_turn_rate_from_lat_accel, get_throttle_out_speed, get_throttle_out_stop,
get_desired_speed_accel_limited, get_stopping_distance) and libraries/AC_PID/AC_PID.cpp (update_all,
update_i). What is kept:

- A PID filters its error at FLTE Hz (first order, alpha = dt / (dt + 1 / (2 pi f))), outputs
  P + I + D and reports FF = target * FF separately (the caller adds it). The integrator grows by
  error * I * dt, clamped to +-IMAX, and only shrinks while ``limit`` is set (the motors saturated).
- Turn rate (ATC_STR_RAT_*): the desired rate is slewed by ATC_STR_ACC_MAX, clamped to ATC_STR_RAT_MAX
  and to the lateral-acceleration limit ATC_TURN_MAX_G * g / max(|speed|, 1 m/s) (never below 1 deg/s);
  output = PID(desired, measured yaw rate) + FF * desired. Rates in rad/s, clockwise positive.
- Speed (ATC_SPEED_*): the desired speed is slewed by ATC_ACCEL_MAX (ATC_DECEL_MAX when slowing);
  throttle = PID(desired, forward speed) + desired * CRUISE_THROTTLE / CRUISE_SPEED (the feed-forward
  reported inside FF); both in [-1, 1] units of full throttle.
- Each controller resets its filter and integrator when it has not run for 200 ms; the stop controller
  returns 0 and resets the speed integrator once the desired speed is 0 and |speed| <= ATC_STOP_SPEED
  (and for 300 ms after). A controller that is not run keeps its last reported values (PID_TUNING
  freezes).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

GRAVITY_M_S2 = 9.80665
TIMEOUT_MS = 200  # AR_ATTCONTROL_TIMEOUT_MS
STOPPED_HOLD_MS = 300
STEER_SPEED_MIN_M_S = 1.0  # AR_ATTCONTROL_STEER_SPEED_MIN

ParamGetter = Callable[[str], float]


def filter_alpha(dt_s: float, cutoff_hz: float) -> float:
    """First-order low-pass gain for one sample (1 = no filtering)."""
    if cutoff_hz <= 0.0 or dt_s <= 0.0:
        return 1.0
    return dt_s / (dt_s + 1.0 / (2.0 * math.pi * cutoff_hz))


@dataclass(frozen=True)
class NavState:
    """The autopilot's own estimate, as its controllers see it (NED metres from the EKF origin)."""

    north_m: float
    east_m: float
    vel_n_m_s: float
    vel_e_m_s: float
    yaw_rad: float  # clockwise from north
    yaw_rate_rad_s: float  # clockwise positive

    @property
    def forward_speed_m_s(self) -> float:
        return self.vel_n_m_s * math.cos(self.yaw_rad) + self.vel_e_m_s * math.sin(self.yaw_rad)


@dataclass
class PidInfo:
    """What PID_TUNING reports of one controller."""

    target: float = 0.0
    actual: float = 0.0
    ff: float = 0.0
    p: float = 0.0
    i: float = 0.0
    d: float = 0.0


class Pid:
    """One AC_PID with gains read from parameters ``{prefix}_P``, ``_I``, ``_D``, ``_FF``, ``_IMAX``, ``_FLTE``."""

    def __init__(self, param: ParamGetter, prefix: str) -> None:
        self._param = param
        self._prefix = prefix
        self.integrator = 0.0
        self._error = 0.0
        self._derivative = 0.0
        self._reset_filter = True
        self.info = PidInfo()

    def gain(self, name: str) -> float:
        return self._param(f"{self._prefix}_{name}")

    def reset_filter(self) -> None:
        self._reset_filter = True

    def reset_i(self) -> None:
        self.integrator = 0.0

    def update(self, target: float, measurement: float, dt_s: float, limit: bool) -> float:
        """P + I + D for this sample (FF is in ``info.ff``)."""
        if not (math.isfinite(target) and math.isfinite(measurement)):
            return 0.0
        error = target - measurement
        if self._reset_filter:
            self._reset_filter = False
            self._error = error
            self._derivative = 0.0
        else:
            last = self._error
            self._error += filter_alpha(dt_s, self.gain("FLTE")) * (error - self._error)
            if dt_s > 0.0:
                self._derivative = (self._error - last) / dt_s
        ki = self.gain("I")
        if ki != 0.0 and dt_s > 0.0:
            shrinking = (self.integrator > 0.0 > self._error) or (self.integrator < 0.0 < self._error)
            if not limit or shrinking:
                imax = self.gain("IMAX")
                self.integrator = max(-imax, min(imax, self.integrator + self._error * ki * dt_s))
        else:
            self.integrator = 0.0
        p = self._error * self.gain("P")
        d = self._derivative * self.gain("D")
        self.info = PidInfo(target, measurement, target * self.gain("FF"), p, self.integrator, d)
        return p + d + self.integrator


class AttitudeControl:
    """AR_AttitudeControl's speed and turn-rate paths (see the module docstring)."""

    def __init__(self, param: ParamGetter) -> None:
        self._param = param
        self.steer_pid = Pid(param, "ATC_STR_RAT")
        self.speed_pid = Pid(param, "ATC_SPEED")
        self.now_ms = 0
        self.nav: NavState | None = None
        self._desired_turn_rate = 0.0
        self._steer_last_ms: int | None = None
        self._desired_speed = 0.0
        self._speed_last_ms: int | None = None
        self._stop_last_ms: int | None = None
        self._thr_limit_low = self._thr_limit_high = False
        self.speed_info = PidInfo()  # the speed PID's info with the cruise feed-forward in ff

    def tick(self, now_ms: int, nav: NavState | None) -> None:
        """The loop's time and estimate for this iteration's calls."""
        self.now_ms = now_ms
        self.nav = nav

    # ------------------------------------------------------------------ helpers
    def forward_speed(self) -> float | None:
        return None if self.nav is None else self.nav.forward_speed_m_s

    @property
    def turn_lat_accel_max(self) -> float:
        return max(self._param("ATC_TURN_MAX_G"), 0.1) * GRAVITY_M_S2

    @property
    def accel_max(self) -> float:
        return self._param("ATC_ACCEL_MAX")

    @property
    def decel_max(self) -> float:
        decel = self._param("ATC_DECEL_MAX")
        return decel if decel > 0.0 else self.accel_max

    def stopping_distance(self, speed_m_s: float) -> float:
        decel = self.decel_max
        if decel <= 0.0 or speed_m_s == 0.0:
            return 0.0
        return 0.5 * speed_m_s * speed_m_s / decel

    def _recent(self, last_ms: int | None) -> bool:
        return last_ms is not None and self.now_ms - last_ms <= TIMEOUT_MS

    def speed_control_active(self) -> bool:
        return self._recent(self._speed_last_ms)

    @property
    def desired_speed(self) -> float:
        return self._desired_speed if self.speed_control_active() else 0.0

    @property
    def desired_turn_rate(self) -> float:
        return self._desired_turn_rate if self._recent(self._steer_last_ms) else 0.0

    @staticmethod
    def turn_rate_from_lat_accel(lat_accel_m_s2: float, speed_m_s: float) -> float:
        if abs(speed_m_s) < STEER_SPEED_MIN_M_S:
            speed_m_s = -STEER_SPEED_MIN_M_S if speed_m_s < 0.0 else STEER_SPEED_MIN_M_S
        return lat_accel_m_s2 / speed_m_s

    def turn_rate_from_heading(self, heading_rad: float, rate_max_rad_s: float) -> float:
        yaw = self.nav.yaw_rad if self.nav is not None else 0.0
        error = math.remainder(heading_rad - yaw, 2.0 * math.pi)
        rate = self._param("ATC_STR_ANG_P") * error
        if rate_max_rad_s > 0.0:
            rate = max(-rate_max_rad_s, min(rate_max_rad_s, rate))
        decel, accel = self._param("ATC_STR_DEC_MAX"), self._param("ATC_STR_ACC_MAX")
        slope = decel if decel > 0.0 else accel
        if slope > 0.0:  # slow down in time to stop at the heading
            bound = math.sqrt(2.0 * abs(error) * math.radians(slope))
            rate = max(-bound, min(bound, rate))
        return rate

    def desired_speed_accel_limited(self, desired_m_s: float, dt_s: float) -> float:
        accel = self.accel_max
        if not self.speed_control_active() or accel <= 0.0:
            return desired_m_s
        dt_s = max(0.0, min(1.0, dt_s))
        decel = self._param("ATC_DECEL_MAX")
        slowing = abs(desired_m_s) < abs(self._desired_speed) and decel > 0.0
        change = (decel if slowing else accel) * dt_s
        return max(self._desired_speed - change, min(self._desired_speed + change, desired_m_s))

    # ------------------------------------------------------------------ turn rate
    def steering_out_rate(self, desired_rad_s: float, limit_left: bool, limit_right: bool, dt_s: float) -> float:
        """Steering in [-1, 1] (can exceed) for a desired turn rate, clockwise positive."""
        dt_s = max(0.0, min(1.0, dt_s))
        if not self._recent(self._steer_last_ms):
            self.steer_pid.reset_filter()
            self.steer_pid.reset_i()
            self._desired_turn_rate = self.nav.yaw_rate_rad_s if self.nav is not None else 0.0
        self._steer_last_ms = self.now_ms
        accel = self._param("ATC_STR_ACC_MAX")
        if accel > 0.0:
            change = math.radians(accel) * dt_s
            lo, hi = self._desired_turn_rate - change, self._desired_turn_rate + change
            desired_rad_s = max(lo, min(hi, desired_rad_s))
        rate = desired_rad_s
        rate_max = self._param("ATC_STR_RAT_MAX")
        if rate_max > 0.0:
            rate = max(-math.radians(rate_max), min(math.radians(rate_max), rate))
        speed = self.forward_speed()
        if speed is not None:
            g_max = max(self.turn_rate_from_lat_accel(self.turn_lat_accel_max, abs(speed)), math.radians(1.0))
            rate = max(-g_max, min(g_max, rate))
        self._desired_turn_rate = rate
        measured = self.nav.yaw_rate_rad_s if self.nav is not None else 0.0
        out = self.steer_pid.update(rate, measured, dt_s, limit_left or limit_right)
        return out + self.steer_pid.info.ff

    # ------------------------------------------------------------------ speed
    def throttle_out_speed(self, desired_m_s: float, limit_low: bool, limit_high: bool, dt_s: float) -> float:
        """Throttle in [-1, 1] (can exceed) for a desired forward speed."""
        dt_s = max(0.0, min(1.0, dt_s))
        speed = self.forward_speed()
        if speed is None:
            return 0.0
        if not self.speed_control_active():
            self.speed_pid.reset_filter()
            self.speed_pid.reset_i()
            self._desired_speed = speed
        self._speed_last_ms = self.now_ms
        self._desired_speed = self.desired_speed_accel_limited(desired_m_s, dt_s)
        cruise_speed, cruise_throttle = self._param("CRUISE_SPEED"), 0.01 * self._param("CRUISE_THROTTLE")
        base = self._desired_speed * cruise_throttle / cruise_speed if cruise_speed > 0 and cruise_throttle > 0 else 0.0
        limit = limit_low or limit_high or self._thr_limit_low or self._thr_limit_high
        out = self.speed_pid.update(self._desired_speed, speed, dt_s, limit) + self.speed_pid.info.ff + base
        info = self.speed_pid.info
        self.speed_info = PidInfo(info.target, info.actual, info.ff + base, info.p, info.i, info.d)
        self._thr_limit_low = self._thr_limit_high = False
        if self._param("ATC_BRAKE") == 0:  # no reverse thrust to brake: never below 0 going forward
            if self._desired_speed >= 0.0 and out <= 0.0:
                out, self._thr_limit_low = 0.0, True
            elif self._desired_speed <= 0.0 and out >= 0.0:
                out, self._thr_limit_high = 0.0, True
        return out

    def throttle_out_stop(self, limit_low: bool, limit_high: bool, dt_s: float) -> tuple[float, bool]:
        """(throttle, stopped) bringing the rover to rest."""
        stopped = self._stop_last_ms is not None and self.now_ms - self._stop_last_ms < STOPPED_HOLD_MS
        desired = self.desired_speed_accel_limited(0.0, dt_s)
        speed = self.forward_speed()
        if speed is None or (desired == 0.0 and abs(speed) <= abs(self._param("ATC_STOP_SPEED"))):
            stopped = True
        if stopped:
            self._stop_last_ms = self._speed_last_ms = self.now_ms
            self.speed_pid.reset_filter()
            self.speed_pid.reset_i()
            self._desired_speed = 0.0
            return 0.0, True
        self._stop_last_ms = None
        return self.throttle_out_speed(desired, limit_low, limit_high, dt_s), False
