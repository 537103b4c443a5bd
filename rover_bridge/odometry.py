"""Wheel odometry (pure): cumulative wheel distances -> pose, integrated exactly along arcs.

Pose convention: x forward (of the start pose), y left, yaw counter-clockwise, float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


def wrap_angle(angle_rad: float) -> float:
    """Wrap to [-pi, pi]."""
    wrapped = math.remainder(angle_rad, 2.0 * math.pi)
    return wrapped


@dataclass(frozen=True, slots=True)
class Pose2D:
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0


def arc_factors(dyaw_rad: float) -> tuple[float, float]:
    """(sin(d)/d, (1 - cos(d))/d): the chord of a unit-length arc turning by d, in the start frame.

    Series near 0 keep the straight-line limit exact instead of dividing by a vanishing angle.
    """
    d = dyaw_rad
    if abs(d) < 1e-4:
        d2 = d * d
        return 1.0 - d2 / 6.0 + d2 * d2 / 120.0, d / 2.0 - d * d2 / 24.0
    return math.sin(d) / d, (1.0 - math.cos(d)) / d


def arc_step(pose: Pose2D, ds_m: float, dyaw_rad: float) -> Pose2D:
    """Move `ds_m` along a circular arc (about the instantaneous centre of curvature) turning `dyaw_rad`."""
    a, b = arc_factors(dyaw_rad)
    fwd = ds_m * a
    left = ds_m * b
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    return Pose2D(x_m=pose.x_m + c * fwd - s * left,
                  y_m=pose.y_m + s * fwd + c * left,
                  yaw_rad=wrap_angle(pose.yaw_rad + dyaw_rad))


class WheelOdometry:
    """Integrates cumulative left/right wheel distances (as WHEEL_DISTANCE carries them)."""

    def __init__(self, track_width_m: float, pose: Pose2D | None = None) -> None:
        if not (math.isfinite(track_width_m) and track_width_m > 0.0):
            raise ValueError(f"track_width_m must be a finite number > 0, got {track_width_m!r}")
        self.track_width_m = float(track_width_m)
        self._pose = pose if pose is not None else Pose2D()
        self._last: tuple[float, float] | None = None

    @property
    def pose(self) -> Pose2D:
        return self._pose

    def update(self, left_m: float, right_m: float) -> Pose2D:
        """Feed the latest cumulative distances; the first reading is only the baseline."""
        if not (math.isfinite(left_m) and math.isfinite(right_m)):
            raise ValueError(f"wheel distances must be finite, got {left_m!r}, {right_m!r}")
        if self._last is not None:
            d_left = left_m - self._last[0]
            d_right = right_m - self._last[1]
            ds = 0.5 * (d_left + d_right)
            dyaw = (d_right - d_left) / self.track_width_m
            self._pose = arc_step(self._pose, ds, dyaw)
        self._last = (left_m, right_m)
        return self._pose

    def reset(self, pose: Pose2D | None = None) -> None:
        """Re-base: set the pose and forget the last reading (the next one is a new baseline)."""
        self._pose = pose if pose is not None else Pose2D()
        self._last = None
