"""The wheel + gyro EKF's models (pure): state layout, motion, measurements, Jacobians and noise.

State (rover-bridge's convention: x forward of the start pose, y left, yaw counter-clockwise)

    0 x_m   1 y_m   2 yaw_rad   3 v_m_s (forward)   4 omega_rad_s (CCW)   5 gyro_bias_rad_s
    6 track_scale    (effective track width / nominal)
    7 radius_ratio   (effective right wheel scale / left)
    8 wheel_yaw_error_rad   (the wheels' cumulative heading minus the true heading)

Motion: v and omega are random walks; the pose moves along the exact circular arc they describe
over dt (odometry.arc_factors), so a spin in place and a straight line are both exact. The wheels'
heading error grows by what the wheel geometry makes of (v, omega) minus omega: nothing with the
nominal geometry, a drift proportional to the distance (radius ratio) or the angle (track) otherwise.

Measurements
- wheels: z = [v_wheels, yaw_wheels]: the nominal wheel surface speed over the interval between two
  WHEEL_DISTANCE stamps, (l + r) / 2, and the heading the wheels have accumulated, the sum of
  (r - l) / L_nominal over every interval (the raw odometry's heading). The heading is cumulative on
  purpose: the encoders' quantisation does not add up in it (each reading's error is bounded), while
  as a rate per interval it is 20-70 times the gyro's noise and would leave the heading to the gyro
  alone. Predicted: v_wheels from (v, omega) and the geometry (mean wheel scale 1: the overall
  distance scale is not observable without an absolute reference), yaw_wheels = yaw + error.
- standstill (with the wheels' rows, once settled, while they are distrusted): z = omega = 0.
- gyro: z = omega + bias.

So the wheels hold the heading as long as they agree with the gyro; when they do not, the
geometry states (a disagreement that grows with the distance or the angle driven) or the error
state itself (slip: see ekf.py) take the difference, and the gyro holds the heading. The gyro's
bias is learnt wherever the wheels are trusted: at rest, driving straight and turning.

Every model is a pure function of the state (and dt, the track) so tests can check the Jacobians by
finite differences; filterpy's KalmanFilter runs them, linearised at the state (arc_ekf.py, ekf.py).
"""

# Kalman-filter notation (F, H, Q, R) reads better than pep8 names here.
# ruff: noqa: N802, N806
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from rover_bridge.odometry import arc_factors, wrap_angle

Vec = npt.NDArray[np.float64]
Mat = npt.NDArray[np.float64]
Floats = Sequence[float]
Rows = Sequence[Sequence[float]] | Mat  # a matrix as rows: a nested list, or an array (both index [i][j])

IX, IY, IYAW, IV, IW, IB, IKT, IKR, IWY = range(9)
N_STATES = 9
PUBLISHED = IW + 1  # the states ODOMETRY carries (x, y, yaw, v, omega): the covariance block it reads
GEOMETRY = (IKT, IKR)
_IDENTITY = np.eye(N_STATES)

# Process noise densities (per second). v and omega follow the sensors closely (a rover changes
# speed far faster than the filter would believe otherwise); bias and geometry drift slowly.
# Units: (m/s^2)^2 s, (rad/s^2)^2 s, (rad/s)^2/s, 1/s.
Q_V = 10.0
Q_OMEGA = 100.0
Q_BIAS = 1e-10
Q_GEOMETRY = 1e-10
# Pose noise that grows with the distance driven and the angle turned (uneven ground):
# variance per metre travelled / per radian turned.
Q_POS_PER_M = 1e-4  # m^2 / m
Q_YAW_PER_M = 1e-8  # rad^2 / m
Q_YAW_PER_RAD = 1e-8  # rad^2 / rad
# The wheels' heading error beyond their geometry (small slip, skid in turns): per metre, per radian.
Q_WHEEL_YAW_PER_M = 1e-8  # rad^2 / m
Q_WHEEL_YAW_PER_RAD = 1e-8  # rad^2 / rad

# Initial uncertainty (1 sigma) of the states that are not known at start.
SIGMA0_V = 0.5
SIGMA0_OMEGA = 1.0
SIGMA0_BIAS = 0.03
SIGMA0_POSE = 1e-3  # the start pose is the origin by definition: tiny, never zero (P stays positive definite)


@dataclass(frozen=True, slots=True)
class NoiseModel:
    """Measurement noise and gating (from [estimator])."""

    gyro_noise_rad_s: float = 0.005
    wheel_noise_m: float = 0.0001
    wheel_noise_fraction: float = 0.02
    gate_sigma: float = 4.0


@dataclass(frozen=True, slots=True)
class GeometryPrior:
    """How far the profile's wheel geometry may be off (1 sigma): the filter learns the rest."""

    track_scale: float
    radius_ratio: float


# ---------------------------------------------------------------- motion

