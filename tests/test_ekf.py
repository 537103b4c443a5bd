"""The EKF: models against finite differences and hand cases, filterpy's steps against their matrix forms
(and against filterpy's own ExtendedKalmanFilter), gating, slip, same-instant
readings, extrapolation."""

# Kalman-filter notation (P, H, R, S, K) reads better than pep8 names here.
# ruff: noqa: N803, N806

from __future__ import annotations

import math

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.estimate.arc_ekf import ArcKalmanFilter, small_inverse
from rover_bridge.estimate.ekf import EXTRAPOLATE_MAX_S, MAX_PREDICT_STEP_S, WheelGyroEKF
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
    PUBLISHED,
    F_jacobian,
    H_jacobian,
    NoiseModel,
    _arc_derivatives,
    ahead,
    fx,
    hx,
    process_noise,
    residual,
    wheel_rate_noise,
    wheel_rates,
    wheel_rates_jacobian,
)
from rover_bridge.estimate.wheel_judge import STILL_SETTLE_S
from rover_bridge.odometry import Pose2D, arc_factors

L = 0.30
# (wheels, gyro, still): the updates the filter makes (a standstill's yaw rate comes with the wheels' rows)
ROWS = [(True, True, False), (True, False, False), (False, True, False), (True, True, True), (True, False, True)]


def _numeric_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    cols = []
    for i in range(x.shape[0]):
        dx = np.zeros_like(x)
        dx[i] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.array(cols).T


