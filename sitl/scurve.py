"""A straight leg's jerk-limited speed profile: where the navigation target is along the leg, when.

ArduPilot's AR_WPNav moves its target along each leg with an S-curve (libraries/AP_Math/SCurve.cpp:
jerk- and snap-limited, corners of "fast" waypoints blended into the next leg). This is a simpler
profile of the same shape: speed rises from ``start_m_s`` to a peak no higher than ``speed_max`` and
falls to ``end_m_s`` at the end of the leg, every change of speed with the acceleration limited to
``accel_max`` and the acceleration changing no faster than ``jerk_max`` (no snap limit, no blending:
a corner is taken at ``end_m_s``, see sitl/wpnav.py). Time is the leg's own clock, which the caller
advances (AR_WPNav slows it down when the vehicle lags behind the target).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class _Change:
    """One jerk-limited change of speed from ``v0`` to ``v1``: jerk +-j for t1, constant accel for t2, -+j for t1."""

    v0: float
    v1: float
    accel_peak: float
    jerk: float
    t1: float
    t2: float

    @classmethod
    def make(cls, v0: float, v1: float, accel_max: float, jerk_max: float) -> _Change:
        dv = abs(v1 - v0)
        if dv == 0.0:
            return cls(v0, v1, 0.0, jerk_max, 0.0, 0.0)
        if dv >= accel_max * accel_max / jerk_max:
            return cls(v0, v1, accel_max, jerk_max, accel_max / jerk_max, dv / accel_max - accel_max / jerk_max)
        t1 = math.sqrt(dv / jerk_max)
        return cls(v0, v1, jerk_max * t1, jerk_max, t1, 0.0)

    @property
    def duration_s(self) -> float:
        return 2.0 * self.t1 + self.t2

    @property
    def distance_m(self) -> float:
        return self.duration_s * 0.5 * (self.v0 + self.v1)  # the speed curve is point-symmetric

    def at(self, t: float) -> tuple[float, float, float]:
        """(distance, speed, acceleration) ``t`` seconds into the change."""
        sign = 1.0 if self.v1 >= self.v0 else -1.0
        j, ap, t1, t2 = self.jerk, self.accel_peak, self.t1, self.t2
        t = max(0.0, min(self.duration_s, t))
        if t < t1:
            return self.v0 * t + sign * j * t**3 / 6.0, self.v0 + sign * j * t * t / 2.0, sign * j * t
        s1, v1 = self.v0 * t1 + sign * j * t1**3 / 6.0, self.v0 + sign * j * t1 * t1 / 2.0
        if t < t1 + t2:
            u = t - t1
            return s1 + v1 * u + sign * ap * u * u / 2.0, v1 + sign * ap * u, sign * ap
        s2, v2 = s1 + v1 * t2 + sign * ap * t2 * t2 / 2.0, v1 + sign * ap * t2
        u = t - t1 - t2
        s = s2 + v2 * u + sign * (ap * u * u / 2.0 - j * u**3 / 6.0)
        return s, v2 + sign * (ap * u - j * u * u / 2.0), sign * (ap - j * u)


def stoppable_speed(length_m: float, accel_max: float, jerk_max: float) -> float:
    """The highest speed from which a jerk-limited stop fits in ``length_m`` (a change is symmetric,
    so this is also the highest speed reachable from rest in that length)."""
    accel_max, jerk_max = max(accel_max, 1e-3), max(jerk_max, 1e-3)
    lo, hi = 0.0, 100.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _Change.make(mid, 0.0, accel_max, jerk_max).distance_m <= length_m else (lo, mid)
    return lo


class LegProfile:
    """Distance, speed and acceleration along a leg of ``length_m`` as functions of the leg's time."""

    def __init__(self, length_m: float, speed_max: float, accel_max: float, jerk_max: float,
                 start_m_s: float = 0.0, end_m_s: float = 0.0) -> None:
        self.length_m = max(0.0, length_m)
        accel_max, jerk_max = max(accel_max, 1e-3), max(jerk_max, 1e-3)
        end_m_s = min(end_m_s, speed_max, self._reachable(start_m_s, accel_max, jerk_max))

        def fits(peak: float) -> bool:
            up = _Change.make(start_m_s, peak, accel_max, jerk_max)
            down = _Change.make(peak, end_m_s, accel_max, jerk_max)
            return up.distance_m + down.distance_m <= self.length_m

        low = max(start_m_s, end_m_s)
        if fits(speed_max):
            peak = max(speed_max, low)
        elif not fits(low):
            peak = low  # cannot even reach the end speed in time: the end of the leg comes early
        else:
            lo, hi = low, speed_max
            for _ in range(40):  # bisection on the peak speed
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if fits(mid) else (lo, mid)
            peak = lo
        self._up = _Change.make(start_m_s, peak, accel_max, jerk_max)
        self._down = _Change.make(peak, end_m_s, accel_max, jerk_max)
        cruise_m = self.length_m - self._up.distance_m - self._down.distance_m
        self._cruise_s = cruise_m / peak if peak > 0.0 and cruise_m > 0.0 else 0.0
        self.peak_m_s = peak
        self.end_m_s = end_m_s

    def _reachable(self, start_m_s: float, accel_max: float, jerk_max: float) -> float:
        """The highest speed the leg's length allows speeding up to from ``start_m_s``."""
        lo, hi = start_m_s, start_m_s + 100.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            fits = _Change.make(start_m_s, mid, accel_max, jerk_max).distance_m <= self.length_m
            lo, hi = (mid, hi) if fits else (lo, mid)
        return lo

    @property
    def duration_s(self) -> float:
        return self._up.duration_s + self._cruise_s + self._down.duration_s

    def at(self, t: float) -> tuple[float, float, float]:
        """(distance along the leg, speed, acceleration) at leg time ``t``; the end is held after it."""
        if t >= self.duration_s:
            return self.length_m, self.end_m_s, 0.0
        if t < self._up.duration_s:
            s, v, a = self._up.at(t)
            return min(self.length_m, s), v, a
        t -= self._up.duration_s
        if t < self._cruise_s:
            return self._up.distance_m + self.peak_m_s * t, self.peak_m_s, 0.0
        s, v, a = self._down.at(t - self._cruise_s)
        return min(self.length_m, self._up.distance_m + self.peak_m_s * self._cruise_s + s), v, a
