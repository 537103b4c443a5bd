"""Estimation accuracy against the sitl emulator's ground truth, in lockstep (deterministic, no sockets).

    python benchmarks/accuracy.py            # the table over every scenario
    python benchmarks/accuracy.py --quick    # a shorter route (for a smoke run)

The emulator drives a fixed route (straight runs, arcs both ways, spins in place, stops; about
130 m) from RC passthrough values; every message it sends is fed to two EstimateCores (without
and with online calibration) at the emulator's time, and their stream requests are answered by
the emulator (WHEEL_DISTANCE's SET_MESSAGE_INTERVAL is refused, as ArduPilot 4.7 does, so the
REQUEST_DATA_STREAM fallback is exercised). Raw wheel odometry is the plain arc integration of
the same WHEEL_DISTANCE data with the nominal geometry.

Columns: distance driven; final position error in m and in % of the distance; maximum heading
error over the run, in degrees; for raw wheel odometry, the EKF, and the EKF with calibration;
then the calibrated track width, with what calibration can find (the track in the units of the
reported distances: true track / mean true-to-nominal radius ratio) and the physical truth.
"""

from __future__ import annotations

import argparse
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
from rover_bridge.odometry import Pose2D
from rover_bridge.params import Profile, profile_from_dict
from sitl import Emulator, Scenario, VehicleConfig
from sitl.scenario import SlipWindow

STEP_S = 0.01
NOMINAL_TRACK_M = 0.30
NOMINAL_RADIUS_M = 0.05


def route(quick: bool) -> list[tuple[float, float, float]]:
    """(duration_s, v_m_s, omega_rad_s CCW) segments."""
    seg: list[tuple[float, float, float]] = [(4.0, 0.0, 0.0)]  # streams come up, the gyro bias settles
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
        with_calibration: bool = True) -> Result:
    emu = Emulator(vehicle, scenario, seed=seed, record_sent=True)
    ekf = _core(profile_from_dict({"estimator": {"stream_rate_hz": STREAM_RATE_HZ}}))
    cal = _core(profile_from_dict({"estimator": {"stream_rate_hz": STREAM_RATE_HZ, "calibrate": True}}))
    drop_rng = random.Random(f"accuracy-drop-{seed}")
    mean_scale = 0.5 * (vehicle.left_radius_true_m + vehicle.right_radius_true_m) / vehicle.wheel_radius_m
    res = Result(name, true_track_m=vehicle.track_true_m, expected_track_m=vehicle.track_true_m / mean_scale)
    t0 = emu.truth
    seen = 0
    now = 0.0

    def truth_pose() -> Pose2D:
        tr = emu.truth
        dn, de = tr.x_m - t0.x_m, tr.y_m - t0.y_m
        c, s = math.cos(t0.yaw_rad), math.sin(t0.yaw_rad)
        fwd, right = c * dn + s * de, -s * dn + c * de
        return Pose2D(fwd, -right, -(tr.yaw_rad - t0.yaw_rad))

    def track(t: Track, pose: Pose2D, truth: Pose2D) -> None:
        t.max_heading_rad = max(t.max_heading_rad, abs(math.remainder(pose.yaw_rad - truth.yaw_rad, 2 * math.pi)))
        t.final_pos_m = math.hypot(pose.x_m - truth.x_m, pose.y_m - truth.y_m)

    for duration, v, w in route(quick):
        half = 0.5 * NOMINAL_TRACK_M * w
        emu.set_radio(1, _pwm(v - half, NOMINAL_RADIUS_M, vehicle.max_rpm))
        emu.set_radio(3, _pwm(v + half, NOMINAL_RADIUS_M, vehicle.max_rpm))
        end = now + duration
        while now < end - 1e-9:
            emu.step(STEP_S)
            now = emu.sim_time_s
            assert emu.sent_log is not None
            for sent_s, msg in emu.sent_log[seen:]:
                if msg.get_type() == "WHEEL_DISTANCE" and (
                        drop_rng.random() < wheel_loss or any(a <= sent_s < b for a, b in wheel_gaps)):
                    continue
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


def scenarios(quick: bool) -> list[Result]:
    return [run(name, vehicle, scenario, quick, **extra) for name, vehicle, scenario, extra in scenario_setups()]


def table(results: list[Result]) -> str:
    head = (f"{'scenario':<18} {'dist m':>7} | {'raw m':>6} {'%':>5} {'hdg':>6} | {'EKF m':>6} {'%':>5} "
            f"{'hdg':>5} | {'cal m':>6} {'%':>5} {'hdg':>5} | track m (expected; true)")
    lines = [head, "-" * len(head)]
    for r in results:
        def cells(t: Track, dist_m: float = r.dist_m) -> str:
            return f"{t.final_pos_m:6.2f} {100 * t.final_pos_m / dist_m:5.2f} {math.degrees(t.max_heading_rad):5.1f}"
        lines.append(f"{r.name:<18} {r.dist_m:7.1f} | {cells(r.raw)} | {cells(r.ekf)} | {cells(r.cal)} | "
                     f"{r.cal_track_m:.4f} ({r.expected_track_m:.4f}; {r.true_track_m:.4f})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one lap instead of four")
    ap.add_argument("--counters", action="store_true", help="also print the EKF core's counters")
    ap.add_argument("--rate", type=float, default=20.0, help="estimator.stream_rate_hz (default 20)")
    args = ap.parse_args(argv)
    global STREAM_RATE_HZ
    STREAM_RATE_HZ = args.rate
    logging.disable(logging.WARNING)  # the cores' STATUSTEXT log lines would drown the table
    results = scenarios(args.quick)
    print(table(results))
    if args.counters:
        for r in results:
            print(r.name, {k: v for k, v in r.counters.items() if v})
    return 0


if __name__ == "__main__":
    sys.exit(main())
