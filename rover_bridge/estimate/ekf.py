"""Wheel + gyro EKF (pure): motion and measurement models, their Jacobians, and a filterpy wrapper.

State (internal convention of rover-bridge: x forward of the start pose, y left, yaw counter-clockwise)

    0 x_m   1 y_m   2 yaw_rad   3 v_m_s (forward)   4 omega_rad_s (CCW)   5 gyro_bias_rad_s
    6 track_scale   (effective track width / nominal)            } estimated with calibrate = true;
    7 radius_ratio  (effective right wheel scale / left)         } otherwise Schmidt "consider" states

Motion: v and omega are random walks; the pose moves along the exact circular arc they describe
over dt (odometry.arc_factors), so a spin in place and a straight line are both exact.

Measurements
- wheels: the nominal wheel surface speeds over the interval between two WHEEL_DISTANCE stamps,
  combined as z = [v_wheel, omega_wheel] = [(l + r) / 2, (r - l) / L_nominal]. With calibration
  the predicted wheel speeds are l = (v - omega*k*L/2) / s_l and r = (v + omega*k*L/2) / s_r, with
  s_l = 2 / (1 + q), s_r = 2q / (1 + q) (mean scale 1: the overall distance scale is not
  observable without an absolute reference, the ratio and the track are - from the gyro).
- gyro: z = omega + bias.

Gating is per sensor on the Mahalanobis distance of the innovation. Wheel slip is a separate test:
the wheels' yaw rate against the gyro's (bias removed) over the same interval; on slip the wheels'
yaw contribution is down-weighted and their velocity variance inflated.

Beyond the textbook EKF: trapezoid corrections of yaw (between gyro samples) and distance (between
wheel readings), since the constant-rate prediction otherwise lags every change of rate by half a
sample; cumulative wheel distances move the pose the real distance over a first interval or a gap;
a standstill bound that tightens with its duration; publishing extrapolates at most
EXTRAPOLATE_MAX_S past the last measurement, and restart_motion continues from that held pose.

Every model is a pure function of (x, dt) so tests can check the Jacobians by finite differences.
These matrix forms are the reference: the filter runs the same models in floats (WheelGyroEKF), and
the tests hold the two together and to filterpy's update. The filter's covariance arithmetic (F P F',
P H', the update of x and P) goes through a kernel: PythonKernel, or the same operations in the same
order in C (_ekf_kernel.c, NativeKernel) where the install built it, equal to the bit (tests hold the two
together); everything else, the filter's logic, is Python once.

filterpy's ExtendedKalmanFilter holds the state (x, P); importing it imports scipy (filterpy's
package and its stats module do), 0.45 s of a 0.7 s start. So it is imported on first use, or,
when the process asked for it (`load_in_background`, rover-bridge run: its own thread, started
before anything else), while the bridge already runs; a filter built before the import finished keeps
its two arrays in a plain holder and moves them into filterpy's at its next prediction. Nothing is
computed differently either way: only x and P of that object are used.
"""

# Kalman-filter notation (F, H, P, Q, R, S, L) reads better than pep8 names here.
# ruff: noqa: N802, N803, N806
from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from operator import sub
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from rover_bridge.odometry import Pose2D, arc_factors, wrap_angle

Vec = npt.NDArray[np.float64]
Mat = npt.NDArray[np.float64]
Floats = Sequence[float]
Rows = Sequence[Sequence[float]] | Mat  # a matrix as rows: a nested list, or an array (both index [i][j])

IX, IY, IYAW, IV, IW, IB, IKT, IKR = range(8)
N_CAL = 8
PUBLISHED = IW + 1  # the states ODOMETRY carries (x, y, yaw, v, omega): the covariance block it reads

# Process noise densities (per second). Chosen so v and omega follow the sensors closely
# (a rover changes speed far faster than the filter would believe otherwise); bias and
# calibration drift slowly. Units: (m/s^2)^2 s, (rad/s^2)^2 s, (rad/s)^2/s, 1/s.
Q_V = 10.0
Q_OMEGA = 100.0
Q_BIAS = 1e-10
Q_CAL = 1e-10
# Pose noise that grows with the distance driven and the angle turned (unmodelled slip,
# uneven ground): variance per metre travelled / per radian turned.
Q_POS_PER_M = 1e-4  # m^2 / m
Q_YAW_PER_M = 2e-5  # rad^2 / m
Q_YAW_PER_RAD = 1e-5  # rad^2 / rad

# Initial uncertainty (1 sigma) of the states that are not known at start.
SIGMA0_V = 0.5
SIGMA0_OMEGA = 1.0
SIGMA0_BIAS = 0.03
SIGMA0_TRACK_SCALE = 0.05
SIGMA0_RADIUS_RATIO = 0.03
SIGMA0_POSE = 1e-3  # the start pose is the origin by definition: tiny, never zero (P stays positive definite)

# Slip handling: how much the wheels' yaw rate is down-weighted and their speed variance inflated.
SLIP_OMEGA_VAR_FACTOR = 1e4
SLIP_V_VAR_FACTOR = 100.0
# When both wheels did not move at all over an interval the rover is standing still (a
# zero-velocity update): the longer the standstill, the better the encoders bound v and omega
# (see update_wheels), down to these floors; that is what makes the gyro bias observable at rest.
STATIONARY_SIGMA_V_M_S = 1e-3
STATIONARY_SIGMA_OMEGA_RAD_S = 1e-3
# A sensor rejected this many times in a row is accepted again: the filter, not the sensor,
# is then the likelier culprit (robot_localization has no such escape and can lock out).
MAX_CONSECUTIVE_REJECTS = 5
MAX_PREDICT_STEP_S = 0.1
# Longer gaps are not integrated (predict_to): at most this / MAX_PREDICT_STEP_S sub-steps per call.
MAX_PREDICT_GAP_S = 1.0
EXTRAPOLATE_MAX_S = 0.2  # publishing: how far past the last measurement the pose may move
COAST_S = 0.3  # a rover whose motors lost power stops within about this (distance = speed x this, 1 sigma)
TRAPEZOID_MAX_DT_S = 0.2  # longer gyro gaps: no trapezoid correction (the rate is not linear over them)
# A measurement stamped less than this after the state is applied at the state's time, without a
# prediction; the interval is predicted with the next one, so no time is lost. ATTITUDE and SCALED_IMU
# are stamped in milliseconds: a wheel reading of the same burst stamped in microseconds (PX4) lands up
# to a millisecond after the gyro's, and each such step was a whole covariance propagation that moved
# nothing. (ArduPilot's WHEEL_DISTANCE, 1000 * millis(), is never later than its ATTITUDE.) The
# trapezoid corrections of yaw and distance are cumulative: what this defers is made up at the next one.
SAME_INSTANT_S = 1e-3


