"""Time per call of the pure core's hot paths: IK + desaturation, odometry update, limiter step.

Prints a table (median of repeats, microseconds per call). Run: python benchmarks/bench_core.py
Not a test: timings depend on the machine; nothing here asserts on them.
"""

from __future__ import annotations

import statistics
import timeit
from collections.abc import Callable

from rover_bridge.kinematics import DiffDrive, Twist2D
from rover_bridge.limits import TwistLimiter, TwistLimits
from rover_bridge.odometry import WheelOdometry

REPEATS = 7
NUMBER = 20_000


def bench(fn: Callable[[], object]) -> tuple[float, float]:
    """(median, min) microseconds per call over REPEATS runs of NUMBER calls."""
    runs = timeit.repeat(fn, number=NUMBER, repeat=REPEATS)
    per_call_us = [r / NUMBER * 1e6 for r in runs]
    return statistics.median(per_call_us), min(per_call_us)


def main() -> None:
    dd = DiffDrive(wheel_radius_m=0.05, track_width_m=0.30)
    max_rad_s = 200.0 * 2.0 * 3.141592653589793 / 60.0
    request = Twist2D(v_m_s=1.0, omega_rad_s=2.0)  # clamps: the slower path of desaturate

    def ik() -> object:
        return dd.to_wheel_speeds(request).desaturate(max_rad_s)

    odo = WheelOdometry(track_width_m=0.30)
    state = [0.0, 0.0]

    def odometry() -> object:
        state[0] += 0.010
        state[1] += 0.012  # a gentle arc: exercises the closed-form branch
        return odo.update(state[0], state[1])

    plain = TwistLimiter(TwistLimits(0.8, 3.0, 1.0, 2.0, 6.0))
    jerky = TwistLimiter(TwistLimits(0.8, 3.0, 1.0, 2.0, 6.0, jerk_v_m_s3=10.0, jerk_omega_rad_s3=60.0))
    targets = [Twist2D(0.8, 3.0), Twist2D(-0.8, -3.0)]
    flip = [0]

    def limiter(lim: TwistLimiter) -> Callable[[], object]:
        def step() -> object:
            flip[0] += 1  # alternate targets every 50 steps so it never just sits on the target
            return lim.step(targets[(flip[0] // 50) % 2], 0.02)
        return step

    rows = [
        ("IK: to_wheel_speeds + desaturate", bench(ik)),
        ("odometry: WheelOdometry.update", bench(odometry)),
        ("limiter: TwistLimiter.step (no jerk)", bench(limiter(plain))),
        ("limiter: TwistLimiter.step (jerk)", bench(limiter(jerky))),
    ]
    print(f"# {REPEATS} repeats x {NUMBER} calls; microseconds per call")
    print(f"{'operation':<40} {'median_us':>10} {'min_us':>8}")
    for name, (median, best) in rows:
        print(f"{name:<40} {median:10.3f} {best:8.3f}")


if __name__ == "__main__":
    main()