def _arc_derivatives(d: float) -> tuple[float, float]:
    """d/dd of arc_factors(d): (a', b') with a = sin d / d, b = (1 - cos d) / d."""
    if abs(d) < 1e-3:
        d2 = d * d
        return -d / 3.0 + d * d2 / 30.0, 0.5 - d2 / 8.0 + d2 * d2 / 144.0
    s, c = math.sin(d), math.cos(d)
    return (d * c - s) / (d * d), (d * s - (1.0 - c)) / (d * d)


def _geometry_factors(q: float) -> tuple[float, float, float, float]:
    """(a, c, da/dq, dc/dq) for a radius ratio q: with s_l = 2 / (1 + q), s_r = 2 q / (1 + q) the wheel
    scales (mean 1), a = (1/s_l + 1/s_r) / 2 = (1 + q)^2 / 4q and c = 1/s_r - 1/s_l = (1 - q^2) / 2q."""
    if q == 1.0:  # the nominal geometry, most of the time
        return 1.0, 0.0, 0.0, -1.0
    return ((1.0 + q) ** 2 / (4.0 * q), (1.0 - q * q) / (2.0 * q), 0.25 * (1.0 - 1.0 / (q * q)),
            -0.5 * (1.0 + 1.0 / (q * q)))


def wheel_rates(x: Vec | Floats, track_width_m: float) -> tuple[float, float]:
    """(v, omega) the wheels read with the nominal geometry when the body moves at the state's (v, omega):
    the left and right surface speeds are (v -+ omega kt L / 2) / s_l,r."""
    return wheel_rates_of(float(x[IV]), float(x[IW]), float(x[IKT]), float(x[IKR]), track_width_m)


def wheel_rates_of(v: float, w: float, kt: float, q: float, track_width_m: float) -> tuple[float, float]:
    """wheel_rates of (v, omega, track scale, radius ratio) given as floats (a state already unpacked)."""
    a, c, _, _ = _geometry_factors(q)
    return a * v + 0.25 * c * kt * w * track_width_m, c * v / track_width_m + a * kt * w


def wheel_rate_partials(v: float, w: float, kt: float, q: float, track_width_m: float
                        ) -> tuple[tuple[float, float, float, float], tuple[float, float, float, float]]:
    """The nonzero entries of d wheel_rates / d x, by (v, omega, track scale, radius ratio): the speed's
    row, then the yaw rate's."""
    a, c, da, dc = _geometry_factors(q)
    L = track_width_m
    return ((a, 0.25 * c * kt * L, 0.25 * c * w * L, da * v + 0.25 * dc * kt * w * L),
            (c / L, a * kt, a * w, dc * v / L + da * kt * w))


def wheel_rates_jacobian(x: Vec | Floats, track_width_m: float) -> Mat:
    """d wheel_rates / d x (2 x N_STATES)."""
    J = np.zeros((2, N_STATES))
    for row, entries in enumerate(wheel_rate_partials(float(x[IV]), float(x[IW]), float(x[IKT]), float(x[IKR]),
                                                      track_width_m)):
        J[row, IV], J[row, IW], J[row, IKT], J[row, IKR] = entries
    return J


def motion(x: Vec, dt_s: float, track_width_m: float) -> tuple[Vec, Mat]:
    """Motion model and its Jacobian, (fx, F): move along the arc of (v, omega) for dt_s; the wheels' heading
    error grows by what they make of the motion; everything else is constant."""
    px, py, yaw, v, w, bias, kt, q, wheel_yaw = x.tolist()
    ds, dyaw = v * dt_s, w * dt_s
    a, b = arc_factors(dyaw)
    da, db = _arc_derivatives(dyaw)
    c, s = math.cos(yaw), math.sin(yaw)
    fwd, left = ds * a, ds * b
    dfwd, dleft = ds * da * dt_s, ds * db * dt_s  # d/domega: dyaw = omega dt
    (_, _, _, _), (r_v, r_w, r_kt, r_kr) = wheel_rate_partials(v, w, kt, q, track_width_m)
    out = np.array((px + (c * fwd - s * left), py + (s * fwd + c * left), wrap_angle(yaw + dyaw), v, w, bias, kt, q,
                    wheel_yaw + (wheel_rates_of(v, w, kt, q, track_width_m)[1] - w) * dt_s))
    F = _IDENTITY.copy()
    F[IX, IYAW], F[IY, IYAW] = -s * fwd - c * left, c * fwd - s * left
    F[IX, IV], F[IY, IV] = dt_s * (c * a - s * b), dt_s * (s * a + c * b)
    F[IX, IW], F[IY, IW] = c * dfwd - s * dleft, s * dfwd + c * dleft
    F[IYAW, IW] = dt_s
    F[IWY, IV], F[IWY, IW], F[IWY, IKT], F[IWY, IKR] = r_v * dt_s, (r_w - 1.0) * dt_s, r_kt * dt_s, r_kr * dt_s
    return out, F


def fx(x: Vec, dt_s: float, track_width_m: float) -> Vec:
    """The motion model (motion)."""
    return motion(x, dt_s, track_width_m)[0]


