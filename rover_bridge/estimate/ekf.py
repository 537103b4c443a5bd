"""The wheel + gyro EKF (pure): filterpy running the models of models.py.

filterpy runs every step (arc_ekf.ArcKalmanFilter: its KalmanFilter's predict and update, on the models
linearised at the state). Around it, what a filter needs in a sampled, imperfect world:

- Time is an argument everywhere (`t_s`, any monotonic time line). The filter keeps the time of its
  state and never moves backwards: a measurement older than the state, or less than SAME_INSTANT_S
  newer, is applied at the state's time (filterpy is not asked to predict; the interval is predicted
  with the next measurement, so no time is lost).
- A gyro sample and a wheel reading of the same instant (ArduPilot sends ATTITUDE and WHEEL_DISTANCE
  in one burst, with one stamp) are one update of three rows: the gyro's waits for the next call.
  filterpy's update takes any rows it is given, but it is called per measurement and cannot know
  that the wheel reading of the gyro's instant is next: that wait (_pending_gyro) is the one piece
  of scheduling kept here.
- Gating, per sensor, on the innovation against the predicted state: further than gate_sigma
  (Mahalanobis), its rows are left out; MAX_CONSECUTIVE_REJECTS in a row are taken (the filter is
  then the likelier culprit). The wheels' heading row is never refused: a jump in it is a lost
  reference, and their heading error takes it (_heading_jump).
- Wheel intervals are judged first (wheel_judge.py: standstill, slip, whether the wheels' heading is
  trusted). Trusted wheels teach the gyro its bias in motion too (a bias taught by wheels later found
  disagreeing is unlearnt, and the turn the yaw followed meanwhile: _unlearn). Not a Schmidt "consider"
  bias once known from rest: a bias the filter may not correct leaves the yaw and the wheels' heading
  error correlated through it, and after the wheels were distrusted their heading row moved the yaw by
  up to 1.8 times its innovation (one count, 0.06 deg, amplified: accuracy.py slip seed 7 lost 0.35 deg
  in the 8 s after the wheels were trusted again).
- Trapezoid corrections of yaw and distance between samples (sampling.py).
- Publishing extrapolates at most EXTRAPOLATE_MAX_S past the last measurement; restart_motion
  continues from that held pose.

The wheel geometry: with `calibrate` the filter learns it (two states, prior wheel_judge.GEOMETRY_UNKNOWN);
without, the profile's is taken as exact, and how far the wheels are off shows as their heading error
(free while they disagree with the gyro: wheel_judge.py).
"""

# Kalman-filter notation (F, H, P, Q, R, S) reads better than pep8 names here.
# ruff: noqa: N802, N803, N806
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

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
    SIGMA0_BIAS,
    SIGMA0_OMEGA,
    SIGMA0_POSE,
    SIGMA0_V,
    Mat,
    NoiseModel,
    Vec,
    ahead,
    process_noise,
    wheel_heading_noise,
)
from rover_bridge.estimate.sampling import SampleCorrections
from rover_bridge.estimate.wheel_judge import GEOMETRY_UNKNOWN, WheelInterval, WheelJudge
from rover_bridge.odometry import Pose2D, wrap_angle

MAX_CONSECUTIVE_REJECTS = 5
MAX_PREDICT_STEP_S = 0.1
# Longer gaps are not integrated (predict_to): at most this / MAX_PREDICT_STEP_S sub-steps per call.
MAX_PREDICT_GAP_S = 1.0
EXTRAPOLATE_MAX_S = 0.2  # publishing: how far past the last measurement the pose may move
COAST_S = 0.3  # a rover whose motors lost power stops within about this (distance = speed x this, 1 sigma)
SAME_INSTANT_S = 1e-3


class Gate:
    """One sensor's innovation gate: a squared Mahalanobis distance past gate_sigma^2 is refused, unless it
    is the MAX_CONSECUTIVE_REJECTS-th refusal in a row (the filter is then the likelier culprit)."""

    def __init__(self, gate_sigma: float) -> None:
        self._gate2 = gate_sigma ** 2
        self.rejects_in_row = 0

    def passes(self, d2: float) -> bool:
        if d2 <= self._gate2 or self.rejects_in_row + 1 >= MAX_CONSECUTIVE_REJECTS:
            self.rejects_in_row = 0
            return True
        self.rejects_in_row += 1
        return False


