"""filterpy's KalmanFilter running the extended (linearised) filter of models.py.

Imports filterpy, and through it scipy (about 0.65 s): only the filter's constructor imports this
module, so a process that builds its filter after its first HEARTBEAT does not wait for it.

An EKF is a Kalman filter on the model linearised at the state; filterpy's KalmanFilter runs both
steps of it:

- predict: filterpy's predict with F (models.motion's Jacobian), Q = models.process_noise and, as its
  control input, what the exact arc adds to F x (B = I, u = fx(x) - F x): x becomes fx(x), P becomes F P F' + Q;
- update: filterpy's update with H from models.measurement and z - h(x) + H x as the measurement: its
  innovation z - H x is then the model's z - h(x) (models.residual: the heading's wrapped); its gain,
  Joseph's form for P. Any of the measurement rows (the wheels' two, with a settled standstill's yaw rate
  three, the gyro's one, or all of them at once).

Why not filterpy's ExtendedKalmanFilter, which does the same with callbacks: its update inverts S with
scipy.linalg.inv, whose validation and LAPACK lookup made it the largest cost of a filter cycle in the
running bridge (measured, cold caches: 240 us of a 750 us cycle, against 60 us for KalmanFilter's
update with the closed-form inverse below; notes in the module's commit). KalmanFilter takes its
inverse as a parameter (`inv`).

KalmanFilter reshapes z to its dim_z before an update (1.4.5 even when H is given): dim_z is set to the
update's rows each time.
"""

# Kalman-filter notation (F, H, Q, R, S) reads better than pep8 names here.
# ruff: noqa: N803, N806
from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter

from rover_bridge.estimate.models import N_STATES, Mat, Vec, measurement, motion, process_noise, residual


def small_inverse(S: Mat) -> Mat:
    """S^-1 for the 1 to 3 rows of an update, in closed form (numpy's inverse for more). Built from floats in
    one array: at 3 rows numpy's own inverse costs 2-3 times as much (its checks and the LAPACK call)."""
    n = len(S)
    if n == 1:
        return 1.0 / S  # type: ignore[no-any-return]
    if n == 2:
        a, b, c, d = S.ravel().tolist()
        det = a * d - b * c
        return np.array((d / det, -b / det, -c / det, a / det)).reshape(2, 2)
    if n == 3:
        a, b, c, d, e, f, g, h, i = S.ravel().tolist()
        A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
        det = a * A + b * B + c * C
        return np.array((A / det, (c * h - b * i) / det, (b * f - c * e) / det, B / det, (a * i - c * g) / det,
                         (c * d - a * f) / det, C / det, (b * g - a * h) / det, (a * e - b * d) / det)).reshape(3, 3)
    return np.linalg.inv(S).astype(np.float64)


class ArcKalmanFilter(KalmanFilter):  # type: ignore[misc]  # filterpy has no type information
    """filterpy's KalmanFilter with the two steps of the extended filter (module docstring)."""

    x: Vec  # filterpy's state and covariance
    P: Mat

    def __init__(self, track_width_m: float, learn_geometry: bool) -> None:
        super().__init__(dim_x=N_STATES, dim_z=1)
        self.track_width_m = track_width_m
        self.learn_geometry = learn_geometry
        self.B = np.eye(N_STATES)  # the control input is what the arc adds to F x
        self.inv = small_inverse

    def predict_arc(self, dt_s: float) -> None:
        """One prediction step of dt_s."""
        x = self.x
        x_new, F = motion(x, dt_s, self.track_width_m)
        self.F = F
        self.Q = process_noise(x, dt_s, self.learn_geometry)
        self.predict(u=x_new - F.dot(x))

    def linearise(self, wheels: bool, gyro: bool, still: bool = False) -> tuple[Mat, Vec]:
        """(H, h(x)) of those rows at the state: what update_rows takes, for a caller that gates on them first."""
        h, H = measurement(self.x, self.track_width_m, wheels, gyro, still)
        return H, h

    def update_rows(self, z: Vec, R: Mat, wheels: bool, gyro: bool,
                    linearised: tuple[Mat, Vec] | None = None, still: bool = False) -> None:
        """The update of the wheels' [speed, heading] rows (with the standstill's yaw rate) and/or the gyro's
        (models.hx), linearised at the state (`linearised`: linearise()'s, if the caller has it)."""
        x = self.x
        H, h = linearised if linearised is not None else self.linearise(wheels, gyro, still)
        self.dim_z = len(z)
        self.R = R
        self.update(residual(z, h) + H.dot(x), H=H)
