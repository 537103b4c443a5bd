"""What the filter's constant-rate prediction misses between two samples (pure): trapezoid corrections.

The prediction moves the state at piecewise-constant speeds: the yaw rate of the last gyro sample, the
mean speed of the last wheel interval. The body's rates change between samples, so every change of
rate leaves the prediction half a sample behind it:

- yaw: the rate moved linearly from one gyro sample's to the next (bias removed), so the turn is the
  trapezoid of the two; without the correction a spin that starts or stops leaves (change x half a
  period) of heading error, 1.3 deg per spin at 20 Hz. A rate that curved between the samples is not
  linear: the heading takes GYRO_SAMPLING_FACTOR x (change x period) of noise.
- distance: wheels measure how far the rover went over each interval (cumulative counts): the pose
  moves by that minus what the prediction moved (v dt / 2 per change of speed otherwise: 12 mm at
  0.5 m/s and 20 Hz). Slipping wheels overstate it: the trapezoid of the speeds instead.

Both keep what the prediction did since their last sample (`predicted`).
"""

from __future__ import annotations

GYRO_SAMPLING_FACTOR = 0.2  # the heading's noise per change of rate between two gyro samples
TRAPEZOID_MAX_DT_S = 0.2  # longer gaps: no trapezoid (the rate is not linear over them)


class SampleCorrections:
    """The bookkeeping of the trapezoid corrections (module docstring), in floats."""

    def __init__(self) -> None:
        self._gyro_prev: tuple[float, float] | None = None  # (time, body yaw rate) of the last gyro sample
        self._turned_rad = 0.0  # what the prediction turned since it
        self.alpha_rad_s2 = 0.0  # the yaw rate's rate of change between the last two gyro samples
        self._wheels_prev: tuple[float, float] | None = None  # (time, speed after that update)
        self._moved_m = 0.0  # what the prediction moved since the last wheel reading

    def predicted(self, v_m_s: float, omega_rad_s: float, dt_s: float) -> None:
        self._turned_rad += omega_rad_s * dt_s
        self._moved_m += v_m_s * dt_s

    def restart(self, held_m: float = 0.0) -> None:
        """The motion restarted (a reboot, a silence): no trapezoid across it; the pose held for
        publishing already moved held_m of the wheels' next interval."""
        self._gyro_prev = self._wheels_prev = None
        self.alpha_rad_s2 = 0.0
        self._turned_rad = 0.0
        self._moved_m += held_m

    def wheel_baseline(self) -> None:
        """The next wheel interval starts here."""
        self._wheels_prev = None
        self._moved_m = 0.0

    def gyro(self, t_s: float, omega_body_rad_s: float) -> tuple[float, float]:
        """A gyro sample (bias removed): (the yaw the prediction missed since the last one, the heading
        variance the sampling adds)."""
        prev = self._gyro_prev
        missed = var = 0.0
        self.alpha_rad_s2 = 0.0
        if prev is not None and 0.0 < t_s - prev[0] <= TRAPEZOID_MAX_DT_S:
            dt = t_s - prev[0]
            change = omega_body_rad_s - prev[1]
            self.alpha_rad_s2 = change / dt
            missed = 0.5 * (prev[1] + omega_body_rad_s) * dt - self._turned_rad
            var = (GYRO_SAMPLING_FACTOR * change * dt) ** 2
        self._gyro_prev = (t_s, omega_body_rad_s)
        self._turned_rad = 0.0
        return missed, var

    def wheels(self, t_s: float, v_m_s: float, distance_m: float | None) -> float:
        """A fused wheel reading: the distance the prediction missed over its interval. `distance_m` is the
        one the wheels measured; None when they slip (the trapezoid of the speeds)."""
        prev = self._wheels_prev
        missed = 0.0
        if distance_m is not None:
            missed = distance_m - self._moved_m
        elif prev is not None and 0.0 < t_s - prev[0] <= TRAPEZOID_MAX_DT_S:
            missed = 0.5 * (prev[1] + v_m_s) * (t_s - prev[0]) - self._moved_m
        self._wheels_prev = (t_s, v_m_s)
        self._moved_m = 0.0
        return missed

    def wheels_refused(self) -> None:
        """A wheel reading left out: the next interval starts at it."""
        self._moved_m = 0.0