@dataclass(frozen=True, slots=True)
class NoiseModel:
    """Measurement noise and gating (from [estimator])."""

    gyro_noise_rad_s: float = 0.005
    wheel_noise_m: float = 0.0005
    wheel_noise_fraction: float = 0.02
    gate_sigma: float = 4.0


# ---------------------------------------------------------------- pure models

def _arc_derivatives(d: float) -> tuple[float, float]:
    """d/dd of arc_factors(d): (a', b') with a = sin d / d, b = (1 - cos d) / d."""
    if abs(d) < 1e-3:
        d2 = d * d
        return -d / 3.0 + d * d2 / 30.0, 0.5 - d2 / 8.0 + d2 * d2 / 144.0
    s, c = math.sin(d), math.cos(d)
    return (d * c - s) / (d * d), (d * s - (1.0 - c)) / (d * d)


def _motion_step(x_m: float, y_m: float, yaw: float, v: float, w: float, dt_s: float
                 ) -> tuple[float, float, float, float, float, float, float, float, float]:
    """fx's new (x, y, yaw) and F_jacobian's six pose entries (d x, d y by yaw, v, omega), which share
    every intermediate; F[IYAW, IW] is dt_s. One function for fx, F_jacobian and predict_to."""
    ds, dyaw = v * dt_s, w * dt_s
    a, b = arc_factors(dyaw)
    da, db = _arc_derivatives(dyaw)
    c, s = math.cos(yaw), math.sin(yaw)
    fwd, left = ds * a, ds * b
    dfwd, dleft = ds * da * dt_s, ds * db * dt_s  # d/domega: dyaw = omega dt
    return (x_m + c * fwd - s * left, y_m + s * fwd + c * left, wrap_angle(yaw + dyaw),
            -s * fwd - c * left, c * fwd - s * left,  # d/dyaw
            dt_s * (c * a - s * b), dt_s * (s * a + c * b),  # d/dv: ds = v dt
            c * dfwd - s * dleft, s * dfwd + c * dleft)  # d/domega


def fx(x: Vec, dt_s: float) -> Vec:
    """Motion model: move along the arc of (v, omega) for dt_s; everything else is constant."""
    out = x.copy()
    out[IX], out[IY], out[IYAW] = _motion_step(float(x[IX]), float(x[IY]), float(x[IYAW]), float(x[IV]),
                                               float(x[IW]), dt_s)[:3]
    return out


def _write_jacobian(F: Mat, step: tuple[float, ...], dt_s: float) -> None:
    F[IX, IYAW], F[IY, IYAW], F[IX, IV], F[IY, IV], F[IX, IW], F[IY, IW] = step[3:]
    F[IYAW, IW] = dt_s


def F_jacobian(x: Vec, dt_s: float, out: Mat | None = None) -> Mat:
    """d fx / d x; written into `out` (an identity matrix, or one this function filled before: it
    always writes the same entries) to spare an allocation per step."""
    F = np.eye(x.shape[0]) if out is None else out
    _write_jacobian(F, _motion_step(float(x[IX]), float(x[IY]), float(x[IYAW]), float(x[IV]), float(x[IW]),
                                    dt_s), dt_s)
    return F


def process_noise_diagonal(x: Vec | Floats, dt_s: float) -> list[float]:
    """The diagonal of Q for one step (Q has nothing off the diagonal)."""
    dist_m = abs(float(x[IV])) * dt_s
    turn_rad = abs(float(x[IW])) * dt_s
    pos = Q_POS_PER_M * dist_m
    q = [pos, pos, Q_YAW_PER_M * dist_m + Q_YAW_PER_RAD * turn_rad, Q_V * dt_s, Q_OMEGA * dt_s, Q_BIAS * dt_s]
    if len(x) == N_CAL:
        q += [Q_CAL * dt_s, Q_CAL * dt_s]
    return q


def process_noise(x: Vec, dt_s: float) -> Mat:
    """Q for one step: random walks of v, omega, bias, calibration; pose noise grows with speed."""
    return np.diag(process_noise_diagonal(x, dt_s))


def _geometry(x: Vec | Floats) -> tuple[float, float]:
    """(track_scale, radius_ratio); nominal (1, 1) without calibration states."""
    if len(x) == N_CAL:
        return float(x[IKT]), float(x[IKR])
    return 1.0, 1.0


def wheel_speeds_from_state(x: Vec | Floats, track_width_m: float) -> tuple[float, float]:
    """Nominal-geometry wheel surface speeds (left, right) the state predicts."""
    kt, q = _geometry(x)
    sl, sr = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
    v, w = float(x[IV]), float(x[IW])
    half = 0.5 * track_width_m * kt * w
    return (v - half) / sl, (v + half) / sr


def hx_wheels(x: Vec, track_width_m: float) -> Vec:
    """Predicted z_wheels = [v_wheel, omega_wheel] (nominal track)."""
    ul, ur = wheel_speeds_from_state(x, track_width_m)
    return np.array([0.5 * (ul + ur), (ur - ul) / track_width_m])


