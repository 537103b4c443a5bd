"""Properties of the filter's math (Hypothesis): the models against independent forms of the same physics,
the Jacobians against finite differences, the consistency window's
verdicts and the trapezoid corrections against exact integrals."""

# Kalman-filter notation (P, H, R) reads better than pep8 names here.

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.estimate.consistency import AGREE_SIGMA, MIN_SPAN_S, ConsistencyWindow
from rover_bridge.estimate.models import (
    IB,
    IKR,
    IKT,
    IV,
    IW,
    IWY,
    IX,
    IY,
    IYAW,
    N_STATES,
    F_jacobian,
    H_jacobian,
    fx,
    hx,
    wheel_rates,
)
from rover_bridge.estimate.sampling import SampleCorrections

PROPS = settings(derandomize=True, database=None, deadline=None, max_examples=200)
L = 0.30


@st.composite
def states(draw: st.DrawFn, geometry: bool = True) -> np.ndarray:
    x = np.zeros(N_STATES)
    x[IX], x[IY] = draw(st.floats(-50.0, 50.0)), draw(st.floats(-50.0, 50.0))
    x[IYAW] = draw(st.floats(-math.pi, math.pi))
    x[IV] = draw(st.floats(-2.0, 2.0))
    x[IW] = draw(st.one_of(st.floats(-3.0, 3.0), st.floats(-1e-5, 1e-5)))  # also the arc's series branch
    x[IB] = draw(st.floats(-0.05, 0.05))
    x[IKT] = draw(st.floats(0.9, 1.1)) if geometry else 1.0
    x[IKR] = draw(st.floats(0.95, 1.05)) if geometry else 1.0
    x[IWY] = draw(st.floats(-0.2, 0.2))
    return x


def _numeric_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    cols = []
    for i in range(N_STATES):
        dx = np.zeros(N_STATES)
        dx[i] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.array(cols).T


# ---------------------------------------------------------------- models

@PROPS
@given(states(), st.floats(0.001, 0.2))
def test_the_motion_jacobian_is_the_derivative_of_the_motion(x: np.ndarray, dt_s: float) -> None:
    def moved(s: np.ndarray) -> np.ndarray:
        out = fx(s, dt_s, L)
        out[IYAW] = s[IYAW] + s[IW] * dt_s  # unwrapped: the derivative of the wrapped yaw is the same
        return out

    np.testing.assert_allclose(F_jacobian(x, dt_s, L), _numeric_jacobian(moved, x), atol=1e-6, rtol=1e-5)


@PROPS
@given(states(), st.booleans(), st.booleans())
def test_the_measurement_jacobian_is_the_derivative_of_the_measurement(x: np.ndarray, wheels: bool,
                                                                         gyro: bool) -> None:
    if not (wheels or gyro):
        return
    np.testing.assert_allclose(H_jacobian(x, L, wheels, gyro), _numeric_jacobian(lambda s: hx(s, L, wheels, gyro), x),
                               atol=1e-7, rtol=1e-6)


@PROPS
@given(states())
def test_the_wheels_read_what_each_wheels_scale_makes_of_the_body_motion(x: np.ndarray) -> None:
    # Independent of models' algebra: with wheel scales s_l = 2 / (1 + q), s_r = 2 q / (1 + q) (mean 1) and
    # the effective track kt L, each wheel's surface moves (v -+ omega kt L / 2) and reads that / its scale.
    v, w, kt, q = x[IV], x[IW], x[IKT], x[IKR]
    s_l, s_r = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
    left, right = (v - 0.5 * w * kt * L) / s_l, (v + 0.5 * w * kt * L) / s_r
    v_read, w_read = wheel_rates(x, L)
    assert math.isclose(v_read, 0.5 * (left + right), rel_tol=1e-9, abs_tol=1e-12)
    assert math.isclose(w_read, (right - left) / L, rel_tol=1e-9, abs_tol=1e-12)


