"""Estimation accuracy against the sitl emulator's ground truth, in lockstep (deterministic, no sockets).

    python benchmarks/accuracy.py                 # the table over every scenario (seed 1)
    python benchmarks/accuracy.py --seeds 1-9     # every scenario for each seed, and the worst of each
    python benchmarks/accuracy.py --quick         # a shorter route (for a smoke run)
    python benchmarks/accuracy.py --moving        # the route starts moving 0.1 s after the first sample
    python benchmarks/accuracy.py --wheels        # the demo's comparison: EKF against its own wheels

The emulator drives a fixed route (straight runs, arcs both ways, spins in place, stops; about
130 m) from RC passthrough values; every message it sends is fed to two EstimateCores (without
and with online calibration) at the emulator's time, and their stream requests are answered by
the emulator (WHEEL_DISTANCE's SET_MESSAGE_INTERVAL is refused, as ArduPilot 4.7 does, so the
REQUEST_DATA_STREAM fallback is exercised). Raw wheel odometry is the plain arc integration of
the same WHEEL_DISTANCE data with the nominal geometry.

Columns: distance driven; final position error in m and in % of the distance; maximum heading
error over the run, in degrees; for raw wheel odometry, the EKF, and the EKF with calibration;
"exact hdg": the final error of dead reckoning with the wheels' mean distance along the truth's heading,
what an exact heading alone leaves (a wrong mean wheel radius scales the distance, which no gyro
observes: miscalibrated's is 1 % large); then the calibrated track width, with what calibration can
find (the track in the units of the reported distances: true track / mean true-to-nominal radius
ratio) and the physical truth.

--wheels compares as `rover-bridge demo` does, on its route (a standstill, a straight, a spin, four legs, a
figure eight; --moving: no standstill): the published ODOMETRY series and the wheel odometry integrated
from WHEEL_DISTANCE, each interpolated at the truth's samples: final and largest position error, largest
heading error (the EKF must not be worse than its own wheels: tests/test_estimate_sitl.py).
"""

from __future__ import annotations

import argparse
import bisect
import logging
import math
import random
import sys
from dataclasses import dataclass, field
from typing import Any

from rover_bridge.estimate.core import EstimateCore
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.odometry import Pose2D, WheelOdometry
from rover_bridge.params import Profile, profile_from_dict
from sitl import Emulator, Scenario, VehicleConfig
from sitl.scenario import SlipWindow

STEP_S = 0.01
NOMINAL_TRACK_M = 0.30
NOMINAL_RADIUS_M = 0.05


def route(quick: bool, moving: bool = False) -> list[tuple[float, float, float]]:
    """(duration_s, v_m_s, omega_rad_s CCW) segments; `moving`: no standstill before the first leg."""
    # streams come up, the gyro bias settles (or not: 0.1 s, then the rover drives off)
    seg: list[tuple[float, float, float]] = [(0.1 if moving else 4.0, 0.0, 0.0)]
    laps = 1 if quick else 4
    for _ in range(laps):
        seg += [(25.0, 0.8, 0.0), (3.0, 0.5, 0.6), (10.0, 0.8, -0.1), (4.0, 0.0, -1.0), (2.0, 0.0, 0.0)]
    seg += [(8.0, 0.6, 0.8), (8.0, 0.6, -0.8), (2.0, 0.0, 0.0)]
    return seg


@dataclass
class Track:
    """Errors of one estimator against the truth, in the start pose's frame (x forward, y left)."""

    max_heading_rad: float = 0.0
    final_pos_m: float = 0.0


@dataclass
class Result:
    name: str
    dist_m: float = 0.0
    raw: Track = field(default_factory=Track)
    ekf: Track = field(default_factory=Track)
    cal: Track = field(default_factory=Track)
    # Dead reckoning with the wheels' nominal mean distance along the truth's heading: what a filter whose
    # heading were exact would reach. A mean wheel radius that is off scales the distance, which no gyro
    # observes: a wheel + gyro estimator is not bound to do better (errors of heading and scale may cancel).
    exact_heading: Track = field(default_factory=Track)
    cal_track_m: float = 0.0
    true_track_m: float = 0.0
    # What calibration can find: the track in the units of the reported wheel distances. The mean
    # radius error is unobservable from a gyro (it scales distance, not turning), so the track comes
    # out divided by the mean of the wheels' true/nominal radius ratios.
    expected_track_m: float = 0.0
    counters: dict[str, int] = field(default_factory=dict)