def _wheel_rows(x: Vec | Floats, track_width_m: float) -> tuple[list[float], list[float]]:
    """The two rows of H_wheels as floats (the filter's form)."""
    n = len(x)
    kt, q = _geometry(x)
    L = track_width_m
    sl, sr = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
    v, w = float(x[IV]), float(x[IW])
    # d ul / d x and d ur / d x at IV, IW (and IKT, IKR with calibration states)
    dul_v, dur_v = 1.0 / sl, 1.0 / sr
    dul_w, dur_w = -0.5 * L * kt / sl, 0.5 * L * kt / sr
    row_v = [0.0, 0.0, 0.0, 0.5 * (dul_v + dur_v), 0.5 * (dul_w + dur_w), 0.0]
    row_w = [0.0, 0.0, 0.0, (dur_v - dul_v) / L, (dur_w - dul_w) / L, 0.0]
    if n == N_CAL:
        dul_kt, dur_kt = -0.5 * L * w / sl, 0.5 * L * w / sr
        dsl, dsr = -2.0 / (1.0 + q) ** 2, 2.0 / (1.0 + q) ** 2
        dul_kr = -(v - 0.5 * L * kt * w) / (sl * sl) * dsl
        dur_kr = -(v + 0.5 * L * kt * w) / (sr * sr) * dsr
        row_v += [0.5 * (dul_kt + dur_kt), 0.5 * (dul_kr + dur_kr)]
        row_w += [(dur_kt - dul_kt) / L, (dur_kr - dul_kr) / L]
    return row_v, row_w


def H_wheels(x: Vec, track_width_m: float) -> Mat:
    """d hx_wheels / d x."""
    return np.array(_wheel_rows(x, track_width_m))


def hx_gyro(x: Vec) -> Vec:
    return np.array([x[IW] + x[IB]])


def H_gyro(x: Vec) -> Mat:
    H = np.zeros((1, x.shape[0]))
    H[0, IW] = H[0, IB] = 1.0
    return H


def _wheel_z(d_left_m: float, d_right_m: float, dt_s: float, track_width_m: float) -> tuple[float, float]:
    ul, ur = d_left_m / dt_s, d_right_m / dt_s
    return 0.5 * (ul + ur), (ur - ul) / track_width_m


def wheel_measurement(d_left_m: float, d_right_m: float, dt_s: float, track_width_m: float) -> Vec:
    """z_wheels from the nominal wheel distance increments over dt_s."""
    return np.array(_wheel_z(d_left_m, d_right_m, dt_s, track_width_m))


def _wheel_r(d_left_m: float, d_right_m: float, dt_s: float, track_width_m: float,
             noise: NoiseModel) -> tuple[float, float, float]:
    """(R00, R01, R11) of wheel_noise."""
    base = (math.sqrt(2.0) * noise.wheel_noise_m / dt_s) ** 2  # two readings per increment
    vl = base + (noise.wheel_noise_fraction * d_left_m / dt_s) ** 2
    vr = base + (noise.wheel_noise_fraction * d_right_m / dt_s) ** 2
    L = track_width_m
    return 0.25 * (vl + vr), 0.5 * (vr - vl) / L, (vl + vr) / (L * L)


def wheel_noise(d_left_m: float, d_right_m: float, dt_s: float, track_width_m: float,
                noise: NoiseModel) -> Mat:
    """R of z_wheels: per-wheel speed variance (reading noise / dt and a fraction of the speed)."""
    r00, r01, r11 = _wheel_r(d_left_m, d_right_m, dt_s, track_width_m, noise)
    return np.array([[r00, r01], [r01, r11]])


# ---------------------------------------------------------------- the filter

_FILTER_CLASS: type | None = None  # filterpy's ExtendedKalmanFilter, once imported
_BACKGROUND = False  # the process imports it in its own thread: do not block on it here


def filter_class() -> type:
    """filterpy's ExtendedKalmanFilter (imported here on first use)."""
    global _FILTER_CLASS
    if _FILTER_CLASS is None:
        from filterpy.kalman import ExtendedKalmanFilter

        _FILTER_CLASS = ExtendedKalmanFilter
    return _FILTER_CLASS


def load_in_background() -> None:
    """Say that the caller imports filterpy in a thread of its own (then calls filter_class() there):
    filters built meanwhile do not wait for it (module docstring)."""
    global _BACKGROUND
    _BACKGROUND = True


class _Holder:
    """x and P until filterpy's filter is imported (module docstring)."""

    def __init__(self) -> None:
        self.x: Vec = np.zeros(0)
        self.P: Mat = np.zeros((0, 0))


# The filter's arithmetic runs in floats on the buffers of filterpy's x and P (class docstring).
_XS = struct.Struct(f"{N_CAL}d")
_PS = struct.Struct(f"{N_CAL * N_CAL}d")


def _propagate(kernel: EkfKernel, x: list[float], p: list[float], dt_s: float, q: list[float], n: int = N_CAL
               ) -> None:
    """x = fx(x, dt_s) and P = F P F' + diag(q), in place, p the row-major n x n covariance: all of it, or
    the block of the first n >= 5 states (x, y, yaw, v, omega: F moves nothing else, so that block of
    F P F' is computed from that block of P alone, with the same operations as in the whole)."""
    x[IX], x[IY], x[IYAW], f02, f12, f03, f13, f04, f14 = _motion_step(x[IX], x[IY], x[IYAW], x[IV], x[IW], dt_s)
    kernel.propagate_cov(p, n, f02, f12, f03, f13, f04, f14, dt_s, q)


