"""The emulator's ArduPilot-skid plant (sitl/skid.py, sitl/vehicles/ardupilot-skid-plant.toml) against what the
real Rover 4.7 SITL (rover-skid, WENC_TYPE 10) was measured doing: the common speed lags 0.29 s, a differential
command turns at once, WHEEL_DISTANCE comes from the 50 Hz loop with 20/20/20/40 ms gaps at 40 Hz (40/60 ms at
20 Hz), increments of 15.904 mm per 20 ms at 0.8 m/s (SITL's per-read truncation), index 0 = the right wheel."""

from __future__ import annotations

import collections
import itertools
import math
from dataclasses import replace
from pathlib import Path

import pytest

from sitl import ConfigError, Emulator, VehicleConfig, load_vehicle, skid
from sitl.mav import MAVLinkMessage
from sitl.physics import PhysicsState, StepInputs

TOML = Path(__file__).resolve().parent.parent / "sitl" / "vehicles" / "ardupilot-skid-plant.toml"
PLANT = replace(load_vehicle(TOML), start_armed=True, gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
MAX_SPEED_M_S = 4.0
TURN_RATE_RAD_S = math.radians(140.0)  # per unit of (m_left - m_right)
TAU_S = 4.0 / 14.0
HALF_TRACK_M = 0.8185111359


def emulator(vehicle: VehicleConfig = PLANT, seed: int = 0, extra1_hz: float = 50.0) -> Emulator:
    emu = Emulator(vehicle, seed=seed, record_sent=True)
    emu.set_param("SR0_EXTRA1", extra1_hz)
    return emu


def run(emu: Emulator, seconds: float, left_pwm: int, right_pwm: int, dt_s: float = 0.01) -> None:
    """MANUAL with the RC passthrough: RC1 drives the left motor, RC3 the right one."""
    emu.set_radio(1, left_pwm)
    emu.set_radio(3, right_pwm)
    end = emu.sim_time_s + seconds
    while emu.sim_time_s < end - 1e-9:
        emu.step(dt_s)


def wheel_distance(emu: Emulator, after_s: float = 0.0) -> list[MAVLinkMessage]:
    assert emu.sent_log is not None
    return [m for t, m in emu.sent_log if m.get_type() == "WHEEL_DISTANCE" and t >= after_s]


def step_trace(emu: Emulator, seconds: float) -> list[tuple[float, float, float]]:
    """(time since now, speed, yaw rate) every 1 ms."""
    t0 = emu.sim_time_s
    trace = []
    while emu.sim_time_s < t0 + seconds - 1e-9:
        emu.step(0.001)
        trace.append((emu.sim_time_s - t0, emu.truth.v_m_s, emu.truth.yaw_rate_rad_s))
    return trace


def test_both_motors_step_lags_0_29_s_and_does_not_turn() -> None:
    emu = emulator()
    run(emu, 0.5, 1500, 1500)
    emu.step(0.005)  # 5 ms into a loop
    emu.set_radio(1, 1600)
    emu.set_radio(3, 1600)
    trace = step_trace(emu, 2.0)
    # Parsed at the end of this loop, output by the next: the motors move 35 ms later (15 + 20).
    start = next(t for t, v, _ in trace if v > 0.0) - 0.001
    assert start == pytest.approx(0.035, abs=1e-6)
    target = 0.2 * MAX_SPEED_M_S
    at_tau = next(v for t, v, _ in trace if t >= start + TAU_S - 1e-9)
    assert at_tau == pytest.approx(target * (1.0 - math.exp(-1.0)), rel=0.01)  # 63 % after one time constant
    t63 = next(t for t, v, _ in trace if v >= 0.632 * target) - start
    assert 0.28 <= t63 <= 0.29
    assert trace[-1][1] == pytest.approx(target, rel=2e-3)  # 6.9 time constants
    assert max(abs(w) for _, _, w in trace) == 0.0
    assert emu.physics_state.accel_m_s2 == pytest.approx(0.0, abs=0.01)


def test_a_differential_command_turns_at_once_while_the_common_speed_still_lags() -> None:
    emu = emulator()
    run(emu, 3.0, 1600, 1600)  # cruising at 0.8 m/s
    emu.set_radio(1, 1700)  # +0.2 on the left only: a clockwise turn and a new common target
    trace = step_trace(emu, 0.1)
    expected = (0.4 - 0.2) * TURN_RATE_RAD_S
    turning = [(t, v, w) for t, v, w in trace if w != 0.0]
    assert 0.02 <= turning[0][0] <= 0.041  # the next loop but one
    assert turning[0][2] == pytest.approx(expected, rel=1e-9)  # all of it in its first millisecond
    assert all(w == pytest.approx(expected, rel=1e-9) for _, _, w in turning)
    assert turning[0][1] < 0.802  # while the speed (target 1.2 m/s) has only started to move
    stopped = emulator()
    run(stopped, 0.5, 1400, 1600)  # spin in place from rest: the full rate, no forward speed
    assert stopped.truth.yaw_rate_rad_s == pytest.approx(-0.4 * TURN_RATE_RAD_S, rel=1e-9)
    assert stopped.truth.v_m_s == pytest.approx(0.0, abs=1e-12)


def test_the_motors_take_an_override_at_the_loop_after_the_one_that_parsed_it_and_hold_it() -> None:
    emu = emulator()
    run(emu, 1.0, 1500, 1500)
    emu.step(0.012)  # 12 ms into the loop that began at 1.000 s
    emu.set_radio(1, 1600)
    trace = step_trace(emu, 0.06)
    moving = [t for t, v, _ in trace if v != 0.0]
    assert moving[0] == pytest.approx(0.028 + 0.001, abs=1e-6)  # loop at 1.020 parses it, 1.040 outputs it
    emu.set_radio(1, 1500)
    emu.step(0.001)  # within a loop the motors keep the last output
    assert emu.truth.yaw_rate_rad_s > 0.0


def test_pure_step_is_the_sim_rover_skid_mix() -> None:
    s = PhysicsState()
    for _ in range(1000):  # 5 s: 17 time constants
        s = skid.step(s, StepInputs(left_cmd=0.5, right_cmd=0.1), 0.005, PLANT)
    assert s.v_m_s == pytest.approx(0.3 * MAX_SPEED_M_S, rel=1e-6)
    assert s.yaw_rate_rad_s == pytest.approx(0.4 * TURN_RATE_RAD_S, rel=1e-6)
    # Each side's SITL-encoder speed: the body speed plus or minus the turn over half the track.
    assert s.left_rad_s * 0.05 == pytest.approx(1.2 + 0.4 * TURN_RATE_RAD_S * HALF_TRACK_M, rel=1e-6)
    assert s.right_rad_s * 0.05 == pytest.approx(1.2 - 0.4 * TURN_RATE_RAD_S * HALF_TRACK_M, rel=1e-6)


def test_wheel_distance_at_50_hz_asked_comes_at_40_hz_in_20_and_40_ms_gaps_with_increments_to_match() -> None:
    emu = emulator(seed=3)
    run(emu, 20.0, 1600, 1600)
    msgs = wheel_distance(emu, after_s=2.0)
    gaps = [(b.time_usec - a.time_usec) // 1000 for a, b in itertools.pairwise(msgs)]
    count = collections.Counter(gaps)
    assert set(count) <= {19, 20, 21, 39, 40, 41}
    assert count[20] / len(gaps) == pytest.approx(0.74, abs=0.04)  # measured 237 of 317
    assert count[40] / len(gaps) == pytest.approx(0.24, abs=0.04)  # measured 76 of 317
    late = sum(count[g] for g in (19, 21, 39, 41))
    assert 0 < late <= 0.05 * len(gaps)  # the scheduler's odd late loop (measured 7 of 317)
    assert len(msgs) / (msgs[-1].time_usec - msgs[0].time_usec) * 1e6 == pytest.approx(40.0, rel=0.02)
    # Uneven increments: one loop's travel or two, each read 15.904 mm per 20 ms (0.6 % short: truncation).
    for (a, b), gap in zip(itertools.pairwise(msgs), gaps, strict=True):
        for i in (0, 1):
            step_m = b.distance[i] - a.distance[i]
            assert step_m == pytest.approx(gap * 0.0159043 / 20.0, abs=1.1 * 2 * math.pi * 0.05 / 3200 * gap / 20)
    speed = (msgs[-1].distance[0] - msgs[0].distance[0]) / ((msgs[-1].time_usec - msgs[0].time_usec) / 1e6)
    assert speed == pytest.approx(0.7952, abs=0.0005)


def test_at_20_hz_the_gaps_alternate_40_and_60_ms() -> None:
    emu = emulator(vehicle=replace(PLANT, loop_late_rate=0.0), extra1_hz=20.0)
    run(emu, 5.0, 1600, 1600)
    msgs = wheel_distance(emu, after_s=1.0)
    gaps = [(b.time_usec - a.time_usec) // 1000 for a, b in itertools.pairwise(msgs)]
    assert set(gaps) == {40, 60}
    assert all(a != b for a, b in itertools.pairwise(gaps))


def test_spin_in_place_index_0_is_the_right_wheel() -> None:
    emu = emulator()
    run(emu, 1.0, 1500, 1500)
    before = wheel_distance(emu)[-1].distance[:2]
    run(emu, 3.0, 1400, 1600)  # left back, right forward: counter-clockwise
    after = wheel_distance(emu)[-1].distance[:2]
    right, left = after[0] - before[0], after[1] - before[1]
    assert emu.truth.yaw_rate_rad_s < 0.0
    assert right > 2.3 and left < -2.3  # 0.8 m/s each side for about 3 s
    assert right == pytest.approx(-left, rel=0.01)
    yawed = -emu.truth.yaw_rate_rad_s * 3.0
    assert right == pytest.approx(yawed * HALF_TRACK_M, rel=0.02)


def test_a_reboot_restarts_the_counts_and_the_loop() -> None:
    emu = emulator(vehicle=replace(PLANT, reboot_silence_s=0.2))
    run(emu, 2.0, 1600, 1600)
    emu.reboot()
    run(emu, 0.5, 1500, 1500)
    emu.set_param("SR0_EXTRA1", 50)
    run(emu, 1.0, 1500, 1500)
    last = wheel_distance(emu)[-1]
    # Braking from 0.8 m/s after the boot: well under the 1.6 m driven before it.
    assert 0.0 < last.distance[0] < 0.3 and last.time_usec < 1.5e6


def test_the_plant_must_report_the_right_wheel_first_and_be_known() -> None:
    with pytest.raises(ConfigError, match="right_left"):
        replace(PLANT, wheel_distance_order="left_right")
    with pytest.raises(ConfigError, match="plant must be one of"):
        VehicleConfig(plant="tank")
    with pytest.raises(ConfigError, match="loop_late_rate"):
        VehicleConfig(loop_late_rate=1.5)


def test_the_default_plant_is_unchanged_and_sends_wheel_distance_at_the_step_ends() -> None:
    emu = Emulator(VehicleConfig(start_armed=True), record_sent=True)
    assert emu.autopilot.skid_loop is None
    emu.set_param("SR0_EXTRA1", 50)
    run(emu, 1.0, 1600, 1600)
    gaps = {(b.time_usec - a.time_usec) // 1000 for a, b in itertools.pairwise(wheel_distance(emu))}
    assert gaps <= {20, 30}  # 25 ms on a 10 ms step grid
