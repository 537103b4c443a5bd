"""WHEEL_DISTANCE ingestion: indices and signs, reboots, spikes, reordering, gaps."""

from __future__ import annotations

import math

import pytest

from rover_bridge.estimate.wheel_input import StepKind, WheelInput
from rover_bridge.params import EncoderParams, RobotParams

ROBOT = RobotParams(wheel_radius_m=0.05, track_width_m=0.3, max_wheel_rpm=200.0)
# fastest surface speed: 200 rpm * 2 pi / 60 * 0.05 m = 1.0472 m/s; a spike is > 2x that over dt (+5 mm)
VMAX = 200.0 * 2 * math.pi / 60 * 0.05


def _wi(**enc: object) -> WheelInput:
    return WheelInput(EncoderParams(**enc), ROBOT)  # type: ignore[arg-type]


def test_first_reading_is_a_baseline_then_steps() -> None:
    wi = _wi()
    assert wi.ingest(1_000_000, 2, [5.0, 7.0]).kind is StepKind.BASELINE
    step = wi.ingest(1_050_000, 2, [5.02, 7.03])
    assert step.kind is StepKind.STEP
    assert step.dt_s == pytest.approx(0.05)
    assert step.d_left_m == pytest.approx(0.02) and step.d_right_m == pytest.approx(0.03)


def test_indices_signs_and_radius_scaling_from_the_profile() -> None:
    robot = RobotParams(wheel_radius_m=0.05, right_wheel_radius_m=0.051)
    wi = WheelInput(EncoderParams(left_index=2, right_index=0, left_reversed=True), robot)
    wi.ingest(0, 3, [1.0, 9.0, -1.0])
    step = wi.ingest(100_000, 3, [1.01, 9.0, -1.02])
    # left is index 2 counting down (reversed): -1.0 -> -1.02 is 0.02 m forward
    assert step.d_left_m == pytest.approx(0.02)
    # right is index 0, radius 0.051 vs the autopilot's nominal 0.05: 0.01 m reads as 0.0102 m
    assert step.d_right_m == pytest.approx(0.0102)


def test_time_going_back_beyond_the_reorder_window_is_a_reboot() -> None:
    wi = _wi()
    wi.ingest(100_000_000, 2, [3.0, 3.0])
    step = wi.ingest(99_000_000, 2, [3.0, 3.0])
    assert step.kind is StepKind.REBOOT and "time back" in step.reason
    assert wi.counters["wheel_reboots"] == 1
    # the reboot reading is the new baseline: the next step is relative to it
    nxt = wi.ingest(99_050_000, 2, [3.01, 3.01])
    assert nxt.kind is StepKind.STEP and nxt.d_left_m == pytest.approx(0.01)


def test_slightly_older_stamp_is_reordering_not_a_reboot() -> None:
    wi = _wi()
    wi.ingest(10_000_000, 2, [3.0, 3.0])
    wi.ingest(10_050_000, 2, [3.01, 3.01])
    assert wi.ingest(10_040_000, 2, [3.005, 3.005]).kind is StepKind.STALE
    assert wi.ingest(10_050_000, 2, [3.01, 3.01]).kind is StepKind.STALE  # duplicate
    assert wi.counters == {**wi.counters, "wheel_stale": 2, "wheel_reboots": 0}


def test_distances_restarting_near_zero_is_a_reboot_even_if_time_moves_on() -> None:
    wi = _wi()
    wi.ingest(1_000_000, 2, [12.0, 11.0])
    step = wi.ingest(1_500_000, 2, [0.001, 0.0])
    assert step.kind is StepKind.REBOOT and "restarted" in step.reason


def test_count_change_is_a_reboot() -> None:
    wi = _wi()
    wi.ingest(1_000_000, 2, [1.0, 1.0])
    step = wi.ingest(1_050_000, 3, [1.0, 1.0, 0.0])
    assert step.kind is StepKind.REBOOT and "count" in step.reason


def test_spike_beyond_twice_the_max_wheel_speed_is_rejected_and_baseline_kept() -> None:
    wi = _wi()
    wi.ingest(0, 2, [0.0, 0.0])
    limit = 2 * VMAX * 0.05 + 0.005  # 0.1097 m in 50 ms
    assert wi.ingest(50_000, 2, [limit * 0.99, 0.0]).kind is StepKind.STEP
    step = wi.ingest(100_000, 2, [limit * 0.99 + 0.5, 0.0])
    assert step.kind is StepKind.SPIKE and wi.counters["wheel_spikes"] == 1
    # the good reading after it spans both intervals from the kept baseline
    good = wi.ingest(150_000, 2, [limit * 0.99 + 0.04, 0.02])
    assert good.kind is StepKind.STEP
    assert good.dt_s == pytest.approx(0.1)
    assert good.d_left_m == pytest.approx(0.04) and good.d_right_m == pytest.approx(0.02)


def test_persistent_spikes_resync_without_integrating_the_jump() -> None:
    wi = _wi()
    wi.ingest(0, 2, [0.0, 0.0])
    kinds = [wi.ingest(50_000 * k, 2, [100.0 + 0.01 * k, 100.0]).kind for k in range(1, 6)]
    assert kinds == [StepKind.SPIKE] * 4 + [StepKind.RESYNC]
    nxt = wi.ingest(300_000, 2, [100.06, 100.0])
    assert nxt.kind is StepKind.STEP and nxt.d_left_m == pytest.approx(0.01)


def test_missing_index_is_bad_input() -> None:
    wi = _wi(left_index=0, right_index=3)
    assert wi.ingest(0, 2, [1.0, 1.0]).kind is StepKind.BAD
    assert wi.ingest(0, 4, [1.0, 1.0, 0.0, float("nan")]).kind is StepKind.BAD
    assert wi.counters["wheel_bad"] == 2


def test_gap_is_counted_and_still_integrated() -> None:
    wi = _wi()
    wi.ingest(0, 2, [0.0, 0.0])
    step = wi.ingest(2_000_000, 2, [1.0, 1.0])  # 2 s without data, 0.5 m/s: plausible, integrated
    assert step.kind is StepKind.STEP and step.d_left_m == pytest.approx(1.0)
    assert wi.counters["wheel_gaps"] == 1