def F_jacobian(x: Vec, dt_s: float, track_width_m: float) -> Mat:
    """d fx / d x (motion)."""
    return motion(x, dt_s, track_width_m)[1]


def ahead(x: Vec, dt_s: float, accel_m_s2: float, alpha_rad_s2: float, track_width_m: float
          ) -> tuple[Vec, Mat]:
    """The state moved on by dt_s (publishing's look-ahead) along the arc of the speeds their rates of
    change carry them to at dt_s / 2, the speeds themselves kept, and the Jacobian of that motion: wheels
    and gyro are read at 20-50 Hz, and a spin that starts or stops changes its rate by 10 rad/s^2 (half
    a degree over 40 ms at a constant rate)."""
    moving = x.copy()
    moving[IV] += 0.5 * accel_m_s2 * dt_s
    moving[IW] += 0.5 * alpha_rad_s2 * dt_s
    out, F = motion(moving, dt_s, track_width_m)
    out[IV], out[IW] = x[IV], x[IW]
    return out, F


def process_noise(x: Vec | Floats, dt_s: float, learn_geometry: bool = True) -> Mat:
    """Q for one step (diagonal): random walks of v, omega, bias and (while it is learnt) geometry; the pose
    and the wheels' heading error get noise in proportion to the distance driven and the angle turned."""
    q_geometry = Q_GEOMETRY * dt_s if learn_geometry else 0.0
    dist_m = abs(float(x[IV])) * dt_s
    turn_rad = abs(float(x[IW])) * dt_s
    pos = Q_POS_PER_M * dist_m
    Q = np.zeros(N_STATES * N_STATES)
    Q[:: N_STATES + 1] = (pos, pos, Q_YAW_PER_M * dist_m + Q_YAW_PER_RAD * turn_rad, Q_V * dt_s, Q_OMEGA * dt_s,
                          Q_BIAS * dt_s, q_geometry, q_geometry,
                          Q_WHEEL_YAW_PER_M * dist_m + Q_WHEEL_YAW_PER_RAD * turn_rad)
    return Q.reshape(N_STATES, N_STATES)


# ---------------------------------------------------------------- measurements

def measurement(x: Vec, track_width_m: float, wheels: bool = True, gyro: bool = True, still: bool = False
                ) -> tuple[Vec, Mat]:
    """Measurement model and its Jacobian, (hx, H): the wheels' [speed, heading] (if `wheels`) and, at a
    standstill (`still`), the body's yaw rate they bound, then the gyro's rate (if `gyro`)."""
    _, _, yaw, v, w, bias, kt, q, wheel_yaw = x.tolist()
    still = still and wheels
    H = np.zeros((2 * wheels + still + gyro, N_STATES))
    z: list[float] = []
    if wheels:
        z += [wheel_rates_of(v, w, kt, q, track_width_m)[0], yaw + wheel_yaw]
        H[0, IV], H[0, IW], H[0, IKT], H[0, IKR] = wheel_rate_partials(v, w, kt, q, track_width_m)[0]
        H[1, IYAW] = H[1, IWY] = 1.0
    if still:  # wheels that stand still hold the body still, whatever their geometry
        z.append(w)
        H[2, IW] = 1.0
    if gyro:
        z.append(w + bias)
        H[-1, IW] = H[-1, IB] = 1.0
    return np.array(z), H


def hx(x: Vec, track_width_m: float, wheels: bool = True, gyro: bool = True, still: bool = False) -> Vec:
    """Predicted z (measurement)."""
    return measurement(x, track_width_m, wheels, gyro, still)[0]


def H_jacobian(x: Vec, track_width_m: float, wheels: bool = True, gyro: bool = True, still: bool = False) -> Mat:
    """d hx / d x (measurement)."""
    return measurement(x, track_width_m, wheels, gyro, still)[1]


def residual(z: Vec, h: Vec) -> Vec:
    """z - h with the wheels' heading difference wrapped (row 1 when they are in z; their heading is not)."""
    y = z - h
    if len(y) >= 2:
        y[1] = math.remainder(float(y[1]), 2.0 * math.pi)
    return y


def wheel_rate_noise(d_left_m: float, d_right_m: float, dt_s: float, track_width_m: float,
                     noise: NoiseModel) -> tuple[float, float]:
    """Variances of the interval's mean speed and yaw rate from the wheels: each wheel's speed has the
    noise of two readings over dt and a fraction of itself (small slip)."""
    base = (math.sqrt(2.0) * noise.wheel_noise_m / dt_s) ** 2
    vl = base + (noise.wheel_noise_fraction * d_left_m / dt_s) ** 2
    vr = base + (noise.wheel_noise_fraction * d_right_m / dt_s) ** 2
    return 0.25 * (vl + vr), (vl + vr) / (track_width_m * track_width_m)


def wheel_heading_noise(track_width_m: float, noise: NoiseModel) -> float:
    """Variance of the wheels' cumulative heading: one reading's error on each wheel (the baseline's is a
    constant, part of the error state)."""
    return 2.0 * (noise.wheel_noise_m / track_width_m) ** 2