@dataclass(frozen=True, slots=True)
class WheelUpdate:
    """What happened to one wheel measurement."""

    accepted: bool
    slip: bool
    stationary: bool
    slip_d2: float  # squared Mahalanobis distance of the wheel/gyro yaw-rate disagreement
    d2: float  # squared Mahalanobis distance of the speed's innovation


class WheelGyroEKF:
    """The extended Kalman filter on the models of models.py, run by filterpy (module docstring).

    `ekf` is filterpy's filter: `ekf.x` (9) and `ekf.P` (9 x 9) are its live state (filterpy replaces
    them at every step; between steps the corrections here change them in place: copy what you keep).
    """

    def __init__(self, track_width_m: float, noise: NoiseModel | None = None, calibrate: bool = False,
                 pose: Pose2D | None = None) -> None:
        from rover_bridge.estimate.arc_ekf import ArcKalmanFilter  # filterpy, and scipy: see arc_ekf

        if not (math.isfinite(track_width_m) and track_width_m > 0.0):
            raise ValueError(f"track_width_m must be a finite number > 0, got {track_width_m!r}")
        self.track_width_m = float(track_width_m)
        self.noise = noise if noise is not None else NoiseModel()
        self.calibrate = calibrate
        self._kf: Any = ArcKalmanFilter(self.track_width_m, learn_geometry=calibrate)
        self.judge = WheelJudge(self.track_width_m, self.noise)
        self.sampling = SampleCorrections()
        self.time_s: float | None = None
        self._pending_gyro: tuple[float, float] | None = None  # (t, omega) passed its gate, not yet fused
        self.wheel_yaw_rad = 0.0  # the wheels' cumulative heading (models: z_wheels[1])
        self._gyro_var = self.noise.gyro_noise_rad_s ** 2
        self._heading_var = wheel_heading_noise(self.track_width_m, self.noise)
        self._gate2 = self.noise.gate_sigma ** 2
        self.gyro_gate, self.wheels_gate = Gate(self.noise.gate_sigma), Gate(self.noise.gate_sigma)
        self.predict_steps = 0  # prediction sub-steps so far: the work the filter did (bounded per call)
        # learnt at rest or with agreeing wheels (_unlearn); the newest becomes sound a checkpoint later
        self._sound_bias = self._newest_sound_bias = (0.0, SIGMA0_BIAS ** 2)
        self.heading_jumps = 0  # times the wheels' heading jumped beyond the gate (see _heading_jump)
        geometry = GEOMETRY_UNKNOWN if calibrate else None  # None: the profile's, exactly
        start = pose if pose is not None else Pose2D()
        self._kf.x = np.array([start.x_m, start.y_m, start.yaw_rad, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0])
        self._kf.P = np.diag(np.square([SIGMA0_POSE, SIGMA0_POSE, SIGMA0_POSE, SIGMA0_V, SIGMA0_OMEGA, SIGMA0_BIAS,
                                        geometry.track_scale if geometry else 0.0,
                                        geometry.radius_ratio if geometry else 0.0, SIGMA0_POSE]))

    # -- accessors (each fuses a waiting gyro sample first)
    @property
    def ekf(self) -> Any:
        """filterpy's filter, current."""
        self._flush()
        return self._kf

    @property
    def x(self) -> Vec:
        return self.ekf.x  # type: ignore[no-any-return]

    @property
    def P(self) -> Mat:
        return self.ekf.P  # type: ignore[no-any-return]

    @property
    def pose(self) -> Pose2D:
        self._flush()
        return self.peek_pose()

    def peek_pose(self) -> Pose2D:
        """The pose at the filter's time without fusing a waiting gyro sample first (bookkeeping that must
        not split a gyro sample from the wheel reading of its instant)."""
        x = self._kf.x
        return Pose2D(float(x[IX]), float(x[IY]), float(x[IYAW]))

    @property
    def wheels_trusted(self) -> bool:
        return self.judge.trusted

    def calibration(self) -> tuple[float, float, float, float]:
        """(track_scale, sigma, radius_ratio, sigma): the geometry the filter has (sigma 0: the profile's, taken
        as exact, without calibration)."""
        x, P = self.x, self._kf.P
        return (float(x[IKT]), math.sqrt(max(0.0, float(P[IKT, IKT]))), float(x[IKR]),
                math.sqrt(max(0.0, float(P[IKR, IKR]))))

    # -- time
    def predict_to(self, t_s: float) -> None:
        """Move the state to t_s. Work is bounded whatever t_s is: a gap longer than MAX_PREDICT_GAP_S
        is a discontinuity (the motion restarts from the held pose, as after a silent link), never
        integrated step by step; a time that is not finite is ignored."""
        if not math.isfinite(t_s):
            return
        if self.time_s is None:
            self.time_s = t_s
            return
        total = t_s - self.time_s
        if total < SAME_INSTANT_S:
            return
        self._flush()
        if total > MAX_PREDICT_GAP_S:
            self.restart_motion(t_s)
            return
        # Sub-steps through a gap, so the covariance grows as the random walks really do (one long
        # step would add the speed noise to the speed only, not to the position it moves).
        steps = max(1, math.ceil(total / MAX_PREDICT_STEP_S))
        dt = total / steps
        self.predict_steps += steps
        kf = self._kf
        for _ in range(steps):
            self.sampling.predicted(float(kf.x[IV]), float(kf.x[IW]), dt)
            kf.predict_arc(dt)
        self.time_s = t_s

    def _lookahead_s(self, t_s: float) -> float:
        return 0.0 if self.time_s is None or not t_s > self.time_s else t_s - self.time_s

    def _ahead(self, x: Vec, dt_s: float) -> tuple[Vec, Mat]:
        return ahead(x, min(dt_s, EXTRAPOLATE_MAX_S), self.judge.accel_m_s2, self.sampling.alpha_rad_s2,
                     self.track_width_m)

    def pose_at(self, t_s: float) -> Pose2D:
        """The pose predicted to t_s (models.ahead, at most EXTRAPOLATE_MAX_S), the filter unchanged (and a
        gyro sample waiting for its wheel reading, a few ms, not fused: see extrapolate)."""
        x = self._kf.x
        dt = self._lookahead_s(t_s)
        if dt > 0.0:
            x = self._ahead(x, dt)[0]
        return Pose2D(float(x[IX]), float(x[IY]), float(x[IYAW]))

    def extrapolate(self, t_s: float, block: int = N_STATES) -> tuple[list[float], list[list[float]]]:
        """State and covariance (rows of its first `block` states: ODOMETRY's are PUBLISHED) predicted to
        t_s, without changing the filter. The pose moves on for at most EXTRAPOLATE_MAX_S past the last
        measurement (a silent link may be a rebooting autopilot whose motors stopped; models.ahead); the
        covariance keeps growing. A look-ahead for publishing, not a step of the filter: F P F' + Q with the
        same F and Q filterpy's predict takes, on all nine states (F's first rows are zero past the fifth column:
        the block is its own; whole arrays cost half what views of them do). (A gyro sample waiting for the
        wheel reading of its instant, a few ms, shows in the next one.)"""
        if not PUBLISHED <= block <= N_STATES:  # the motion model moves the first five: a smaller block is not one
            raise ValueError(f"block must be {PUBLISHED} to {N_STATES} states, got {block}")
        kf = self._kf
        x, P = kf.x, kf.P
        dt = self._lookahead_s(t_s)
        if dt > 0.0:
            Q = process_noise(x, dt, kf.learn_geometry)
            if dt > MAX_PREDICT_STEP_S:  # one step standing for several (predict_to's sub-steps)
                Q = Q * (dt / MAX_PREDICT_STEP_S)
            x, F = self._ahead(x, dt)
            P = F.dot(P).dot(F.T) + Q
        return x.tolist(), P[:block, :block].tolist()

    def restart_motion(self, t_s: float, new_time_s: float | None = None) -> None:
        """After an autopilot reboot or a silence: continue from the pose published now, speeds unknown.

        The motors lose power while the board restarts, so the rover has coasted to a stop somewhere
        near the held pose; nothing measured the silence, so the pose covariance takes the coasting
        distance and the speeds restart at zero with their initial uncertainty.
        """
        held_m = float(self.x[IV]) * min(self._lookahead_s(t_s), EXTRAPOLATE_MAX_S)
        xs, ps = self.extrapolate(t_s)
        x, P = np.array(xs), np.array(ps)
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
        self._kf.x, self._kf.P = x, P
        # The held pose is at t_s; the filter's clock goes on from new_time_s (an autopilot that
        # rebooted restarts its boot clock near zero).
        self.time_s = t_s if new_time_s is None else new_time_s
        self.judge.restart()
        self.sampling.restart(held_m)  # the held pose already moved this far of the wheels' next interval

    def wheel_baseline(self) -> None:
        """The next wheel interval starts here (first reading, re-base after a reboot or resync); the wheels'
        heading restarts at the filter's (yaw + error), so it measures turns from here on: the error state's
        error is then exactly minus the yaw's (its row of P is minus the yaw's)."""
        self.sampling.wheel_baseline()
        self.judge.restart()
        x, P = self.x, self._kf.P
        self.wheel_yaw_rad = float(x[IYAW]) + float(x[IWY])
        P[IWY, :] = -P[IYAW, :]
        P[:, IWY] = -P[:, IYAW]
        P[IWY, IWY] = P[IYAW, IYAW]

    # -- updates
    def update_gyro(self, t_s: float, omega_rad_s: float) -> bool:
        """A gyro yaw rate (CCW +, rad/s) at t_s. False when it failed the gate (not fused). Fused with the
        next call: in one update with a wheel reading of the same instant, else alone (module docstring)."""
        self.predict_to(t_s)
        self._flush()
        x, P = self._kf.x, self._kf.P
        y = omega_rad_s - float(x[IW] + x[IB])
        S = float(P[IW, IW] + 2.0 * P[IW, IB] + P[IB, IB]) + self._gyro_var
        if not (S > 0.0 and self.gyro_gate.passes(y * y / S)):  # S > 0 unless P is broken: never fused then
            return False
        self._pending_gyro = (t_s, omega_rad_s)
        # At once: a wheel reading of this instant measured that turn.
        missed_rad, var = self.sampling.gyro(t_s, omega_rad_s - float(x[IB]))
        x[IYAW] = wrap_angle(float(x[IYAW]) + missed_rad)
        P[IYAW, IYAW] += var
        return True

    def _flush(self) -> None:
        """Fuse a waiting gyro sample alone."""
        if self._pending_gyro is not None:
            self._update(None)

    def update_wheels(self, t_s: float, d_left_m: float, d_right_m: float, dt_s: float,
                      gyro_omega_rad_s: float | None = None, gyro_spread_rad_s: float = 0.0) -> WheelUpdate:
        """Fuse the nominal wheel distance increments over the last dt_s (ending at t_s).

        `gyro_omega_rad_s` is the gyro's mean yaw rate over the same interval (raw, bias included),
        if any: it is the reference of the slip test and the consistency window; `gyro_spread_rad_s`
        half the range of the gyro samples over the interval (an omega that changed within it is not slip).
        """
        pending = self._pending_gyro
        if pending is not None and not abs(t_s - pending[0]) < SAME_INSTANT_S:
            self._flush()
        self.predict_to(t_s)
        L = self.track_width_m
        self.wheel_yaw_rad += (d_right_m - d_left_m) / L
        kf = self._kf
        x, P = kf.x, kf.P
        trusted = self.judge.trusted
        j = self.judge.judge(t_s, WheelInterval(d_left_m, d_right_m, dt_s, gyro_omega_rad_s, gyro_spread_rad_s), x, P)
        if trusted and not self.judge.trusted:
            self._unlearn(x, P)
        if j.slip or j.step:  # a step of the yaw rate is not a ramp: publishing does not extrapolate it
            self.sampling.alpha_rad_s2 = 0.0
        P[IWY, IWY] = j.heading_var  # slip, or the wheels not trusted: their heading error is free
        self._heading_jump(x, P)
        still = j.r_still is not None
        H, h = linearised = kf.linearise(True, self._pending_gyro is not None, still)  # the update's: speed row gates
        y = j.z_v - float(h[0])
        d2 = y * y / (float(H[0].dot(P).dot(H[0])) + j.r_v)
        accepted = self.wheels_gate.passes(d2)
        if accepted:
            self._update((j.z_v, j.r_v), linearised, j.r_still)
            x = kf.x
            q = float(x[IKR])
            missed_m = self.sampling.wheels(t_s, float(x[IV]), None if j.slip else
                                            (d_left_m + q * d_right_m) / (1.0 + q))
            yaw = float(x[IYAW])
            x[IX] += math.cos(yaw) * missed_m
            x[IY] += math.sin(yaw) * missed_m
        else:
            self._flush()
            self.sampling.wheels_refused()
        if j.stationary or self.judge.agreed:
            self._sound_bias, self._newest_sound_bias = self._newest_sound_bias, (float(kf.x[IB]), float(kf.P[IB, IB]))
        return WheelUpdate(accepted, j.slip, j.stationary, j.slip_d2, d2)

    def _unlearn(self, x: Vec, P: Mat) -> None:
        """The wheels now disagree with the gyro: the bias they taught since it was last sound (a checkpoint
        before the newest: the window that agreed last can hold the start of the disagreement) was their error,
        back to it, uncorrelated; the yaw gives back their turn beyond the gyro's in the disagreeing window,
        which it followed (their heading error takes it)."""
        turn, (x[IB], var) = self.judge.distrust_turn_rad, self._sound_bias
        x[IYAW], x[IWY] = wrap_angle(float(x[IYAW]) - turn), x[IWY] + turn
        P[IB, :] = P[:, IB] = 0.0
        P[IB, IB] = var

    def _heading_jump(self, x: Vec, P: Mat) -> None:
        """The wheels' heading further from the filter's (yaw + error) than the gate: they lost their
        reference (slip the interval's test missed, a wheel in the air, a miscounted reading). The error
        state takes the jump (process noise of its size), so the wheels measure turns from here on."""
        y = math.remainder(self.wheel_yaw_rad - float(x[IYAW]) - float(x[IWY]), 2.0 * math.pi)
        S = float(P[IYAW, IYAW] + 2.0 * P[IYAW, IWY] + P[IWY, IWY]) + self._heading_var
        if y * y > self._gate2 * S:
            self.heading_jumps += 1
            P[IWY, IWY] += y * y

    def _update(self, wheels: tuple[float, float] | None, linearised: tuple[Mat, Vec] | None = None,
                r_still: float | None = None) -> None:
        """One filterpy update of the waiting gyro sample (if any) and the wheels' (speed z, variance) with
        their heading (if given) and a standstill's zero yaw rate (variance r_still, if given); `linearised`:
        those rows' (H, h(x)) if already known."""
        kf, gyro, self._pending_gyro = self._kf, self._pending_gyro, None
        z: list[float] = []
        r: list[float] = []
        if wheels is not None:
            z += [wheels[0], self.wheel_yaw_rad]
            r += [wheels[1], self._heading_var]
            if r_still is not None:
                z.append(0.0)
                r.append(r_still)
        if gyro is not None:
            z.append(gyro[1])
            r.append(self._gyro_var)
        R = np.zeros((len(r), len(r)))
        R.flat[:: len(r) + 1] = r
        kf.update_rows(np.array(z), R, wheels is not None, gyro is not None, linearised, r_still is not None)
        kf.x[IYAW] = wrap_angle(float(kf.x[IYAW]))

    # -- resets
    def set_pose(self, pose: Pose2D, sigma_m: float = SIGMA0_POSE, sigma_yaw_rad: float = SIGMA0_POSE) -> None:
        """Put the pose at `pose` with a small uncertainty; velocities, bias and geometry are kept, and the
        wheels' heading turns with the pose (it is in the filter's frame)."""
        x, P = self.x, self._kf.P
        self.wheel_yaw_rad += wrap_angle(pose.yaw_rad - float(x[IYAW]))
        x[IX], x[IY], x[IYAW] = pose.x_m, pose.y_m, wrap_angle(pose.yaw_rad)
        P[0:3, :] = 0.0
        P[:, 0:3] = 0.0
        P[IX, IX] = P[IY, IY] = sigma_m ** 2
        P[IYAW, IYAW] = sigma_yaw_rad ** 2
