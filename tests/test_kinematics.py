"""Diff-drive kinematics: hand-computed cases, then properties (Hypothesis, derandomized)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.kinematics import (
    DiffDrive,
    Twist2D,
    WheelSpeeds,
    m_s_to_rad_s,
    m_to_ticks,
    rad_s_to_m_s,
    rad_s_to_rpm,
    rpm_to_rad_s,
    ticks_to_m,
)
from rover_bridge.params import RobotParams

# Deterministic in CI: same examples every run, no example database on disk.
PROPS = settings(derandomize=True, database=None, deadline=None, max_examples=300)

DD = DiffDrive(wheel_radius_m=0.05, track_width_m=0.30)


# --- hand-computed -------------------------------------------------------------------------------

def test_zero_twist_gives_stopped_wheels() -> None:
    assert DD.to_wheel_speeds(Twist2D()) == WheelSpeeds(0.0, 0.0)
    assert DD.to_twist(WheelSpeeds()) == Twist2D(0.0, 0.0)


def test_straight_line() -> None:
    # 0.5 m/s on 0.05 m wheels: 10 rad/s each.
    ws = DD.to_wheel_speeds(Twist2D(v_m_s=0.5, omega_rad_s=0.0))
    assert ws.left_rad_s == pytest.approx(10.0, abs=1e-12)
    assert ws.right_rad_s == pytest.approx(10.0, abs=1e-12)


def test_spin_in_place_ccw_drives_right_wheel_forward() -> None:
    # omega = 1 rad/s CCW: each wheel moves 0.15 m/s, left back, right forward: 3 rad/s.
    ws = DD.to_wheel_speeds(Twist2D(v_m_s=0.0, omega_rad_s=1.0))
    assert ws.left_rad_s == pytest.approx(-3.0, abs=1e-12)
    assert ws.right_rad_s == pytest.approx(3.0, abs=1e-12)


def test_arc_and_back() -> None:
    # v = 0.5, omega = 1: left (0.5 - 0.15) / 0.05 = 7, right (0.5 + 0.15) / 0.05 = 13.
    ws = DD.to_wheel_speeds(Twist2D(v_m_s=0.5, omega_rad_s=1.0))
    assert ws.left_rad_s == pytest.approx(7.0)
    assert ws.right_rad_s == pytest.approx(13.0)
    tw = DD.to_twist(WheelSpeeds(left_rad_s=7.0, right_rad_s=13.0))
    assert tw.v_m_s == pytest.approx(0.5, abs=1e-12)
    assert tw.omega_rad_s == pytest.approx(1.0, abs=1e-12)


def test_reverse_right_turn() -> None:
    # v = -0.3, omega = -2: left (-0.3 + 0.3) / 0.05 = 0, right (-0.3 - 0.3) / 0.05 = -12.
    ws = DD.to_wheel_speeds(Twist2D(v_m_s=-0.3, omega_rad_s=-2.0))
    assert ws.left_rad_s == pytest.approx(0.0, abs=1e-12)
    assert ws.right_rad_s == pytest.approx(-12.0, abs=1e-12)


def test_unequal_radii() -> None:
    dd = DiffDrive(wheel_radius_m=0.05, track_width_m=0.4,
                   left_wheel_radius_m=0.04, right_wheel_radius_m=0.06)
    assert (dd.left_radius_m, dd.right_radius_m) == (0.04, 0.06)
    # Straight at 0.6 m/s: the smaller left wheel turns faster, 15 vs 10 rad/s.
    ws = dd.to_wheel_speeds(Twist2D(v_m_s=0.6, omega_rad_s=0.0))
    assert ws.left_rad_s == pytest.approx(15.0)
    assert ws.right_rad_s == pytest.approx(10.0)
    # Both wheels at 10 rad/s: left 0.4 m/s, right 0.6 m/s -> v 0.5, omega 0.2 / 0.4 = 0.5.
    tw = dd.to_twist(WheelSpeeds(10.0, 10.0))
    assert tw.v_m_s == pytest.approx(0.5)
    assert tw.omega_rad_s == pytest.approx(0.5)


def test_from_params_takes_per_wheel_radii() -> None:
    robot = RobotParams(wheel_radius_m=0.05, track_width_m=0.3, left_wheel_radius_m=0.051)
    dd = DiffDrive.from_params(robot)
    assert dd.left_radius_m == 0.051
    assert dd.right_radius_m == 0.05
    assert dd.track_width_m == 0.3


def test_desaturate_hand_computed() -> None:
    # Largest is 40 > 20: common factor 0.5.
    out = WheelSpeeds(left_rad_s=10.0, right_rad_s=-40.0).desaturate(20.0)
    assert out.left_rad_s == pytest.approx(5.0)
    assert out.right_rad_s == pytest.approx(-20.0)
    inside = WheelSpeeds(left_rad_s=-19.0, right_rad_s=20.0)
    assert inside.desaturate(20.0) == inside


def test_value_types_are_frozen() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        Twist2D().v_m_s = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        WheelSpeeds().left_rad_s = 1.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        DD.track_width_m = 1.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"wheel_radius_m": 0.0, "track_width_m": 0.3}, "wheel_radius_m"),
        ({"wheel_radius_m": -0.05, "track_width_m": 0.3}, "wheel_radius_m"),
        ({"wheel_radius_m": 0.05, "track_width_m": math.nan}, "track_width_m"),
        ({"wheel_radius_m": 0.05, "track_width_m": math.inf}, "track_width_m"),
        ({"wheel_radius_m": 0.05, "track_width_m": 0.3, "left_wheel_radius_m": 0.0}, "left_wheel_radius_m"),
        ({"wheel_radius_m": 0.05, "track_width_m": 0.3, "right_wheel_radius_m": -1.0},
         "right_wheel_radius_m"),
        ({"wheel_radius_m": True, "track_width_m": 0.3}, "wheel_radius_m"),
    ],
)
def test_bad_geometry_raises_with_the_parameter_name(kwargs: dict[str, float], name: str) -> None:
    with pytest.raises(ValueError, match=rf"{name} must be a finite number > 0"):
        DiffDrive(**kwargs)


@pytest.mark.parametrize("limit", [0.0, -1.0, math.nan, math.inf])
def test_desaturate_rejects_bad_limit(limit: float) -> None:
    with pytest.raises(ValueError, match="max_rad_s"):
        WheelSpeeds(1.0, 1.0).desaturate(limit)


def test_unit_helpers() -> None:
    assert rpm_to_rad_s(60.0) == pytest.approx(2.0 * math.pi)
    assert rad_s_to_rpm(math.pi) == pytest.approx(30.0)
    assert rad_s_to_m_s(10.0, 0.05) == pytest.approx(0.5)
    assert m_s_to_rad_s(0.5, 0.05) == pytest.approx(10.0)
    # One revolution of a 0.05 m wheel with a 3200-count encoder.
    assert ticks_to_m(3200, 3200, 0.05) == pytest.approx(2.0 * math.pi * 0.05)
    assert ticks_to_m(-1600, 3200, 0.05) == pytest.approx(-math.pi * 0.05)
    assert m_to_ticks(2.0 * math.pi * 0.05, 3200, 0.05) == pytest.approx(3200.0)
    bad_calls: list[Callable[[], float]] = [lambda: ticks_to_m(1, 0, 0.05), lambda: ticks_to_m(1, 3200, 0.0),
                lambda: m_to_ticks(1, 3200, -0.05), lambda: m_to_ticks(1, math.nan, 0.05),
                lambda: m_s_to_rad_s(1.0, 0.0)]
    for bad in bad_calls:
        with pytest.raises(ValueError):
            bad()


# --- properties ----------------------------------------------------------------------------------

speeds = st.floats(min_value=-20.0, max_value=20.0, allow_nan=False)
rates = st.floats(min_value=-30.0, max_value=30.0, allow_nan=False)
radii = st.floats(min_value=0.01, max_value=1.0)
tracks = st.floats(min_value=0.05, max_value=5.0)
wheel = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)


@PROPS
@given(v=speeds, w=rates, r=radii, track=tracks)
def test_ik_then_fk_returns_the_twist(v: float, w: float, r: float, track: float) -> None:
    dd = DiffDrive(wheel_radius_m=r, track_width_m=track)
    tw = dd.to_twist(dd.to_wheel_speeds(Twist2D(v, w)))
    assert tw.v_m_s == pytest.approx(v, rel=1e-9, abs=1e-9)
    assert tw.omega_rad_s == pytest.approx(w, rel=1e-9, abs=1e-9)


@PROPS
@given(v=speeds, w=rates, r=radii, rl=radii, rr=radii, track=tracks)
def test_ik_then_fk_with_unequal_radii(v: float, w: float, r: float, rl: float, rr: float,
                                       track: float) -> None:
    dd = DiffDrive(wheel_radius_m=r, track_width_m=track, left_wheel_radius_m=rl, right_wheel_radius_m=rr)
    tw = dd.to_twist(dd.to_wheel_speeds(Twist2D(v, w)))
    assert tw.v_m_s == pytest.approx(v, rel=1e-9, abs=1e-9)
    assert tw.omega_rad_s == pytest.approx(w, rel=1e-9, abs=1e-9)


@PROPS
@given(left=wheel, right=wheel, limit=st.floats(min_value=0.1, max_value=500.0))
def test_desaturate_keeps_ratio_sign_and_bound(left: float, right: float, limit: float) -> None:
    ws = WheelSpeeds(left, right)
    out = ws.desaturate(limit)
    # Bound.
    assert abs(out.left_rad_s) <= limit and abs(out.right_rad_s) <= limit
    # Never increases a speed.
    assert abs(out.left_rad_s) <= abs(left) and abs(out.right_rad_s) <= abs(right)
    # Sign (turn direction) survives, down to the sign bit of a zero.
    for before, after in ((left, out.left_rad_s), (right, out.right_rad_s)):
        assert math.copysign(1.0, after) == math.copysign(1.0, before)
        assert (after == 0.0) <= (abs(before) < 1e-300 or before == 0.0)
    # Ratio (curvature) survives: left/right cross-multiplied.
    assert out.left_rad_s * right == pytest.approx(out.right_rad_s * left, rel=1e-9, abs=1e-9)
    largest = max(abs(left), abs(right))
    if largest <= limit:
        assert out == ws  # untouched
    else:
        assert max(abs(out.left_rad_s), abs(out.right_rad_s)) == pytest.approx(limit, rel=1e-12)


@PROPS
@given(v=speeds, w=rates, limit=st.floats(min_value=0.5, max_value=50.0))
def test_desaturated_twist_keeps_curvature(v: float, w: float, limit: float) -> None:
    # What the robot gets after a clamp drives the same path, only slower.
    tw = DD.to_twist(DD.to_wheel_speeds(Twist2D(v, w)).desaturate(limit))
    assert tw.v_m_s * w == pytest.approx(tw.omega_rad_s * v, rel=1e-9, abs=1e-9)
    assert abs(tw.v_m_s) <= abs(v) + 1e-12 and abs(tw.omega_rad_s) <= abs(w) + 1e-12
