"""Differential-drive kinematics (pure): body twist <-> wheel speeds, desaturation, unit helpers.

Convention inside rover-bridge: v forward, omega counter-clockwise positive,
    left_rad_s  = (v - omega * L / 2) / r_left
    right_rad_s = (v + omega * L / 2) / r_right
MAVLink's clockwise-positive yaw rates are converted in rover_bridge.frames, nowhere else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.params import RobotParams

RAD_S_PER_RPM = 2.0 * math.pi / 60.0


@dataclass(frozen=True, slots=True)
class Twist2D:
    """Body velocity: forward speed and yaw rate (counter-clockwise positive)."""

    v_m_s: float = 0.0
    omega_rad_s: float = 0.0


@dataclass(frozen=True, slots=True)
class WheelSpeeds:
    """Angular speed of each wheel; positive drives the robot forward."""

    left_rad_s: float = 0.0
    right_rad_s: float = 0.0

    def desaturate(self, max_rad_s: float) -> WheelSpeeds:
        """Scale both wheels by one common factor so neither exceeds `max_rad_s`.

        One common factor keeps the left/right ratio, so the path's curvature and the turn
        direction survive the clamp (clamping each wheel alone would turn an arc into a
        tighter or wider one). Speeds inside the limit come back unchanged.
        """
        if not (math.isfinite(max_rad_s) and max_rad_s > 0.0):
            raise ValueError(f"max_rad_s must be a finite number > 0, got {max_rad_s!r}")
        largest = max(abs(self.left_rad_s), abs(self.right_rad_s))
        if largest <= max_rad_s:
            return self
        scale = max_rad_s / largest
        # min() guards the bound against a last-bit rounding overshoot of the product.
        left = math.copysign(min(abs(self.left_rad_s) * scale, max_rad_s), self.left_rad_s)
        right = math.copysign(min(abs(self.right_rad_s) * scale, max_rad_s), self.right_rad_s)
        return WheelSpeeds(left_rad_s=left, right_rad_s=right)

    def is_finite(self) -> bool:
        return math.isfinite(self.left_rad_s) and math.isfinite(self.right_rad_s)


def _check_positive(name: str, value: float) -> float:
    if (isinstance(value, bool) or not isinstance(value, (int, float))
            or not math.isfinite(value) or value <= 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


@dataclass(frozen=True, slots=True)
class DiffDrive:
    """Geometry of a differential-drive robot and its inverse/forward kinematics."""

    wheel_radius_m: float
    track_width_m: float
    left_wheel_radius_m: float | None = None
    right_wheel_radius_m: float | None = None

    def __post_init__(self) -> None:
        _check_positive("wheel_radius_m", self.wheel_radius_m)
        _check_positive("track_width_m", self.track_width_m)
        if self.left_wheel_radius_m is not None:
            _check_positive("left_wheel_radius_m", self.left_wheel_radius_m)
        if self.right_wheel_radius_m is not None:
            _check_positive("right_wheel_radius_m", self.right_wheel_radius_m)

    @classmethod
    def from_params(cls, robot: RobotParams) -> DiffDrive:
        return cls(wheel_radius_m=robot.wheel_radius_m, track_width_m=robot.track_width_m,
                   left_wheel_radius_m=robot.left_wheel_radius_m,
                   right_wheel_radius_m=robot.right_wheel_radius_m)

    @property
    def left_radius_m(self) -> float:
        return self.wheel_radius_m if self.left_wheel_radius_m is None else self.left_wheel_radius_m

    @property
    def right_radius_m(self) -> float:
        return self.wheel_radius_m if self.right_wheel_radius_m is None else self.right_wheel_radius_m

    def to_wheel_speeds(self, twist: Twist2D) -> WheelSpeeds:
        half = 0.5 * twist.omega_rad_s * self.track_width_m
        return WheelSpeeds(left_rad_s=(twist.v_m_s - half) / self.left_radius_m,
                           right_rad_s=(twist.v_m_s + half) / self.right_radius_m)

    def to_twist(self, wheels: WheelSpeeds) -> Twist2D:
        left_m_s = wheels.left_rad_s * self.left_radius_m
        right_m_s = wheels.right_rad_s * self.right_radius_m
        return Twist2D(v_m_s=0.5 * (left_m_s + right_m_s),
                       omega_rad_s=(right_m_s - left_m_s) / self.track_width_m)


def rad_s_to_rpm(rad_s: float) -> float:
    return rad_s / RAD_S_PER_RPM


def rpm_to_rad_s(rpm: float) -> float:
    return rpm * RAD_S_PER_RPM


def rad_s_to_m_s(rad_s: float, radius_m: float) -> float:
    """Surface speed of a wheel of `radius_m` turning at `rad_s`."""
    return rad_s * radius_m


def m_s_to_rad_s(m_s: float, radius_m: float) -> float:
    return m_s / _check_positive("radius_m", radius_m)


def ticks_to_m(ticks: float, counts_per_rev: float, radius_m: float) -> float:
    """Distance rolled by a wheel whose encoder counted `ticks`."""
    return (ticks / _check_positive("counts_per_rev", counts_per_rev)
            * 2.0 * math.pi * _check_positive("radius_m", radius_m))


def m_to_ticks(distance_m: float, counts_per_rev: float, radius_m: float) -> float:
    """Encoder ticks counted while a wheel of `radius_m` rolls `distance_m`."""
    return (distance_m / (2.0 * math.pi * _check_positive("radius_m", radius_m))
            * _check_positive("counts_per_rev", counts_per_rev))


@dataclass(frozen=True, slots=True)
class MeasuredWheels:
    """Wheel speeds measured by the encoders: the mean over an interval ending at `stamp_s` (autopilot time)."""

    stamp_s: float
    speeds: WheelSpeeds