def _pwm(wheel_m_s: float, radius_m: float, max_rpm: float) -> int:
    max_rad_s = max_rpm * 2.0 * math.pi / 60.0
    return round(1500 + 500 * max(-1.0, min(1.0, wheel_m_s / radius_m / max_rad_s)))


def _core(profile: Profile) -> EstimateCore:
    identity = Identity.from_profile(profile)
    core = EstimateCore(profile, identity, Reporter(identity))
    core.defer_fusion = True  # as the running bridge (BridgeCore) has it
    return core


STREAM_RATE_HZ = 20.0


def run(name: str, vehicle: VehicleConfig, scenario: Scenario, quick: bool, seed: int = 1,
        wheel_loss: float = 0.0, wheel_gaps: tuple[tuple[float, float], ...] = (),
        with_calibration: bool = True, moving: bool = False) -> Result:
    emu = Emulator(vehicle, scenario, seed=seed, record_sent=True)
    ekf = _core(profile_from_dict({"estimator": {"stream_rate_hz": STREAM_RATE_HZ}}))
    cal = _core(profile_from_dict({"estimator": {"stream_rate_hz": STREAM_RATE_HZ, "calibrate": True}}))
    drop_rng = random.Random(f"accuracy-drop-{seed}")
    mean_scale = 0.5 * (vehicle.left_radius_true_m + vehicle.right_radius_true_m) / vehicle.wheel_radius_m
    res = Result(name, true_track_m=vehicle.track_true_m, expected_track_m=vehicle.track_true_m / mean_scale)
    t0 = emu.truth
    seen = 0
    now = 0.0
    exact_xy = [0.0, 0.0]
    wheel_mean_m: float | None = None  # the last WHEEL_DISTANCE's mean nominal distance
    yaw_before = 0.0  # the truth's heading at the last WHEEL_DISTANCE

    def truth_pose() -> Pose2D:
        tr = emu.truth
        dn, de = tr.x_m - t0.x_m, tr.y_m - t0.y_m
        c, s = math.cos(t0.yaw_rad), math.sin(t0.yaw_rad)
        fwd, right = c * dn + s * de, -s * dn + c * de
        return Pose2D(fwd, -right, -(tr.yaw_rad - t0.yaw_rad))

    def track(t: Track, pose: Pose2D, truth: Pose2D) -> None:
        t.max_heading_rad = max(t.max_heading_rad, abs(math.remainder(pose.yaw_rad - truth.yaw_rad, 2 * math.pi)))
        t.final_pos_m = math.hypot(pose.x_m - truth.x_m, pose.y_m - truth.y_m)

    for duration, v, w in route(quick, moving):
        half = 0.5 * NOMINAL_TRACK_M * w
        emu.set_radio(1, _pwm(v - half, NOMINAL_RADIUS_M, vehicle.max_rpm))
        emu.set_radio(3, _pwm(v + half, NOMINAL_RADIUS_M, vehicle.max_rpm))
        end = now + duration
        while now < end - 1e-9:
            emu.step(STEP_S)
            now = emu.sim_time_s
            assert emu.sent_log is not None
            yaw_now = truth_pose().yaw_rad
            for sent_s, msg in emu.sent_log[seen:]:
                if msg.get_type() == "WHEEL_DISTANCE" and (
                        drop_rng.random() < wheel_loss or any(a <= sent_s < b for a, b in wheel_gaps)):
                    continue
                if msg.get_type() == "WHEEL_DISTANCE":
                    mean_m = 0.5 * (float(msg.distance[0]) + float(msg.distance[1]))
                    if wheel_mean_m is not None:  # along the truth's mean heading since the last reading
                        yaw_mid = yaw_before + 0.5 * math.remainder(yaw_now - yaw_before, 2 * math.pi)
                        exact_xy[0] += math.cos(yaw_mid) * (mean_m - wheel_mean_m)
                        exact_xy[1] += math.sin(yaw_mid) * (mean_m - wheel_mean_m)
                    wheel_mean_m, yaw_before = mean_m, yaw_now
                inc = Incoming(Link.AUTOPILOT, msg)
                for out in ekf.handle(inc, sent_s).out:
                    if out.dest is Link.AUTOPILOT:
                        emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
                if with_calibration:
                    cal.handle(inc, sent_s)
            seen = len(emu.sent_log)
            for out in ekf.tick(now):
                if out.dest is Link.AUTOPILOT:
                    emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
            if with_calibration:
                cal.tick(now)
            if ekf.state.time_s is None:
                continue
            truth = truth_pose()
            track(res.exact_heading, Pose2D(exact_xy[0], exact_xy[1], truth.yaw_rad), truth)
            track(res.raw, ekf.raw_pose, truth)
            track(res.ekf, ekf.pose_at(now), truth)
            if with_calibration:
                track(res.cal, cal.pose_at(now), truth)
    tr = emu.truth
    # The truth's wheel distances are signed ground paths; the body's is their mean.
    res.dist_m = 0.5 * abs(tr.left_distance_true_m + tr.right_distance_true_m)  # the route only drives forward
    res.cal_track_m = cal.state.track_width_m
    res.counters = dict(ekf.counters)
    return res


