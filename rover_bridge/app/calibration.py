"""`rover-bridge calibrate`'s bring-up sequence and what it identifies (pure: samples and time in).

For a rover on the ground with room around it. After a standstill (the gyro's bias), the sequence:

1. PWM steps per wheel, each direction, the other wheel at trim (the rover pivots about it): each
   step settles, then the wheel's speed is averaged (WHEEL_DISTANCE, as the bridge measures it). The
   first clear step of each wheel is a wiring check against the gyro: a left wheel driven forward
   must turn the rover clockwise about the right one, and its own encoder must count forward.
2. Straight runs forward and back at equal wheel speeds (through the curves just measured): the
   gyro's turn against the wheels' gives the right/left radius ratio.
3. Spins in place both ways: the gyro's turn against the wheels' speed difference gives the
   effective track width (what the wheels' distances say about turning; skid steering makes it
   larger than the physical track). Both ways, so the gyro's bias cancels.

Identified: per wheel and direction the deadband edge and the PWM -> speed table (the speed at full
PWM over the profile's top speed is the wheel's gain), the effective track, the radius ratio; as a
profile patch ([robot] track_width_m and per-wheel radii with their mean kept, [control] curves)
that the profile loader accepts. The sequence never runs a step's PWM without the safety paths of
the command core (CommandCore.set_direct): link loss, disarm, a stop mode or a fault end it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from rover_bridge.app.loop_tuning import EncoderTiming, LoopTuning, Response, fit_step, mean_response
from rover_bridge.command.outputs import SpeedCurve, WheelPwm
from rover_bridge.kinematics import MeasuredWheels
from rover_bridge.params import Profile

FULL_OFFSETS_US = (25, 50, 75, 100, 150, 250, 350, 500)
QUICK_OFFSETS_US = (50, 150, 500)
STANDSTILL_S = 3.0
SETTLE_S = 0.4  # neutral between steps (the rover stops)
STEP_S = 1.0  # each step; its speed is the mean over the last MEASURE_S
MEASURE_S = 0.5
RUN_S = 3.0  # straight runs and spins; measured over the last RUN_MEASURE_S
RUN_MEASURE_S = 2.0
MOVING_FRACTION = 0.03  # of the top speed: a wheel moving at all (the deadband's edge)
RUN_FRACTION = 0.4  # straight runs and spins at this fraction of the slower wheel's top speed
CHECK_OFFSET_US = 150  # the wiring check's step (the first clearly moving one)


@dataclass(frozen=True, slots=True)
class Step:
    name: str
    left_us: int
    right_us: int
    duration_s: float
    kind: str  # settle | wheel | straight | spin
    wheel: str = ""  # left | right for a wheel step
    offset_us: int = 0


@dataclass
class Window:
    """Samples collected during one step's measuring window."""

    left: list[float] = field(default_factory=list)
    right: list[float] = field(default_factory=list)
    gyro: list[float] = field(default_factory=list)  # CCW, bias removed

    def mean(self, values: list[float]) -> float:
        return sum(values) / len(values) if values else math.nan


@dataclass(frozen=True, slots=True)
class WheelResult:
    pwm_us: tuple[float, ...]
    speed_rad_s: tuple[float, ...]
    deadband_us: tuple[float, float]  # (reverse edge, forward edge), offsets from trim
    gain_forward: float  # speed at full PWM / the profile's top speed
    gain_reverse: float


@dataclass(frozen=True, slots=True)
class CalibrationResult:
    left: WheelResult
    right: WheelResult
    track_width_m: float
    radius_ratio: float  # right / left effective radius
    left_radius_m: float
    right_radius_m: float
    tuning: LoopTuning | None = None  # the loop's gains from the runs' responses (rover_bridge.app.loop_tuning)

    def patch_toml(self, header: str = "") -> str:
        """A profile patch the loader accepts: copy these keys into your profile."""
        def floats(values: tuple[float, ...], digits: int) -> str:
            return "[" + ", ".join(f"{v:.{digits}f}" for v in values) + "]"

        lines = robot_patch_lines(header, self.track_width_m, self.radius_ratio, self.left_radius_m,
                                  self.right_radius_m, "from spins against the gyro")
        lines += [
            "",
            "[control]",
            f"left_curve_pwm_us = {floats(self.left.pwm_us, 1)}",
            f"left_curve_rad_s = {floats(self.left.speed_rad_s, 3)}",
            f"right_curve_pwm_us = {floats(self.right.pwm_us, 1)}",
            f"right_curve_rad_s = {floats(self.right.speed_rad_s, 3)}",
        ]
        if self.tuning is not None:
            lines += self.tuning.patch_lines()
        return "\n".join(lines) + "\n"


