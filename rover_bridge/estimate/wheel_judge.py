"""What one wheel interval is worth to the filter (pure): its speed measurement, slip, standstill, and
whether the wheels' heading is trusted.

- Standstill: wheels that have not moved by a reading's resolution for T seconds bound the mean speed
  by resolution / T (the bound tightens with T, down to STATIONARY_SIGMA_V_M_S). Once settled
  (STILL_SETTLE_S), distrusted wheels also bound the body's yaw rate: their heading row, free, no longer
  holds the yaw at rest, and without this a rover that drove off on bad wheels never learnt its gyro's bias
  (accuracy.py --moving miscalibrated: 3.74 % of the distance, worst of seeds 1-9; 1.38 % with it).
- Slip: the wheels' yaw rate over the interval against the gyro's (bias removed), with the gyro's
  noise and bias, the spread of its samples over the interval (an omega that changed within it is
  not slip) and at least SLIP_GEOMETRY's geometry uncertainty (a rover whose geometry is off is not
  slipping), past the gate in two intervals running, the same way (a spinning wheel keeps spinning).
  On slip the speed is the one the slower wheel and the gyro give (a slipping wheel turns faster than
  the ground under it), and the wheels' heading error takes the disagreement. One interval past the
  gate, or one the other way than the interval before, is a step: a yaw that wobbles faster than the
  samples (a real Rover SITL's go-to start: 0.2-0.6 rad/s each way every 50 ms, whose skid model turns
  at once) aliases between the gyro's instants and the wheels' means. Taken for slip, that wobble's
  "slower wheel" speed, with that model's 1.64 m track, read -0.56 m/s for a rover driving at +0.5, and
  the go-to lost about 0.8 m of its 4.9 m and stopped 0.9 m past its target.
- A step: the interval's disagreement beyond STEP_SIGMA without the spread's allowance, and beyond a
  count's rounding on each wheel (the gyro's rate jumped and the wheels did not follow: slip starting or
  ending within the interval, which the spread hides from the slip test). Its turn is unknown, so the
  wheels' heading error takes the disagreement as on slip; the speed is fused as usual. Without this the
  wheels' heading pulled the yaw at each slip edge (accuracy.py slip: 0.7-0.9 deg per edge, 3.1 deg worst
  of seeds 1-9). The interval after a step settles the same way (without being a step): the body's rate can
  still overshoot what the wheels show there (a real Rover SITL's turn onset: gyro 3 % above the wheels for
  one 0.1 s interval). Learnt from, that one interval taught the track 2.8 % off with 0.4 % sigma, and the
  consistency window then distrusted the right wheels against the wrong track for good (tests/data's SITL
  log: 1.590 m calibrated against 1.633 m measured live; 1.635 m with the settling interval).
- Trust (consistency.py): while the wheels and the gyro disagree, the wheels' heading error is free
  (the heading they predict, yaw + error, is DISTRUST_SIGMA_RAD uncertain: a floor on the error alone
  was none once the yaw was as uncertain, its mirror) and the gyro holds the heading; they are trusted
  again after a standstill, once a whole window in motion agrees.
"""

# Kalman-filter notation (P for a covariance) reads better than pep8 names here.
# ruff: noqa: N803, N806
from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.estimate.consistency import ConsistencyWindow
from rover_bridge.estimate.models import (
    IB,
    IKR,
    IKT,
    IV,
    IW,
    IWY,
    IYAW,
    GeometryPrior,
    Mat,
    NoiseModel,
    Vec,
    wheel_rate_noise,
    wheel_rate_partials,
    wheel_rates,
)