def scenario_setups() -> list[tuple[str, VehicleConfig, Scenario, dict[str, Any]]]:
    """(name, vehicle, scenario, extra run() arguments) of every benchmark scenario."""
    base = VehicleConfig(start_armed=True)
    mis = VehicleConfig(start_armed=True, true_right_radius_m=NOMINAL_RADIUS_M * 1.02,
                        true_track_width_m=NOMINAL_TRACK_M * 1.03)
    slip = Scenario(slips=(SlipWindow("left", 20.0, 26.0, 0.3), SlipWindow("both", 33.0, 35.0, 0.2),
                           SlipWindow("right", 80.0, 84.0, 0.4)))
    return [
        ("clean", base, Scenario(), {}),
        ("miscalibrated", mis, Scenario(), {}),
        ("slip", base, slip, {}),
        ("gyro bias 0.01", VehicleConfig(start_armed=True, gyro_bias_rad_s=0.01), Scenario(), {}),
        ("encoder drop-outs", base, Scenario(), {"wheel_loss": 0.2, "wheel_gaps": ((30.0, 32.0), (70.0, 71.0))}),
    ]


def scenarios(quick: bool, seed: int = 1, moving: bool = False) -> list[Result]:
    return [run(name, vehicle, scenario, quick, seed, moving=moving, **extra)
            for name, vehicle, scenario, extra in scenario_setups()]


def table(results: list[Result], seeds: list[int] | None = None) -> str:
    """One row per result (with its seed when `seeds` is given), then the worst of each scenario over them."""
    head = (f"{'scenario':<18} {'seed':>4} {'dist m':>7} | {'raw m':>6} {'%':>5} {'hdg':>6} | {'EKF m':>6} {'%':>5} "
            f"{'hdg':>5} | {'cal m':>6} {'%':>5} {'hdg':>5} | {'exact hdg %':>11} | track m (expected; true)")
    lines = [head, "-" * len(head)]

    def cells(t: Track, dist_m: float) -> str:
        return f"{t.final_pos_m:6.2f} {100 * t.final_pos_m / dist_m:5.2f} {math.degrees(t.max_heading_rad):5.1f}"

    for k, r in enumerate(results):
        seed = "" if seeds is None else str(seeds[k])
        lines.append(f"{r.name:<18} {seed:>4} {r.dist_m:7.1f} | {cells(r.raw, r.dist_m)} | {cells(r.ekf, r.dist_m)} | "
                     f"{cells(r.cal, r.dist_m)} | {100 * r.exact_heading.final_pos_m / r.dist_m:11.2f} | "
                     f"{r.cal_track_m:.4f} ({r.expected_track_m:.4f}; {r.true_track_m:.4f})")
    if seeds is not None and len(set(seeds)) > 1:
        lines.append("worst over the seeds: % of the distance, heading deg")
        for name in dict.fromkeys(r.name for r in results):
            rs = [r for r in results if r.name == name]

            def worst(get: Any, rs: list[Result] = rs) -> str:
                pct = max(100 * get(r).final_pos_m / r.dist_m for r in rs)
                return f"{pct:5.2f} % {max(math.degrees(get(r).max_heading_rad) for r in rs):5.1f} deg"
            exact = max(100 * r.exact_heading.final_pos_m / r.dist_m for r in rs)
            lines.append(f"{name:<18} raw {worst(lambda r: r.raw)} | EKF {worst(lambda r: r.ekf)} | "
                         f"cal {worst(lambda r: r.cal)} | exact heading {exact:5.2f} %")
    return "\n".join(lines)