class EkfKernel(Protocol):
    """The filter's covariance arithmetic: PythonKernel, or the same in C (NATIVE_KERNEL, module docstring).
    Lists of floats in and out, row-major matrices; the functions may change their list arguments."""

    def propagate_cov(self, p: list[float], n: int, f02: float, f12: float, f03: float, f13: float, f04: float,
                      f14: float, dt_s: float, q: list[float], /) -> None: ...

    def column_sum(self, p: list[float], n: int, i: int, j: int, c: float, /) -> list[float]: ...

    def wheel_columns(self, p: list[float], hv3: float, hv4: float, hv6: float, hv7: float, hw3: float,
                      hw4: float, hw6: float, hw7: float, /) -> tuple[list[float], list[float]]: ...

    def whiten(self, u: list[float], w: list[float], c00: float, c10: float, c11: float, /
               ) -> tuple[list[float], list[float]]: ...

    def fuse(self, x: list[float], p: list[float], mask: list[float], fixed: list[int], a: list[float], e0: float,
             b: list[float] | None, e1: float, /) -> tuple[list[float], list[float]]: ...


class PythonKernel:
    """The reference kernel, in Python: what every platform runs without a C compiler, and what the C
    kernel is held to bit for bit (same operations, same order)."""

    @staticmethod
    def propagate_cov(p: list[float], n: int, f02: float, f12: float, f03: float, f13: float, f04: float,
                      f14: float, dt_s: float, q: list[float], /) -> None:
        """P = F P F' + diag(q), in place; F is the identity but for 7 entries (F_jacobian: f02 = F[x, yaw],
        f13 = F[y, v], ..., and F[yaw, omega] = dt_s), so F P changes the rows x, y, yaw only and (F P) F'
        their columns only: about 60 products instead of two 8 x 8 matrix products. The block of x, y,
        yaw is taken from its upper triangle and the columns from the rows, so P stays exactly symmetric."""
        r2, r3, r4 = p[2 * n:3 * n], p[3 * n:4 * n], p[4 * n:5 * n]
        t0 = [a + f02 * b + f03 * c + f04 * d for a, b, c, d in zip(p[0:n], r2, r3, r4, strict=True)]
        t1 = [a + f12 * b + f13 * c + f14 * d for a, b, c, d in zip(p[n:2 * n], r2, r3, r4, strict=True)]
        t2 = [b + dt_s * d for b, d in zip(r2, r4, strict=True)]
        n01 = t0[1] + f12 * t0[2] + f13 * t0[3] + f14 * t0[4]
        n02 = t0[2] + dt_s * t0[4]
        n12 = t1[2] + dt_s * t1[4]
        t0[0] += f02 * t0[2] + f03 * t0[3] + f04 * t0[4] + q[0]
        t1[1] += f12 * t1[2] + f13 * t1[3] + f14 * t1[4] + q[1]
        t2[2] += dt_s * t2[4] + q[2]
        t0[1], t0[2], t1[0], t1[2], t2[0], t2[1] = n01, n02, n01, n12, n02, n12
        p[0:n], p[n:2 * n], p[2 * n:3 * n] = t0, t1, t2
        for i in range(3, n):
            k = n * i
            p[k], p[k + 1], p[k + 2] = t0[i], t1[i], t2[i]
            p[k + i] += q[i]

    @staticmethod
    def column_sum(p: list[float], n: int, i: int, j: int, c: float, /) -> list[float]:
        """(P[:, i] + P[:, j]) / c: the gyro's P H' / sqrt(S) (H picks omega and bias)."""
        return [(u + v) / c for u, v in zip(p[i::n], p[j::n], strict=True)]

    @staticmethod
    def wheel_columns(p: list[float], hv3: float, hv4: float, hv6: float, hv7: float, hw3: float, hw4: float,
                      hw6: float, hw7: float, /) -> tuple[list[float], list[float]]:
        """The wheels' P H' as two columns: H's rows are zero but at v, omega and the two geometry states."""
        n = N_CAL
        u = [p[k + IV] * hv3 + p[k + IW] * hv4 + p[k + IKT] * hv6 + p[k + IKR] * hv7 for k in range(0, n * n, n)]
        w = [p[k + IV] * hw3 + p[k + IW] * hw4 + p[k + IKT] * hw6 + p[k + IKR] * hw7 for k in range(0, n * n, n)]
        return u, w

    @staticmethod
    def whiten(u: list[float], w: list[float], c00: float, c10: float, c11: float, /
               ) -> tuple[list[float], list[float]]:
        """The columns [u w] times C^-T, C = [[c00, 0], [c10, c11]] the Cholesky factor of S."""
        a = [ui / c00 for ui in u]
        return a, [(wi - c10 * ai) / c11 for wi, ai in zip(w, a, strict=True)]

    @staticmethod
    def fuse(x: list[float], p: list[float], mask: list[float], fixed: list[int], a: list[float], e0: float,
             b: list[float] | None, e1: float, /) -> tuple[list[float], list[float]]:
        """x + M [a b] e and P - (a a' + b b') but at the `fixed` entries (WheelGyroEKF._fuse says why).
        Every entry in one pass: a_i a_j = a_j a_i exactly, so P, exactly symmetric as every writer here
        leaves it, stays so."""
        if b is None:
            x = [xi + mi * ai * e0 for xi, mi, ai in zip(x, mask, a, strict=True)]
            out = list(map(sub, p, [ai * aj for ai in a for aj in a]))
        else:
            x = [xi + mi * (ai * e0 + bi * e1) for xi, mi, ai, bi in zip(x, mask, a, b, strict=True)]
            out = list(map(sub, p, [ai * aj + bi * bj for ai, bi in zip(a, b, strict=True)
                                    for aj, bj in zip(a, b, strict=True)]))
        for k in fixed:
            out[k] = p[k]
        return x, out


class NativeKernel:
    """The C kernel (_ekf_kernel.c) as an EkfKernel: its module's functions. A filter holds this rather than
    the module, which cannot be deep-copied (tests copy whole cores); a kernel is stateless, so every copy
    of a filter shares it."""

    def __init__(self) -> None:
        from rover_bridge.estimate import _ekf_kernel as k  # ImportError where the install did not build it

        self.propagate_cov = k.propagate_cov
        self.column_sum = k.column_sum
        self.wheel_columns = k.wheel_columns
        self.whiten = k.whiten
        self.fuse = k.fuse

    def __copy__(self) -> NativeKernel:
        return self

    def __deepcopy__(self, memo: dict[int, object]) -> NativeKernel:
        return self


