"""Wheel speeds -> per-wheel PWM -> RC_CHANNELS_OVERRIDE or DO_SET_SERVO messages (pure).

PWM is linear in wheel speed: pwm_trim at 0, pwm_max at +max_wheel_rad_s, pwm_min at
-max_wheel_rad_s (the two halves may have different slopes when trim is off-centre), a
reversed motor mirrors the speed first, and the result is a whole number of microseconds
clamped to [pwm_min, pwm_max]. A wheel with a measured map ([control] *_curve_pwm_us and
*_curve_rad_s, what `rover-bridge calibrate` writes) is driven through that map instead: the
PWM whose measured steady speed is the wanted one, interpolated between the points, so a
deadband and a curved or weak motor are compensated (the map already holds the direction, so
*_reversed does not apply to it); zero speed is pwm_trim.

RC_CHANNELS_OVERRIDE values (MAVLink common.xml): on ch1-8, 65535 (UINT16_MAX) leaves a
channel alone and 0 releases it to the RC radio; on ch9-18, 0 or 65535 leaves it alone and
65534 (UINT16_MAX - 1) releases it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.kinematics import WheelSpeeds
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.params import Profile

RC_CHANNELS = 18
IGNORE_CH1_8 = 65535
IGNORE_CH9_18 = 0
RELEASE_CH1_8 = 0
RELEASE_CH9_18 = 65534


@dataclass(frozen=True, slots=True)
class WheelPwm:
    """Pulse widths sent to the left and right motor outputs."""

    left_us: int
    right_us: int


def _ignore_value(channel: int) -> int:
    return IGNORE_CH1_8 if channel <= 8 else IGNORE_CH9_18


def _release_value(channel: int) -> int:
    return RELEASE_CH1_8 if channel <= 8 else RELEASE_CH9_18


_IGNORE_ALL = tuple(_ignore_value(ch) for ch in range(1, RC_CHANNELS + 1))


@dataclass(frozen=True, slots=True)
class SpeedCurve:
    """A wheel's measured PWM -> steady speed map: PWM increasing, speed non-decreasing, spanning 0."""

    pwm_us: tuple[float, ...]
    speed_rad_s: tuple[float, ...]

    @property
    def max_forward_rad_s(self) -> float:
        return self.speed_rad_s[-1]

    @property
    def max_reverse_rad_s(self) -> float:
        return self.speed_rad_s[0]

    def pwm_for(self, rad_s: float, trim_us: float) -> float:
        """The PWM for a wheel speed (inverse of the map); trim for 0, the end points beyond the range."""
        if rad_s == 0.0:
            return trim_us
        pwm, speed = self.pwm_us, self.speed_rad_s
        if rad_s >= speed[-1]:
            return pwm[-1]
        if rad_s <= speed[0]:
            return pwm[0]
        if rad_s > 0.0:  # the first segment that reaches it, from the deadband's upper edge on
            for i in range(len(speed) - 1):
                if speed[i] < rad_s <= speed[i + 1]:
                    return pwm[i] + (rad_s - speed[i]) / (speed[i + 1] - speed[i]) * (pwm[i + 1] - pwm[i])
        else:  # going down from the deadband's lower edge
            for i in range(len(speed) - 1, 0, -1):
                if speed[i - 1] <= rad_s < speed[i]:
                    return pwm[i] - (speed[i] - rad_s) / (speed[i] - speed[i - 1]) * (pwm[i] - pwm[i - 1])
        return trim_us  # pragma: no cover - unreachable for a valid curve


