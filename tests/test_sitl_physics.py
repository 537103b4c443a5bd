"""Physics of the sitl emulator: hand-computed cases with tight tolerances (pure, no sockets)."""

from __future__ import annotations

import itertools
import math

import pytest

from sitl import Emulator, Scenario, VehicleConfig
from sitl.physics import PhysicsState, StepInputs, encoder_counts, pwm_to_command, step, wrap_pi
from sitl.scenario import EncoderDropout, SlipPatch, SlipWindow

V = VehicleConfig(gyro_noise_rad_s=0.0, gyro_bias_rad_s=0.0)
MAX_WHEEL_RAD_S = 200.0 * 2.0 * math.pi / 60.0
MAX_V_M_S = MAX_WHEEL_RAD_S * 0.05


def run(inputs: StepInputs, seconds: float, vehicle: VehicleConfig = V, dt_s: float = 0.005) -> PhysicsState:
    s = PhysicsState()
    for _ in range(round(seconds / dt_s)):
        s = step(s, inputs, dt_s, vehicle)
    return s


def lagged_distance_m(v_max_m_s: float, t_s: float, tau_s: float) -> float:
    """Distance covered from rest by a first-order lag towards v_max."""
    return v_max_m_s * (t_s - tau_s * (1.0 - math.exp(-t_s / tau_s)))


def test_full_pwm_straight_drive_covers_v_t_within_the_motor_lag() -> None:
    s = run(StepInputs(left_cmd=1.0, right_cmd=1.0), 3.0)
    expected = lagged_distance_m(MAX_V_M_S, 3.0, 0.1)
    assert s.x_m == pytest.approx(expected, rel=1e-4)
    # The lag costs exactly v*tau of distance compared with an ideal motor.
    assert MAX_V_M_S * 3.0 - s.x_m == pytest.approx(MAX_V_M_S * 0.1, rel=1e-3)
    assert s.y_m == pytest.approx(0.0, abs=1e-12)
    assert s.yaw_rad == pytest.approx(0.0, abs=1e-12)
    assert s.v_m_s == pytest.approx(MAX_V_M_S, rel=1e-6)


def test_motor_reaches_63_percent_after_one_time_constant() -> None:
    s = run(StepInputs(left_cmd=1.0, right_cmd=1.0), 0.1, dt_s=0.001)
    assert s.left_rad_s == pytest.approx(MAX_WHEEL_RAD_S * (1.0 - math.exp(-1.0)), rel=1e-6)


def test_spin_in_place_equal_opposite_encoders_and_geometric_yaw_rate() -> None:
    s = run(StepInputs(left_cmd=1.0, right_cmd=-1.0), 2.0)
    assert s.left_encoder_angle_rad == pytest.approx(-s.right_encoder_angle_rad, rel=1e-12)
    assert s.left_encoder_angle_rad > 10.0
    # Left forward, right back: clockwise (positive) rotation at 2 v / track.
    assert s.yaw_rate_rad_s == pytest.approx(2.0 * MAX_V_M_S / 0.30, rel=1e-6)
    assert math.hypot(s.x_m, s.y_m) < 1e-9


def test_left_faster_turns_clockwise_towards_east() -> None:
    s = run(StepInputs(left_cmd=1.0, right_cmd=0.5), 0.5)
    assert s.yaw_rate_rad_s > 0.0
    assert s.yaw_rad > 0.0
    assert s.y_m > 0.0  # heading north and turning right moves east


def test_arc_matches_closed_form_circle() -> None:
    # Constant wheel speeds from the start (no lag transient): start at steady speeds.
    w_l, w_r = 10.0, 6.0
    s0 = PhysicsState(left_rad_s=w_l, right_rad_s=w_r)
    cmd = StepInputs(left_cmd=w_l / MAX_WHEEL_RAD_S, right_cmd=w_r / MAX_WHEEL_RAD_S)
    s = s0
    for _ in range(400):
        s = step(s, cmd, 0.005, V)
    v = 0.05 * (w_l + w_r) / 2
    omega = 0.05 * (w_l - w_r) / 0.30
    t = 2.0
    radius = v / omega
    assert s.x_m == pytest.approx(radius * math.sin(omega * t), abs=1e-9)
    assert s.y_m == pytest.approx(radius * (1.0 - math.cos(omega * t)), abs=1e-9)


def test_encoder_quantisation_steps_match_resolution() -> None:
    cpr = 16
    resolution_m = 2.0 * math.pi * 0.05 / cpr
    emu = Emulator(vehicle=VehicleConfig(encoder_cpr=cpr, start_armed=True), seed=1)
    emu.set_radio(1, 1600)
    emu.set_radio(3, 1600)
    seen: set[float] = set()
    for _ in range(300):
        emu.step(0.01)
        seen.add(emu.wheel_distances_m[0])
    steps = sorted(seen)
    assert len(steps) > 10
    for d in steps:
        assert d / resolution_m == pytest.approx(round(d / resolution_m), abs=1e-9)
    gaps = {round((b - a) / resolution_m) for a, b in itertools.pairwise(steps)}
    assert min(gaps) == 1  # single-count steps are visible at this speed
    # Quantised reading never exceeds the true rotation and lags it by less than one count.
    true_m = emu.physics_state.left_encoder_angle_rad * 0.05
    assert 0.0 <= true_m - emu.wheel_distances_m[0] < resolution_m


