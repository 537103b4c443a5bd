"""Rover's skid-steering output and the PWM of its ThrottleLeft/Right outputs, as behaviour.

Read in ArduPilot (Rover 4.7): libraries/AR_Motors/AP_MotorsUGV.cpp (set_throttle, slew_limit_throttle,
output_skid_steering, output_throttle, have_skid_steering) and libraries/SRV_Channel/SRV_Channel.cpp
(pwm_from_angle). What is kept:

- Throttle in percent, clamped to +-MOT_THR_MAX while armed; slewed by MOT_SLEWRATE %/s before mixing
  (the slew sets the throttle limit flags).
- The mixer (thrust asymmetry 1): steering and throttle in [-1, 1]; the steering range is the full
  one; on saturation (|throttle| + |steering| > 1) MOT_STR_THR_MIX >= 0.5 keeps the steering and lowers
  the throttle, below 0.5 the other way round; left = throttle + steering, right = throttle - steering.
  Limit flags (steer left/right, throttle lower/upper) tell the controllers to stop integrating.
- Disarmed: both outputs at trim, every limit flag set.
- Functions 73/74 are angle outputs of +-1000: PWM = TRIM + value * (MAX - TRIM) / 1000 above zero,
  TRIM - value * (TRIM - MIN) / 1000 below (truncated to whole microseconds), SERVOn_REVERSED mirrors
  the value. New outputs default to MIN 1100, MAX 1900: 80 % of the demand reaches a 1000-2000 ESC.
- Rover is skid-steering when some output has function 73 and some output 74.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

FUNC_THROTTLE_LEFT = 73
FUNC_THROTTLE_RIGHT = 74
ANGLE_HIGH_OUT = 1000.0  # SRV_Channels::set_angle(k_throttleLeft/Right, 1000)


def pwm_from_angle(value: float, pwm_min: int, pwm_max: int, pwm_trim: int, reversed_: bool) -> int:
    """An angle output's PWM for ``value`` in +-1000 (SRV_Channel::pwm_from_angle)."""
    if reversed_:
        value = -value
    value = max(-ANGLE_HIGH_OUT, min(ANGLE_HIGH_OUT, value))
    if value > 0.0:
        return pwm_trim + int(value * (pwm_max - pwm_trim) / ANGLE_HIGH_OUT)
    return pwm_trim - int(-value * (pwm_trim - pwm_min) / ANGLE_HIGH_OUT)


@dataclass
class MotorLimits:
    steer_left: bool = True
    steer_right: bool = True
    throttle_lower: bool = True
    throttle_upper: bool = True


class SkidMotors:
    """AP_MotorsUGV's skid-steering path: set_throttle / set_steering, then ``output`` each loop."""

    def __init__(self, param: Callable[[str], float]) -> None:
        self._param = param
        self.throttle_pct = 0.0
        self.steering = 0.0  # -4500 .. 4500, positive turns clockwise
        self._throttle_prev_pct = 0.0
        self.limit = MotorLimits()
        self.left = 0.0  # last mixed outputs, [-1, 1]
        self.right = 0.0

    def set_throttle(self, pct: float, armed: bool) -> None:
        if armed:  # AP_MotorsUGV ignores throttle while disarmed
            thr_max = self._param("MOT_THR_MAX")
            self.throttle_pct = max(-thr_max, min(thr_max, pct))

    def set_steering(self, value: float) -> None:
        self.steering = value

    def output(self, armed: bool, dt_s: float) -> tuple[float, float]:
        """Mix into (left, right) in [-1, 1]; updates the limit flags."""
        if not armed:
            self.throttle_pct = 0.0
        self.limit = MotorLimits(False, False, False, False)
        slew = self._param("MOT_SLEWRATE")
        if slew > 0.0:  # slew_limit_throttle
            step = slew * dt_s
            limited = max(self._throttle_prev_pct - step, min(self._throttle_prev_pct + step, self.throttle_pct))
            self.limit.throttle_upper |= self.throttle_pct > limited
            self.limit.throttle_lower |= self.throttle_pct < limited
            self.throttle_pct = limited
        self._throttle_prev_pct = self.throttle_pct
        thr_max = self._param("MOT_THR_MAX")
        lim = self.limit
        lim.steer_left |= not armed or self.steering <= -4500.0
        lim.steer_right |= not armed or self.steering >= 4500.0
        lim.throttle_lower |= not armed or self.throttle_pct <= -thr_max
        lim.throttle_upper |= not armed or self.throttle_pct >= thr_max
        if not armed:
            self.left = self.right = 0.0
            return 0.0, 0.0
        steering = max(-1.0, min(1.0, self.steering / 4500.0))
        throttle = self.throttle_pct * 0.01
        if throttle > 1.0:
            lim.throttle_upper, throttle = True, 1.0
        elif throttle < -1.0:
            lim.throttle_lower, throttle = True, -1.0
        saturation = max(throttle + abs(steering), -(throttle - abs(steering)))
        if saturation > 1.0:
            steering0, throttle0 = steering, throttle
            mix = max(0.0, min(1.0, self._param("MOT_STR_THR_MIX")))
            fair = 1.0 / saturation
            if mix >= 0.5:  # keep the steering, give up throttle
                steering *= fair + (1.0 - fair) * (mix - 0.5) / 0.5
                throttle = (1.0 - abs(steering)) if throttle >= 0.0 else (abs(steering) - 1.0)
            else:  # keep the throttle, give up steering
                throttle *= fair + (1.0 - fair) * (0.5 - mix) / 0.5
                sign = 1.0 if steering > 0.0 else -1.0
                steering = ((1.0 - throttle) if throttle >= 0.0 else (throttle + 1.0)) * sign
            if abs(steering) < abs(steering0):
                lim.steer_left |= steering0 < 0.0
                lim.steer_right |= steering0 > 0.0
            if abs(throttle) < abs(throttle0):
                lim.throttle_lower |= throttle0 < 0.0
                lim.throttle_upper |= throttle0 > 0.0
        self.left, self.right = throttle + steering, throttle - steering
        return self.left, self.right
