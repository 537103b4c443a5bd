"""Twist limiter: hand-computed steps, the ros_controllers #561 regression, then properties."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.kinematics import Twist2D
from rover_bridge.limits import TwistLimiter, TwistLimits
from rover_bridge.params import LimitsParams

PROPS = settings(derandomize=True, database=None, deadline=None, max_examples=150)

PLAIN = TwistLimits(max_v_m_s=0.8, max_omega_rad_s=3.0, accel_m_s2=1.0, decel_m_s2=2.0, alpha_rad_s2=6.0)
JERKY = TwistLimits(max_v_m_s=0.8, max_omega_rad_s=3.0, accel_m_s2=1.0, decel_m_s2=2.0, alpha_rad_s2=6.0,
                    jerk_v_m_s3=10.0, jerk_omega_rad_s3=60.0)


def run(lim: TwistLimiter, target: Twist2D, dt_s: float, n: int) -> list[Twist2D]:
    return [lim.step(target, dt_s) for _ in range(n)]


# --- hand-computed -------------------------------------------------------------------------------

def test_accelerates_at_accel_and_lands_exactly() -> None:
    lim = TwistLimiter(PLAIN)
    out = run(lim, Twist2D(0.5, 0.0), 0.1, 6)
    # 1 m/s^2 for 0.1 s per step: 0.1, 0.2, ... and exactly 0.5, then it stays.
    assert [o.v_m_s for o in out[:4]] == pytest.approx([0.1, 0.2, 0.3, 0.4])
    assert out[4].v_m_s == 0.5 and out[5].v_m_s == 0.5


def test_decelerates_at_decel_to_exactly_zero() -> None:
    lim = TwistLimiter(PLAIN, initial=Twist2D(0.8, 0.0))
    out = run(lim, Twist2D(), 0.1, 5)
    # 2 m/s^2 braking: 0.6, 0.4, 0.2, 0.0, 0.0.
    assert [o.v_m_s for o in out[:3]] == pytest.approx([0.6, 0.4, 0.2])
    assert out[3].v_m_s == 0.0 and out[4].v_m_s == 0.0


def test_velocity_is_clamped() -> None:
    lim = TwistLimiter(PLAIN)
    out = run(lim, Twist2D(5.0, -50.0), 0.1, 20)
    assert all(abs(o.v_m_s) <= 0.8 and abs(o.omega_rad_s) <= 3.0 for o in out)
    assert out[-1] == Twist2D(0.8, -3.0)


def test_sign_change_decelerates_then_accelerates_within_one_step() -> None:
    # From +0.1 toward -0.5: 0.05 s braking at 2 m/s^2 reaches 0, then 0.05 s at 1 m/s^2: -0.05.
    lim = TwistLimiter(PLAIN, initial=Twist2D(0.1, 0.0))
    assert lim.step(Twist2D(-0.5, 0.0), 0.1).v_m_s == pytest.approx(-0.05, abs=1e-12)
    # Then growing the other way at accel: -0.15.
    assert lim.step(Twist2D(-0.5, 0.0), 0.1).v_m_s == pytest.approx(-0.15, abs=1e-12)


def test_slowing_to_a_smaller_same_sign_target_uses_decel() -> None:
    lim = TwistLimiter(PLAIN, initial=Twist2D(0.8, 0.0))
    assert lim.step(Twist2D(0.5, 0.0), 0.1).v_m_s == pytest.approx(0.6)
    assert lim.step(Twist2D(0.5, 0.0), 0.1).v_m_s == 0.5


def test_axes_are_independent() -> None:
    lim = TwistLimiter(PLAIN)
    out = lim.step(Twist2D(0.5, 3.0), 0.1)
    # v at 1 m/s^2, omega at 6 rad/s^2, each on its own.
    assert out.v_m_s == pytest.approx(0.1)
    assert out.omega_rad_s == pytest.approx(0.6)
    only_w = TwistLimiter(PLAIN).step(Twist2D(0.0, 3.0), 0.1)
    assert only_w == Twist2D(0.0, pytest.approx(0.6))  # type: ignore[arg-type]


def test_jerk_limited_start_hand_computed() -> None:
    # Jerk 10 m/s^3, dt 0.01 s: the rate grows 0.1 m/s^2 per step and v integrates its average.
    lim = TwistLimiter(JERKY)
    v1 = lim.step(Twist2D(0.8, 0.0), 0.01).v_m_s
    v2 = lim.step(Twist2D(0.8, 0.0), 0.01).v_m_s
    assert v1 == pytest.approx(0.5 * 0.1 * 0.01)  # 0.0005
    assert v2 == pytest.approx(0.0005 + 0.5 * (0.1 + 0.2) * 0.01)  # 0.002
    # Accel limit reached after 0.1 s (1 m/s^2 / 10 m/s^3), then v grows at most 1 m/s^2.
    prev = v2
    for _ in range(30):
        v = lim.step(Twist2D(0.8, 0.0), 0.01).v_m_s
        assert v - prev <= 1.0 * 0.01 + 1e-12
        prev = v


def test_jerk_limited_stop_never_goes_through_zero_ros_controllers_561() -> None:
    # Full speed, then a stop: v must come to exactly 0 and never be negative on the way.
    lim = TwistLimiter(JERKY, initial=Twist2D(0.8, 3.0))
    out = run(lim, Twist2D(), 0.01, 300)
    assert all(o.v_m_s >= 0.0 and o.omega_rad_s >= 0.0 for o in out)
    assert out[-1] == Twist2D(0.0, 0.0)
    # And while still accelerating hard in reverse, a stop does not swing through zero either.
    lim = TwistLimiter(JERKY)
    run(lim, Twist2D(-0.8, -3.0), 0.01, 25)  # rate now large and negative
    assert lim.current.v_m_s < 0.0
    out = run(lim, Twist2D(), 0.01, 300)
    assert all(o.v_m_s <= 0.0 and o.omega_rad_s <= 0.0 for o in out)
    assert out[-1] == Twist2D(0.0, 0.0)


def test_jerk_limited_target_equal_to_current_does_not_drift() -> None:
    # Still accelerating when the target is moved to the current value: the value stays put.
    lim = TwistLimiter(JERKY)
    run(lim, Twist2D(0.8, 0.0), 0.01, 20)
    here = lim.current
    assert run(lim, here, 0.01, 10)[-1] == here


@pytest.mark.parametrize("dt", [0.0, -0.01, math.nan, math.inf])
def test_bad_dt_raises_and_changes_nothing(dt: float) -> None:
    lim, twin = TwistLimiter(JERKY), TwistLimiter(JERKY)
    for limiter in (lim, twin):
        run(limiter, Twist2D(0.6, 2.0), 0.01, 7)  # mid-ramp: a non-zero acceleration state
    before = lim.current
    with pytest.raises(ValueError, match="dt_s must be a finite number > 0"):
        lim.step(Twist2D(0.6, 2.0), dt)
    assert lim.current == before
    # The hidden acceleration state is unchanged too: both continue identically.
    assert run(lim, Twist2D(0.6, 2.0), 0.01, 5) == run(twin, Twist2D(0.6, 2.0), 0.01, 5)


@pytest.mark.parametrize("target", [Twist2D(math.nan, 0.0), Twist2D(0.0, math.inf), Twist2D(-math.inf, 0.0)])
def test_non_finite_target_raises_and_changes_nothing(target: Twist2D) -> None:
    lim = TwistLimiter(PLAIN, initial=Twist2D(0.3, 1.0))
    with pytest.raises(ValueError, match="target must be finite"):
        lim.step(target, 0.02)
    assert lim.current == Twist2D(0.3, 1.0)


def test_reset_zeroes_the_acceleration_state() -> None:
    lim = TwistLimiter(JERKY)
    run(lim, Twist2D(0.8, 3.0), 0.01, 15)
    lim.reset(Twist2D(0.3, 1.0))
    fresh = TwistLimiter(JERKY, initial=Twist2D(0.3, 1.0))
    assert lim.current == Twist2D(0.3, 1.0)
    assert run(lim, Twist2D(0.8, 3.0), 0.01, 10) == run(fresh, Twist2D(0.8, 3.0), 0.01, 10)
    lim.reset()
    assert lim.current == Twist2D()


def test_time_to_stop_hand_computed() -> None:
    # No jerk: v 0.8 at 2 m/s^2 = 0.4 s; omega 3 at 6 rad/s^2 = 0.5 s; the twist stops when both have.
    assert TwistLimiter(PLAIN, initial=Twist2D(0.8, 3.0)).time_to_stop_s() == pytest.approx(0.5)
    assert TwistLimiter(PLAIN, initial=Twist2D(-0.8, 0.0)).time_to_stop_s() == pytest.approx(0.4)
    assert TwistLimiter(PLAIN).time_to_stop_s() == 0.0
    # Jerk 10, decel 2, from 0.8 m/s with zero rate: decel^2 / jerk = 0.4 <= 0.8, so the rate
    # profile is a trapezoid: 0.8 / 2 + 2 / 10 = 0.6 s.
    only_v = TwistLimits(max_v_m_s=1.0, max_omega_rad_s=1.0, accel_m_s2=1.0, decel_m_s2=2.0, alpha_rad_s2=1.0,
                         jerk_v_m_s3=10.0)
    assert TwistLimiter(only_v, initial=Twist2D(0.8, 0.0)).time_to_stop_s() == pytest.approx(0.6)
    # From 0.1 m/s (< 0.4) it is a triangle: 2 sqrt(0.1 / 10) = 0.2 s.
    assert TwistLimiter(only_v, initial=Twist2D(0.1, 0.0)).time_to_stop_s() == pytest.approx(0.2)


def test_from_params_maps_every_field() -> None:
    p = LimitsParams(max_linear_m_s=1.1, max_angular_rad_s=2.2, max_linear_accel_m_s2=3.3,
                     max_linear_decel_m_s2=4.4, max_angular_accel_rad_s2=5.5, max_linear_jerk_m_s3=6.6,
                     max_angular_jerk_rad_s3=None)
    assert TwistLimits.from_params(p) == TwistLimits(1.1, 2.2, 3.3, 4.4, 5.5, 6.6, None)


@pytest.mark.parametrize("field", ["max_v_m_s", "accel_m_s2", "decel_m_s2", "alpha_rad_s2", "jerk_v_m_s3"])
@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_bad_limits_raise(field: str, bad: float) -> None:
    kwargs: dict[str, float | None] = {"max_v_m_s": 1.0, "max_omega_rad_s": 1.0, "accel_m_s2": 1.0,
                                       "decel_m_s2": 1.0, "alpha_rad_s2": 1.0}
    kwargs[field] = bad
    with pytest.raises(ValueError, match=rf"{field} must be a finite number > 0"):
        TwistLimits(**kwargs)  # type: ignore[arg-type]


# --- properties ----------------------------------------------------------------------------------

@st.composite
def limiters(draw: st.DrawFn) -> tuple[TwistLimiter, float]:
    """A limiter with random limits (sometimes jerk-limited), driven through a random history."""
    jerk = draw(st.one_of(st.none(), st.floats(min_value=2.0, max_value=200.0)))
    limits = TwistLimits(
        max_v_m_s=draw(st.floats(min_value=0.1, max_value=3.0)),
        max_omega_rad_s=draw(st.floats(min_value=0.2, max_value=5.0)),
        accel_m_s2=draw(st.floats(min_value=0.5, max_value=10.0)),
        decel_m_s2=draw(st.floats(min_value=0.5, max_value=10.0)),
        alpha_rad_s2=draw(st.floats(min_value=1.0, max_value=20.0)),
        jerk_v_m_s3=jerk, jerk_omega_rad_s3=None if jerk is None else 4.0 * jerk)
    dt = draw(st.sampled_from([0.005, 0.01, 0.02, 0.05, 0.1]))
    lim = TwistLimiter(limits)
    history = draw(st.lists(st.tuples(st.floats(-4.0, 4.0), st.floats(-6.0, 6.0)), max_size=25))
    for v, w in history:
        lim.step(Twist2D(v, w), dt)
    return lim, dt


def axes(t: Twist2D) -> tuple[float, float]:
    return t.v_m_s, t.omega_rad_s


@PROPS
@given(case=limiters(), target=st.tuples(st.floats(-4.0, 4.0), st.floats(-6.0, 6.0)))
def test_never_overshoots_and_reaches_the_target_exactly(case: tuple[TwistLimiter, float],
                                                         target: tuple[float, float]) -> None:
    lim, dt = case
    lims = lim.limits
    goal = (max(-lims.max_v_m_s, min(lims.max_v_m_s, target[0])),
            max(-lims.max_omega_rad_s, min(lims.max_omega_rad_s, target[1])))
    start = axes(lim.current)
    for _ in range(5000):
        prev = axes(lim.current)
        now = axes(lim.step(Twist2D(*target), dt))
        for i in range(2):
            # Never on the far side of the target from where this run started.
            assert (goal[i] - now[i]) * (goal[i] - start[i]) >= 0.0
            if lims.jerk_v_m_s3 is None:
                # Without jerk it also moves monotonically toward the target.
                assert (now[i] - prev[i]) * (goal[i] - prev[i]) >= 0.0
        assert abs(now[0]) <= lims.max_v_m_s and abs(now[1]) <= lims.max_omega_rad_s
        if now == goal:
            break
    assert axes(lim.current) == goal  # exactly, not approximately
    assert axes(lim.step(Twist2D(*target), dt)) == goal  # and it stays: no chattering


@PROPS
@given(case=limiters())
def test_never_reverses_from_a_zero_target(case: tuple[TwistLimiter, float]) -> None:
    lim, dt = case
    start = axes(lim.current)
    bound_s = lim.time_to_stop_s()
    elapsed = 0.0
    while axes(lim.current) != (0.0, 0.0):
        now = axes(lim.step(Twist2D(), dt))
        elapsed += dt
        assert now[0] * start[0] >= 0.0 and now[1] * start[1] >= 0.0
        assert elapsed < 100.0
    # time_to_stop_s is a continuous-time bound: the discrete run ends in the step that crosses it
    # (no jerk) or, jerk-limited, a few steps later: the braking curve is sampled, and when jerk * dt
    # exceeds the rate limits (10 Hz with a stiff jerk) it lands by creeping. Measured over 60,000
    # random limiters and histories each: at most 1.0, 1.7, 2.9 and 5.2 steps at dt 0.005, 0.02, 0.05, 0.1.
    slack = dt if lim.limits.jerk_v_m_s3 is None else 6.0 * dt
    assert elapsed < bound_s + slack + 1e-9


@PROPS
@given(case=limiters(), targets=st.lists(st.tuples(st.floats(-4.0, 4.0), st.floats(-6.0, 6.0)),
                                         min_size=1, max_size=40))
def test_rate_limits_hold_without_jerk(case: tuple[TwistLimiter, float],
                                       targets: list[tuple[float, float]]) -> None:
    lim, dt = case
    lims = lim.limits
    if lims.jerk_v_m_s3 is not None:
        lim = TwistLimiter(TwistLimits(lims.max_v_m_s, lims.max_omega_rad_s, lims.accel_m_s2,
                                       lims.decel_m_s2, lims.alpha_rad_s2), initial=lim.current)
    eps = 1e-9
    for target in targets:
        prev = lim.current
        now = lim.step(Twist2D(*target), dt)
        dv = abs(now.v_m_s - prev.v_m_s)
        assert abs(now.omega_rad_s - prev.omega_rad_s) <= lims.alpha_rad_s2 * dt + eps
        assert dv <= max(lims.accel_m_s2, lims.decel_m_s2) * dt + eps
        if prev.v_m_s * now.v_m_s >= 0.0:  # no zero crossing within the step
            if abs(now.v_m_s) > abs(prev.v_m_s):
                assert dv <= lims.accel_m_s2 * dt + eps
            else:
                assert dv <= lims.decel_m_s2 * dt + eps
        else:
            # Crossing: braking to zero takes |prev| / decel, the rest of the step grows at accel.
            brake_s = abs(prev.v_m_s) / lims.decel_m_s2
            assert brake_s <= dt + eps
            assert abs(now.v_m_s) <= lims.accel_m_s2 * (dt - brake_s) + eps


@PROPS
@given(case=limiters(), targets=st.lists(st.tuples(st.floats(-4.0, 4.0), st.floats(-6.0, 6.0)),
                                         min_size=1, max_size=40))
def test_jerk_limit_holds_away_from_the_target(case: tuple[TwistLimiter, float],
                                               targets: list[tuple[float, float]]) -> None:
    # Acceleration (estimated from the trapezoid) changes at most jerk * dt between steps, except
    # where the limiter lands on the target or the velocity limit and drops the rate to zero.
    lim, dt = case
    jerk = lim.limits.jerk_v_m_s3
    if jerk is None:
        return
    lims = lim.limits
    lim.reset(lim.current)
    prev_a = 0.0
    for target in targets:
        goal = max(-lims.max_v_m_s, min(lims.max_v_m_s, target[0]))
        for _ in range(3):
            before = lim.current.v_m_s
            now = lim.step(Twist2D(target[0], 0.0), dt).v_m_s
            if now == goal or abs(now) == lims.max_v_m_s:
                prev_a = 0.0
                continue
            # v_new = v + (a_prev + a_new) / 2 * dt  ->  a_new = 2 (dv / dt) - a_prev
            a_new = 2.0 * (now - before) / dt - prev_a
            assert abs(a_new - prev_a) <= jerk * dt + 1e-6
            assert abs(a_new) <= max(lims.accel_m_s2, lims.decel_m_s2) + 1e-6
            prev_a = a_new