GEOMETRY_UNKNOWN = GeometryPrior(track_scale=0.05, radius_ratio=0.03)  # calibrate = true: the prior
SLIP_GEOMETRY = GEOMETRY_UNKNOWN  # the slip test allows at least this much geometry error
SLIP_V_VAR_FACTOR = 100.0  # slip without a gyro: the wheels' speed variance times this
SLIP_OTHER_WHEEL_VAR_FACTOR = 4.0  # slip: the other wheel may slip a little too
SLIP_YAW_FACTOR = 2.0  # slip: the heading error takes this many times the disagreement (1 sigma)
# A step (module docstring): the disagreement without the spread's allowance beyond this many sigma. A rate that
# changes through the motors' lag stays far inside it (no step in clean runs of accuracy.py or the demo's route).
STEP_SIGMA = 2.0
# ... and more than rounding: a reading is off by up to half a count (wheel_noise_m is that error's sigma, a
# count's sqrt(12)th), so an interval's turn by up to a count on each wheel. A spin's onset in real time read
# 0.2 rad/s over 20 ms on the wheels against the gyro's mean of 0.125: 2.3 sigma, but 0.7 of a count a wheel;
# taken for a step, it freed the heading and the EKF kept 0.1 deg against exact wheels (one demo run in twenty).
STEP_ROUNDING_COUNTS = 1.0
STATIONARY_SIGMA_V_M_S = 1e-3
# A standstill bounds the yaw rate (each wheel within its speed bound) once the motors' tail has died out:
# a body still creeping after a spin reads no count for a while (1024 counts a turn: 0.3 mm).
STILL_SETTLE_S = 1.0
DISTRUST_SIGMA_RAD = 1.0  # the wheels' heading error while they disagree with the gyro: anything
MAX_INTERVAL_S = 0.2  # longer intervals: their mean speed is not extrapolated


@dataclass(frozen=True, slots=True)
class WheelInterval:
    """One wheel interval: the nominal distance increments over dt_s, and the gyro over the same interval
    (its mean rate, bias included, and half the range of its samples), if any."""

    d_left_m: float
    d_right_m: float
    dt_s: float
    gyro_omega_rad_s: float | None = None
    gyro_spread_rad_s: float = 0.0


@dataclass(frozen=True, slots=True)
class WheelJudgement:
    """What the interval measures (the wheels' mean speed z_v with variance r_v) and what it says."""

    z_v: float
    r_v: float
    slip: bool
    stationary: bool
    slip_d2: float  # squared Mahalanobis distance of the wheel/gyro yaw-rate disagreement
    heading_var: float  # variance the wheels' heading error gets before this interval is fused
    step: bool = False  # the gyro's rate jumped within the interval and the wheels did not follow (docstring)
    r_still: float | None = None  # a settled standstill: variance of the yaw rate it bounds (0 rad/s), else None


