"""What the filter makes of a wheel interval before fusing it (wheel_judge, consistency) and what its
prediction misses between samples (sampling): hand cases, each decision on its own."""

# Kalman-filter notation (P for a covariance) reads better than pep8 names here.
# ruff: noqa: N806

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from rover_bridge.estimate.consistency import AGREE_WINDOWS, WINDOW_S, ConsistencyWindow
from rover_bridge.estimate.models import IB, IKR, IKT, IV, IW, IWY, IYAW, N_STATES, NoiseModel
from rover_bridge.estimate.sampling import GYRO_SAMPLING_FACTOR, SampleCorrections
from rover_bridge.estimate.wheel_judge import (
    DISTRUST_SIGMA_RAD,
    STATIONARY_SIGMA_V_M_S,
    WheelInterval,
    WheelJudge,
)

L = 0.30
NOISE = NoiseModel()
DT = 0.05


def _state(v: float = 0.5, w: float = 0.0, bias: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    x = np.zeros(N_STATES)
    x[IV], x[IW], x[IB] = v, w, bias
    x[IKT] = x[IKR] = 1.0
    P = np.diag([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-8, 0.0, 0.0, 1e-6])
    return x, P


def _interval(v: float, w_wheels: float, w_gyro: float | None, dt: float = DT) -> WheelInterval:
    return WheelInterval((v - 0.5 * w_wheels * L) * dt, (v + 0.5 * w_wheels * L) * dt, dt, w_gyro)


# ---------------------------------------------------------------- wheel_judge

def test_a_standstill_bounds_the_speed_tighter_the_longer_it_lasts() -> None:
    noise = NoiseModel(wheel_noise_m=0.001)
    judge = WheelJudge(L, noise)
    x, P = _state(v=0.0)
    variances = [judge.judge(t * DT, WheelInterval(0.0, 0.0, DT, 0.0), x, P).r_v for t in range(1, 200)]
    assert variances[0] == pytest.approx((noise.wheel_noise_m / DT) ** 2)
    assert variances[9] == pytest.approx((noise.wheel_noise_m / (10 * DT)) ** 2)  # still for 0.5 s
    assert variances[-1] == STATIONARY_SIGMA_V_M_S**2  # never tighter than this
    assert all(b <= a for a, b in itertools.pairwise(variances))


def test_the_speed_is_the_one_at_the_end_of_the_interval() -> None:
    # Wheels measure each interval's mean: accelerating from 0.4 to 0.5 m/s (means) the speed at the end
    # of the second interval is half an interval further, 0.55 m/s.
    judge = WheelJudge(L, NOISE)
    x, P = _state()
    judge.judge(DT, _interval(0.4, 0.0, 0.0), x, P)
    j = judge.judge(2 * DT, _interval(0.5, 0.0, 0.0), x, P)
    assert j.z_v == pytest.approx(0.55)
    assert judge.accel_m_s2 == pytest.approx(2.0)


def test_slip_takes_the_speed_of_the_slower_wheel_and_frees_the_wheels_heading() -> None:
    judge = WheelJudge(L, NOISE)
    x, P = _state()
    # the left wheel spins 0.3 m/s faster than the ground; the right one and the gyro (0) say 0.5 m/s
    first = judge.judge(DT, WheelInterval(0.8 * DT, 0.5 * DT, DT, 0.0), x, P)
    assert first.step and not first.slip  # one interval past the gate: a step, the wheels' speed kept
    assert first.z_v == pytest.approx(0.65)
    j = judge.judge(2 * DT, WheelInterval(0.8 * DT, 0.5 * DT, DT, 0.0), x, P)  # it goes on: slip
    assert j.slip and j.z_v == pytest.approx(0.5)
    assert j.heading_var >= P[IWY, IWY] + (0.3 / L * DT) ** 2  # the disagreement, at least


def test_a_yaw_that_wobbles_faster_than_the_samples_is_steps_not_slip() -> None:
    # A real Rover SITL's go-to start on its 1.64 m model track: the skid model turns at once, and the wheels'
    # yaw rate over each 40-60 ms interval swung -0.36, -0.49, -0.09, +0.23, -0.62 rad/s against the gyro's
    # instants at the ends (the intervals below are that run's).
    # Disagreements past the gate that change sign from one interval to the next are aliasing, not a
    # spinning wheel: each is a step, and the speed stays the wheels' (taken for slip, the slower wheel and
    # the gyro gave -0.02 m/s for a rover driving at +0.17 and the go-to stopped 0.9 m past its target).
    track = 1.6370222718
    judge = WheelJudge(track, NOISE)
    x, P = _state(v=0.2, w=-0.3)
    intervals = [(0.0193, -0.0163, 0.06, -0.0995, 0.097), (0.0189, -0.0129, 0.04, -0.2768, 0.081),
                 (0.0147, 0.0056, 0.06, -0.3192, 0.038), (0.0039, 0.0189, 0.04, -0.1741, 0.107),
                 (0.0294, 0.0202, 0.06, -0.0236, 0.044), (0.0413, 0.0010, 0.04, -0.0867, 0.107),
                 (0.0625, 0.0127, 0.061, -0.3390, 0.146), (0.0254, 0.0294, 0.04, -0.4234, 0.061)]
    t = 0.0
    past_gate = 0
    for dl, dr, dt, gyro, spread in intervals:
        t += dt
        j = judge.judge(t, WheelInterval(dl, dr, dt, gyro, spread), x, P)
        past_gate += j.slip_d2 > NOISE.gate_sigma ** 2
        assert not j.slip
        assert j.z_v == pytest.approx(0.5 * (dl + dr) / dt, abs=0.1)  # the wheels' speed, not a slower one
    assert past_gate >= 3  # the slip test's gate alone would have called these slip


def test_the_wheels_heading_is_trusted_again_only_after_a_standstill_and_whole_agreeing_windows() -> None:
    judge = WheelJudge(L, NOISE)
    x, P = _state(w=0.5)
    t = 0.0

    def drive(seconds: float, w_wheels: float, w_gyro: float, v: float = 0.5) -> float:
        nonlocal t
        var = 0.0
        for _ in range(round(seconds / DT)):
            t += DT
            var = judge.judge(t, _interval(v, w_wheels, w_gyro), x, P).heading_var
        return var

    assert drive(2.0, 0.5, 0.5) == P[IWY, IWY] and judge.trusted  # they agree
    # distrusted: the heading they predict (yaw + their error) is free
    free = DISTRUST_SIGMA_RAD**2 - P[IYAW, IYAW] - 2.0 * P[IYAW, IWY]
    # the wheels turn 3 % less than the gyro (a track 3 % off): not slip, but they disagree over the window
    assert drive(1.0, 0.485, 0.5) >= free and not judge.trusted
    assert drive(3.0, 0.5, 0.5) >= free  # agreeing again in motion is not enough
    drive(0.5, 0.0, 0.0, v=0.0)  # a standstill
    assert not judge.trusted
    drive(WINDOW_S * (AGREE_WINDOWS + 0.5), 0.5, 0.5)
    assert judge.trusted



def test_distrusted_wheels_heading_is_free_also_when_the_yaw_is_unknown() -> None:
    # Hours without a standstill: the yaw (bias integrated) is 2 rad uncertain, and the wheels' heading error, last
    # re-anchored to it, is its mirror (yaw + error known to a reading). A floor of DISTRUST_SIGMA_RAD on the error
    # alone (it is already 2 rad) left the heading they predict a reading's width: distrusted wheels held the yaw
    # rate again and taught the gyro their drift as a bias.
    judge = WheelJudge(L, NOISE)
    x, P = _state(w=0.5)
    P[IYAW, IYAW] = P[IWY, IWY] = 4.0
    P[IYAW, IWY] = P[IWY, IYAW] = -4.0 + 1e-6
    t = 0.0
    for _ in range(round(0.5 / DT)):  # disagreeing (a track 3 % off)
        t += DT
        var = judge.judge(t, _interval(0.5, 0.485, 0.5), x, P).heading_var
    assert not judge.trusted
    assert P[IYAW, IYAW] + 2.0 * P[IYAW, IWY] + var >= DISTRUST_SIGMA_RAD**2

def test_the_slip_test_allows_the_gyros_noise_bias_and_spread() -> None:
    judge = WheelJudge(L, NOISE)
    x, P = _state(w=0.5, bias=0.01)
    # the gyro reads bias + rate: 0.51 is the wheels' 0.5
    assert judge.slip_d2(0.5, 1e-6, 0.51, x, P) == pytest.approx(0.0, abs=1e-9)
    d2 = judge.slip_d2(0.6, 1e-6, 0.51, x, P)
    assert judge.slip_d2(0.6, 1e-6, 0.51, x, P, gyro_spread_rad_s=0.1) < d2  # a rate that changed within


def test_a_step_of_the_gyros_rate_the_wheels_did_not_follow_frees_their_heading_but_keeps_their_speed() -> None:
    # Slip starting within the interval: the gyro's rate jumps from 0 to 0.8 rad/s (its samples' mean 0.4,
    # their spread 0.4), the wheels still read a straight 0.8 m/s. The spread hides it from the slip test;
    # the wheels' heading must not hold the yaw through it.
    judge = WheelJudge(L, NOISE)
    x, P = _state(v=0.8)
    j = judge.judge(DT, WheelInterval(0.8 * DT, 0.8 * DT, DT, 0.4, 0.4), x, P)
    assert not j.slip and j.step
    assert j.z_v == pytest.approx(0.8)  # the speed is the wheels'
    assert j.heading_var >= P[IWY, IWY] + (0.4 * DT) ** 2  # the turn they missed, at least


def test_a_step_is_not_held_against_the_wheels_by_the_consistency_window() -> None:
    # A slip edge's interval is a step (its heading already freed): agreeing wheels around it stay trusted,
    # and it is not part of what the yaw gives back if they are distrusted later.
    judge = WheelJudge(L, NOISE)
    x, P = _state(v=0.8)
    t = 0.0
    for k in range(60):
        t += DT
        gyro = 0.3 if k in (20, 21) else 0.0  # the wheels miss 0.3 rad/s for two intervals (a slip's edge)
        j = judge.judge(t, WheelInterval(0.8 * DT, 0.8 * DT, DT, gyro), x, P)
        assert j.step == (k in (20, 21)) and not j.slip
    assert judge.trusted

def test_the_interval_after_a_step_settles_without_teaching_the_heading() -> None:
    # A turn's onset on a real Rover SITL: the wheels lead the gyro (a step), and in the next interval the
    # body's rate overshoots the wheels' by 3 %. Learnt from, that interval taught the track 2.8 % off; it is
    # not a step itself, and the one after it is judged as usual.
    judge = WheelJudge(L, NOISE)
    x, P = _state(v=0.8)
    turn = 0.6
    wheels = ((0.8 - 0.5 * turn * L) * DT, (0.8 + 0.5 * turn * L) * DT)
    assert judge.judge(DT, WheelInterval(*wheels, DT, 0.3 * turn, 0.5 * turn), x, P).step  # within the spread
    settling = judge.judge(2 * DT, WheelInterval(*wheels, DT, turn * 1.03, 0.0), x, P)
    assert not settling.step and not settling.slip
    assert settling.heading_var >= P[IWY, IWY] + (0.03 * turn * DT) ** 2
    after = judge.judge(3 * DT, WheelInterval(*wheels, DT, turn, 0.0), x, P)
    assert not after.step and after.heading_var == P[IWY, IWY]


def test_a_turn_the_wheels_follow_is_not_a_step() -> None:
    # The same change of the gyro's rate with the wheels turning as the body does (a turn through the
    # motors' lag): nothing is freed.
    judge = WheelJudge(L, NOISE)
    x, P = _state(v=0.8)
    j = judge.judge(DT, WheelInterval((0.8 - 0.5 * 0.38 * L) * DT, (0.8 + 0.5 * 0.38 * L) * DT, DT, 0.4, 0.4), x, P)
    assert not j.slip and not j.step
    assert j.heading_var == P[IWY, IWY]


# ---------------------------------------------------------------- consistency

def test_a_window_judges_only_a_whole_window_with_motion_in_it() -> None:
    window = ConsistencyWindow()

    def run(seconds: float, dist_m: float) -> list[bool | None]:
        verdicts = []
        for _ in range(round(seconds / DT)):
            window.add(DT, 0.0, 0.0, 1e-8, dist_m)
            verdicts.append(window.agree(1e-8, 1e-8))
        return verdicts

    assert run(2.0, 0.0) == [None] * 40  # no motion: agreement proves nothing
    window.clear()
    verdicts = run(WINDOW_S * AGREE_WINDOWS, 0.025)  # AGREE_WINDOWS whole windows of motion: trust
    assert verdicts.index(True) == len(verdicts) - 1


def test_a_disagreement_is_judged_at_once_against_what_the_noise_and_the_geometry_allow() -> None:
    window = ConsistencyWindow()
    for _ in range(round(0.3 / DT)):
        window.add(DT, 0.01, 0.002, 1e-8, 0.025)  # 2 mrad per interval against 0.1 mrad of noise
    assert window.agree(1e-8, 1e-8) is False
    # the same disagreement is the geometry's when its uncertainty then (1 sigma) was as large
    for _ in range(round(0.3 / DT)):
        window.add(DT, 0.01, 0.002, 1e-8, 0.025, geometry_rad=0.001)
    assert window.agree(1e-8, 1e-8) is None



def test_an_agreement_the_bias_doubt_could_hide_is_no_verdict() -> None:
    # Wheels drifting 0.05 rad/s from the gyro (a radius 2 % off at 0.8 m/s) with the bias unknown (0.02 rad/s,
    # a start without a standstill): within 5 sigma, but only thanks to the bias's doubt: no agreement. With the
    # bias known the same drift is a disagreement; with agreeing wheels it is an agreement.
    def verdicts(drift_rad_s: float, bias_var: float) -> list[bool | None]:
        window, out = ConsistencyWindow(), []
        for _ in range(round(WINDOW_S * AGREE_WINDOWS / DT)):
            window.add(DT, drift_rad_s * DT, drift_rad_s * DT, 1e-8, 0.04)
            out.append(window.agree(bias_var, 1e-8))
        return out

    assert set(verdicts(0.05, 0.02**2)) == {None}
    assert False in verdicts(0.05, 0.0002**2)
    assert verdicts(0.0, 0.0002**2)[-1] is True

# ---------------------------------------------------------------- sampling

def test_the_turn_between_gyro_samples_is_their_trapezoid() -> None:
    s = SampleCorrections()
    assert s.gyro(0.0, 0.0) == (0.0, 0.0)  # the first sample: nothing to correct
    s.predicted(0.0, 0.0, 0.02)  # the prediction turned at the last sample's rate, 0
    missed, var = s.gyro(0.02, 1.0)  # the rate rose to 1 rad/s: the body turned 0.01 rad
    assert missed == pytest.approx(0.01)
    assert var == pytest.approx((GYRO_SAMPLING_FACTOR * 1.0 * 0.02) ** 2)
    assert s.alpha_rad_s2 == pytest.approx(50.0)
    s.predicted(0.0, 1.0, 0.02)
    assert s.gyro(0.04, 1.0) == (pytest.approx(0.0), 0.0)  # a constant rate: the prediction was right
    s.restart()
    assert s.gyro(0.5, 2.0) == (0.0, 0.0)  # no trapezoid across a restart


def test_the_distance_is_what_the_wheels_measured_or_the_trapezoid_while_they_slip() -> None:
    s = SampleCorrections()
    s.predicted(0.4, 0.0, 0.05)  # the prediction moved 0.02 m
    assert s.wheels(0.05, 0.5, 0.0225) == pytest.approx(0.0025)  # the wheels went 0.0225
    s.predicted(0.5, 0.0, 0.05)
    assert s.wheels(0.10, 0.6, None) == pytest.approx(0.5 * (0.5 + 0.6) * 0.05 - 0.025)  # slip
    s.predicted(0.6, 0.0, 0.05)
    s.wheels_refused()
    assert s.wheels(0.20, 0.6, 0.03) == pytest.approx(0.03)  # the refused reading started the interval
    assert math.isclose(s.wheels(0.25, 0.6, 0.0), 0.0)


def test_a_spin_onset_the_wheels_counts_round_up_is_not_a_step() -> None:
    # rover-bridge demo in real time, a spin starting: over 20 ms the wheels' counts (0.3 mm) read 0.2 rad/s, the
    # gyro's two samples a mean of 0.125 (spread 0.071). 2.3 sigma, but 0.7 of a count on each wheel: taken for a
    # step, the heading was freed and the EKF kept 0.1 deg against the exact wheels for the rest of the run.
    judge = WheelJudge(L, NOISE)
    x, P = _state(v=0.0, w=0.1)
    j = judge.judge(0.02, WheelInterval(-0.00061, 0.00061, 0.02, 0.1253, 0.071), x, P)
    assert not j.step and not j.slip
    assert j.heading_var == P[IWY, IWY]  # the wheels' heading holds the yaw