# ---------------------------------------------------------------- the demo's comparison (--wheels)

def demo_route(moving: bool = False, scale: float = 0.45) -> list[tuple[float, float, float]]:
    """`rover-bridge demo --quick`'s route as PWM segments: a standstill (none with `moving`), a straight, a
    spin, four legs each after a quarter turn, a figure eight, a stop."""
    seg: list[tuple[float, float, float]] = [(0.1 if moving else 2.0, 0.0, 0.0), (4.0 * scale, 0.5, 0.0),
                                             (2.0 * math.pi / 1.5 * max(scale, 0.5), 0.0, 1.5)]
    for _ in range(4):
        seg += [(math.pi / 2.0, 0.0, 1.0), (3.2 * scale, 0.4, 0.0)]
    lap = 2.0 * math.pi * max(scale, 0.5)
    return [*seg, (lap, 0.4, 1.0), (lap, 0.4, -1.0), (2.5, 0.0, 0.0)]


@dataclass(frozen=True)
class AgainstWheels:
    """The demo's figures (m, deg): wheel odometry and the published EKF against the truth."""

    distance_m: float
    wheel_final_m: float
    wheel_max_m: float
    wheel_heading_max_deg: float
    ekf_final_m: float
    ekf_max_m: float
    ekf_heading_max_deg: float


def _interpolate(series: list[tuple[float, Pose2D]], t: float) -> Pose2D | None:
    times = [s[0] for s in series]
    i = bisect.bisect_left(times, t)
    if not series or t < times[0] or t > times[-1]:
        return None
    if times[i] == t or i == 0:
        return series[i][1]
    (t0, a), (t1, b) = series[i - 1], series[i]
    f = (t - t0) / (t1 - t0)
    return Pose2D(a.x_m + f * (b.x_m - a.x_m), a.y_m + f * (b.y_m - a.y_m),
                  a.yaw_rad + f * math.remainder(b.yaw_rad - a.yaw_rad, 2.0 * math.pi))


def against_wheels(vehicle: VehicleConfig, scenario: Scenario, seed: int = 1, moving: bool = False,
                   estimator: dict[str, Any] | None = None) -> AgainstWheels:
    """The demo's comparison in lockstep (module docstring)."""
    emu = Emulator(vehicle, scenario, seed=seed, record_sent=True)
    core = _core(profile_from_dict({"estimator": estimator or {}, "odometry": {"targets": "gcs"}}))
    wheels = WheelOdometry(track_width_m=NOMINAL_TRACK_M)
    t0 = emu.truth
    truth: list[tuple[float, Pose2D]] = []
    wheel: list[tuple[float, Pose2D]] = []
    ekf: list[tuple[float, Pose2D]] = []
    seen = 0
    now = 0.0

    def answer(outs: Any) -> None:
        for out in outs:
            if out.dest is Link.AUTOPILOT:
                emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
            elif out.msg.get_type() == "ODOMETRY":  # FRD: y right, yaw clockwise
                m = out.msg
                ekf.append((m.time_usec * 1e-6, Pose2D(m.x, -m.y, -2.0 * math.atan2(m.q[3], m.q[0]))))

    for duration, v, w in demo_route(moving):
        half = 0.5 * NOMINAL_TRACK_M * w
        emu.set_radio(1, _pwm(v - half, NOMINAL_RADIUS_M, vehicle.max_rpm))
        emu.set_radio(3, _pwm(v + half, NOMINAL_RADIUS_M, vehicle.max_rpm))
        end = now + duration
        while now < end - 1e-9:
            emu.step(STEP_S)
            now = emu.sim_time_s
            assert emu.sent_log is not None
            for sent_s, msg in emu.sent_log[seen:]:
                if msg.get_type() == "WHEEL_DISTANCE":
                    pose = wheels.update(left_m=float(msg.distance[0]), right_m=float(msg.distance[1]))
                    wheel.append((msg.time_usec * 1e-6, pose))
                answer(core.handle(Incoming(Link.AUTOPILOT, msg), sent_s).out)
            seen = len(emu.sent_log)
            answer(core.tick(now))
            tr = emu.truth
            dn, de = tr.x_m - t0.x_m, tr.y_m - t0.y_m
            c, s_ = math.cos(t0.yaw_rad), math.sin(t0.yaw_rad)
            truth.append((now, Pose2D(c * dn + s_ * de, s_ * dn - c * de, -(tr.yaw_rad - t0.yaw_rad))))
    errors = []
    for t, tp in truth[::5]:  # the demo's truth: 20 Hz
        wp, ep = _interpolate(wheel, t), _interpolate(ekf, t)
        if wp is None or ep is None:
            continue
        errors.append((math.hypot(wp.x_m - tp.x_m, wp.y_m - tp.y_m), math.hypot(ep.x_m - tp.x_m, ep.y_m - tp.y_m),
                       abs(math.degrees(math.remainder(wp.yaw_rad - tp.yaw_rad, 2 * math.pi))),
                       abs(math.degrees(math.remainder(ep.yaw_rad - tp.yaw_rad, 2 * math.pi)))))
    tr = emu.truth
    return AgainstWheels(0.5 * abs(tr.left_distance_true_m + tr.right_distance_true_m),
                         errors[-1][0], max(e[0] for e in errors), max(e[2] for e in errors),
                         errors[-1][1], max(e[1] for e in errors), max(e[3] for e in errors))