@dataclass(frozen=True, slots=True)
class OutputMap:
    """The profile's output section plus the wheel speed that means full PWM."""

    mode: str
    left_channel: int
    right_channel: int
    pwm_min: int
    pwm_trim: int
    pwm_max: int
    max_wheel_rad_s: float
    left_reversed: bool = False
    right_reversed: bool = False
    left_curve: SpeedCurve | None = None
    right_curve: SpeedCurve | None = None

    def __post_init__(self) -> None:
        if self.mode not in ("rc_override", "servo"):
            raise ValueError(f"mode must be rc_override or servo, got {self.mode!r}")
        if not self.pwm_min < self.pwm_trim < self.pwm_max:
            raise ValueError("expected pwm_min < pwm_trim < pwm_max")
        if self.left_channel == self.right_channel or not (
                1 <= self.left_channel <= RC_CHANNELS and 1 <= self.right_channel <= RC_CHANNELS):
            raise ValueError("left_channel and right_channel must be distinct channels in 1..18")
        if not (math.isfinite(self.max_wheel_rad_s) and self.max_wheel_rad_s > 0):
            raise ValueError("max_wheel_rad_s must be a finite number > 0")

    @classmethod
    def from_profile(cls, profile: Profile) -> OutputMap:
        o, c = profile.output, profile.control

        def curve(pwm: tuple[float, ...], speed: tuple[float, ...]) -> SpeedCurve | None:
            return SpeedCurve(tuple(pwm), tuple(speed)) if pwm else None

        return cls(mode=o.mode, left_channel=o.left_channel, right_channel=o.right_channel, pwm_min=o.pwm_min,
                   pwm_trim=o.pwm_trim, pwm_max=o.pwm_max, max_wheel_rad_s=profile.robot.max_wheel_rad_s,
                   left_reversed=o.left_reversed, right_reversed=o.right_reversed,
                   left_curve=curve(c.left_curve_pwm_us, c.left_curve_rad_s),
                   right_curve=curve(c.right_curve_pwm_us, c.right_curve_rad_s))

    def speed_range(self, left: bool) -> tuple[float, float]:
        """(fastest reverse, fastest forward) speed this wheel can be driven at, rad/s."""
        curve = self.left_curve if left else self.right_curve
        if curve is None:
            return -self.max_wheel_rad_s, self.max_wheel_rad_s
        return curve.max_reverse_rad_s, curve.max_forward_rad_s

    @property
    def neutral(self) -> WheelPwm:
        return WheelPwm(self.pwm_trim, self.pwm_trim)

    def wheel_pwm_us(self, rad_s: float, reversed_: bool) -> int:
        """One wheel's speed (forward +) -> its PWM."""
        if not math.isfinite(rad_s):
            raise ValueError(f"wheel speed must be finite, got {rad_s!r}")
        fraction = max(-1.0, min(1.0, rad_s / self.max_wheel_rad_s))
        if reversed_:
            fraction = -fraction
        span = self.pwm_max - self.pwm_trim if fraction >= 0 else self.pwm_trim - self.pwm_min
        pwm = round(self.pwm_trim + fraction * span)
        return max(self.pwm_min, min(self.pwm_max, pwm))

    def curve_pwm_us(self, rad_s: float, curve: SpeedCurve) -> int:
        if not math.isfinite(rad_s):
            raise ValueError(f"wheel speed must be finite, got {rad_s!r}")
        pwm = round(curve.pwm_for(rad_s, float(self.pwm_trim)))
        return max(self.pwm_min, min(self.pwm_max, pwm))

    def to_pwm(self, wheels: WheelSpeeds) -> WheelPwm:
        lc, rc = self.left_curve, self.right_curve
        left = (self.wheel_pwm_us(wheels.left_rad_s, self.left_reversed) if lc is None
                else self.curve_pwm_us(wheels.left_rad_s, lc))
        right = (self.wheel_pwm_us(wheels.right_rad_s, self.right_reversed) if rc is None
                 else self.curve_pwm_us(wheels.right_rad_s, rc))
        return WheelPwm(left, right)

    def command(self, pwm: WheelPwm, target_system: int, target_component: int) -> list[MAVLinkMessage]:
        """The messages that set both wheels to `pwm` in the configured mode."""
        if self.mode == "servo":
            return [servo_command(self.left_channel, pwm.left_us, target_system, target_component),
                    servo_command(self.right_channel, pwm.right_us, target_system, target_component)]
        # At command.rate_hz and on every request: the 18 channels from a template, not a dict per call.
        chans = list(_IGNORE_ALL)
        chans[self.left_channel - 1] = pwm.left_us
        chans[self.right_channel - 1] = pwm.right_us
        return [mavlink.MAVLink_rc_channels_override_message(target_system, target_component, *chans)]

    def release(self, target_system: int, target_component: int) -> list[MAVLinkMessage]:
        """Hand the two channels back to the RC radio (rc_override); servo mode has no release: trim."""
        if self.mode == "servo":
            return self.command(self.neutral, target_system, target_component)
        values = {ch: _release_value(ch) for ch in (self.left_channel, self.right_channel)}
        return [rc_override(values, target_system, target_component)]


def rc_override(values: dict[int, int], target_system: int, target_component: int) -> MAVLinkMessage:
    """RC_CHANNELS_OVERRIDE setting the channels in `values` (1-based) and leaving all others alone."""
    chans = [values.get(ch, _ignore_value(ch)) for ch in range(1, RC_CHANNELS + 1)]
    return mavlink.MAVLink_rc_channels_override_message(target_system, target_component, *chans)


def servo_command(servo: int, pwm_us: int, target_system: int, target_component: int) -> MAVLinkMessage:
    """COMMAND_LONG MAV_CMD_DO_SET_SERVO: param1 = output number, param2 = PWM (us)."""
    return mavlink.MAVLink_command_long_message(target_system, target_component, mavlink.MAV_CMD_DO_SET_SERVO,
                                                0, float(servo), float(pwm_us), 0.0, 0.0, 0.0, 0.0, 0.0)