class WheelJudge:
    """Judges each wheel interval against the filter's state (module docstring)."""

    def __init__(self, track_width_m: float, noise: NoiseModel) -> None:
        self.track_width_m = track_width_m
        self.noise = noise
        self._gate2 = noise.gate_sigma ** 2
        self._reading_var = 2.0 * (noise.wheel_noise_m / track_width_m) ** 2  # one reading's heading noise
        # a turn within this is the counts' rounding, not a step (STEP_ROUNDING_COUNTS)
        self._rounding_rad = 2.0 * STEP_ROUNDING_COUNTS * math.sqrt(12.0) * noise.wheel_noise_m / track_width_m
        self._still_since_s: float | None = None  # start of the current standstill
        self.window = ConsistencyWindow()
        self.trusted = True  # the wheels' heading: trusted, or free while they disagree with the gyro
        self.agreed = False  # the last interval completed agreeing windows (what the filter learnt is sound)
        self.distrust_turn_rad = 0.0  # the wheels' turn beyond the gyro's in the window that found them disagreeing
        self._may_trust = True  # a standstill since the last disagreement
        self._prev: tuple[float, float, float] | None = None  # the last interval's (mean speed, variance, dt)
        self._after_step = False  # the last interval was a step: this one settles (module docstring)
        self._slip_y = 0.0  # the last interval's disagreement (rad/s) if it was past the gate, else 0
        self.accel_m_s2 = 0.0  # from the last two intervals' mean speeds (publishing extrapolates with it)

    def restart(self) -> None:
        """The motion restarted (a reboot, a silence, a new baseline): the standstill, if any, and the last
        interval's speed are forgotten."""
        self._still_since_s = None
        self._prev = None
        self._after_step = False
        self._slip_y = 0.0
        self.accel_m_s2 = 0.0

    def judge(self, t_s: float, w: WheelInterval, x: Vec, P: Mat) -> WheelJudgement:
        """The interval ending at t_s against the state (x, P) predicted to t_s."""
        L = self.track_width_m
        self.agreed = False
        if w.d_left_m == 0.0 and w.d_right_m == 0.0:
            if self._still_since_s is None:
                self._still_since_s = t_s - w.dt_s
            self._prev = None
            self._after_step = False
            self._slip_y = 0.0
            self.accel_m_s2 = 0.0
            still_s = max(w.dt_s, t_s - self._still_since_s)
            self.window.clear()
            self._may_trust = True
            sigma_v = max(STATIONARY_SIGMA_V_M_S, self.noise.wheel_noise_m / still_s)
            # Only for distrusted wheels: trusted ones hold the yaw through their heading row already.
            r_still = (2.0 * sigma_v / L) ** 2 if still_s >= STILL_SETTLE_S and not self.trusted else None
            return WheelJudgement(0.0, sigma_v ** 2, False, True, 0.0, self._distrust_var(P), r_still=r_still)
        self._still_since_s = None
        mean_v = 0.5 * (w.d_left_m + w.d_right_m) / w.dt_s
        r_v, r_omega = wheel_rate_noise(w.d_left_m, w.d_right_m, w.dt_s, L, self.noise)
        z_v, r_end = self._speed_at_end(mean_v, r_v, w.dt_s)
        d2, y, step_d2 = self._slip_test((w.d_right_m - w.d_left_m) / (L * w.dt_s), r_omega, w, x, P)
        slip_var = float(P[IWY, IWY]) + (SLIP_YAW_FACTOR * y * w.dt_s) ** 2
        past_gate = d2 > self._gate2
        sustained = past_gate and y * self._slip_y > 0.0  # the interval before was past the gate the same way
        self._slip_y = y if past_gate else 0.0
        if sustained:
            self._prev = None
            self._after_step = False
            self.accel_m_s2 = 0.0
            self.window.clear()
            z_v, r_v = self._slip_speed(w, x, r_v)
            return WheelJudgement(z_v, r_v, True, False, d2, max(self._distrust_var(P), slip_var))
        # past the gate once, or the other way than the interval before: a step (module docstring)
        step = past_gate or (step_d2 > STEP_SIGMA ** 2 and abs(y) * w.dt_s > self._rounding_rad)
        settling, self._after_step = self._after_step, step
        if step or settling:  # the yaw did not follow the wheels here (or may still lag them): nor does the window
            self.window.clear()
            return WheelJudgement(z_v, r_end, False, False, d2, max(self._distrust_var(P), slip_var), step)
        self._check_agreement(w, y * w.dt_s, x, P)
        return WheelJudgement(z_v, r_end, False, False, d2, self._distrust_var(P))

    def _speed_at_end(self, mean_v: float, r_v: float, dt_s: float) -> tuple[float, float]:
        """(speed, variance) at the end of the interval, the reading's time: wheels measure the mean speed of
        each interval, half an interval behind every change of speed (0.125 m/s in a stop from 0.5 m/s at
        20 Hz: the published pose then ran 5 mm past it). Extrapolated from the last two means (a constant
        acceleration over them); the mean itself after a standstill, slip or a gap."""
        prev, self._prev = self._prev, (mean_v, r_v, dt_s)
        if prev is None or prev[2] > MAX_INTERVAL_S or dt_s > MAX_INTERVAL_S:
            self.accel_m_s2 = 0.0
            return mean_v, r_v
        self.accel_m_s2 = (mean_v - prev[0]) / (0.5 * (dt_s + prev[2]))
        k = dt_s / (dt_s + prev[2])
        return mean_v + k * (mean_v - prev[0]), (1.0 + k) ** 2 * r_v + k * k * prev[1]

    def _distrust_var(self, P: Mat) -> float:
        if self.trusted:
            return float(P[IWY, IWY])
        # Free relative to the yaw: the heading the wheels predict (yaw + error) is DISTRUST_SIGMA_RAD uncertain
        return max(float(P[IWY, IWY]), DISTRUST_SIGMA_RAD ** 2 - float(P[IYAW, IYAW]) - 2.0 * float(P[IYAW, IWY]))

    def _slip_test(self, z_omega_rad_s: float, r_omega: float, w: WheelInterval, x: Vec, P: Mat
                   ) -> tuple[float, float, float]:
        """(d2, y, d2 without the spread's allowance): the wheels' yaw rate against what they would read if the
        body turned at gyro - bias."""
        if w.gyro_omega_rad_s is None:
            return 0.0, 0.0, 0.0
        L = self.track_width_m
        _, _, _, v, _, b, kt, q, _ = x.tolist()
        omega = w.gyro_omega_rad_s - b
        _, h_w, h_kt, h_kr = wheel_rate_partials(v, omega, kt, q, L)[1]
        var = (r_omega + h_w ** 2 * (self.noise.gyro_noise_rad_s ** 2 + float(P[IB, IB]))
               + h_kt ** 2 * max(float(P[IKT, IKT]), SLIP_GEOMETRY.track_scale ** 2)
               + h_kr ** 2 * max(float(P[IKR, IKR]), SLIP_GEOMETRY.radius_ratio ** 2))
        xs = x.copy()
        xs[IW] = omega
        y = z_omega_rad_s - wheel_rates(xs, L)[1]
        return y * y / (var + (h_w * w.gyro_spread_rad_s) ** 2), y, y * y / var

    def slip_d2(self, z_omega_rad_s: float, r_omega: float, gyro_omega_rad_s: float | None, x: Vec, P: Mat,
                gyro_spread_rad_s: float = 0.0) -> float:
        """Squared Mahalanobis distance between the wheels' yaw rate (z_omega_rad_s, variance r_omega) and
        the gyro's (bias removed)."""
        return self._slip_test(z_omega_rad_s, r_omega, WheelInterval(0.0, 0.0, 1.0, gyro_omega_rad_s,
                                                                     gyro_spread_rad_s), x, P)[0]

    def _slip_speed(self, w: WheelInterval, x: Vec, r_v: float) -> tuple[float, float]:
        """(z, variance) of the wheels' mean speed while they slip: what they would read at the body speed the
        slower wheel and the gyro give; without the gyro, the reading, SLIP_V_VAR_FACTOR times less sure."""
        if w.gyro_omega_rad_s is None:
            return 0.5 * (w.d_left_m + w.d_right_m) / w.dt_s, r_v * SLIP_V_VAR_FACTOR
        xs = x.copy()
        L = self.track_width_m
        omega = w.gyro_omega_rad_s - float(x[IB])
        q = float(x[IKR])
        half = 0.5 * float(x[IKT]) * omega * L
        from_left = w.d_left_m / w.dt_s * 2.0 / (1.0 + q) + half
        from_right = w.d_right_m / w.dt_s * 2.0 * q / (1.0 + q) - half
        xs[IV], xs[IW] = min(from_left, from_right, key=abs), omega
        return wheel_rates(xs, L)[0], r_v * SLIP_OTHER_WHEEL_VAR_FACTOR

    def _check_agreement(self, w: WheelInterval, disagreement_rad: float, x: Vec, P: Mat) -> None:
        """Feed the consistency window (the interval's disagreement with the gyro, from the slip test); distrust at
        its first disagreement, trust again (after a standstill) at its first agreement."""
        if w.gyro_omega_rad_s is None:  # no reference: the last verdict stands
            self.window.clear()
            return
        L = self.track_width_m
        turn_rad, dist_m = (w.d_right_m - w.d_left_m) / L, 0.5 * (w.d_left_m + w.d_right_m)
        geometry_rad = math.sqrt(float(P[IKT, IKT])) * abs(turn_rad) + math.sqrt(float(P[IKR, IKR])) * abs(dist_m) / L
        self.window.add(w.dt_s, turn_rad, disagreement_rad,
                        (self.noise.gyro_noise_rad_s ** 2 + w.gyro_spread_rad_s ** 2) * w.dt_s * w.dt_s, dist_m,
                        geometry_rad)
        agree = self.window.agree(float(P[IB, IB]), self._reading_var)
        if agree is False:
            if self.trusted:
                self.distrust_turn_rad = self.window.disagreement_rad
            self.trusted = self._may_trust = False
        elif agree:
            self.agreed = True
            self.trusted = self.trusted or self._may_trust
