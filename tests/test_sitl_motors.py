"""Imperfect motors in the sitl emulator: gains, curved PWM map, deadzone, battery sag, load, stall."""

from __future__ import annotations

import math
from typing import Any

import pytest

from sitl import ConfigError, Emulator, Scenario, VehicleConfig
from sitl.physics import PhysicsState, StepInputs, motor_gains, speed_fraction, step
from sitl.scenario import LoadWindow, StallWindow

V = VehicleConfig(gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
MAX_WHEEL_RAD_S = 200.0 * 2.0 * math.pi / 60.0
DT_S = 0.005


def run(
    inputs: StepInputs, seconds: float, vehicle: VehicleConfig = V, state: PhysicsState | None = None
) -> PhysicsState:
    s = state if state is not None else PhysicsState()
    for _ in range(round(seconds / DT_S)):
        s = step(s, inputs, DT_S, vehicle)
    return s


def drive(emu: Emulator, until_s: float) -> None:
    while emu.sim_time_s < until_s - 1e-9:
        emu.step(0.01)


def armed_emulator(scenario: Scenario | None = None, **vehicle: Any) -> Emulator:
    cfg = VehicleConfig(start_armed=True, gyro_noise_rad_s=0.0, **vehicle)
    return Emulator(vehicle=cfg, scenario=scenario)


def test_defaults_reproduce_the_ideal_linear_motor_bit_for_bit() -> None:
    s = run(StepInputs(left_cmd=0.5, right_cmd=-0.3), 2.0)
    # The motor model before imperfect motors existed, step by step.
    alpha = 1.0 - math.exp(-DT_S / 0.1)
    left = right = 0.0
    for _ in range(round(2.0 / DT_S)):
        left = left + (0.5 * MAX_WHEEL_RAD_S - left) * alpha
        right = right + (-0.3 * MAX_WHEEL_RAD_S - right) * alpha
    assert (s.left_rad_s, s.right_rad_s) == (left, right)
    assert s.left_rad_s == pytest.approx(0.5 * MAX_WHEEL_RAD_S, rel=1e-8)
    assert motor_gains(V, 3600.0) == (1.0, 1.0)
    assert speed_fraction(0.37, 1.0) == 0.37


def test_motor_gains_scale_each_wheel_and_the_ratio_holds_at_steady_state() -> None:
    weak_left = VehicleConfig(left_motor_gain=0.8, gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
    s = run(StepInputs(left_cmd=0.6, right_cmd=0.6), 2.0, vehicle=weak_left)
    assert s.right_rad_s == pytest.approx(0.6 * MAX_WHEEL_RAD_S, rel=1e-7)
    assert s.left_rad_s == pytest.approx(0.8 * 0.6 * MAX_WHEEL_RAD_S, rel=1e-7)
    assert s.left_rad_s / s.right_rad_s == pytest.approx(0.8, rel=1e-7)
    assert s.yaw_rad < -0.1  # the weak left side makes the robot pull left (counter-clockwise)


def test_motor_gain_ratio_through_the_emulator_pwm_path() -> None:
    emu = armed_emulator(right_motor_gain=0.9)
    emu.set_radio(1, 1800)
    emu.set_radio(3, 1800)
    drive(emu, 2.0)
    t = emu.truth
    assert t.right_wheel_rad_s / t.left_wheel_rad_s == pytest.approx(0.9, rel=1e-7)
    assert t.yaw_rad > 0.1  # weak right side: pulls clockwise (right)


def test_curve_exponent_gives_c_to_the_power_at_half_command_both_directions() -> None:
    curved = VehicleConfig(motor_curve_exponent=1.5, gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
    s = run(StepInputs(left_cmd=0.5, right_cmd=-0.5), 2.0, vehicle=curved)
    assert s.left_rad_s == pytest.approx(0.5**1.5 * MAX_WHEEL_RAD_S, rel=1e-7)
    assert s.right_rad_s == pytest.approx(-(0.5**1.5) * MAX_WHEEL_RAD_S, rel=1e-7)
    full = run(StepInputs(left_cmd=1.0, right_cmd=1.0), 2.0, vehicle=curved)
    assert full.left_rad_s == pytest.approx(MAX_WHEEL_RAD_S, rel=1e-7)  # the ends stay put


def test_curve_applies_after_the_deadzone_mapping() -> None:
    emu = armed_emulator(motor_curve_exponent=2.0, deadzone_pwm=40)
    half_pwm = 1500 + 40 + (500 - 40) // 2  # command exactly 0.5 after the deadzone
    emu.set_radio(1, half_pwm)
    emu.set_radio(3, half_pwm)
    drive(emu, 2.0)
    assert emu.truth.left_wheel_rad_s == pytest.approx(0.25 * MAX_WHEEL_RAD_S, rel=1e-7)


@pytest.mark.parametrize("offset_us", [35, -35])
def test_deadzone_40_holds_the_wheels_still_just_inside(offset_us: int) -> None:
    emu = armed_emulator(deadzone_pwm=40)
    emu.set_radio(1, 1500 + offset_us)
    emu.set_radio(3, 1500 + offset_us)
    drive(emu, 1.0)
    assert emu.truth.left_wheel_rad_s == 0.0
    assert emu.truth.right_wheel_rad_s == 0.0
    assert emu.wheel_distances_m == (0.0, 0.0)


def test_deadzone_40_drives_just_outside_at_the_remapped_command() -> None:
    emu = armed_emulator(deadzone_pwm=40)
    emu.set_radio(1, 1560)
    emu.set_radio(3, 1440)
    drive(emu, 2.0)
    expected = 20 / 460 * MAX_WHEEL_RAD_S  # (60 - 40) / (500 - 40) of full speed
    assert emu.truth.left_wheel_rad_s == pytest.approx(expected, rel=1e-7)
    assert emu.truth.right_wheel_rad_s == pytest.approx(-expected, rel=1e-7)
    assert emu.wheel_distances_m[0] > 0.05


def test_load_window_slows_only_its_wheel_only_inside_the_window() -> None:
    emu = armed_emulator(Scenario(loads=(LoadWindow(start_s=2.0, end_s=4.0, fraction=0.25, wheel="left"),)))
    emu.set_radio(1, 2000)
    emu.set_radio(3, 2000)
    drive(emu, 1.99)
    before = emu.truth
    assert before.left_wheel_rad_s == pytest.approx(MAX_WHEEL_RAD_S, rel=1e-7)
    drive(emu, 3.99)
    inside = emu.truth
    assert inside.left_wheel_rad_s == pytest.approx(0.75 * MAX_WHEEL_RAD_S, rel=1e-7)
    assert inside.right_wheel_rad_s == pytest.approx(MAX_WHEEL_RAD_S, rel=1e-7)
    drive(emu, 6.0)
    assert emu.truth.left_wheel_rad_s == pytest.approx(MAX_WHEEL_RAD_S, rel=1e-7)


def test_loads_default_to_both_wheels_and_overlaps_multiply() -> None:
    sc = Scenario.from_events(
        [
            {"type": "load", "start_s": 1.0, "end_s": 3.0, "fraction": 0.5},
            {"type": "load", "wheel": "right", "start_s": 2.0, "duration_s": 2.0, "fraction": 0.2},
        ]
    )
    assert sc.speed_scale("left", 0.5) == 1.0
    assert sc.speed_scale("left", 2.5) == 0.5
    assert sc.speed_scale("right", 1.5) == 0.5
    assert sc.speed_scale("right", 2.5) == pytest.approx(0.4)
    assert sc.speed_scale("right", 3.5) == pytest.approx(0.8)
    assert sc.speed_scale("right", 4.0) == 1.0


def test_stall_holds_the_wheel_and_its_encoder_still_and_it_recovers_through_the_lag() -> None:
    emu = armed_emulator(Scenario(stalls=(StallWindow(wheel="right", start_s=1.0, end_s=2.0),)))
    emu.set_radio(1, 2000)
    emu.set_radio(3, 2000)
    drive(emu, 1.0)
    assert emu.truth.right_wheel_rad_s == pytest.approx(MAX_WHEEL_RAD_S, rel=1e-3)
    left_at_stall, right_at_stall = emu.wheel_distances_m
    angle_at_stall = emu.physics_state.right_angle_rad
    drive(emu, 2.0)
    assert emu.truth.right_wheel_rad_s == 0.0
    assert emu.wheel_distances_m[1] == right_at_stall  # no encoder counts while held
    assert emu.physics_state.right_angle_rad == angle_at_stall
    assert emu.wheel_distances_m[0] - left_at_stall > 0.9  # the other wheel keeps driving
    # Pivoting on the held right wheel: clockwise at v_left / track.
    assert emu.truth.yaw_rate_rad_s == pytest.approx(MAX_WHEEL_RAD_S * 0.05 / 0.30, rel=1e-6)
    # Released: spins up from rest, 63 % after one motor time constant, full speed later.
    drive(emu, 2.1)
    assert emu.truth.right_wheel_rad_s == pytest.approx(MAX_WHEEL_RAD_S * (1.0 - math.exp(-1.0)), rel=1e-6)
    drive(emu, 3.5)
    assert emu.truth.right_wheel_rad_s == pytest.approx(MAX_WHEEL_RAD_S, rel=1e-5)
    assert emu.wheel_distances_m[1] - right_at_stall > 1.0


def test_stall_in_pure_physics_freezes_speed_angle_and_ground_path() -> None:
    moving = run(StepInputs(left_cmd=1.0, right_cmd=1.0), 1.0)
    held = run(StepInputs(left_cmd=1.0, right_cmd=1.0, left_stalled=True, right_stalled=True), 0.5, state=moving)
    assert (held.left_rad_s, held.right_rad_s) == (0.0, 0.0)
    assert held.left_encoder_angle_rad == moving.left_encoder_angle_rad
    assert held.left_distance_true_m == moving.left_distance_true_m
    assert (held.x_m, held.y_m) == (moving.x_m, moving.y_m)


def test_battery_sag_lowers_speed_by_the_fraction_per_minute_and_floors_at_half() -> None:
    sagging = VehicleConfig(battery_sag_per_min=0.1, left_motor_gain=0.8, gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
    s = run(StepInputs(left_cmd=1.0, right_cmd=1.0), 180.0, vehicle=sagging)
    # After 3 minutes 30 % is gone; the lag trails the falling target by ~sag/60 * tau.
    assert s.right_rad_s == pytest.approx(0.7 * MAX_WHEEL_RAD_S, abs=5e-4 * MAX_WHEEL_RAD_S)
    assert s.left_rad_s == pytest.approx(0.8 * 0.7 * MAX_WHEEL_RAD_S, abs=5e-4 * MAX_WHEEL_RAD_S)
    assert motor_gains(sagging, 180.0) == pytest.approx((0.8 * 0.7, 0.7))
    assert motor_gains(sagging, 0.0) == (0.8, 1.0)
    fast = VehicleConfig(battery_sag_per_min=0.5)
    assert motor_gains(fast, 30.0) == pytest.approx((0.75, 0.75))
    assert motor_gains(fast, 60.0) == pytest.approx((0.5, 0.5))
    assert motor_gains(fast, 600.0) == (0.5, 0.5)  # floored at half the start value


def test_battery_sag_follows_emulator_simulated_time() -> None:
    emu = armed_emulator(battery_sag_per_min=0.2)
    emu.set_radio(1, 2000)
    emu.set_radio(3, 2000)
    drive(emu, 60.0)
    assert emu.truth.left_wheel_rad_s == pytest.approx(0.8 * MAX_WHEEL_RAD_S, abs=1e-3 * MAX_WHEEL_RAD_S)


def test_vehicle_validation_rejects_bad_motor_values_all_at_once() -> None:
    with pytest.raises(ConfigError) as err:
        VehicleConfig.from_mapping(
            {
                "left_motor_gain": 0.0,
                "right_motor_gain": float("nan"),
                "motor_curve_exponent": 5.5,
                "battery_sag_per_min": 0.6,
            },
            source="bad.toml",
        )
    problems = err.value.problems
    assert len(problems) == 4
    assert "left_motor_gain must be a positive number, got 0.0" in problems
    assert "right_motor_gain must be a positive number, got nan" in problems
    assert any(p.startswith("motor_curve_exponent must be in (0, 5]") for p in problems)
    assert any(p.startswith("battery_sag_per_min must be in [0, 0.5]") for p in problems)
    with pytest.raises(ConfigError, match=r"motor_curve_exponent must be in \(0, 5\]"):
        VehicleConfig(motor_curve_exponent=0.0)
    with pytest.raises(ConfigError, match=r"battery_sag_per_min must be in \[0, 0.5\]"):
        VehicleConfig(battery_sag_per_min=-0.01)
    with pytest.raises(ConfigError, match="left_motor_gain: wrong type str"):
        VehicleConfig.from_mapping({"left_motor_gain": "0.8"})
    ok = VehicleConfig.from_mapping({"motor_curve_exponent": 5, "battery_sag_per_min": 0.5, "right_motor_gain": 2})
    assert (ok.motor_curve_exponent, ok.battery_sag_per_min, ok.right_motor_gain) == (5.0, 0.5, 2.0)


def test_scenario_validation_rejects_bad_load_and_stall_events() -> None:
    with pytest.raises(ConfigError) as err:
        Scenario.from_events(
            [
                {"type": "load", "start_s": 0.0, "end_s": 1.0, "fraction": 1.0},
                {"type": "load", "wheel": "middle", "start_s": 0.0, "end_s": 1.0, "fraction": 0.1},
                {"type": "stall", "wheel": "left", "start_s": 2.0, "end_s": 1.0},
                {"type": "stall", "start_s": 0.0, "end_s": 1.0},
                {"type": "load", "start_s": 0.0, "end_s": 1.0, "ratio": 0.3},
            ],
            source="s.toml",
        )
    problems = err.value.problems
    assert problems[0] == "event[0]: fraction must be in [0, 1) (1 would stop the wheel: use a stall), got 1.0"
    assert problems[1].startswith("event[1]: wheel must be one of")
    assert problems[2] == "event[2]: end_s must be after start_s"
    assert problems[3].startswith("event[3] (stall):") and "wheel" in problems[3]
    assert problems[4].startswith("event[4] (load):") and "ratio" in problems[4]
    assert len(problems) == 5
