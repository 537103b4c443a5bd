"""EKF models: Jacobians against finite differences, hand-derived motion cases, gating, slip."""

# Kalman-filter notation (P, H, R, S, K) reads better than pep8 names here.
# ruff: noqa: N803, N806

from __future__ import annotations

import math

import numpy as np
import pytest

from rover_bridge.estimate.ekf import (
    IB,
    IKR,
    IKT,
    IV,
    IW,
    IX,
    IY,
    IYAW,
    N_CAL,
    PUBLISHED,
    F_jacobian,
    H_gyro,
    H_wheels,
    NoiseModel,
    WheelGyroEKF,
    _arc_derivatives,
    fx,
    hx_gyro,
    hx_wheels,
    wheel_measurement,
    wheel_noise,
)
from rover_bridge.odometry import Pose2D, arc_factors

L = 0.30


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
        x = np.zeros(N_CAL)
        x[IX], x[IY] = rng.uniform(-5, 5, 2)
        x[IYAW] = rng.uniform(-3.0, 3.0)
        x[IV] = rng.uniform(-1.5, 1.5)
        # every third state turns almost not at all: the series branch of the arc factors
        x[IW] = rng.uniform(-2.0, 2.0) if k % 3 else rng.uniform(-1e-5, 1e-5)
        x[IB] = rng.uniform(-0.05, 0.05)
        x[IKT] = rng.uniform(0.9, 1.1)
        x[IKR] = rng.uniform(0.95, 1.05)
        states.append(x)
    return states


@pytest.mark.parametrize("dt_s", [0.02, 0.05, 0.5])
def test_motion_jacobian_matches_finite_differences(dt_s: float) -> None:
    for x in _random_states(12, seed=7):
        numeric = _numeric_jacobian(lambda s: fx(s, dt_s), x)
        np.testing.assert_allclose(F_jacobian(x, dt_s), numeric, atol=2e-7, rtol=1e-6)


def test_measurement_jacobians_match_finite_differences() -> None:
    for x in _random_states(12, seed=11):
        np.testing.assert_allclose(H_wheels(x, L), _numeric_jacobian(lambda s: hx_wheels(s, L), x),
                                   atol=1e-7, rtol=1e-6)
        np.testing.assert_allclose(H_gyro(x), _numeric_jacobian(hx_gyro, x), atol=1e-9)


def test_arc_derivatives_continuous_across_the_series_switch() -> None:
    for d in (-2.0, -1e-3 * 1.0001, -1e-3 * 0.9999, -1e-6, 0.0, 1e-6, 1e-3 * 0.9999, 1e-3 * 1.0001, 1.5):
        eps = 1e-6
        num_a = (arc_factors(d + eps)[0] - arc_factors(d - eps)[0]) / (2 * eps)
        num_b = (arc_factors(d + eps)[1] - arc_factors(d - eps)[1]) / (2 * eps)
        da, db = _arc_derivatives(d)
        assert da == pytest.approx(num_a, abs=1e-7)
        assert db == pytest.approx(num_b, abs=1e-7)