@PROPS
@given(states(geometry=False), st.floats(0.001, 0.5), st.floats(0.001, 0.5))
def test_two_steps_along_the_arc_are_one_step(x: np.ndarray, dt1_s: float, dt2_s: float) -> None:
    # The pose moves along the exact arc of (v, omega): splitting a step changes nothing.
    two = fx(fx(x, dt1_s, L), dt2_s, L)
    one = fx(x, dt1_s + dt2_s, L)
    np.testing.assert_allclose(two[[IX, IY]], one[[IX, IY]], atol=1e-9)
    assert abs(math.remainder(two[IYAW] - one[IYAW], 2 * math.pi)) < 1e-9
    # and the arc is a circle: the chord's length is 2 R sin(turn / 2) for R = v / omega
    turn, dist = x[IW] * (dt1_s + dt2_s), x[IV] * (dt1_s + dt2_s)
    chord = math.hypot(one[IX] - x[IX], one[IY] - x[IY])
    expected = abs(dist) if abs(turn) < 1e-9 else abs(2.0 * dist / turn * math.sin(0.5 * turn))
    assert math.isclose(chord, expected, rel_tol=1e-6, abs_tol=1e-9)


# ---------------------------------------------------------------- consistency window

@PROPS
@given(st.floats(0.01, 0.1), st.floats(0.2, 1.0), st.floats(1e-9, 1e-6), st.floats(1e-9, 1e-6))
def test_wheels_that_turn_as_the_gyro_does_are_never_distrusted(dt_s: float, speed_m_s: float, gyro_var: float,
                                                                reading_var: float) -> None:
    window = ConsistencyWindow()
    verdicts = []
    for _ in range(round(3.0 / dt_s)):
        window.add(dt_s, 0.01, 0.0, gyro_var, speed_m_s * dt_s)
        verdicts.append(window.agree(1e-8, reading_var))
    assert False not in verdicts
    assert True in verdicts  # three seconds of motion: at least two whole windows agreed


@PROPS
@given(st.floats(0.01, 0.1), st.floats(1e-9, 1e-6), st.floats(1e-9, 1e-6), st.floats(1.05, 10.0))
def test_a_disagreement_beyond_the_noise_is_distrusted_as_soon_as_a_window_is_judged(
        dt_s: float, gyro_var: float, reading_var: float, factor: float) -> None:
    window = ConsistencyWindow()
    n = math.floor(MIN_SPAN_S / dt_s) + 1  # the first interval with a window long enough to judge
    bias_var = 1e-8
    span = n * dt_s
    allowed = AGREE_SIGMA * math.sqrt(2.0 * reading_var + n * gyro_var + bias_var * span * span)
    verdicts = []
    for _ in range(n):
        window.add(dt_s, 0.01, factor * allowed / n, gyro_var, 0.01)
        verdicts.append(window.agree(bias_var, reading_var))
    assert True not in verdicts
    assert next(v for v in verdicts if v is not None) is False


# ---------------------------------------------------------------- sampling

@PROPS
@given(st.lists(st.tuples(st.floats(0.005, 0.19), st.floats(-3.0, 3.0)), min_size=2, max_size=20),  # < the 0.2 s limit
       st.floats(-3.0, 3.0))
def test_the_prediction_plus_the_correction_is_the_turn_of_a_rate_that_moves_linearly(
        samples: list[tuple[float, float]], first_rad_s: float) -> None:
    # The body's rate moves linearly between gyro samples; the filter predicts at the last sample's rate
    # (in sub-steps) and each sample adds the missed part: the total is the exact integral.
    s = SampleCorrections()
    t, rate = 0.0, first_rad_s
    s.gyro(t, rate)
    turned = exact = 0.0
    for dt, new_rate in samples:
        for _ in range(3):
            s.predicted(0.0, rate, dt / 3)
            turned += rate * dt / 3
        exact += 0.5 * (rate + new_rate) * dt
        t += dt
        missed, var = s.gyro(t, new_rate)
        turned += missed
        assert var >= 0.0
        rate = new_rate
    assert math.isclose(turned, exact, abs_tol=1e-9)


@PROPS
@given(st.lists(st.tuples(st.floats(0.005, 0.2), st.floats(-1.0, 1.0), st.floats(0.0, 0.05)), min_size=1,
                max_size=20))
def test_the_position_moves_by_what_the_wheels_measured(intervals: list[tuple[float, float, float]]) -> None:
    s = SampleCorrections()
    t = moved = measured = 0.0
    v = 0.0
    for dt, new_v, distance in intervals:
        s.predicted(v, 0.0, dt)
        moved += v * dt
        t += dt
        moved += s.wheels(t, new_v, distance)
        measured += distance
        v = new_v
    assert math.isclose(moved, measured, abs_tol=1e-9)
