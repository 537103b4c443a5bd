"""filterpy's KalmanFilter running the extended (linearised) filter of models.py.

Imports filterpy, and through it scipy (about 0.65 s): only the filter's constructor imports this
module, so a process that builds its filter after its first HEARTBEAT does not wait for it.

Why KalmanFilter and not filterpy's ExtendedKalmanFilter: the same equations, at less than half the
cost per update (ExtendedKalmanFilter inverts S with scipy.linalg.inv, a third of its time on 1 to 3
rows, and calls back for h and H). An EKF is a Kalman filter on the model linearised at the state:

- predict: filterpy's predict with F (models.F_jacobian) and, as its control input, what the exact arc
  adds to F x (B = I, u = fx(x) - F x): x becomes fx(x), P becomes F P F' + Q;
- update: filterpy's update with H (models.H_jacobian) and z - h(x) + H x as the measurement: its
  innovation z - H x is then the model's z - h(x) (the heading's wrapped), its gain, Joseph's P.

filterpy >= 2.0: 1.4's KalmanFilter.update reshapes z to the filter's dim_z even when H is given, so
a measurement of another number of rows (the wheels' two, the gyro's one, three together) fails.
"""

# Kalman-filter notation (F, H, Q, R) reads better than pep8 names here.
# ruff: noqa: N803, N806
from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter

from rover_bridge.estimate.models import N_STATES, F_jacobian, H_jacobian, Mat, Vec, fx, hx, process_noise, residual

_IDENTITY = np.eye(N_STATES)



class ArcKalmanFilter(KalmanFilter):  # type: ignore[misc]  # filterpy has no type information
    """filterpy's KalmanFilter with the two steps of the extended filter (module docstring)."""

    def __init__(self, track_width_m: float, learn_geometry: bool) -> None:
        super().__init__(dim_x=N_STATES, dim_z=1)
        self.track_width_m = track_width_m
        self.learn_geometry = learn_geometry

    def predict_arc(self, dt_s: float, Q: Mat | None = None) -> None:
        """One prediction step of dt_s, with the process noise of dt_s unless Q is given."""
        x = self.x
        F = F_jacobian(x, dt_s, self.track_width_m)
        self.predict(u=fx(x, dt_s, self.track_width_m) - F @ x, B=_IDENTITY, F=F,
                     Q=process_noise(x, dt_s, self.learn_geometry) if Q is None else Q)

    def update_rows(self, z: Vec, R: Mat, wheels: bool, gyro: bool) -> None:
        """The update of the wheels' [speed, heading] rows and/or the gyro's (models.hx)."""
        x = self.x
        H = H_jacobian(x, self.track_width_m, wheels, gyro)
        self.update(residual(z, hx(x, self.track_width_m, wheels, gyro)) + H @ x, R=R, H=H)
