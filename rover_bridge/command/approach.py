"""How fast a go-to may drive toward its point (pure): the fastest speed from which the rover still stops on it.

A time-optimal approach under the profile's limits: the limiter ramps up at max_linear_accel_m_s2 to the
cruise speed, holds it, and the speed asked for falls along the braking curve of max_linear_decel_m_s2 so
that the rover comes to rest on the point, not short of it at a crawl. What the rover does lags what is
asked: a command waits up to one output period to go out, the wheels follow it through their own lag
(control.reference_s: the response the wheel speed loop expects of them), and a jerk limit takes
decel / jerk to build the braking up. The braking curve is the rover's stopping distance from the speed v
asked for, all of that lag_s counted:

    d(v) = v^2 / (2 a) + v * lag_s + lag_s * wheel_s * a * v / (v + settle)

the distance of the braking ramp, the distance covered during the lag, and what the wheels carry on top:
braking at the full rate they run ahead of what they were asked by wheel_s * a (a first-order lag behind a
ramp), over the lag. The command brakes at the full rate down to the settle speed (which the limiter then
takes to zero in one output), so the last term is whole at speed and fades only below it: a rover that
stopped short still creeps in. The speed asked for is d's inverse at the distance left. In the simulation
of tests/test_navigation.py (a first-order wheel of 0, 0.15 and 0.3 s, the curve told its lag) an 8 m go-to
at 3 m/s stopped 0.001-0.019 m short of the point; with the last term fading with the curve's own
deceleration instead (a v / (v + a lag_s)) it stopped 0.04 and 0.15 m past it at 0.15 and 0.3 s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.params import Profile

BISECTIONS = 40  # the speed to 1e-12 of its bracket: far below any speed a wheel can be told


@dataclass(frozen=True, slots=True)
class StopProfile:
    """The braking curve of a go-to (module doc); settle_m_s is "nearly stopped": a command the limiter
    takes to zero within one output period."""

    decel_m_s2: float
    lag_s: float  # from a command to the rover's speed answering it, all of it
    wheel_s: float  # the part of it that is a first-order lag (the wheels'), not a delay
    settle_m_s: float

    @classmethod
    def of(cls, profile: Profile) -> StopProfile:
        decel = profile.limits.max_linear_decel_m_s2
        return cls(decel, approach_lag_s(profile), wheel_lag_s(profile), decel / profile.command.rate_hz)

    def stop_distance_m(self, speed_m_s: float) -> float:
        """How far the rover goes from asking for `speed_m_s`, the command then falling along the curve."""
        v, a, lag = abs(speed_m_s), self.decel_m_s2, self.lag_s
        if v == 0.0:
            return 0.0
        return v * v / (2.0 * a) + v * lag + lag * self.wheel_s * a * v / (v + self.settle_m_s)

    def speed_m_s(self, remaining_m: float) -> float:
        """The fastest speed from which the rover still stops within `remaining_m` (0 at or past the point)."""
        if remaining_m <= 0.0:
            return 0.0
        lo, hi = 0.0, math.sqrt(2.0 * self.decel_m_s2 * remaining_m)  # d(v) >= v^2 / 2a
        for _ in range(BISECTIONS):  # d(v) grows with v: bisect
            mid = 0.5 * (lo + hi)
            if self.stop_distance_m(mid) > remaining_m:
                hi = mid
            else:
                lo = mid
        return lo


def approach_lag_s(profile: Profile) -> float:
    """From a go-to's command to the rover's speed answering it: one output period (a command goes out at the
    next output) and the wheels' response (wheel_lag_s)."""
    return 1.0 / profile.command.rate_hz + wheel_lag_s(profile)


def wheel_lag_s(profile: Profile) -> float:
    """The wheels' response: control.reference_s (what the wheel speed loop expects of them) and, with a jerk
    limit, half the time it takes to build the full deceleration up (the mean delay of a linear ramp)."""
    lag = profile.control.reference_s
    jerk = profile.limits.max_linear_jerk_m_s3
    if jerk is not None:
        lag += 0.5 * profile.limits.max_linear_decel_m_s2 / jerk
    return lag