def _random_states(n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    states = []
    for k in range(n):
        x = np.zeros(N_STATES)
        x[IX], x[IY] = rng.uniform(-5, 5, 2)
        x[IYAW] = rng.uniform(-3.0, 3.0)
        x[IV] = rng.uniform(-1.5, 1.5)
        # every third state turns almost not at all: the series branch of the arc factors
        x[IW] = rng.uniform(-2.0, 2.0) if k % 3 else rng.uniform(-1e-5, 1e-5)
        x[IB] = rng.uniform(-0.05, 0.05)
        x[IKT] = rng.uniform(0.9, 1.1)
        x[IKR] = rng.uniform(0.95, 1.05)
        x[IWY] = rng.uniform(-0.1, 0.1)
        states.append(x)
    return states


def _random_covariance(rng: np.random.Generator, geometry: bool = True) -> np.ndarray:
    A = rng.normal(0.0, 0.1, (N_STATES, N_STATES))
    P = A @ A.T + np.diag(rng.uniform(1e-4, 1e-2, N_STATES))
    if not geometry:  # calibrate = false: the geometry is exact
        P[[IKT, IKR], :] = 0.0
        P[:, [IKT, IKR]] = 0.0
    return P


# ---------------------------------------------------------------- models

@pytest.mark.parametrize("dt_s", [0.02, 0.05, 0.5])
def test_motion_jacobian_matches_finite_differences(dt_s: float) -> None:
    for x in _random_states(12, seed=7):
        numeric = _numeric_jacobian(lambda s: fx(s, dt_s, L), x)
        np.testing.assert_allclose(F_jacobian(x, dt_s, L), numeric, atol=2e-7, rtol=1e-6)


@pytest.mark.parametrize(("wheels", "gyro", "still"), ROWS)
def test_measurement_jacobians_match_finite_differences(wheels: bool, gyro: bool, still: bool) -> None:
    for x in _random_states(12, seed=11):
        numeric = _numeric_jacobian(lambda s: hx(s, L, wheels, gyro, still), x)
        np.testing.assert_allclose(H_jacobian(x, L, wheels, gyro, still), numeric, atol=1e-7, rtol=1e-6)
        np.testing.assert_allclose(wheel_rates_jacobian(x, L), _numeric_jacobian(
            lambda s: np.array(wheel_rates(s, L)), x), atol=1e-7, rtol=1e-6)


def test_arc_derivatives_continuous_across_the_series_switch() -> None:
    for d in (-2.0, -1e-3 * 1.0001, -1e-3 * 0.9999, -1e-6, 0.0, 1e-6, 1e-3 * 0.9999, 1e-3 * 1.0001, 1.5):
        eps = 1e-6
        num_a = (arc_factors(d + eps)[0] - arc_factors(d - eps)[0]) / (2 * eps)
        num_b = (arc_factors(d + eps)[1] - arc_factors(d - eps)[1]) / (2 * eps)
        da, db = _arc_derivatives(d)
        assert da == pytest.approx(num_a, abs=1e-7)
        assert db == pytest.approx(num_b, abs=1e-7)


def _state(v: float = 0.0, w: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    x = np.zeros(N_STATES)
    x[IV], x[IW], x[IYAW] = v, w, yaw
    x[IKT] = x[IKR] = 1.0
    return x


def test_motion_model_hand_cases() -> None:
    # straight: 1 m/s for 2 s along yaw 0
    np.testing.assert_allclose(fx(_state(v=1.0), 2.0, L)[[IX, IY, IYAW]], [2.0, 0.0, 0.0], atol=1e-12)
    # spin in place: a quarter turn left, no translation
    np.testing.assert_allclose(fx(_state(w=math.pi / 2), 1.0, L)[[IX, IY, IYAW]], [0.0, 0.0, math.pi / 2],
                               atol=1e-12)
    # quarter circle of radius 1 to the left: ends at (1, 1) facing +y
    np.testing.assert_allclose(fx(_state(v=1.0, w=1.0), math.pi / 2, L)[[IX, IY, IYAW]],
                               [1.0, 1.0, math.pi / 2], atol=1e-12)
    # the same arc starting at yaw = 90 deg: ends at (-1, 1)
    np.testing.assert_allclose(fx(_state(v=1.0, w=1.0, yaw=math.pi / 2), math.pi / 2, L)[[IX, IY]], [-1.0, 1.0],
                               atol=1e-12)
    # the nominal geometry: the wheels' heading error does not grow; a track 10 % wide: 10 % of the turn
    assert fx(_state(v=1.0, w=1.0), 0.5, L)[IWY] == 0.0
    wide = _state(v=1.0, w=1.0)
    wide[IKT] = 1.1
    assert fx(wide, 0.5, L)[IWY] == pytest.approx(0.05)


def test_wheel_model_hand_values() -> None:
    # 0.5 m/s forward, 1 rad/s left, nominal geometry: wheels at 0.35 and 0.65 m/s
    x = _state(v=0.5, w=1.0)
    np.testing.assert_allclose(wheel_rates(x, L), [0.5, 1.0])
    # track 10 % wider than nominal: the same body rate spreads the wheels 10 % more
    x[IKT] = 1.1
    np.testing.assert_allclose(wheel_rates(x, L), [0.5, 1.1])
    # right wheel 2 % larger (ratio 1.02): left scale 2/2.02, right 2*1.02/2.02 -> the right encoder
    # reads less than the ground moves, the left more
    x = _state(v=1.0)
    x[IKR] = 1.02
    ul, ur = 1.0 * 2.02 / 2.0, 1.0 * 2.02 / 2.04
    np.testing.assert_allclose(wheel_rates(x, L), [0.5 * (ul + ur), (ur - ul) / L])
    # the measurements: the wheels' speed and heading (yaw + their error), the gyro's rate + bias
    x = _state(v=0.5, w=1.0, yaw=0.3)
    x[IWY], x[IB] = 0.02, 0.01
    np.testing.assert_allclose(hx(x, L), [0.5, 0.32, 1.01])


def test_wheel_noise_hand_values() -> None:
    noise = NoiseModel(wheel_noise_m=0.001, wheel_noise_fraction=0.1)
    # dt 0.1: base per-wheel speed variance (sqrt(2) * 0.001 / 0.1)^2 = 2e-4; speeds 0.1 and 0.3 m/s
    r_v, r_omega = wheel_rate_noise(0.01, 0.03, 0.1, L, noise)
    vl, vr = 2e-4 + 1e-4, 2e-4 + 9e-4
    assert r_v == pytest.approx(0.25 * (vl + vr))
    assert r_omega == pytest.approx((vl + vr) / L**2)


def test_the_wheels_heading_difference_is_wrapped_and_nothing_else() -> None:
    z, h = np.array([0.5, math.pi - 0.01, 0.2]), np.array([0.4, -math.pi + 0.01, 0.1])
    np.testing.assert_allclose(residual(z, h), [0.1, -0.02, 0.1], atol=1e-12)
    np.testing.assert_allclose(residual(np.array([7.0]), np.array([0.5])), [6.5])  # a gyro row alone


def test_the_look_ahead_moves_at_the_speeds_half_way_and_keeps_them() -> None:
    x = _state(v=0.5, w=0.2)
    moved, F = ahead(x, 0.1, 0.0, 0.0, L)
    np.testing.assert_allclose(moved, fx(x, 0.1, L))
    np.testing.assert_allclose(F, F_jacobian(x, 0.1, L))
    # braking at 2 m/s^2 and spinning down at 4 rad/s^2: the arc of (0.4, 0.0) over 0.1 s; speeds unchanged
    braking, _ = ahead(_state(v=0.5, w=0.2), 0.1, -2.0, -4.0, L)
    np.testing.assert_allclose(braking[[IX, IY, IYAW]], [0.04, 0.0, 0.0], atol=1e-12)
    assert (braking[IV], braking[IW]) == (0.5, 0.2)


# ---------------------------------------------------------------- filterpy's steps

@settings(max_examples=200, deadline=None)
@given(st.integers(1, 4), st.integers(0, 2**32 - 1))
def test_the_small_inverse_is_the_inverse(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    S = A @ A.T + np.diag(rng.uniform(1e-6, 1.0, n)) * 10.0 ** rng.uniform(-8, 0)
    np.testing.assert_allclose(small_inverse(S) @ S, np.eye(n), atol=1e-6)
    np.testing.assert_allclose(small_inverse(S), np.linalg.inv(S), rtol=1e-6)


def _arc_filter(x: np.ndarray, P: np.ndarray, calibrate: bool) -> ArcKalmanFilter:
    kf = ArcKalmanFilter(L, learn_geometry=calibrate)
    kf.x, kf.P = x.copy(), P.copy()
    return kf


@pytest.mark.parametrize("calibrate", [False, True])
@pytest.mark.parametrize("seed", range(10))
def test_the_prediction_is_the_extended_filters(seed: int, calibrate: bool) -> None:
    # filterpy's KalmanFilter predict with the arc as its control input: x = fx(x), P = F P F' + Q.
    rng = np.random.default_rng(seed)
    x, P = _random_states(1, seed)[0], _random_covariance(rng)
    kf = _arc_filter(x, P, calibrate)
    assert isinstance(kf, KalmanFilter)
    kf.predict_arc(0.037)
    F = F_jacobian(x, 0.037, L)
    np.testing.assert_allclose(kf.x, fx(x, 0.037, L), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kf.P, F @ P @ F.T + process_noise(x, 0.037, calibrate), rtol=1e-10, atol=1e-15)
    if not calibrate:  # the geometry is not a random walk without calibration
        assert kf.P[IKT, IKT] == P[IKT, IKT] and kf.P[IKR, IKR] == P[IKR, IKR]


@pytest.mark.parametrize(("wheels", "gyro", "still"), ROWS)
@pytest.mark.parametrize("seed", range(10))
def test_the_update_is_filterpys_extended_kalman_filter(seed: int, wheels: bool, gyro: bool, still: bool) -> None:
    # KalmanFilter's update on z - h(x) + H x is ExtendedKalmanFilter's update with h, H and the wrapped
    # residual: the same gain, the same Joseph P.
    rng = np.random.default_rng(seed)
    x, P = _random_states(1, seed)[0], _random_covariance(rng)
    z = hx(x, L, wheels, gyro, still) + rng.normal(0.0, 0.01, 2 * wheels + still + gyro)
    if wheels:
        z[1] += 2.0 * math.pi  # the wheels' heading a turn away: the same heading
    R = np.diag(rng.uniform(1e-5, 1e-3, len(z)))
    kf = _arc_filter(x, P, calibrate=True)
    kf.update_rows(z, R, wheels, gyro, still=still)
    ref = ExtendedKalmanFilter(dim_x=N_STATES, dim_z=len(z))
    ref.x, ref.P = x.copy(), P.copy()
    ref.update(z, H_jacobian, hx, R=R, args=(L, wheels, gyro, still), hx_args=(L, wheels, gyro, still),
               residual=residual)
    np.testing.assert_allclose(kf.x, ref.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(kf.P, ref.P, rtol=1e-7, atol=1e-13)


# ---------------------------------------------------------------- the filter around them

def _settled(calibrate: bool = False) -> WheelGyroEKF:
    """A filter driven straight at 0.5 m/s for 2 s with agreeing wheels and gyro."""
    ekf = WheelGyroEKF(L, calibrate=calibrate)
    t = 0.0
    for _ in range(40):
        t += 0.05
        ekf.update_gyro(t, 0.0)
        ekf.update_wheels(t, 0.025, 0.025, 0.05, gyro_omega_rad_s=0.0)
    return ekf


def test_the_filter_is_filterpys() -> None:
    ekf = _settled()
    assert isinstance(ekf.ekf, KalmanFilter)
    assert ekf.ekf.x is ekf.x and ekf.ekf.P is ekf.P


def test_gyro_outlier_rejected_and_normal_sample_accepted() -> None:
    ekf = _settled()
    omega_before = float(ekf.x[IW])
    assert not ekf.update_gyro(2.05, 20.0)  # 20 rad/s out of nowhere, 50 ms after 0
    assert float(ekf.x[IW]) == pytest.approx(omega_before, abs=1e-3)
    assert ekf.gyro_gate.rejects_in_row == 1
    assert ekf.update_gyro(2.06, 0.01)
    assert ekf.gyro_gate.rejects_in_row == 0


def test_persistent_gyro_rejections_end_in_acceptance() -> None:
    ekf = _settled()
    results = [ekf.update_gyro(2.05 + 0.01 * k, 20.0) for k in range(6)]
    # four rejected, the fifth in a row is taken (the filter is the likelier culprit by then)
    assert results[:5] == [False, False, False, False, True]


def test_slip_detected_when_wheels_and_gyro_disagree() -> None:
    ekf = _settled()
    # left wheel spins 50 % faster than the right at 0.5 m/s: wheels say -0.83 rad/s, the gyro 0; once is a
    # step (wheel_judge), in two intervals running it is slip
    first = ekf.update_wheels(2.05, 0.0375, 0.025, 0.05, gyro_omega_rad_s=0.0)
    assert not first.slip and first.accepted
    res = ekf.update_wheels(2.10, 0.0375, 0.025, 0.05, gyro_omega_rad_s=0.0)
    assert res.slip and res.accepted
    ekf2 = _settled()
    res2 = ekf2.update_wheels(2.05, 0.0251, 0.0249, 0.05, gyro_omega_rad_s=0.0)
    assert not res2.slip


def test_slipping_wheels_leave_the_heading_to_the_gyro_and_the_speed_to_the_slower_wheel() -> None:
    ekf = _settled()
    yaw = ekf.pose.yaw_rad
    for t in (2.05, 2.10, 2.15):  # slip from the second interval on (wheel_judge)
        ekf.update_gyro(t, 0.0)
        ekf.update_wheels(t, 0.0375, 0.025, 0.05, gyro_omega_rad_s=0.0)
    # the wheels alone would turn it 0.12 rad and say 0.625 m/s; the gyro holds the heading, the right
    # (slower) wheel gives the speed
    assert abs(ekf.pose.yaw_rad - yaw) < 1e-3
    assert abs(float(ekf.x[IW])) < 0.05
    assert float(ekf.x[IV]) == pytest.approx(0.5, abs=0.01)


def test_set_pose_keeps_velocity_and_shrinks_pose_uncertainty() -> None:
    ekf = _settled()
    ekf.set_pose(Pose2D(1.0, -2.0, 0.5))
    assert ekf.pose == Pose2D(1.0, -2.0, 0.5)
    assert float(ekf.x[IV]) == pytest.approx(0.5, abs=0.01)
    assert float(ekf.P[IX, IX]) < 1e-5 and float(ekf.P[IX, IV]) == 0.0
    # the wheels' heading turned with the pose: the next reading is no jump
    ekf.update_wheels(2.05, 0.025, 0.025, 0.05, gyro_omega_rad_s=0.0)
    assert ekf.heading_jumps == 0 and ekf.pose.yaw_rad == pytest.approx(0.5, abs=1e-4)


def test_a_new_wheel_baseline_measures_turns_from_the_filters_heading() -> None:
    ekf = _settled()
    ekf.ekf.x[IWY] = 0.03
    ekf.wheel_baseline()
    x, P = ekf.x, ekf.P
    assert ekf.wheel_yaw_rad == pytest.approx(float(x[IYAW]) + 0.03)
    # the error state's error is minus the yaw's: yaw + error (what the wheels read) is known exactly
    h = np.zeros(N_STATES)
    h[IYAW] = h[IWY] = 1.0
    assert float(h @ P @ h) == pytest.approx(0.0, abs=1e-18)
    np.testing.assert_allclose(P, P.T, rtol=1e-12, atol=1e-20)


@pytest.mark.parametrize("calibrate", [False, True])
def test_a_gyro_sample_and_wheels_of_one_instant_are_one_update(calibrate: bool,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    # The gyro's row waits for the wheel reading of its stamp: one filterpy update of the three rows on
    # the predicted state (then the distance correction moves x and y only).
    ekf = _settled(calibrate)
    judged = []
    judge = ekf.judge.judge
    monkeypatch.setattr(ekf.judge, "judge", lambda *a: judged.append(judge(*a)) or judged[-1])
    t = 2.05
    ekf.update_gyro(t, 0.02)
    assert ekf._pending_gyro is not None  # not fused yet
    x0, P0 = ekf._kf.x.copy(), ekf._kf.P.copy()
    res = ekf.update_wheels(t, 0.0249, 0.0252, 0.05, gyro_omega_rad_s=0.02)
    assert res.accepted and not res.slip and ekf._pending_gyro is None
    (j,) = judged
    P0[IWY, IWY] = j.heading_var
    kf = _arc_filter(x0, P0, calibrate)
    noise = NoiseModel()
    z = np.array([j.z_v, ekf.wheel_yaw_rad, 0.02])
    R = np.diag([j.r_v, 2.0 * (noise.wheel_noise_m / L) ** 2, noise.gyro_noise_rad_s**2])
    kf.update_rows(z, R, True, True)
    keep = [IYAW, IV, IW, IB, IKT, IKR, IWY]
    np.testing.assert_allclose(ekf.x[keep], kf.x[keep], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ekf.P, kf.P, rtol=1e-12, atol=1e-18)


def test_trusted_wheels_in_motion_teach_the_bias_also_after_rest() -> None:
    # 10 s at rest learn a bias of 0.01; driving, the gyro's bias is 0.012 (it moved with temperature) and
    # the trusted wheels see the body turn 0.2 rad/s where the gyro reads 0.212: they teach it the new bias
    # (a bias learnt at rest was a Schmidt consider state before, never corrected in motion).
    ekf = WheelGyroEKF(L)
    t = 0.0
    for _ in range(200):
        t += 0.05
        ekf.update_gyro(t, 0.01)
        ekf.update_wheels(t, 0.0, 0.0, 0.05, gyro_omega_rad_s=0.01)
    assert float(ekf.x[IB]) == pytest.approx(0.01, abs=1e-3) and float(ekf.P[IB, IB]) < 0.002**2
    for _ in range(400):  # 20 s
        t += 0.05
        ekf.update_gyro(t, 0.212)
        ekf.update_wheels(t, 0.025 - 0.0015, 0.025 + 0.0015, 0.05, gyro_omega_rad_s=0.212)  # 0.2 rad/s
    assert ekf.wheels_trusted
    assert 0.011 < float(ekf.x[IB]) < 0.0122  # more than half way in 20 s, not past it


def test_a_reading_within_a_millisecond_of_the_state_costs_no_prediction() -> None:
    ekf = _settled()
    t = float(ekf.time_s or 0.0) + 0.02
    ekf.update_gyro(t, 0.0)
    steps = ekf.predict_steps
    ekf.update_wheels(t + 0.0004, 0.01, 0.01, 0.02, gyro_omega_rad_s=0.0)
    assert ekf.predict_steps == steps  # the same instant at the stamps' millisecond resolution
    assert ekf.time_s == t  # the 0.4 ms is predicted with the next interval, not lost
    ekf.update_gyro(t + 0.02, 0.0)
    assert ekf.predict_steps == steps + 1


@pytest.mark.parametrize("gyro_first", [True, False])
def test_readings_a_fraction_of_a_millisecond_apart_drive_the_path_of_simultaneous_ones(gyro_first: bool) -> None:
    # ATTITUDE is stamped in ms, WHEEL_DISTANCE (PX4) in us: the gyro reading of a burst lands up to a
    # millisecond off the wheels', by a varying amount. Applied at the state's time, the turn and the
    # distance of that fraction must still count exactly once.
    v, w, period = 0.4, 0.2, 0.02
    d_left, d_right = (v - w * L / 2) * period, (v + w * L / 2) * period
    offsets = [0.0, 0.0007, 0.0003, 0.0009, 0.0]  # the gyro's lag (gyro first) or lead behind the wheels
    together, apart = WheelGyroEKF(L), WheelGyroEKF(L)
    worst_m = worst_rad = 0.0
    for k in range(1, 301):  # 6 s: 1.2 rad of arc
        t = k * period
        together.update_gyro(t, w)
        together.update_wheels(t, d_left, d_right, period, gyro_omega_rad_s=w)
        off = offsets[k % len(offsets)]
        if gyro_first:
            apart.update_gyro(t - off, w)
            apart.update_wheels(t, d_left, d_right, period, gyro_omega_rad_s=w)
        else:
            apart.update_wheels(t, d_left, d_right, period, gyro_omega_rad_s=w)
            apart.update_gyro(t + off, w)
        (xa, _), (xb, _) = together.extrapolate(t + 0.01), apart.extrapolate(t + 0.01)
        if k == 1:  # the very first gyro sample, if after the wheels, is still waiting (extrapolate)
            continue
        worst_m = max(worst_m, math.hypot(xb[IX] - xa[IX], xb[IY] - xa[IY]))
        worst_rad = max(worst_rad, abs(xb[IYAW] - xa[IYAW]))
    assert worst_m < 1e-3  # at most the 1 ms of travel and turn, never accumulated
    assert worst_rad < 1e-3
    assert xa[IYAW] == pytest.approx(w * (300 * period + 0.01), abs=0.01)  # and the path is the true one


def _random_filter(seed: int, calibrate: bool) -> WheelGyroEKF:
    rng = np.random.default_rng(seed)
    f = WheelGyroEKF(L, calibrate=calibrate)
    f.predict_to(0.0)
    x = rng.normal(size=N_STATES)
    x[IKT], x[IKR] = 1.0 + 0.05 * rng.normal(), 1.0 + 0.05 * rng.normal()
    f.ekf.x, f.ekf.P = x, _random_covariance(rng, calibrate)
    return f


@pytest.mark.parametrize("calibrate", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_a_gap_is_predicted_in_sub_steps(seed: int, calibrate: bool) -> None:
    f = _random_filter(seed, calibrate)
    x, P = f.x.copy(), f.P.copy()
    f.predict_to(0.25)  # three steps of 1/12 s
    for _ in range(3):
        F = F_jacobian(x, 0.25 / 3, L)
        x, P = fx(x, 0.25 / 3, L), F @ P @ F.T + process_noise(x, 0.25 / 3, calibrate)
    np.testing.assert_allclose(f.x, x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f.P, P, rtol=1e-9, atol=1e-14)
    assert f.predict_steps == 3 and f.time_s == 0.25


@pytest.mark.parametrize("seed", range(10))
def test_extrapolation_is_the_matrix_form(seed: int) -> None:
    f = _random_filter(seed, calibrate=False)
    x0, p0 = f.x.copy(), f.P.copy()
    for dt in (0.0, 0.013, 0.35):
        x, rows = f.extrapolate(dt)
        moved = min(dt, EXTRAPOLATE_MAX_S)
        F = F_jacobian(x0, moved, L)
        p_ref = F @ p0 @ F.T + process_noise(x0, dt, False) * max(1.0, dt / MAX_PREDICT_STEP_S)
        if dt == 0.0:
            p_ref = p0
        np.testing.assert_allclose(x, fx(x0, moved, L), rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.array(rows), p_ref, rtol=1e-12, atol=1e-15)
        # ODOMETRY's block (x, y, yaw, v, omega) alone: the same numbers, computed from that block only.
        x5, rows5 = f.extrapolate(dt, PUBLISHED)
        assert x5 == x and np.allclose(rows5, [row[:PUBLISHED] for row in rows[:PUBLISHED]], rtol=1e-14, atol=0)
    assert np.array_equal(f.x, x0) and np.array_equal(f.P, p0)  # the filter did not move
    with pytest.raises(ValueError, match="block"):
        f.extrapolate(0.01, PUBLISHED - 1)  # x, y, yaw move with v and omega: no block without them


def test_the_geometry_is_exact_without_calibration_and_learnt_with_it() -> None:
    assert WheelGyroEKF(L).calibration() == (1.0, 0.0, 1.0, 0.0)
    kt, s_kt, q, s_q = WheelGyroEKF(L, calibrate=True).calibration()
    assert (kt, q) == (1.0, 1.0) and s_kt > 0.0 and s_q > 0.0


def test_a_bias_taught_by_wheels_that_then_disagree_is_unlearnt() -> None:
    # Driving off at once (no standstill) straight on a right wheel 2 % large: the wheels read a turn the gyro
    # does not see. Trusted at first, they teach the gyro a bias; as the speed rises (a bias would not grow
    # with it) the window finds them disagreeing before it ever agreed: that bias was theirs, not the gyro's:
    # back to the prior (the last sound value), and it stays there.
    ekf = WheelGyroEKF(L)
    t, dt = 0.0, 0.02
    learnt = 0.0
    for _ in range(150):
        v = 0.2 + 0.8 * min(1.0, t / 1.5)
        t += dt
        ekf.update_gyro(t, 0.0)
        ekf.update_wheels(t, v * dt, 1.02 * v * dt, dt, gyro_omega_rad_s=0.0)
        if ekf.wheels_trusted:
            learnt = min(learnt, float(ekf.x[IB]))
    assert learnt < -0.005  # what the disagreeing wheels had taught it
    assert not ekf.wheels_trusted
    assert abs(float(ekf.x[IB])) < 0.001
    assert ekf.P[IB, IB] == pytest.approx(0.03 ** 2, rel=0.01)


def test_wheels_off_from_a_moving_start_neither_teach_a_bias_nor_win_back_trust_on_the_bias_doubt() -> None:
    # Driving off at once (no standstill: the bias is the prior's, 0.03 rad/s) on a right wheel 2 % large, the
    # wheels are distrusted within a second and their heading drifts 0.053 rad/s from the body's. Two ways they
    # took the heading back (benchmarks/accuracy.py --moving miscalibrated: 180 deg): once the yaw's uncertainty
    # (the bias's, integrated) passed 1 rad their "free" heading error was no longer free relative to the yaw
    # and taught the gyro their drift as a bias; and after a stop, windows "agreed" only because the bias's doubt
    # (5 sigma: 0.15 rad/s) covered the drift, so they were trusted and taught it, the yaw jumping with it.
    ekf = WheelGyroEKF(L)
    t, dt = 0.0, 0.1
    worst, trusted_again = 0.0, False
    for start, seconds in ((0.0, 36.0), (38.0, 8.0)):  # a stop from 36 to 38 s
        while t < start - 1e-9:
            t += dt
            ekf.update_gyro(t, 0.0)
            ekf.update_wheels(t, 0.0, 0.0, dt, gyro_omega_rad_s=0.0)
        while t < start + seconds - 1e-9:
            v = min(0.8, 0.2 + 0.8 * (t - start) / 1.5)  # the speed rises: a drift that grows with it is no bias
            t += dt
            ekf.update_gyro(t, 0.0)  # the body goes straight; the gyro has no bias
            ekf.update_wheels(t, v * dt, 1.02 * v * dt, dt, gyro_omega_rad_s=0.0)
            trusted_again = trusted_again or (t > 2.0 and ekf.wheels_trusted)
            worst = max(worst, abs(math.remainder(float(ekf.x[IYAW]), 2 * math.pi)))
    assert not trusted_again
    assert abs(float(ekf.x[IB])) < 0.002  # not their drift (0.053)
    assert math.degrees(worst) < 4.0  # what the yaw followed while they were trusted at first (2.2 deg), no more


def test_wheels_found_disagreeing_give_back_the_turn_the_yaw_followed() -> None:
    # An arc at 0.6 rad/s on a track 3 % off: the wheels read 3 % less turn. Trusted until the consistency
    # window finds them out, they hold the yaw meanwhile; when they are distrusted the yaw gives that turn
    # back (the gyro, here exact, turned the body 0.6 rad/s) and their heading error takes it.
    ekf = WheelGyroEKF(L)
    t, dt = 0.0, 0.05
    for _ in range(100):  # 5 s at rest
        t += dt
        ekf.update_gyro(t, 0.0)
        ekf.update_wheels(t, 0.0, 0.0, dt, gyro_omega_rad_s=0.0)
    truth = float(ekf.x[IYAW])
    errors = []
    while ekf.wheels_trusted and t < 10.0:
        t += dt
        truth += 0.6 * dt
        ekf.update_gyro(t, 0.6)
        turn = 0.97 * 0.6 * dt * L
        wheel_heading = ekf.wheel_yaw_rad + 0.97 * 0.6 * dt
        ekf.update_wheels(t, 0.5 * dt - 0.5 * turn, 0.5 * dt + 0.5 * turn, dt, gyro_omega_rad_s=0.6)
        errors.append(abs(math.remainder(float(ekf.x[IYAW]) - truth, 2 * math.pi)))
    assert not ekf.wheels_trusted
    assert errors[-2] > 0.002  # the yaw had followed the wheels (0.15 deg)
    assert errors[-1] < 0.75 * errors[-2]  # and gave back what the window saw of it
    # their heading is what they measured: yaw + error
    assert float(ekf.x[IYAW] + ekf.x[IWY]) == pytest.approx(wheel_heading, abs=1e-3)


def test_a_settled_standstill_teaches_the_bias_that_distrusted_wheels_cannot() -> None:
    # A moving start on a right wheel 2 % large: distrusted within a second, the wheels teach nothing, and their
    # heading row no longer holds the yaw at rest either. Stopped, they still bound the body's yaw rate (wheels
    # that do not turn hold the body still, whatever their geometry): after STILL_SETTLE_S the gyro's reading is
    # its bias. The motors' tail before that is not taken for one.
    bias = 0.004
    ekf = WheelGyroEKF(L)
    t, dt = 0.0, 0.05
    while t < 10.0 - 1e-9:
        v = min(0.8, 0.2 + 0.8 * t / 1.5)  # the speed rises: a drift that grows with it is no bias
        t += dt
        ekf.update_gyro(t, bias)
        ekf.update_wheels(t, v * dt, 1.02 * v * dt, dt, gyro_omega_rad_s=bias)
    assert not ekf.wheels_trusted
    before = float(ekf.x[IB])
    assert abs(before - bias) > 0.002  # nothing taught it yet
    stop = t
    while t < stop + STILL_SETTLE_S - dt - 1e-9:  # not settled: the motors' tail may still turn the body
        t += dt
        ekf.update_gyro(t, bias + 0.02)
        ekf.update_wheels(t, 0.0, 0.0, dt, gyro_omega_rad_s=bias + 0.02)
    assert float(ekf.x[IB]) == pytest.approx(before, abs=1e-5)
    while t < stop + 6.0 - 1e-9:
        t += dt
        ekf.update_gyro(t, bias)
        ekf.update_wheels(t, 0.0, 0.0, dt, gyro_omega_rad_s=bias)
    assert not ekf.wheels_trusted
    assert float(ekf.x[IB]) == pytest.approx(bias, abs=0.0005)
    assert math.sqrt(float(ekf.P[IB, IB])) < 0.002
