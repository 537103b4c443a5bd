"""EstimateCore against the sitl emulator in lockstep, in-process (deterministic, no sockets)."""

from __future__ import annotations

import itertools
import logging
import math
import sys
from pathlib import Path

import pytest

from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import profile_from_dict
from sitl import Emulator, Scenario, VehicleConfig

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import accuracy


@pytest.fixture(autouse=True)
def _quiet() -> None:
    logging.getLogger("rover_bridge").setLevel(logging.ERROR)


def test_miscalibrated_drive_ekf_beats_raw_odometry_within_the_targets() -> None:
    mis = VehicleConfig(start_armed=True, true_right_radius_m=0.05 * 1.02, true_track_width_m=0.30 * 1.03)
    res = accuracy.run("miscalibrated", mis, Scenario(), quick=True, seed=2, with_calibration=False)
    assert res.dist_m > 35.0
    assert res.ekf.max_heading_rad < math.radians(2.0)
    assert res.raw.max_heading_rad > 3.0 * res.ekf.max_heading_rad
    assert res.ekf.final_pos_m < 0.01 * res.dist_m
    # the stream requests went through the DENIED -> REQUEST_DATA_STREAM path and data flowed at 20 Hz
    assert res.counters["stream_fallbacks"] == 1 and res.counters["wheel_steps"] > 20 * 55


@pytest.mark.parametrize("name", ["miscalibrated", "slip"])
def test_full_route_over_100_m_ekf_heading_3x_better_than_raw(name: str) -> None:
    # The benchmark's own scenarios (2 % radius and 3 % track error; slip windows on either wheel), full
    # four-lap route, fixed seed. Bounds: position within 1 % of the distance, heading within 3 deg
    # (the benchmark's 2 deg target holds for this seed; other seeds reach about 2.6 deg).
    _, vehicle, scenario, extra = next(s for s in accuracy.scenario_setups() if s[0] == name)
    res = accuracy.run(name, vehicle, scenario, quick=False, seed=1, with_calibration=False, **extra)
    assert res.dist_m >= 100.0
    assert res.ekf.final_pos_m < 0.01 * res.dist_m
    assert res.ekf.max_heading_rad < math.radians(3.0)
    assert res.raw.max_heading_rad >= 3.0 * res.ekf.max_heading_rad
    if name == "miscalibrated":  # the reference column: a 1 % mean wheel radius, which no gyro observes, alone
        # leaves more than 0.3 % of the distance on the exact heading (the route ends 41 m from its start)
        assert 0.003 * res.dist_m < res.exact_heading.final_pos_m < 0.004 * res.dist_m


@pytest.mark.parametrize("moving", [False, True], ids=["standstill first", "moving at once"])
@pytest.mark.parametrize("name", ["clean", "gyro-bias"])
@pytest.mark.parametrize("seed", [1, 2])
def test_the_published_estimate_is_never_worse_than_its_own_wheels(name: str, seed: int, moving: bool) -> None:
    # `rover-bridge demo`'s comparison on its route: wheels that agree with the gyro (a 0.02 rad/s bias is
    # the gyro's problem) hold the estimate; the published ODOMETRY is within 3 mm and 0.1 deg of plain wheel
    # odometry everywhere, also when the rover drives off 0.1 s after the first sample (no standstill).
    vehicle, scenario = accuracy.WHEELS_SCENARIOS[name]
    r = accuracy.against_wheels(vehicle, scenario, seed, moving)
    assert r.distance_m > 5.0
    assert r.ekf_final_m <= r.wheel_final_m + 0.003
    assert r.ekf_max_m <= r.wheel_max_m + 0.003
    assert r.ekf_heading_max_deg <= r.wheel_heading_max_deg + 0.1


def test_reset_counter_rises_exactly_once_across_an_emulator_reboot() -> None:
    emu = Emulator(VehicleConfig(start_armed=True), Scenario(), seed=3, record_sent=True)
    core = accuracy._core(profile_from_dict({}))
    seen = 0
    poses = []

    def step(seconds: float, left_pwm: int, right_pwm: int) -> None:
        nonlocal seen
        emu.set_radio(1, left_pwm)
        emu.set_radio(3, right_pwm)
        for _ in range(round(seconds / 0.01)):
            emu.step(0.01)
            assert emu.sent_log is not None
            for sent_s, msg in emu.sent_log[seen:]:
                for out in core.handle(Incoming(Link.AUTOPILOT, msg), sent_s).out:
                    if out.dest is Link.AUTOPILOT:
                        emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
            seen = len(emu.sent_log)
            for out in core.tick(emu.sim_time_s):
                if out.dest is Link.AUTOPILOT:
                    emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
            poses.append(core.pose_at(emu.sim_time_s))

    step(3.0, 1500, 1500)
    step(5.0, 1650, 1700)  # a gentle left arc
    before = core.pose_at(emu.sim_time_s)
    assert core.reset_counter == 0
    emu.reboot()
    step(1.0, 1500, 1500)  # silent board, wheels stopped by the reboot
    step(6.0, 1650, 1650)
    assert core.reset_counter == 1
    assert core.counters["reboots"] == 1
    # no jump: consecutive published poses never differ by more than the rover can move in 10 ms
    jumps = [math.hypot(b.x_m - a.x_m, b.y_m - a.y_m) for a, b in itertools.pairwise(poses)]
    assert max(jumps) < 0.05
    # and the estimate kept going after the reboot (streams were asked for again)
    after = core.pose_at(emu.sim_time_s)
    assert math.hypot(after.x_m - before.x_m, after.y_m - before.y_m) > 1.0


def test_the_published_pose_does_not_trail_the_truth_after_an_acceleration() -> None:
    # The wheels measure the mean speed of each interval, so the filter's speed is half an interval late
    # in every change of speed; integrating it left the pose v * dt / 2 behind (12 mm at 0.5 m/s with
    # 20 Hz WHEEL_DISTANCE) for as long as the rover drove. The cumulative distances now place it.
    emu = Emulator(VehicleConfig(start_armed=True, gyro_noise_rad_s=0.0), Scenario(), seed=1, record_sent=True)
    core = accuracy._core(profile_from_dict({"estimator": {"stream_rate_hz": 20.0}}))
    seen = 0
    errors_mm = []
    pwm = accuracy._pwm(0.5, 0.05, 200.0)
    for i in range(800):  # 2 s still, then 6 s at 0.5 m/s
        emu.set_radio(1, 1500 if i < 200 else pwm)
        emu.set_radio(3, 1500 if i < 200 else pwm)
        emu.step(0.01)
        assert emu.sent_log is not None
        for sent_s, msg in emu.sent_log[seen:]:
            for out in core.handle(Incoming(Link.AUTOPILOT, msg), sent_s).out:
                if out.dest is Link.AUTOPILOT:
                    emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
        seen = len(emu.sent_log)
        for out in core.tick(emu.sim_time_s):
            if out.dest is Link.AUTOPILOT:
                emu.handle_message(out.msg, src_system=out.src_system, src_component=out.src_component)
        if i >= 400:  # at constant speed
            errors_mm.append(1000.0 * (core.pose_at(emu.sim_time_s).x_m - emu.truth.x_m))
    assert emu.truth.v_m_s > 0.45
    assert max(abs(e) for e in errors_mm) < 2.0, (min(errors_mm), max(errors_mm))