def _native_kernel() -> EkfKernel | None:
    """The C kernel, where the install built it (pyproject.toml: a C compiler was found); else None."""
    try:
        kernel: EkfKernel = NativeKernel()
    except ImportError:
        return None
    return kernel


PYTHON_KERNEL: EkfKernel = PythonKernel()
NATIVE_KERNEL: EkfKernel | None = _native_kernel()
DEFAULT_KERNEL: EkfKernel = NATIVE_KERNEL if NATIVE_KERNEL is not None else PYTHON_KERNEL


def kernel_name(kernel: EkfKernel) -> str:
    """"native" (C) or "python": what the stats and the start-up log say."""
    return "python" if isinstance(kernel, PythonKernel) else "native"


def _rows(p: Floats, n: int = N_CAL) -> list[list[float]]:
    return [list(p[i:i + n]) for i in range(0, n * n, n)]


@dataclass(frozen=True, slots=True)
class WheelUpdate:
    """What happened to one wheel measurement."""

    accepted: bool
    slip: bool
    stationary: bool
    slip_d2: float  # squared Mahalanobis distance of the wheel/gyro yaw-rate disagreement
    d2: float  # squared Mahalanobis distance of the (possibly down-weighted) innovation


class WheelGyroEKF:
    """filterpy's ExtendedKalmanFilter with the models above, gating and slip handling.

    Time is an argument everywhere (`t_s`, any monotonic time line); the filter keeps the time of
    its state and never moves backwards: a measurement older than the state, or less than
    SAME_INSTANT_S newer, is applied at the state's time (a few ms of skew between streams is far
    below what the model resolves).

    filterpy's filter holds the state: `ekf.x` (8) and `ekf.P` (8 x 8) are its two arrays, current
    after every call. The arithmetic of the running filter reads them into floats, computes in
    floats and writes them back, in place (one struct call each way): inside the running bridge a
    prediction and an update in numpy cost several times their tight-loop time (each numpy call
    runs cold code after a wake-up), and floats run in the interpreter loop the rest of the pass
    uses anyway. The matrix forms (fx, F_jacobian, hx_*, H_*, filterpy's update) are the reference
    the float forms are tested against. So the arrays are live: copy them to keep a snapshot.
    """

    def __init__(self, track_width_m: float, noise: NoiseModel | None = None, calibrate: bool = False,
                 pose: Pose2D | None = None, kernel: EkfKernel | None = None) -> None:
        if not (math.isfinite(track_width_m) and track_width_m > 0.0):
            raise ValueError(f"track_width_m must be a finite number > 0, got {track_width_m!r}")
        self.track_width_m = float(track_width_m)
        self.noise = noise if noise is not None else NoiseModel()
        self.calibrate = calibrate
        self.kernel = kernel if kernel is not None else DEFAULT_KERNEL
        n = N_CAL  # geometry states always: estimated with calibrate, considered without
        self.n = n
        self._consider: list[int] = [] if calibrate else [IKT, IKR]
        self.ekf: Any = filter_class()(dim_x=n, dim_z=1) if _FILTER_CLASS or not _BACKGROUND else _Holder()
        self._held = isinstance(self.ekf, _Holder)
        self.time_s: float | None = None
        self._still_since_s: float | None = None  # start of the current standstill (wheels not moving)
        # Trapezoid bookkeeping between gyro samples (see update_gyro).
        self._gyro_prev: tuple[float, float] | None = None  # (time, omega after that update)
        self._turned_since_gyro_rad = 0.0
        self._wheels_prev: tuple[float, float] | None = None  # (time, v after that update)
        self._moved_since_wheels_m = 0.0
        self._gyro_var = self.noise.gyro_noise_rad_s ** 2
        # 1 for estimated states, 0 for considered ones: masks the gain.
        self._mask = [0.0 if i in self._consider else 1.0 for i in range(n)]
        # Entries of P between two considered states: no update changes them (see _fuse).
        self._fixed = [n * i + j for i in self._consider for j in self._consider]
        self._gate2 = self.noise.gate_sigma ** 2
        self.rejects_in_row = {"wheels": 0, "gyro": 0}
        self.predict_steps = 0  # prediction sub-steps so far: the work the filter did (bounded per call)
        self._init_state(pose if pose is not None else Pose2D())

    def _init_state(self, pose: Pose2D) -> None:
        x = np.zeros(self.n)
        x[IX], x[IY], x[IYAW] = pose.x_m, pose.y_m, pose.yaw_rad
        sig = [SIGMA0_POSE, SIGMA0_POSE, SIGMA0_POSE, SIGMA0_V, SIGMA0_OMEGA, SIGMA0_BIAS]
        if self.n == N_CAL:
            x[IKT] = x[IKR] = 1.0
            sig += [SIGMA0_TRACK_SCALE, SIGMA0_RADIUS_RATIO]
        self.ekf.x = x
        self.ekf.P = np.diag(np.square(sig))

    def _adopt(self, cls: type) -> None:
        """Move x and P into filterpy's filter, now imported."""
        held = self.ekf
        ekf = cls(dim_x=self.n, dim_z=1)
        ekf.x, ekf.P = held.x, held.P
        self.ekf, self._held = ekf, False

    def _load(self) -> tuple[list[float], list[float]]:
        """x and P (row-major) as floats."""
        return list(_XS.unpack_from(self.ekf.x)), list(_PS.unpack_from(self.ekf.P))

    def _store(self, x: Floats, p: Floats) -> None:
        """Write x and P back into filterpy's arrays, in place."""
        _XS.pack_into(self.ekf.x, 0, *x)
        _PS.pack_into(self.ekf.P, 0, *p)

    # -- accessors
    @property
    def x(self) -> Vec:
        return self.ekf.x  # type: ignore[no-any-return]

    @property
    def P(self) -> Mat:
        return self.ekf.P  # type: ignore[no-any-return]

    @property
    def pose(self) -> Pose2D:
        x, y, yaw = _XS.unpack_from(self.ekf.x)[:3]
        return Pose2D(x, y, yaw)

    # -- time
    def predict_to(self, t_s: float) -> None:
        """Move the state to t_s. Work is bounded whatever t_s is: a gap longer than MAX_PREDICT_GAP_S
        is a discontinuity (the motion restarts from the held pose, as after a silent link), never
        integrated step by step; a time that is not finite is ignored."""
        self._store(*self._predicted(t_s))

    def _predicted(self, t_s: float) -> tuple[list[float], list[float]]:
        """predict_to(t_s) as floats: the caller stores them (or changes them first)."""
        if self._held and _FILTER_CLASS is not None:
            self._adopt(_FILTER_CLASS)
        if not math.isfinite(t_s):
            return self._load()
        if self.time_s is None:
            self.time_s = t_s
            return self._load()
        total = t_s - self.time_s
        if total < SAME_INSTANT_S:
            return self._load()
        if total > MAX_PREDICT_GAP_S:
            self.restart_motion(t_s)
            return self._load()
        # Sub-steps through a gap, so the covariance grows as the random walks really do (one long
        # step would add the speed noise to the speed only, not to the position it moves).
        steps = max(1, math.ceil(total / MAX_PREDICT_STEP_S))
        dt = total / steps
        self.predict_steps += steps
        x, p = self._load()
        kernel = self.kernel
        for _ in range(steps):
            v, w = x[IV], x[IW]
            _propagate(kernel, x, p, dt, process_noise_diagonal(x, dt))
            self._turned_since_gyro_rad += w * dt
            self._moved_since_wheels_m += v * dt
        self.time_s = t_s
        return x, p

    def extrapolate(self, t_s: float, block: int = N_CAL) -> tuple[list[float], list[list[float]]]:
        """State and covariance (as rows) predicted to t_s, without changing the filter (for publishing);
        with `block` (5 to 8), the covariance of the first `block` states only (ODOMETRY's: PUBLISHED)."""
        if not PUBLISHED <= block <= N_CAL:  # the motion model moves the first five: a smaller block is not one
            raise ValueError(f"block must be {PUBLISHED} to {N_CAL} states, got {block}")
        x, p = self._load()
        if block < N_CAL:
            p = [v for i in range(0, N_CAL * block, N_CAL) for v in p[i:i + block]]
        if self.time_s is None or t_s <= self.time_s:
            return x, _rows(p, block)
        dt = t_s - self.time_s
        # The pose moves on for at most EXTRAPOLATE_MAX_S past the last measurement (a silent link
        # may be a rebooting autopilot whose motors stopped); the covariance keeps growing.
        scale = max(1.0, dt / MAX_PREDICT_STEP_S)
        _propagate(self.kernel, x, p, min(dt, EXTRAPOLATE_MAX_S), [q * scale for q in process_noise_diagonal(x, dt)],
                   block)
        return x, _rows(p, block)

    def restart_motion(self, t_s: float, new_time_s: float | None = None) -> None:
        """After an autopilot reboot: continue from the pose published now, speeds unknown near zero.

        The motors lose power while the board restarts, so the rover has coasted to a stop somewhere
        near the held pose; nothing measured the silence, so the pose covariance takes the coasting
        distance and the speeds restart at zero with their initial uncertainty.
        """
        held_m = float(self.ekf.x[IV]) * min(max(0.0, t_s - (self.time_s or t_s)), EXTRAPOLATE_MAX_S)
        x, P = self.ekf.x, self.ekf.P
        x[:], P[:] = self.extrapolate(t_s)  # in place: filterpy's arrays stay the ones holding the state
        coast_m = abs(float(x[IV])) * COAST_S
        coast_rad = abs(float(x[IW])) * COAST_S
        x[IV] = x[IW] = 0.0
        for i in (IV, IW):
            P[i, :] = 0.0
            P[:, i] = 0.0
        P[IV, IV], P[IW, IW] = SIGMA0_V**2, SIGMA0_OMEGA**2
        P[IX, IX] += coast_m**2
        P[IY, IY] += coast_m**2
        P[IYAW, IYAW] += coast_rad**2
        # The held pose is at t_s; the filter's clock goes on from new_time_s (an autopilot that
        # rebooted restarts its boot clock near zero).
        self.time_s = t_s if new_time_s is None else new_time_s
        self._gyro_prev = self._wheels_prev = None
        self._still_since_s = None
        self._turned_since_gyro_rad = 0.0
        # The held pose already moved this far of the wheels' next interval.
        self._moved_since_wheels_m += held_m

    def wheel_baseline(self) -> None:
        """The next wheel interval starts here (first reading, re-base after a reboot or resync)."""
        self._wheels_prev = None
        self._moved_since_wheels_m = 0.0

    # -- updates
    def _gate(self, sensor: str, d2: float) -> bool:
        if d2 <= self._gate2 or self.rejects_in_row[sensor] + 1 >= MAX_CONSECUTIVE_REJECTS:
            self.rejects_in_row[sensor] = 0
            return True
        self.rejects_in_row[sensor] += 1
        return False

    def _fuse(self, x: list[float], p: list[float], a: list[float], e0: float, b: list[float] | None = None,
              e1: float = 0.0) -> tuple[list[float], list[float]]:
        """EKF update of (x, P) in floats, for a measurement of one or two rows given in whitened form:
        with S = H P H' + R = C C' (C lower triangular, Cholesky), the columns [a b] of P H' C^-T and
        e = C^-1 y (y the innovation); for one row, a = P H' / sqrt(S), e0 = y / sqrt(S) and no b.

        Without calibration the geometry states are *consider* states (Schmidt-Kalman): their gain
        rows are zero, so they stay at nominal, but their uncertainty still weighs every update - a
        wheel-geometry error is systematic, and without this the filter would average it over
        thousands of samples and learn it as gyro bias (2 % radius error at 0.8 m/s looks like
        0.05 rad/s of bias). With calibration nothing is considered and this is the textbook update
        (tests check it against filterpy's ExtendedKalmanFilter.update).

        The gain is K = M P H' S^-1 (M the 0/1 mask of estimated states), so x moves by
        M [a b] e. The covariance is Joseph's form, exact for any gain: with G = P H' S^-1 H P =
        a a' + b b', P - K H P - P H' K' + K S K' is P - (M G + G M - M G M): G everywhere but
        between two considered states, where P stays."""
        x, p = self.kernel.fuse(x, p, self._mask, self._fixed, a, e0, b, e1)
        x[IYAW] = wrap_angle(x[IYAW])
        return x, p

    def _gyro_innovation(self, x: Floats, p: Floats, omega_rad_s: float) -> tuple[float, float, float]:
        """(y, S, d2) of a gyro sample: H = d(omega + bias)/dx picks two states, so all of it is scalar."""
        n = self.n
        y = omega_rad_s - (x[IW] + x[IB])
        S = p[n * IW + IW] + 2.0 * p[n * IW + IB] + p[n * IB + IB] + self._gyro_var
        return y, S, y * y / S

    def update_gyro(self, t_s: float, omega_rad_s: float) -> bool:
        """Fuse one gyro yaw rate (CCW +, rad/s). False when it failed the gate (not fused)."""
        x, p = self._predicted(t_s)
        y, S, d2 = self._gyro_innovation(x, p, omega_rad_s)
        if not (S > 0.0 and self._gate("gyro", d2)):  # S > 0 unless P is broken: never fused then
            self._store(x, p)
            return False
        # H picks omega and bias: P H' is the sum of their two columns.
        n = self.n
        c = math.sqrt(S)
        x, p = self._fuse(x, p, self.kernel.column_sum(p, n, IW, IB, c), y / c)
        # Trapezoid: the prediction turned at piecewise-constant rates, while the body's rate moved
        # from the last gyro sample's to this one's. Without this every change of yaw rate leaves a
        # heading error of (change x half a sample period), 1.3 deg per spin at 20 Hz.
        omega_now = x[IW]
        prev = self._gyro_prev
        if prev is not None and 0.0 < t_s - prev[0] <= TRAPEZOID_MAX_DT_S:
            missed = 0.5 * (prev[1] + omega_now) * (t_s - prev[0]) - self._turned_since_gyro_rad
            x[IYAW] = wrap_angle(x[IYAW] + missed)
        self._store(x, p)
        self._gyro_prev = (t_s, omega_now)
        self._turned_since_gyro_rad = 0.0
        return True

    def slip_d2(self, z_omega_rad_s: float, r11: float, gyro_omega_rad_s: float | None,
                gyro_spread_rad_s: float = 0.0, state: tuple[Floats, Floats] | None = None) -> float:
        """Squared Mahalanobis distance between the wheels' yaw rate (z_omega_rad_s, variance r11) and
        the gyro's (bias removed).

        The reference is what the wheels would read if the body turned at gyro - bias, with the
        state's geometry; its variance adds the gyro noise, the bias and the calibration uncertainty.
        """
        if gyro_omega_rad_s is None:
            return 0.0
        x, p = self._load() if state is None else state
        n = self.n
        # hx_wheels[1] and H_wheels[1] at x with omega = gyro - bias, in floats (tests hold it to the two
        # functions).
        L = self.track_width_m
        kt, q = _geometry(x)
        sl, sr = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
        v, w = x[IV], gyro_omega_rad_s - x[IB]
        half = 0.5 * L * kt * w
        predicted = ((v + half) / sr - (v - half) / sl) / L
        h_w = (0.5 * L * kt / sr - -0.5 * L * kt / sl) / L
        # The spread of the gyro samples over the interval covers an omega that changed within it.
        var = r11 + h_w ** 2 * (self._gyro_var + p[n * IB + IB] + gyro_spread_rad_s**2)
        if n == N_CAL:
            g0 = (0.5 * L * w / sr - -0.5 * L * w / sl) / L
            dsl, dsr = -2.0 / (1.0 + q) ** 2, 2.0 / (1.0 + q) ** 2
            g1 = (-(v + 0.5 * L * kt * w) / (sr * sr) * dsr - -(v - 0.5 * L * kt * w) / (sl * sl) * dsl) / L
            var += g0 * g0 * p[n * IKT + IKT] + 2.0 * g0 * g1 * p[n * IKT + IKR] + g1 * g1 * p[n * IKR + IKR]
        y = z_omega_rad_s - predicted
        return y * y / var

    def update_wheels(self, t_s: float, d_left_m: float, d_right_m: float, dt_s: float,
                      gyro_omega_rad_s: float | None = None, gyro_spread_rad_s: float = 0.0) -> WheelUpdate:
        """Fuse the nominal wheel distance increments over the last dt_s (ending at t_s).

        `gyro_omega_rad_s` is the gyro's mean yaw rate over the same interval (raw, bias included),
        if any: it is the reference of the slip test; `gyro_spread_rad_s` half the range of the gyro
        samples over the interval (an omega that changed within it is not slip).
        """
        x, p = self._predicted(t_s)
        L = self.track_width_m
        stationary = d_left_m == 0.0 and d_right_m == 0.0
        if stationary:
            # Wheels that have not moved by a reading's resolution for T seconds bound the mean speed
            # by resolution / T: a rover still turning slowly at the end of a spin reads "still" for
            # one interval, and must not teach the filter a gyro bias. The bound tightens with T.
            if self._still_since_s is None:
                self._still_since_s = t_s - dt_s
            still_s = max(dt_s, t_s - self._still_since_s)
            res = self.noise.wheel_noise_m
            z0 = z1 = r01 = 0.0
            r00 = max(STATIONARY_SIGMA_V_M_S, res / still_s) ** 2
            r11 = max(STATIONARY_SIGMA_OMEGA_RAD_S, 2.0 * res / (L * still_s)) ** 2
        else:
            self._still_since_s = None
            z0, z1 = _wheel_z(d_left_m, d_right_m, dt_s, L)
            r00, r01, r11 = _wheel_r(d_left_m, d_right_m, dt_s, L, self.noise)
        slip_d2 = self.slip_d2(z1, r11, gyro_omega_rad_s, gyro_spread_rad_s, (x, p))
        # The wheels measure the interval's mean rate, the state is the rate at its end: while the
        # rate changes they differ by up to the change over the interval (a spin-up is not an outlier).
        r11 += gyro_spread_rad_s**2
        slip = slip_d2 > self._gate2 and not stationary
        if slip:
            r11 *= SLIP_OMEGA_VAR_FACTOR
            r01 *= math.sqrt(SLIP_OMEGA_VAR_FACTOR * SLIP_V_VAR_FACTOR)
            r00 *= SLIP_V_VAR_FACTOR
        n = self.n
        hv, hw = _wheel_rows(x, L)
        ul, ur = wheel_speeds_from_state(x, L)
        y0, y1 = z0 - 0.5 * (ul + ur), z1 - (ur - ul) / L
        # P H': H is zero but at v, omega and the two geometry states.
        hv3, hv4, hv6, hv7 = hv[IV], hv[IW], hv[IKT], hv[IKR]
        hw3, hw4, hw6, hw7 = hw[IV], hw[IW], hw[IKT], hw[IKR]
        u, w = self.kernel.wheel_columns(p, hv3, hv4, hv6, hv7, hw3, hw4, hw6, hw7)
        s00 = hv3 * u[IV] + hv4 * u[IW] + hv6 * u[IKT] + hv7 * u[IKR] + r00
        s01 = hv3 * w[IV] + hv4 * w[IW] + hv6 * w[IKT] + hv7 * w[IKR] + r01
        s11 = hw3 * w[IV] + hw4 * w[IW] + hw6 * w[IKT] + hw7 * w[IKR] + r11
        # S = C C' (Cholesky): the whitened innovation e = C^-1 y gives d2 = y' S^-1 y = |e|^2, and the
        # whitened columns of P H' the update (_fuse).
        c00 = math.sqrt(s00) if s00 > 0.0 else 0.0
        c10 = s01 / c00 if c00 > 0.0 else 0.0
        rest = s11 - c10 * c10
        if not (c00 > 0.0 and rest > 0.0):  # S is positive definite unless P is broken: never fused then
            self._store(x, p)
            return WheelUpdate(False, slip, stationary, slip_d2, math.inf)
        c11 = math.sqrt(rest)
        e0 = y0 / c00
        e1 = (y1 - c10 * e0) / c11
        d2 = e0 * e0 + e1 * e1
        # Only the velocity part decides the gate when the yaw part is already down-weighted.
        gate_d2 = e0 * e0 if slip else d2 / 2.0
        if not self._gate("wheels", gate_d2):
            self._store(x, p)
            self._moved_since_wheels_m = 0.0  # the next interval starts at this reading
            return WheelUpdate(False, slip, stationary, slip_d2, d2)
        a, b = self.kernel.whiten(u, w, c00, c10, c11)
        x, p = self._fuse(x, p, a, e0, b, e1)
        v_now = x[IV]
        prev = self._wheels_prev
        missed: float | None = None
        if not slip:
            # The wheels measured how far the rover went over the interval; the prediction moved it at
            # the state's speed, which is the mean speed of the interval before (the wheels measure
            # means), half an interval late in every change of speed: v * dt / 2 behind after each
            # acceleration (12 mm at 0.5 m/s and 20 Hz). The cumulative distances put it where it is.
            _kt, q = _geometry(x)
            sl, sr = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
            missed = 0.5 * (sl * d_left_m + sr * d_right_m) - self._moved_since_wheels_m
        elif prev is not None and 0.0 < t_s - prev[0] <= TRAPEZOID_MAX_DT_S:
            # Slipping wheels overstate the distance: trapezoid of the (down-weighted) speeds instead.
            missed = 0.5 * (prev[1] + v_now) * (t_s - prev[0]) - self._moved_since_wheels_m
        if missed is not None:
            yaw = x[IYAW]
            x[IX] += math.cos(yaw) * missed
            x[IY] += math.sin(yaw) * missed
        if slip:
            # Honest velocity variance: slipping wheels overstate the speed by an unknown amount.
            p[n * IV + IV] += (SLIP_V_VAR_FACTOR - 1.0) * r00 / SLIP_V_VAR_FACTOR
        self._store(x, p)
        self._wheels_prev = (t_s, v_now)
        self._moved_since_wheels_m = 0.0
        return WheelUpdate(True, slip, stationary, slip_d2, d2)

    # -- resets
    def set_pose(self, pose: Pose2D, sigma_m: float = SIGMA0_POSE,
                 sigma_yaw_rad: float = SIGMA0_POSE) -> None:
        """Put the pose at `pose` with a small uncertainty; velocities, bias and calibration are kept."""
        x, P = self.ekf.x, self.ekf.P
        x[IX], x[IY], x[IYAW] = pose.x_m, pose.y_m, wrap_angle(pose.yaw_rad)
        P[0:3, :] = 0.0
        P[:, 0:3] = 0.0
        P[IX, IX] = P[IY, IY] = sigma_m ** 2
        P[IYAW, IYAW] = sigma_yaw_rad ** 2

    def calibration(self) -> tuple[float, float, float, float]:
        """(track_scale, sigma, radius_ratio, sigma); nominal (1, prior sigma, 1, prior sigma) without calibration."""
        x, p = self._load()
        n = self.n
        return (x[IKT], math.sqrt(max(0.0, p[n * IKT + IKT])), x[IKR], math.sqrt(max(0.0, p[n * IKR + IKR])))