WHEELS_SCENARIOS = {
    "clean": (VehicleConfig(start_armed=True), Scenario()),
    "gyro-bias": (VehicleConfig(start_armed=True, gyro_bias_rad_s=0.02), Scenario()),
    "miscalibrated": (VehicleConfig(start_armed=True, true_right_radius_m=0.051, true_track_width_m=0.309),
                      Scenario()),
    "slip": (VehicleConfig(start_armed=True), Scenario(slips=(SlipWindow("left", 6.0, 10.0, 0.3),
                                                             SlipWindow("right", 18.0, 21.0, 0.25)))),
}


def wheels_table(seeds: list[int], moving: bool) -> str:
    head = (f"{'scenario':<14} {'seed':>4} {'dist m':>6} | {'wheels final/max mm':>19} {'hdg':>5} | "
            f"{'EKF final/max mm':>17} {'hdg':>5} | EKF <= wheels + 3 mm, + 0.1 deg")
    lines = [head, "-" * len(head)]
    for name, (vehicle, scenario) in WHEELS_SCENARIOS.items():
        for seed in seeds:
            r = against_wheels(vehicle, scenario, seed, moving)
            ok = (r.ekf_final_m <= r.wheel_final_m + 0.003 and r.ekf_max_m <= r.wheel_max_m + 0.003
                  and r.ekf_heading_max_deg <= r.wheel_heading_max_deg + 0.1)
            lines.append(f"{name:<14} {seed:>4} {r.distance_m:6.2f} | {1000 * r.wheel_final_m:8.1f} / "
                         f"{1000 * r.wheel_max_m:8.1f} {r.wheel_heading_max_deg:5.2f} | {1000 * r.ekf_final_m:7.1f} / "
                         f"{1000 * r.ekf_max_m:7.1f} {r.ekf_heading_max_deg:5.2f} | {'yes' if ok else 'no'}")
    return "\n".join(lines)


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one lap instead of four")
    ap.add_argument("--seeds", default="1", help="emulator seeds, e.g. 1-9 (default 1)")
    ap.add_argument("--moving", action="store_true", help="start moving 0.1 s after the first sample")
    ap.add_argument("--wheels", action="store_true", help="the demo's comparison against the wheels (docstring)")
    ap.add_argument("--counters", action="store_true", help="also print the EKF core's counters")
    ap.add_argument("--rate", type=float, default=20.0, help="estimator.stream_rate_hz (default 20)")
    args = ap.parse_args(argv)
    global STREAM_RATE_HZ
    STREAM_RATE_HZ = args.rate
    logging.disable(logging.WARNING)  # the cores' STATUSTEXT log lines would drown the table
    seeds = _seeds(args.seeds)
    if args.wheels:
        print(wheels_table(seeds, args.moving))
        return 0
    results = [r for seed in seeds for r in scenarios(args.quick, seed, args.moving)]
    print(table(results, [seed for seed in seeds for _ in scenario_setups()]))
    if args.counters:
        for r in results:
            print(r.name, {k: v for k, v in r.counters.items() if v})
    return 0


if __name__ == "__main__":
    sys.exit(main())