def test_encoder_counts_floor_including_reverse() -> None:
    assert encoder_counts(2.0 * math.pi, 100) == 100
    assert encoder_counts(2.0 * math.pi * 0.999, 100) == 99
    assert encoder_counts(-1e-6, 100) == -1


def test_slip_makes_encoders_read_more_than_ground_moved() -> None:
    s = run(StepInputs(left_cmd=1.0, right_cmd=1.0, left_slip=0.4, right_slip=0.4), 2.0)
    encoder_m = s.left_encoder_angle_rad * 0.05
    assert s.left_distance_true_m == pytest.approx(0.6 * encoder_m, rel=1e-9)
    assert s.x_m == pytest.approx(0.6 * encoder_m, rel=1e-9)


def test_one_wheel_slipping_turns_the_body() -> None:
    s = run(StepInputs(left_cmd=1.0, right_cmd=1.0, left_slip=0.5), 1.0)
    assert s.yaw_rad < 0.0  # left contact slower: turns counter-clockwise (left)


def test_calibration_error_encoders_use_nominal_radius() -> None:
    vehicle = VehicleConfig(
        true_left_radius_m=0.055, true_right_radius_m=0.055, start_armed=True, gyro_noise_rad_s=0.0
    )
    emu = Emulator(vehicle=vehicle)
    emu.set_radio(1, 2000)
    emu.set_radio(3, 2000)
    for _ in range(200):
        emu.step(0.01)
    reported = emu.wheel_distances_m[0]
    assert reported == pytest.approx(emu.truth.left_distance_true_m * 0.05 / 0.055, abs=2e-3)
    assert emu.truth.x_m > reported


def test_gyro_bias_makes_ahrs_yaw_drift_while_standing_still() -> None:
    vehicle = VehicleConfig(gyro_bias_rad_s=0.01, gyro_noise_rad_s=0.0)
    s = run(StepInputs(), 10.0, vehicle=vehicle)
    assert s.yaw_rad == 0.0
    assert s.ahrs_yaw_rad == pytest.approx(0.1, rel=1e-9)


def test_pwm_to_command_deadzone_limits_and_reverse() -> None:
    assert pwm_to_command(1500, V) == 0.0
    assert pwm_to_command(1510, V) == 0.0  # inside the 10 us deadzone
    assert pwm_to_command(2000, V) == 1.0
    assert pwm_to_command(2100, V) == 1.0
    assert pwm_to_command(1000, V) == -1.0
    assert pwm_to_command(1755, V) == pytest.approx(245 / 490)
    assert pwm_to_command(2000, V, reversed_=True) == -1.0
    assert pwm_to_command(0, V) == 0.0


def test_wrap_pi() -> None:
    assert wrap_pi(math.pi + 0.1) == pytest.approx(-math.pi + 0.1)
    assert wrap_pi(-math.pi) == pytest.approx(math.pi)
    assert wrap_pi(0.3) == pytest.approx(0.3)


def test_scenario_slip_window_and_encoder_dropout_in_emulator() -> None:
    scenario = Scenario(
        slips=(SlipWindow("left", 1.0, 2.0, 0.5),),
        dropouts=(EncoderDropout("right", 1.0, 1.5),),
    )
    emu = Emulator(vehicle=VehicleConfig(start_armed=True), scenario=scenario)
    emu.set_radio(1, 2000)
    emu.set_radio(3, 2000)
    for _ in range(100):
        emu.step(0.01)
    left_before, right_before = emu.wheel_distances_m
    truth_before = emu.truth
    for _ in range(50):
        emu.step(0.01)
    left_mid, right_mid = emu.wheel_distances_m
    assert right_mid == right_before  # drop-out: the right encoder lost every count
    assert emu.truth.right_distance_true_m - truth_before.right_distance_true_m > 0.4
    assert left_mid - left_before > 0.4
    # Left wheel slips at 0.5: its contact covers half what its encoder reports.
    assert emu.truth.left_distance_true_m - truth_before.left_distance_true_m == pytest.approx(
        0.5 * (left_mid - left_before), abs=2e-3
    )
    assert emu.truth.yaw_rad < 0.0  # left slipping: turned left


def test_slip_patch_only_acts_inside_the_patch() -> None:
    patch = SlipPatch(x_min_m=1.0, x_max_m=100.0, y_min_m=-10.0, y_max_m=10.0, ratio=0.5)
    assert Scenario(patches=(patch,)).slip_ratio("left", 0.0, 0.5, 0.0) == 0.0
    assert Scenario(patches=(patch,)).slip_ratio("right", 0.0, 1.5, 0.0) == 0.5
    emu = Emulator(vehicle=VehicleConfig(start_armed=True), scenario=Scenario(patches=(patch,)))
    emu.set_radio(1, 2000)
    emu.set_radio(3, 2000)
    for _ in range(300):
        emu.step(0.01)
    encoder_m = emu.wheel_distances_m[0]
    assert emu.truth.x_m < encoder_m - 0.5  # slipped in the patch
    assert emu.truth.x_m > 1.0