def _state(v: float = 0.0, w: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    x = np.zeros(N_CAL)
    x[IV], x[IW], x[IYAW] = v, w, yaw
    x[IKT] = x[IKR] = 1.0
    return x


def test_motion_model_hand_cases() -> None:
    # straight: 1 m/s for 2 s along yaw 0
    np.testing.assert_allclose(fx(_state(v=1.0), 2.0)[[IX, IY, IYAW]], [2.0, 0.0, 0.0], atol=1e-12)
    # spin in place: a quarter turn left, no translation
    np.testing.assert_allclose(fx(_state(w=math.pi / 2), 1.0)[[IX, IY, IYAW]], [0.0, 0.0, math.pi / 2],
                               atol=1e-12)
    # quarter circle of radius 1 to the left: ends at (1, 1) facing +y
    np.testing.assert_allclose(fx(_state(v=1.0, w=1.0), math.pi / 2)[[IX, IY, IYAW]],
                               [1.0, 1.0, math.pi / 2], atol=1e-12)
    # the same arc starting at yaw = 90 deg: ends at (-1, 1)
    np.testing.assert_allclose(fx(_state(v=1.0, w=1.0, yaw=math.pi / 2), math.pi / 2)[[IX, IY]], [-1.0, 1.0],
                               atol=1e-12)


def test_wheel_model_hand_values() -> None:
    # 0.5 m/s forward, 1 rad/s left, nominal geometry: wheels at 0.35 and 0.65 m/s
    x = _state(v=0.5, w=1.0)
    np.testing.assert_allclose(hx_wheels(x, L), [0.5, 1.0])
    # track 10 % wider than nominal: the same body rate spreads the wheels 10 % more
    x[IKT] = 1.1
    np.testing.assert_allclose(hx_wheels(x, L), [0.5, 1.1])
    # right wheel 2 % larger (ratio 1.02): left scale 2/2.02, right 2*1.02/2.02 -> the right encoder
    # reads less than the ground moves, the left more
    x = _state(v=1.0)
    x[IKR] = 1.02
    ul, ur = 1.0 * 2.02 / 2.0, 1.0 * 2.02 / 2.04
    np.testing.assert_allclose(hx_wheels(x, L), [0.5 * (ul + ur), (ur - ul) / L])


def test_wheel_noise_hand_values() -> None:
    noise = NoiseModel(wheel_noise_m=0.001, wheel_noise_fraction=0.1)
    # dt 0.1: base per-wheel speed variance (sqrt(2) * 0.001 / 0.1)^2 = 2e-4; speeds 0.1 and 0.3 m/s
    r_cov = wheel_noise(0.01, 0.03, 0.1, L, noise)
    vl, vr = 2e-4 + 1e-4, 2e-4 + 9e-4
    expected = [[0.25 * (vl + vr), 0.5 * (vr - vl) / L], [0.5 * (vr - vl) / L, (vl + vr) / L**2]]
    np.testing.assert_allclose(r_cov, expected)


def _settled(calibrate: bool = False) -> WheelGyroEKF:
    """A filter driven straight at 0.5 m/s for 2 s with agreeing wheels and gyro."""
    ekf = WheelGyroEKF(L, calibrate=calibrate)
    t = 0.0
    for _ in range(40):
        t += 0.05
        ekf.update_wheels(t, 0.025, 0.025, 0.05, gyro_omega_rad_s=0.0)
        ekf.update_gyro(t, 0.0)
    return ekf


def test_gyro_outlier_rejected_and_normal_sample_accepted() -> None:
    ekf = _settled()
    omega_before = float(ekf.x[IW])
    assert not ekf.update_gyro(2.05, 20.0)  # 20 rad/s out of nowhere, 50 ms after 0
    assert float(ekf.x[IW]) == pytest.approx(omega_before, abs=1e-3)
    assert ekf.rejects_in_row["gyro"] == 1
    assert ekf.update_gyro(2.06, 0.01)
    assert ekf.rejects_in_row["gyro"] == 0


def test_persistent_gyro_rejections_end_in_acceptance() -> None:
    ekf = _settled()
    results = [ekf.update_gyro(2.05 + 0.01 * k, 20.0) for k in range(6)]
    # four rejected, the fifth in a row is taken (the filter is the likelier culprit by then)
    assert results[:5] == [False, False, False, False, True]


def test_slip_detected_when_wheels_and_gyro_disagree() -> None:
    ekf = _settled()
    # left wheel spins 50 % faster than the right at 0.5 m/s: wheels say -0.83 rad/s, the gyro 0
    res = ekf.update_wheels(2.05, 0.0375, 0.025, 0.05, gyro_omega_rad_s=0.0)
    assert res.slip and res.accepted
    ekf2 = _settled()
    res2 = ekf2.update_wheels(2.05, 0.0251, 0.0249, 0.05, gyro_omega_rad_s=0.0)
    assert not res2.slip


def test_slip_down_weights_the_wheels_yaw() -> None:
    ekf = _settled()
    ekf.update_wheels(2.05, 0.0375, 0.025, 0.05, gyro_omega_rad_s=0.0)
    # the wheels alone would say omega = -0.83 rad/s; the down-weighted update barely moves it
    assert abs(float(ekf.x[IW])) < 0.05


def test_set_pose_keeps_velocity_and_shrinks_pose_uncertainty() -> None:
    ekf = _settled()
    ekf.set_pose(Pose2D(1.0, -2.0, 0.5))
    assert ekf.pose == Pose2D(1.0, -2.0, 0.5)
    assert float(ekf.x[IV]) == pytest.approx(0.5, abs=0.01)
    assert float(ekf.P[IX, IX]) < 1e-5 and float(ekf.P[IX, IV]) == 0.0


# ---------------------------------------------------------------- the hand-written update

def _filter_at_random_state(rng: np.random.Generator, calibrate: bool) -> tuple[WheelGyroEKF, np.ndarray, np.ndarray]:
    """A filter put at a random state and positive-definite covariance, and copies of both."""
    x = np.array([0.3, -0.2, 0.4, 0.6, 0.3, 0.01, 1.02, 0.98]) + rng.normal(0.0, 0.05, N_CAL)
    A = rng.normal(0.0, 0.1, (N_CAL, N_CAL))
    P = A @ A.T + np.diag(rng.uniform(1e-4, 1e-2, N_CAL))
    ekf = WheelGyroEKF(L, calibrate=calibrate)
    ekf.ekf.x, ekf.ekf.P = x.copy(), P.copy()
    return ekf, x, P


def _filterpy_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, hx: np.ndarray,
                     R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from filterpy.kalman import ExtendedKalmanFilter

    ref = ExtendedKalmanFilter(dim_x=N_CAL, dim_z=z.shape[0])
    ref.x, ref.P = x.copy(), P.copy()
    ref.update(z, lambda _x: H, lambda _x: hx, R=R)
    ref.x[IYAW] = math.remainder(float(ref.x[IYAW]), 2.0 * math.pi)
    return ref.x, ref.P


def _joseph_consider(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, hx: np.ndarray,
                     R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The Schmidt-Kalman update in matrix form: the gain rows of the geometry states zeroed, Joseph's P."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    K[[IKT, IKR], :] = 0.0
    I_KH = np.eye(N_CAL) - K @ H
    return x + K @ (z - hx), I_KH @ P @ I_KH.T + K @ R @ K.T


@pytest.mark.parametrize("calibrate", [False, True])
@pytest.mark.parametrize("seed", range(10))
def test_the_float_wheel_update_is_the_matrix_update(seed: int, calibrate: bool) -> None:
    """update_wheels in floats (P H' from H's four nonzero columns, S, the masked gain, Joseph's P) is
    filterpy's ExtendedKalmanFilter.update with hx_wheels, H_wheels and wheel_noise when nothing is
    considered, the zero-gain-row Joseph form when the geometry is; then the distance correction."""
    rng = np.random.default_rng(seed)
    ekf, x, P = _filter_at_random_state(rng, calibrate)
    ekf.predict_to(1.0)  # the filter's time: no prediction in the update below
    H, hx = H_wheels(x, L), hx_wheels(x, L)
    dl, dr, dt = hx[0] * 0.05 - 0.5 * hx[1] * L * 0.05, hx[0] * 0.05 + 0.5 * hx[1] * L * 0.05, 0.05
    dl, dr = dl + rng.normal(0.0, 0.002), dr + rng.normal(0.0, 0.002)
    z = wheel_measurement(dl, dr, dt, L)
    R = wheel_noise(dl, dr, dt, L, NoiseModel())
    res = ekf.update_wheels(1.0, dl, dr, dt)
    assert res.accepted and not res.slip
    x_ref, p_ref = (_filterpy_update if calibrate else _joseph_consider)(x, P, z, H, hx, R)
    q = x_ref[IKR]
    missed = 0.5 * (2.0 / (1.0 + q) * dl + 2.0 * q / (1.0 + q) * dr)  # nothing predicted since the last reading
    x_ref[IX] += math.cos(x_ref[IYAW]) * missed
    x_ref[IY] += math.sin(x_ref[IYAW]) * missed
    np.testing.assert_allclose(ekf.x, x_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ekf.P, p_ref, rtol=1e-7, atol=1e-12)
    assert np.array_equal(ekf.P, ekf.P.T)  # exactly symmetric
    if not calibrate:
        assert ekf.x[IKT] == x[IKT] and ekf.x[IKR] == x[IKR]  # considered: never moved


@pytest.mark.parametrize("calibrate", [False, True])
@pytest.mark.parametrize("seed", range(10))
def test_the_float_gyro_update_is_the_matrix_update(seed: int, calibrate: bool) -> None:
    rng = np.random.default_rng(seed)
    ekf, x, P = _filter_at_random_state(rng, calibrate)
    ekf.predict_to(1.0)
    H, hx = H_gyro(x), hx_gyro(x)
    z = hx + 0.003
    R = np.array([[ekf._gyro_var]])
    assert ekf.update_gyro(1.0, float(z[0]))
    x_ref, p_ref = (_filterpy_update if calibrate else _joseph_consider)(x, P, z, H, hx, R)
    np.testing.assert_allclose(ekf.x, x_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ekf.P, p_ref, rtol=1e-7, atol=1e-12)
    assert np.array_equal(ekf.P, ekf.P.T)
    if not calibrate:
        assert ekf.x[IKT] == x[IKT] and ekf.x[IKR] == x[IKR]


def test_the_arrays_are_filterpys_and_updated_in_place() -> None:
    # filterpy's filter holds the state: the float arithmetic writes into its arrays, it never rebinds them.
    from filterpy.kalman import ExtendedKalmanFilter

    ekf = WheelGyroEKF(L)
    assert isinstance(ekf.ekf, ExtendedKalmanFilter)
    x_arr, p_arr = ekf.ekf.x, ekf.ekf.P
    before = p_arr.copy()
    ekf.update_gyro(0.01, 0.2)
    ekf.update_wheels(0.02, 0.004, 0.0045, 0.01, 0.2)
    ekf.predict_to(0.05)
    assert ekf.ekf.x is x_arr and ekf.ekf.P is p_arr
    assert not np.array_equal(p_arr, before) and x_arr[IW] > 0.0


def test_a_filter_built_while_filterpy_loads_in_the_background_moves_into_it_unchanged(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # rover-bridge run imports filterpy (and scipy, 0.45 s) in a thread of its own: a filter built before
    # that finished holds x and P itself and moves them into filterpy's filter at its next prediction.
    import rover_bridge.estimate.ekf as ekf_module

    cls = ekf_module.filter_class()
    monkeypatch.setattr(ekf_module, "_FILTER_CLASS", None)
    monkeypatch.setattr(ekf_module, "_BACKGROUND", True)
    early, normal = WheelGyroEKF(0.3), None
    assert not isinstance(early.ekf, cls)
    early.update_gyro(0.01, 0.1)
    monkeypatch.setattr(ekf_module, "_FILTER_CLASS", cls)  # the thread finished
    normal = WheelGyroEKF(0.3)
    normal.update_gyro(0.01, 0.1)
    for f in (early, normal):
        f.update_wheels(0.02, 0.004, 0.0045, 0.01, 0.1)
    assert isinstance(early.ekf, cls) and isinstance(normal.ekf, cls)
    assert np.array_equal(early.x, normal.x) and np.array_equal(early.P, normal.P)


def _random_filter(seed: int, calibrate: bool) -> WheelGyroEKF:
    rng = np.random.default_rng(seed)
    f = WheelGyroEKF(L, calibrate=calibrate)
    f.predict_to(0.0)
    x = rng.normal(size=N_CAL)
    x[IKT], x[IKR] = 1.0 + 0.05 * rng.normal(), 1.0 + 0.05 * rng.normal()
    a = rng.normal(size=(N_CAL, N_CAL))
    f.ekf.x, f.ekf.P = x, a @ a.T * 0.01
    return f


@pytest.mark.parametrize("calibrate", [False, True])
@pytest.mark.parametrize("seed", range(20))
def test_the_float_prediction_step_is_fx_f_jacobian_and_q(seed: int, calibrate: bool) -> None:
    # predict_to writes fx, F_jacobian and process_noise_diagonal out in floats, touching only the rows and
    # columns F changes: x bit for bit, P to rounding (the products are summed in another order) and
    # exactly symmetric.
    from rover_bridge.estimate.ekf import process_noise_diagonal

    f = _random_filter(seed, calibrate)
    x0, p0 = f.x.copy(), f.P.copy()
    f.predict_to(0.037)
    F = F_jacobian(x0, 0.037)
    p_ref = F @ p0 @ F.T
    p_ref.flat[:: N_CAL + 1] += process_noise_diagonal(x0, 0.037)
    assert np.array_equal(f.x, fx(x0, 0.037))
    np.testing.assert_allclose(f.P, p_ref, rtol=1e-12, atol=1e-15)
    assert np.array_equal(f.P, f.P.T)


@pytest.mark.parametrize("seed", range(10))
def test_extrapolation_is_the_matrix_form(seed: int) -> None:
    from rover_bridge.estimate.ekf import EXTRAPOLATE_MAX_S, MAX_PREDICT_STEP_S, process_noise

    f = _random_filter(seed, calibrate=False)
    x0, p0 = f.x.copy(), f.P.copy()
    for dt in (0.0, 0.013, 0.35):
        x, rows = f.extrapolate(dt)
        moved = min(dt, EXTRAPOLATE_MAX_S)
        F = F_jacobian(x0, moved)
        p_ref = F @ p0 @ F.T + process_noise(x0, dt) * max(1.0, dt / MAX_PREDICT_STEP_S)
        np.testing.assert_allclose(x, fx(x0, moved), rtol=0, atol=0)
        np.testing.assert_allclose(np.array(rows), p_ref, rtol=1e-12, atol=1e-15)
        # ODOMETRY's block (x, y, yaw, v, omega) alone: the same numbers, computed from that block only.
        x5, rows5 = f.extrapolate(dt, PUBLISHED)
        assert x5 == x and rows5 == [row[:PUBLISHED] for row in rows[:PUBLISHED]]
    assert np.array_equal(f.x, x0) and np.array_equal(f.P, p0)  # the filter did not move
    with pytest.raises(ValueError, match="block"):
        f.extrapolate(0.01, PUBLISHED - 1)  # x, y, yaw move with v and omega: no block without them


@pytest.mark.parametrize("calibrate", [False, True])
@pytest.mark.parametrize("seed", range(20))
def test_the_slip_distance_in_floats_is_the_one_from_hx_and_h(seed: int, calibrate: bool) -> None:
    f = _random_filter(seed, calibrate)
    z = np.array([0.4, 0.7])
    R = np.array([[0.01, 0.001], [0.001, 0.02]])
    gyro, spread = 0.35, 0.02
    xg = f.x.copy()
    xg[IW] = gyro - f.x[IB]
    hg = H_wheels(xg, L)[1]
    var = float(R[1, 1]) + float(hg[IW]) ** 2 * (f._gyro_var + float(f.P[IB, IB]) + spread**2)
    g = hg[IKT:]
    var += float(g @ f.P[IKT:, IKT:] @ g)
    ref = (float(z[1]) - float(hx_wheels(xg, L)[1])) ** 2 / var
    assert f.slip_d2(float(z[1]), float(R[1, 1]), gyro, spread) == pytest.approx(ref, rel=1e-13)


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
        worst_m = max(worst_m, math.hypot(xb[IX] - xa[IX], xb[IY] - xa[IY]))
        worst_rad = max(worst_rad, abs(xb[IYAW] - xa[IYAW]))
    assert worst_m < 1e-3  # at most the 1 ms of travel and turn, never accumulated
    assert worst_rad < 1e-3
    assert xa[IYAW] == pytest.approx(w * (300 * period + 0.01), abs=0.01)  # and the path is the true one