def robot_patch_lines(header: str, track_width_m: float, radius_ratio: float, left_radius_m: float,
                      right_radius_m: float, source: str) -> list[str]:
    """The header as comments and the [robot] keys of a profile patch (calibrate's, and the fleet report's)."""
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    return [
        *lines,
        "[robot]",
        f"track_width_m = {track_width_m:.4f}  # effective (skid steering), {source}",
        f"left_wheel_radius_m = {left_radius_m:.5f}  # ratio {radius_ratio:.4f}, the mean kept",
        f"right_wheel_radius_m = {right_radius_m:.5f}",
    ]


def radii_for_ratio(mean_radius_m: float, radius_ratio: float) -> tuple[float, float]:
    """(left, right) radii with right / left = radius_ratio and their mean kept."""
    return mean_radius_m * 2.0 / (1.0 + radius_ratio), mean_radius_m * 2.0 * radius_ratio / (1.0 + radius_ratio)


class Calibration:
    """The sequence (see the module docstring). The shell calls `tick(now)` for the PWM to drive (None
    when done or aborted), and hands it every wheel sample and the gyro (`sample`)."""

    def __init__(self, profile: Profile, quick: bool = False) -> None:
        self.profile = profile
        out = profile.output
        self.trim = out.pwm_trim
        self.top_rad_s = profile.robot.max_wheel_rad_s
        self.offsets = QUICK_OFFSETS_US if quick else FULL_OFFSETS_US
        self.steps: list[Step] = [Step("standstill", self.trim, self.trim, STANDSTILL_S, "settle")]
        for wheel in ("left", "right"):
            for sign in (1, -1):
                for off in self.offsets:
                    pwm = max(out.pwm_min, min(out.pwm_max, self.trim + sign * off))
                    left, right = (pwm, self.trim) if wheel == "left" else (self.trim, pwm)
                    self.steps.append(Step("settle", self.trim, self.trim, SETTLE_S, "settle"))
                    self.steps.append(Step(f"{wheel} {'+' if sign > 0 else '-'}{off} us", left, right, STEP_S,
                                           "wheel", wheel, sign * off))
        self._runs_from = len(self.steps)  # straight runs and spins are added once the curves are known
        self.index = -1
        self._step_start_s = 0.0
        self.windows: dict[int, Window] = {}
        # Each run's response from its start, as the loop would see it: (arrival time, common, turn) speeds.
        self.traces: dict[int, list[tuple[float, float, float]]] = {}
        self._starts_s: dict[int, float] = {}  # when each step's PWM went out
        self.stamps_s: list[float] = []  # every wheel sample's own stamp (the encoder's interval and jitter)
        self.error: str | None = None
        self.done = False
        self.result: CalibrationResult | None = None
        self._curves: tuple[WheelResult, WheelResult] | None = None

    # ------------------------------------------------------------------ progress
    @property
    def step(self) -> Step | None:
        return self.steps[self.index] if 0 <= self.index < len(self.steps) else None

    @property
    def total_s(self) -> float:
        runs = 4 * (SETTLE_S + RUN_S) if self._curves is None else 0.0
        return sum(s.duration_s for s in self.steps) + runs

    def elapsed_s(self, now_s: float) -> float:
        done = sum(s.duration_s for s in self.steps[: max(0, self.index)])
        return done + (now_s - self._step_start_s if self.step is not None else 0.0)

    # ------------------------------------------------------------------ inputs
    def sample(self, wheels: MeasuredWheels, gyro_ccw_rad_s: float | None, now_s: float) -> None:
        step = self.step
        self.stamps_s.append(wheels.stamp_s)
        if step is None or step.kind == "settle":
            return
        s = wheels.speeds
        if step.kind in ("straight", "spin"):
            self.traces.setdefault(self.index, []).append(
                (now_s, 0.5 * (s.left_rad_s + s.right_rad_s), 0.5 * (s.right_rad_s - s.left_rad_s)))
        window_s = MEASURE_S if step.kind == "wheel" else RUN_MEASURE_S
        if now_s < self._step_start_s + step.duration_s - window_s:
            return
        w = self.windows.setdefault(self.index, Window())
        w.left.append(wheels.speeds.left_rad_s)
        w.right.append(wheels.speeds.right_rad_s)
        if gyro_ccw_rad_s is not None:
            w.gyro.append(gyro_ccw_rad_s)

    # ------------------------------------------------------------------ time
    def tick(self, now_s: float) -> WheelPwm | None:
        if self.done or self.error is not None:
            return None
        if self.index < 0:
            self.index, self._step_start_s = 0, now_s
        step = self.steps[self.index]
        if now_s >= self._step_start_s + step.duration_s:
            self._finished(self.index)
            if self.error is not None:
                return None
            self.index += 1
            self._step_start_s = now_s
            self._starts_s[self.index] = now_s
            if self.index == self._runs_from and self._curves is None:
                self._curves = (self._wheel_result("left"), self._wheel_result("right"))
                if self.error is not None:
                    return None
                self._add_runs()
            if self.index >= len(self.steps):
                self.result = self._identify()
                self.done = True
                return None
            step = self.steps[self.index]
        return WheelPwm(step.left_us, step.right_us)

    def abort(self, reason: str) -> None:
        if not self.done:
            self.error = reason

    # ------------------------------------------------------------------ checks and identification
    def _finished(self, index: int) -> None:
        step = self.steps[index]
        if step.kind != "wheel" or step.offset_us != CHECK_OFFSET_US:
            return
        w = self.windows.get(index)
        if w is None or not w.left:
            self.error = "no wheel speeds arrived during the steps (WHEEL_DISTANCE stream, WENC_* set?)"
            return
        own = w.mean(w.left if step.wheel == "left" else w.right)
        other = w.mean(w.right if step.wheel == "left" else w.left)
        turn = w.mean(w.gyro)
        moving = MOVING_FRACTION * self.top_rad_s
        # Driving the left wheel forward pivots the rover clockwise (omega < 0) about the right one.
        expected_turn = -1.0 if step.wheel == "left" else 1.0
        if abs(own) < moving and abs(other) > moving:
            self.error = (f"the {step.wheel} output moved the other wheel's encoder: channels or encoder "
                          "indices swapped (output.*_channel, encoders.*_index)")
        elif abs(own) < moving and abs(other) < moving:
            self.error = (f"the {step.wheel} wheel did not move at +{CHECK_OFFSET_US} us: check its channel, "
                          "SERVOn_FUNCTION (51..66 passthrough), the motor's power and the encoder")
        elif math.isfinite(turn) and turn * expected_turn < 0.0 and own > 0.0:
            self.error = (f"the {step.wheel} wheel turns backwards but its encoder counts forward: the motor "
                          f"and the encoder are both reversed (output.{step.wheel}_reversed and "
                          f"encoders.{step.wheel}_reversed)")
        elif math.isfinite(turn) and turn * expected_turn < 0.0:
            self.error = (f"the {step.wheel} motor runs backwards for PWM above trim: set output.{step.wheel}"
                          "_reversed = true (or swap the motor's wires), then calibrate again")
        elif own < 0.0:
            self.error = (f"the {step.wheel} encoder counts backwards (the rover turned the right way): set "
                          f"encoders.{step.wheel}_reversed = true, then calibrate again")

    def _wheel_result(self, wheel: str) -> WheelResult:
        points: list[tuple[float, float]] = []
        for i, step in enumerate(self.steps[: self._runs_from]):
            if step.kind == "wheel" and step.wheel == wheel:
                w = self.windows.get(i)
                mean = w.mean(w.left if wheel == "left" else w.right) if w is not None else math.nan
                if math.isfinite(mean):
                    points.append((float(self.trim + step.offset_us), mean))
        moving = MOVING_FRACTION * self.top_rad_s
        fwd = sorted((p, s) for p, s in points if p > self.trim and s > moving)
        rev = sorted(((p, s) for p, s in points if p < self.trim and s < -moving), reverse=True)
        if len(fwd) < 2 or len(rev) < 2:
            self.error = f"the {wheel} wheel moved at fewer than two steps in a direction: no curve can be fitted"
            return WheelResult((), (), (0.0, 0.0), math.nan, math.nan)
        edge_f = _zero_crossing(fwd[0], fwd[1], lo=self.trim, hi=fwd[0][0])
        edge_r = _zero_crossing(rev[0], rev[1], lo=rev[0][0], hi=self.trim)
        pwm, speed = _monotone([p for p, _ in reversed(rev)] + [edge_r, edge_f] + [p for p, _ in fwd],
                               [s for _, s in reversed(rev)] + [0.0, 0.0] + [s for _, s in fwd])
        full_f = max(s for _, s in fwd)
        full_r = min(s for _, s in rev)
        return WheelResult(tuple(pwm), tuple(speed), (edge_r - self.trim, edge_f - self.trim),
                           full_f / self.top_rad_s, -full_r / self.top_rad_s)

    def _add_runs(self) -> None:
        assert self._curves is not None
        left, right = (SpeedCurve(c.pwm_us, c.speed_rad_s) for c in self._curves)
        speed = RUN_FRACTION * min(left.max_forward_rad_s, -left.max_reverse_rad_s, right.max_forward_rad_s,
                                   -right.max_reverse_rad_s)

        def pwm(curve: SpeedCurve, rad_s: float) -> int:
            return round(curve.pwm_for(rad_s, float(self.trim)))

        for name, kind, sl, sr in (("straight forward", "straight", speed, speed),
                                   ("straight back", "straight", -speed, -speed),
                                   ("spin left", "spin", -speed, speed), ("spin right", "spin", speed, -speed)):
            self.steps.append(Step("settle", self.trim, self.trim, SETTLE_S, "settle"))
            self.steps.append(Step(name, pwm(left, sl), pwm(right, sr), RUN_S, kind))

    def _identify(self) -> CalibrationResult | None:
        assert self._curves is not None
        r_nom = self.profile.robot.wheel_radius_m
        tracks, ratios = [], []
        spins: list[tuple[float, float]] = []
        for i, step in enumerate(self.steps):
            w = self.windows.get(i)
            if w is None or not w.gyro or step.kind not in ("straight", "spin"):
                continue
            vl, vr, turn = w.mean(w.left) * r_nom, w.mean(w.right) * r_nom, w.mean(w.gyro)
            if step.kind == "spin" and abs(turn) > 1e-3:
                tracks.append((vr - vl) / turn)
                spins.append((vr - vl, turn))
            elif step.kind == "straight":
                ratios.append((vl, vr, turn))
        if not tracks:
            self.error = "no gyro during the spins: the track width cannot be identified"
            return None
        # Both spins together: a gyro bias adds to one turn and takes from the other.
        track = sum(abs(dv) for dv, _ in spins) / sum(abs(t) for _, t in spins)
        q_values = []
        for vl, vr, turn in ratios:
            num, den = 2.0 * vl + turn * track, 2.0 * vr - turn * track
            if abs(den) > 1e-6 and num / den > 0.0:
                q_values.append(num / den)
        q = sum(q_values) / len(q_values) if q_values else 1.0
        left, right = self._curves
        return CalibrationResult(left, right, track, q, *radii_for_ratio(r_nom, q), self._tuning())

    def _tuning(self) -> LoopTuning | None:
        """Each motion's response to its runs (both directions), the encoder's timing, and the gains."""
        fits: dict[str, list[Response | None]] = {"straight": [], "spin": []}
        for i, step in enumerate(self.steps):
            trace = self.traces.get(i)
            if trace and step.kind in fits:
                column = 1 if step.kind == "straight" else 2
                start = self._starts_s.get(i, trace[0][0])
                fits[step.kind].append(fit_step([r[0] for r in trace], [r[column] for r in trace], start))
        return LoopTuning.identify(mean_response(fits["straight"]), mean_response(fits["spin"]),
                                   EncoderTiming.from_stamps(self.stamps_s), self.profile.control.speed_window_s)


def _zero_crossing(a: tuple[float, float], b: tuple[float, float], lo: float, hi: float) -> float:
    """PWM where the line through two (pwm, speed) points reaches zero speed, clamped to [lo, hi]."""
    (p0, s0), (p1, s1) = a, b
    edge = p0 if s1 == s0 else p0 - s0 * (p1 - p0) / (s1 - s0)
    return min(max(edge, lo), hi)


def _monotone(pwm: list[float], speed: list[float]) -> tuple[list[float], list[float]]:
    """A map the loader accepts: PWM strictly increasing (nudged by 0.1 us), speeds never decreasing."""
    out_p, out_s = [pwm[0]], [speed[0]]
    for p, s in zip(pwm[1:], speed[1:], strict=True):
        out_p.append(max(p, out_p[-1] + 0.1))
        out_s.append(max(s, out_s[-1]))
    return out_p, out_s
