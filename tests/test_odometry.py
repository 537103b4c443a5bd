"""Wheel odometry: hand-computed poses, then properties (Hypothesis, derandomized)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.odometry import Pose2D, WheelOdometry, arc_factors, arc_step, wrap_angle

PROPS = settings(derandomize=True, database=None, deadline=None, max_examples=200)


def drive(odo: WheelOdometry, *readings: tuple[float, float]) -> Pose2D:
    pose = odo.pose
    for left, right in readings:
        pose = odo.update(left_m=left, right_m=right)
    return pose


def assert_pose(pose: Pose2D, x: float, y: float, yaw: float, tol: float = 1e-12) -> None:
    assert pose.x_m == pytest.approx(x, abs=tol)
    assert pose.y_m == pytest.approx(y, abs=tol)
    assert pose.yaw_rad == pytest.approx(yaw, abs=tol)


# --- hand-computed -------------------------------------------------------------------------------

def test_first_reading_is_only_the_baseline() -> None:
    odo = WheelOdometry(track_width_m=0.3)
    assert odo.update(left_m=5.0, right_m=7.0) == Pose2D(0.0, 0.0, 0.0)
    assert odo.update(left_m=5.0, right_m=7.0) == Pose2D(0.0, 0.0, 0.0)  # no motion, no change


def test_straight_line() -> None:
    pose = drive(WheelOdometry(track_width_m=0.3), (0.0, 0.0), (1.0, 1.0))
    assert_pose(pose, 1.0, 0.0, 0.0)


def test_spin_in_place_quarter_turn() -> None:
    # Each wheel rolls a quarter of the circle of radius L/2 = 0.15 m: 0.15 * pi/2, opposite ways.
    d = 0.15 * math.pi / 2.0
    pose = drive(WheelOdometry(track_width_m=0.3), (0.0, 0.0), (-d, d))
    assert_pose(pose, 0.0, 0.0, math.pi / 2.0)


def test_known_arc() -> None:
    # Track 1 m, left 1 m, right 2 m: path length 1.5 m, heading change 1 rad, radius 1.5 m
    # about a centre on the left: x = 1.5 sin 1, y = 1.5 (1 - cos 1).
    pose = drive(WheelOdometry(track_width_m=1.0), (0.0, 0.0), (1.0, 2.0))
    assert_pose(pose, 1.5 * math.sin(1.0), 1.5 * (1.0 - math.cos(1.0)), 1.0)


def test_known_arc_in_small_steps_is_the_same_arc() -> None:
    # Exact integration: splitting a constant-curvature move changes nothing.
    odo = WheelOdometry(track_width_m=1.0)
    pose = drive(odo, *[(i / 10.0, 2.0 * i / 10.0) for i in range(11)])
    assert_pose(pose, 1.5 * math.sin(1.0), 1.5 * (1.0 - math.cos(1.0)), 1.0)


def test_reverse_straight() -> None:
    pose = drive(WheelOdometry(track_width_m=0.3), (10.0, 10.0), (9.0, 9.0))
    assert_pose(pose, -1.0, 0.0, 0.0)


def test_reverse_arc() -> None:
    # Backing up with the right wheel rolling back further: rotation by -1 rad about the same
    # centre (0, 1.5) on the left. Start point relative to centre (0, -1.5) rotated by -1:
    # (-1.5 sin 1, -1.5 cos 1); plus the centre: (-1.5 sin 1, 1.5 (1 - cos 1)).
    pose = drive(WheelOdometry(track_width_m=1.0), (0.0, 0.0), (-1.0, -2.0))
    assert_pose(pose, -1.5 * math.sin(1.0), 1.5 * (1.0 - math.cos(1.0)), -1.0)


def test_yaw_is_wrapped() -> None:
    # Three quarter turns CCW: yaw 3pi/2 wraps to -pi/2.
    d = 0.15 * math.pi / 2.0
    pose = drive(WheelOdometry(track_width_m=0.3), (0.0, 0.0), (-d, d), (-2 * d, 2 * d), (-3 * d, 3 * d))
    assert_pose(pose, 0.0, 0.0, -math.pi / 2.0, tol=1e-9)


def test_nearly_straight_has_no_blow_up() -> None:
    # Heading change 1e-9 rad over ~1 m: y = ds * (1 - cos d) / d ~= ds * d / 2.
    ds = 1.0 + 0.5e-9
    pose = drive(WheelOdometry(track_width_m=1.0), (0.0, 0.0), (1.0, 1.0 + 1e-9))
    assert pose.x_m == pytest.approx(ds, abs=1e-15)
    assert pose.y_m == pytest.approx(ds * 1e-9 / 2.0, rel=1e-9)
    assert pose.yaw_rad == pytest.approx(1e-9, rel=1e-6)


def test_arc_factors_are_continuous_at_the_series_switch() -> None:
    # Both branches (series below the threshold, closed form above) agree at the seam.
    for d in (1e-4, -1e-4):
        below, above = arc_factors(d * (1 - 1e-9)), arc_factors(d * (1 + 1e-9))
        assert below[0] == pytest.approx(above[0], rel=1e-12)
        assert below[1] == pytest.approx(above[1], rel=1e-8)
    assert arc_factors(0.0) == (1.0, 0.0)
    assert arc_factors(math.pi) == pytest.approx((0.0, 2.0 / math.pi), abs=1e-15)


def test_arc_step_from_a_rotated_pose() -> None:
    # Facing +y (yaw pi/2), a straight metre moves +y.
    pose = arc_step(Pose2D(1.0, 2.0, math.pi / 2.0), ds_m=1.0, dyaw_rad=0.0)
    assert_pose(pose, 1.0, 3.0, math.pi / 2.0)


def test_reset_rebases() -> None:
    odo = WheelOdometry(track_width_m=0.3)
    drive(odo, (0.0, 0.0), (3.0, 3.0))
    odo.reset(Pose2D(1.0, 2.0, math.pi / 2.0))
    assert odo.update(left_m=100.0, right_m=100.0) == Pose2D(1.0, 2.0, math.pi / 2.0)  # new baseline
    assert_pose(odo.update(left_m=101.0, right_m=101.0), 1.0, 3.0, math.pi / 2.0)
    odo.reset()
    assert odo.pose == Pose2D()


def test_wrap_angle() -> None:
    assert wrap_angle(3.0 * math.pi / 2.0) == pytest.approx(-math.pi / 2.0)
    assert wrap_angle(-3.0 * math.pi / 2.0) == pytest.approx(math.pi / 2.0)
    assert wrap_angle(0.25) == 0.25
    assert wrap_angle(4.0 * math.pi + 0.25) == pytest.approx(0.25)


@pytest.mark.parametrize("track", [0.0, -0.3, math.nan, math.inf])
def test_bad_track_raises(track: float) -> None:
    with pytest.raises(ValueError, match="track_width_m must be a finite number > 0"):
        WheelOdometry(track_width_m=track)


def test_non_finite_reading_raises_and_keeps_state() -> None:
    odo = WheelOdometry(track_width_m=0.3)
    drive(odo, (0.0, 0.0), (1.0, 1.0))
    with pytest.raises(ValueError, match="finite"):
        odo.update(left_m=math.nan, right_m=1.0)
    assert_pose(odo.update(left_m=2.0, right_m=2.0), 2.0, 0.0, 0.0)  # baseline still (1, 1)


# --- properties ----------------------------------------------------------------------------------

step = st.tuples(st.floats(min_value=-0.5, max_value=0.5), st.floats(min_value=-0.5, max_value=0.5))


@PROPS
@given(track=st.floats(min_value=0.1, max_value=2.0), steps=st.lists(step, min_size=1, max_size=40))
def test_mirrored_wheels_mirror_the_pose(track: float, steps: list[tuple[float, float]]) -> None:
    a, b = WheelOdometry(track), WheelOdometry(track)
    a.update(0.0, 0.0)
    b.update(0.0, 0.0)
    left = right = 0.0
    for dl, dr in steps:
        left, right = left + dl, right + dr
        pa, pb = a.update(left, right), b.update(right, left)
        assert pb.x_m == pytest.approx(pa.x_m, abs=1e-9)
        assert pb.y_m == pytest.approx(-pa.y_m, abs=1e-9)
        assert wrap_angle(pb.yaw_rad + pa.yaw_rad) == pytest.approx(0.0, abs=1e-9)


@PROPS
@given(track=st.floats(min_value=0.1, max_value=2.0), radius=st.floats(min_value=0.0, max_value=5.0),
       ccw=st.booleans(), backwards=st.booleans(),
       cuts=st.lists(st.floats(min_value=0.01, max_value=1.0), min_size=1, max_size=50))
def test_full_circle_returns_to_start(track: float, radius: float, ccw: bool, backwards: bool,
                                      cuts: list[float]) -> None:
    # One lap of a circle of `radius` (0 = spin in place), cut into uneven pieces.
    inner, outer = 2.0 * math.pi * (radius - track / 2.0), 2.0 * math.pi * (radius + track / 2.0)
    total_left, total_right = (inner, outer) if ccw else (outer, inner)
    sign = -1.0 if backwards else 1.0
    odo = WheelOdometry(track)
    odo.update(0.0, 0.0)
    done = 0.0
    total = sum(cuts)
    pose = odo.pose
    for cut in cuts:
        done += cut
        frac = min(done / total, 1.0)
        pose = odo.update(sign * frac * total_left, sign * frac * total_right)
    assert pose.x_m == pytest.approx(0.0, abs=1e-9)
    assert pose.y_m == pytest.approx(0.0, abs=1e-9)
    assert wrap_angle(pose.yaw_rad) == pytest.approx(0.0, abs=1e-9)


@PROPS
@given(x=st.floats(min_value=-1e6, max_value=1e6))
def test_wrap_angle_range_and_equivalence(x: float) -> None:
    w = wrap_angle(x)
    assert -math.pi <= w <= math.pi
    assert math.sin(w) == pytest.approx(math.sin(x), abs=1e-6)
    assert math.cos(w) == pytest.approx(math.cos(x), abs=1e-6)
