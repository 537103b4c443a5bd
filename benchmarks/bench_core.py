"""Time per call of the pure core's hot paths: IK + desaturation, odometry, limiter, EKF and estimate flow.

Prints a table (median of repeats, microseconds per call). Run: python benchmarks/bench_core.py
Not a test: timings depend on the machine; nothing here asserts on them.
"""

from __future__ import annotations

import statistics
import timeit
from collections.abc import Callable, Iterator

from rover_bridge.estimate.core import EstimateCore
from rover_bridge.estimate.ekf import WheelGyroEKF
from rover_bridge.kinematics import DiffDrive, Twist2D
from rover_bridge.limits import TwistLimiter, TwistLimits
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.odometry import WheelOdometry
from rover_bridge.params import Profile

REPEATS = 7
# A gentle arc at 0.4 m/s, 0.2 rad/s: 20 ms of wheel distance per reading (track 0.30 m).
D_LEFT_M, D_RIGHT_M = 0.02 * (0.4 - 0.2 * 0.15), 0.02 * (0.4 + 0.2 * 0.15)
NUMBER = 20_000


def bench(fn: Callable[[], object]) -> tuple[float, float]:
    """(median, min) microseconds per call over REPEATS runs of NUMBER calls."""
    runs = timeit.repeat(fn, number=NUMBER, repeat=REPEATS)
    per_call_us = [r / NUMBER * 1e6 for r in runs]
    return statistics.median(per_call_us), min(per_call_us)


def ekf_rows() -> Iterator[tuple[str, tuple[float, float]]]:
    """The estimate flow at 50 Hz on a gentle arc: filter steps alone, then whole decoded messages."""
    for calibrate in (False, True):
        ekf = WheelGyroEKF(0.30, calibrate=calibrate)
        clock = [0.0]

        def gyro(ekf: WheelGyroEKF = ekf, t: list[float] = clock) -> object:
            t[0] += 0.02
            return ekf.update_gyro(t[0], 0.2)

        def wheels(ekf: WheelGyroEKF = ekf, t: list[float] = clock) -> object:
            t[0] += 0.02
            return ekf.update_wheels(t[0], D_LEFT_M, D_RIGHT_M, 0.02, 0.2)

        def extrapolate(ekf: WheelGyroEKF = ekf, t: list[float] = clock) -> object:
            return ekf.extrapolate(t[0] + 0.01)

        tag = "calibrate" if calibrate else "geometry exact"
        yield from [(f"EKF ({tag}): update_gyro", bench(gyro)), (f"EKF ({tag}): update_wheels", bench(wheels)),
                    (f"EKF ({tag}): extrapolate", bench(extrapolate))]
    profile = Profile()
    identity = Identity.from_profile(profile)
    core = EstimateCore(profile, identity, Reporter(identity))
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

    def wire(msg: MAVLinkMessage) -> MAVLinkMessage:
        return ap.decode(bytearray(msg.pack(ap)))

    hb = wire(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                0, 0, 4, 3))
    clock = [100.0, 0.0]
    core.handle(Incoming(Link.AUTOPILOT, hb), clock[0])

    def message() -> object:
        # One wheel reading, then one gyro sample, 10 ms apart (50 Hz each), as fresh messages.
        clock[0] += 0.01
        k = round(clock[0] * 100)
        if k % 2:
            clock[1] += 0.008
            distances = [clock[1], clock[1] * 1.1] + [0.0] * 14
            msg = mavlink.MAVLink_wheel_distance_message(round(clock[0] * 1e6), 2, distances)
        else:
            msg = mavlink.MAVLink_attitude_message(round(clock[0] * 1e3), 0.0, 0.0, 0.0, 0.0, 0.0, -0.2)
        msg._header = mavlink.MAVLink_header(msg.id, srcSystem=1, srcComponent=1)  # as if received
        return core.handle(Incoming(Link.AUTOPILOT, msg), clock[0])

    def odometry() -> object:
        return core.odometry_message(clock[0] + 0.005)

    yield ("EstimateCore.handle (wheels/gyro mix)", bench(message))
    yield ("EstimateCore.odometry_message", bench(odometry))


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
        *ekf_rows(),
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
