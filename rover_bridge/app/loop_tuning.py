"""The wheel speed loop's gains from the rover (pure): `rover-bridge calibrate`'s open-loop steps in, gains out.

The loop (rover_bridge/command/wheel_control.py) closes two motions, driving (the wheels' common speed)
and turning (half their difference), each on its own plant. Calibrate's straight runs are steps of the
common motion and its spins steps of the turning one, driven through the measured PWM maps (the
feedforward), from rest. Each step's response, as the loop would see it (wheel samples on arrival), is
fitted with a first-order lag plus a delay by the two-point method (Smith: the times to 28.3 % and
63.2 % of the final speed give lag = 1.5 (t63 - t28) and delay = t63 - lag).

The rule (SIMC, Skogestad 2003, a lambda/IMC tuning for that model):

    delay_eff = delay + the speed window's extra half (the loop averages over speed_window_s; the fit's
                samples average over one interval)
    tau_c     = 2 * delay_eff                  (the closed loop's time constant: robust, not tight)
    kp        = lag / (tau_c + delay_eff)
    ki        = kp / min(lag, 4 * (tau_c + delay_eff))       (1 / (tau_c + delay_eff) for no lag)
    reference = lag                            (the reference model is the plant the fit found)

A motion that answers at once (ArduPilot SITL's skid turn) gets no proportional gain and an integrator
alone, which a pure delay tolerates; a lagging one gets the P that its lag affords.
"""

from __future__ import annotations

import itertools
import math
import statistics
from dataclasses import dataclass

LOW, HIGH = 1.0 - math.exp(-1.0 / 3.0), 1.0 - math.exp(-1.0)  # 28.3 % and 63.2 % of the final value
FINAL_S = 1.0  # a step's final speed: the mean over its last second
MIN_LAG_S = 0.01  # the smallest reference lag the profile accepts


@dataclass(frozen=True, slots=True)
class Response:
    """A step's first-order-plus-delay fit, from the step's command."""

    lag_s: float
    delay_s: float


@dataclass(frozen=True, slots=True)
class Gains:
    kp: float
    ki_1_s: float
    reference_s: float


def fit_step(times_s: list[float], values: list[float], start_s: float) -> Response | None:
    """The fit of one step's response (times on the caller's clock, the step commanded at start_s); None when
    the response never settles in one direction (no final value to take fractions of)."""
    end_s = times_s[-1] if times_s else start_s
    tail = [v for t, v in zip(times_s, values, strict=True) if t >= end_s - FINAL_S]
    if len(tail) < 3:
        return None
    final = statistics.fmean(tail)
    if final == 0.0:
        return None
    crossing: list[float] = []
    for fraction in (LOW, HIGH):
        level = fraction * final
        prev_t, prev_v = start_s, 0.0
        for t, v in zip(times_s, values, strict=True):
            if t < start_s:
                continue
            if v / final >= fraction:  # crossed between the previous sample and this one: interpolate
                share = (level - prev_v) / (v - prev_v) if v != prev_v else 1.0
                crossing.append(prev_t + max(0.0, min(1.0, share)) * (t - prev_t))
                break
            prev_t, prev_v = t, v
        else:
            return None
    t28, t63 = crossing[0] - start_s, crossing[1] - start_s
    lag = max(0.0, 1.5 * (t63 - t28))
    return Response(lag, max(0.0, t63 - lag))


def mean_response(responses: list[Response | None]) -> Response | None:
    """The mean of the fits that exist (both directions of a motion)."""
    found = [r for r in responses if r is not None]
    if not found:
        return None
    return Response(statistics.fmean(r.lag_s for r in found), statistics.fmean(r.delay_s for r in found))


def gains(response: Response, speed_window_s: float, interval_s: float) -> Gains:
    """The rule of the module docstring."""
    delay = response.delay_s + max(0.0, 0.5 * (speed_window_s - interval_s))
    tau_c = 2.0 * delay
    lag = response.lag_s
    if not tau_c + delay > 0.0:  # a plant with neither lag nor delay: the slowest sensible loop is still one
        delay, tau_c = interval_s, 2.0 * interval_s
    kp = lag / (tau_c + delay)
    integral_s = min(lag, 4.0 * (tau_c + delay))
    ki = kp / integral_s if integral_s > 1e-6 else 1.0 / (tau_c + delay)
    return Gains(kp, ki, max(MIN_LAG_S, lag))


@dataclass(frozen=True, slots=True)
class EncoderTiming:
    interval_s: float  # the median interval between WHEEL_DISTANCE stamps
    jitter_s: float  # their standard deviation

    @staticmethod
    def from_stamps(stamps_s: list[float]) -> EncoderTiming | None:
        gaps = [b - a for a, b in itertools.pairwise(stamps_s) if b > a]
        if len(gaps) < 3:
            return None
        return EncoderTiming(statistics.median(gaps), statistics.pstdev(gaps))


@dataclass(frozen=True, slots=True)
class LoopTuning:
    """What calibrate measured of the two motions and the gains the rule gives."""

    driving: Response
    turning: Response
    encoder: EncoderTiming
    driving_gains: Gains
    turning_gains: Gains

    @staticmethod
    def identify(driving: Response | None, turning: Response | None, encoder: EncoderTiming | None,
                 speed_window_s: float) -> LoopTuning | None:
        if driving is None or turning is None or encoder is None:
            return None
        return LoopTuning(driving, turning, encoder, gains(driving, speed_window_s, encoder.interval_s),
                          gains(turning, speed_window_s, encoder.interval_s))

    def patch_lines(self) -> list[str]:
        d, t = self.driving_gains, self.turning_gains
        return [
            "# the loop's gains by the SIMC rule (rover_bridge/app/loop_tuning.py): driving lag "
            f"{self.driving.lag_s:.3f} s delay {self.driving.delay_s:.3f} s, turning lag {self.turning.lag_s:.3f} s "
            f"delay {self.turning.delay_s:.3f} s",
            f"kp = {d.kp:.3f}", f"ki_1_s = {d.ki_1_s:.3f}", f"reference_s = {d.reference_s:.3f}",
            f"turn_kp = {t.kp:.3f}", f"turn_ki_1_s = {t.ki_1_s:.3f}", f"turn_reference_s = {t.reference_s:.3f}",
        ]

    def report_rows(self) -> list[tuple[str, str]]:
        d, t = self.driving_gains, self.turning_gains
        return [
            ("driving: lag / delay", f"{self.driving.lag_s:.3f} / {self.driving.delay_s:.3f} s"),
            ("turning: lag / delay", f"{self.turning.lag_s:.3f} / {self.turning.delay_s:.3f} s"),
            ("encoder interval / jitter",
             f"{self.encoder.interval_s * 1e3:.1f} / {self.encoder.jitter_s * 1e3:.1f} ms"),
            ("driving kp / ki / reference", f"{d.kp:.2f} / {d.ki_1_s:.2f} 1/s / {d.reference_s:.3f} s"),
            ("turning kp / ki / reference", f"{t.kp:.2f} / {t.ki_1_s:.2f} 1/s / {t.reference_s:.3f} s"),
        ]
