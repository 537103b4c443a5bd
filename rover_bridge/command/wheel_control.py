"""Closed-loop wheel speeds (pure): the speed each wheel was asked for, on real motors.

Between the kinematics and the PWM map ([control] mode = closed_loop). The two wheels' speeds are
split into the two motions a skid rover has, each its own plant:

    common = (left + right) / 2    (driving: its speed lags the motors, the body's mass)
    turn   = (right - left) / 2    (turning: on a skid rover it may not lag at all: ArduPilot's SITL
                                    model turns the instant its motors differ)

and each is closed on its own (two degrees of freedom: feedforward, a reference model, PI):

    u = target + kp * e + I,    e = r(t - delay) - measured,    I += ki * e * dt

in wheel speed units (rad/s); u (per wheel: common - turn, common + turn) then goes through the PWM
map (the measured curve where the profile has one: the feedforward).

- r, the reference model, is the target through a first-order lag (reference_s for driving,
  turn_reference_s for turning): the response the feedforward alone should give. It is compared with
  the measurement as it was when that was measured (`delay`: the measurement's own age, half the
  span it averages, see below). The error is then only what the feedforward gets wrong (a weak motor,
  a load, a deadband), not the plant's lag or the encoder's delay: a ramp does not wind the
  integrator up, and a loop tuned for one plant does not ring on another. The integrators learn only once
  the reference has settled (SETTLED_FRACTION): a plant faster or slower than the model (the defaults
  know neither) shows a transient error that is its lag, not a deficit to integrate.
- The gains come from the rover: `rover-bridge calibrate` measures each motion's lag and the encoder's
  delay and writes them by the lambda (IMC) rule (rover_bridge.app.calibration.loop_gains). The
  defaults assume nothing: no proportional gain (a plant that answers at once, behind a delay of two
  encoder intervals, rings under any P of 1 or more), and an integrator slow enough to be stable
  on a pure delay and on a lag of 0.3 s alike. Slower than a tuned loop; never ringing.
- The measured speed is the mean over the last speed_window_s of WHEEL_DISTANCE samples (the distance
  travelled over their span): ArduPilot stamps WHEEL_DISTANCE with its send time while its encoders
  are read on another 50 Hz task, so sample by sample the increments are uneven (0, 1 or 2 readings
  in one message: speeds off by 100 %); over a window the error is one reading at each end.
- Desaturation: when a wheel's u is beyond what its motor can do (its map's range), both wheels' u
  are scaled by one common factor, as the open-loop clamp does, so the path's curvature is kept.
- Anti-windup: while the output is saturated, or the kinematics already scaled the targets down, or a
  wheel is held at zero by the direction rule (below) or slowed by the handover slew, the integrators
  may only shrink; they are clamped to integrator_max_fraction of the top speed.
- Handover slew: for HANDOVER_S after the loop (re)starts, a wheel's command shrinks by at most
  max_step_rad_s2 per second, the wheel acceleration the limiter's own limits allow: a loop taking
  over a moving rover (from the autopilot's own demand, which it does not close) does not cut a wheel
  faster than the limiter would. A growing command is not slewed, nor a stop.
- Resets: targets of zero (neutral, idle, timeout done, link lost, disarmed, refused, stopped) clear
  the integrators and give zero: a stop never kicks a wheel backwards. A non-zero target is never
  answered with the opposite direction either (braking is the limiter's ramp, not reverse thrust).
- Missing samples: the loop acts only on a current measurement, one no older than OVERDUE_INTERVALS
  of the encoder's own sample interval. Without one it holds: u = target + the correction the
  integrators had learnt, per wheel scaled with its target (never more than it was, none for a target
  of the other sign), the integrators frozen, no P term. A sample that spans more than
  encoder_timeout_s (the first after a silence) is the mean over the silence: the window starts
  again. Encoders silent for encoder_timeout_s are stale (`closed` False: the core says so once).
- Slip (the estimator's verdict): the integrators are frozen (slipping wheels read too fast).
- Stall: a wheel below STILL_FRACTION of its target while commanded beyond
  BREAKAWAY_FRACTION of its top speed is held (stalled or jammed): the integrators stop and the reference
  model starts again from the measured speeds, so when it is released it spins up to the steady command,
  not a wound-up one. Below that command a still wheel is
  a deadband or a weak low end that the integrators must find.

A D term is left out: at 20-50 Hz encoder rates a derivative of a differentiated distance is noise.

WiringMonitor: at bring-up the most common failure of per-wheel control is wiring (a swapped
channel, a reversed motor or encoder, swapped encoder indices). A wheel commanded above
fault_min_fraction of its top speed that turns the wrong way, or not at all, for fault_time_s is
a fault; it says which wheel, what it did and what to check.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
from rover_bridge.params import ControlParams

STILL_FRACTION = 0.1  # measured below this fraction of the target: the wheel does not turn
BREAKAWAY_FRACTION = 0.4  # ... while commanded at least this fraction of its top speed (below: a deadband to find)
BACKWARDS_FRACTION = 0.2  # measured at least this fraction of the target, opposite sign: wrong way
SWAP_TOLERANCE = 0.3  # each wheel within this fraction of the other's target: swapped
SWAP_MIN_DIFFERENCE = 0.3  # the two targets must differ by this fraction of the larger to tell a swap
RUNAWAY_FACTOR = 1.5  # measured beyond this times the target (plus a margin of the top speed): runs away,
RUNAWAY_MARGIN = 0.1  # what a closed loop does to a wheel whose encoder is another wheel's
# A measurement is current while no older than this many of the encoder's sample intervals: one lost
# sample (two intervals) is not a silence yet.
OVERDUE_INTERVALS = 2.5
HANDOVER_S = 1.0  # the slew's window after the loop (re)starts (docstring)
# The integrators learn only while the reference has settled within this fraction of the target (or of the top
# speed, near zero): during a step the plant's own lag, whatever it is, is not mistaken for a weak motor.
SETTLED_FRACTION = 0.05
HISTORY_S = 1.0  # how far back the reference model's past is kept for the measurement's delay


def to_modes(left: float, right: float) -> tuple[float, float]:
    """Wheel speeds -> (common, turn)."""
    return 0.5 * (left + right), 0.5 * (right - left)


def to_wheels(common: float, turn: float) -> tuple[float, float]:
    """(common, turn) -> wheel speeds (left, right)."""
    return common - turn, common + turn


class SpeedWindow:
    """The wheels' mean speeds over the last `window_s` of samples, on the samples' own stamps."""

    def __init__(self, window_s: float, max_interval_s: float = 1.0) -> None:
        self.window_s = window_s
        self.max_interval_s = max_interval_s
        self.value: WheelSpeeds | None = None
        self.interval_s: float | None = None  # between the last two samples' stamps
        self.span_s = 0.0  # how long the value averages over
        self._stamp_s: float | None = None
        self._parts: deque[tuple[float, float, float]] = deque()  # (span, left * span, right * span)

    def update(self, sample: MeasuredWheels) -> WheelSpeeds | None:
        """The mean speeds; None for a sample that spans more than max_interval_s (the mean over a
        silence, not the wheels' speed) or the first one (its span is not known): the window starts again."""
        stamp = self._stamp_s
        self._stamp_s = sample.stamp_s
        span = sample.stamp_s - stamp if stamp is not None else math.nan
        if not span > 0.0 or span > self.max_interval_s:  # first, after a silence, or a clock restart
            self._parts.clear()
            self.value, self.interval_s, self.span_s = None, None, 0.0
            return None
        self.interval_s = span
        s = sample.speeds
        parts = self._parts
        parts.append((span, s.left_rad_s * span, s.right_rad_s * span))
        total = sum(p[0] for p in parts)
        while len(parts) > 1 and total - parts[0][0] >= self.window_s - 1e-9:
            total -= parts.popleft()[0]
        self.span_s = total
        self.value = WheelSpeeds(sum(p[1] for p in parts) / total, sum(p[2] for p in parts) / total)
        return self.value

    def reset(self) -> None:
        self._parts.clear()
        self.value, self.interval_s, self._stamp_s, self.span_s = None, None, None, 0.0


class ReferenceModel:
    """The response the feedforward should give: each motion's target through its own lag, with its past
    kept so that a measurement is compared with the reference as it was when it was measured."""

    def __init__(self, lags_s: tuple[float, float]) -> None:
        self.lags_s = lags_s
        self.value: list[float] | None = None  # (common, turn); None: starts from the measured speeds
        self._past: deque[tuple[float, float, float]] = deque()  # (time, common, turn)

    def start(self, modes: tuple[float, float], now_s: float) -> None:
        self.value = list(modes)
        self._past.clear()
        self._past.append((now_s, *modes))

    def follow(self, targets: tuple[float, float], dt_s: float, now_s: float) -> None:
        value = self.value
        if value is None:
            return
        for k in (0, 1):
            value[k] += (1.0 - math.exp(-dt_s / self.lags_s[k]) if dt_s > 0.0 else 0.0) * (targets[k] - value[k])
        past = self._past
        past.append((now_s, value[0], value[1]))
        while len(past) > 1 and now_s - past[1][0] >= HISTORY_S:
            past.popleft()

    def at(self, when_s: float) -> tuple[float, float]:
        """The reference at `when_s` (the latest one not after it; the oldest kept if none)."""
        chosen = self._past[0]
        for entry in self._past:
            if entry[0] > when_s:
                break
            chosen = entry
        return chosen[1], chosen[2]

    def reset(self) -> None:
        self.value = None
        self._past.clear()


@dataclass(frozen=True, slots=True)
class LoopResult:
    command: WheelSpeeds  # what goes to the PWM map
    saturated: bool  # the common factor scaled the command down (or the targets were already scaled)
    closed: bool  # the encoders are fresh (a sample within encoder_timeout_s); False: stale, the loop holds


class WheelSpeedLoop:
    """Feedforward + reference model + PI per motion, anti-windup and a shared desaturation (module doc)."""

    def __init__(self, params: ControlParams, left_range: tuple[float, float],
                 right_range: tuple[float, float], max_step_rad_s2: float = math.inf) -> None:
        self.kp = (params.kp, params.turn_kp)
        self.ki = (params.ki_1_s, params.turn_ki_1_s)
        self.max_step_rad_s2 = max_step_rad_s2  # the most a wheel's command may change per second (docstring)
        self._last: list[float] | None = None  # the last command, while the loop runs
        self._running_s = 0.0  # since the loop (re)started: the slew's window (docstring)
        self.timeout_s = params.encoder_timeout_s
        self.ranges = (left_range, right_range)  # (fastest reverse, fastest forward), rad/s
        self.i_max = params.integrator_max_fraction * min(max(-lo, hi) for lo, hi in self.ranges)
        self.settled_floor = SETTLED_FRACTION * min(max(-lo, hi) for lo, hi in self.ranges)
        self.window = SpeedWindow(params.speed_window_s, params.encoder_timeout_s)
        self.reference = ReferenceModel((params.reference_s, params.turn_reference_s))
        self.integral = [0.0, 0.0]  # (common, turn)
        self._learnt_at = [0.0, 0.0]  # the wheel targets the integrators last learnt at (what a hold scales by)
        self.measured: WheelSpeeds | None = None
        self._measured_s: float | None = None  # arrival time of the last sample (the caller's clock)

    def measure(self, sample: MeasuredWheels, now_s: float) -> None:
        if not sample.speeds.is_finite():
            return
        value = self.window.update(sample)
        if value is not None:  # None: the mean over a silence, not a measurement
            self.measured = value
            self._measured_s = now_s

    def fresh(self, now_s: float) -> bool:
        return self._measured_s is not None and now_s - self._measured_s < self.timeout_s

    def current(self, now_s: float) -> bool:
        """Fresh, and no older than OVERDUE_INTERVALS sample intervals: a measurement the loop acts on."""
        interval = self.window.interval_s
        if not self.fresh(now_s) or self._measured_s is None:
            return False
        return interval is None or now_s - self._measured_s <= OVERDUE_INTERVALS * interval

    def wheel_integral(self) -> tuple[float, float]:
        """The integrators' correction per wheel (left, right)."""
        return to_wheels(*self.integral)

    def reset(self) -> None:
        self.integral = [0.0, 0.0]
        self.reference.reset()  # starts from the measured speeds on the next command
        self._last = None
        self._running_s = 0.0

    def command(self, target: WheelSpeeds, dt_s: float, now_s: float, pre_scaled: bool = False,
                freeze: bool = False) -> LoopResult:
        targets = (target.left_rad_s, target.right_rad_s)
        if targets == (0.0, 0.0):
            self.reset()
            return LoopResult(target, False, False)
        self._running_s += dt_s
        modes = to_modes(*targets)
        measured = self.measured
        if measured is None or not self.current(now_s) or self._measured_s is None:
            self.reference.follow(modes, dt_s, now_s)  # keeps following: no error piles up for the return
            return self._hold(targets, pre_scaled, self.fresh(now_s))
        speeds = (measured.left_rad_s, measured.right_rad_s)
        if self.reference.value is None:  # the wheels are where they are: no error to correct yet
            self.reference.start(to_modes(*speeds), now_s - dt_s)
        self.reference.follow(modes, dt_s, now_s)
        held = self._stalled(targets, speeds)
        if any(held):  # the reference starts again from where the wheels are: released, no error piled up
            self.reference.start(to_modes(*speeds), now_s)
        # The measurement stands for the middle of the span it averages, when it arrived minus half of it.
        reference = self.reference.at(self._measured_s - 0.5 * self.window.span_s)
        seen = to_modes(*speeds)
        errors = (reference[0] - seen[0], reference[1] - seen[1])
        asked_modes = [t + kp * e + i for t, kp, e, i in zip(modes, self.kp, errors, self.integral, strict=True)]
        asked = list(to_wheels(*asked_modes))
        raw = self._slew(asked, dt_s)
        u, saturated = self._limit(list(raw), targets, pre_scaled)
        # The integrators may only shrink while a wheel cannot have what it asks (anti-windup, module doc).
        restrained = saturated or any(
            raw[k] != asked[k] or (raw[k] != 0.0 if targets[k] == 0.0 else (raw[k] > 0.0) != (targets[k] > 0.0))
            for k in (0, 1))
        if not freeze and not any(held) and dt_s > 0.0:
            # While the reference still moves, what the plant does is its lag, not a deficit: learn nothing new (a
            # correction that proves too large, a jam's onset, may still unwind). One tolerance for both motions, on
            # the larger target: the two settle together, or the one settled first would take a wheel's whole deficit.
            tolerance = SETTLED_FRACTION * max(abs(modes[0]), abs(modes[1]), self.settled_floor)
            for m in (0, 1):
                moving = abs(modes[m] - reference[m]) > tolerance
                grown = self.integral[m] + self.ki[m] * errors[m] * dt_s
                if (restrained or moving) and abs(grown) > abs(self.integral[m]):
                    continue
                self.integral[m] = max(-self.i_max, min(self.i_max, grown))
        self._learnt_at = list(targets)
        self._last = list(u)
        return LoopResult(WheelSpeeds(u[0], u[1]), saturated, True)

    def _stalled(self, targets: tuple[float, float], speeds: tuple[float, float]) -> list[bool]:
        """Which wheels are below STILL_FRACTION of their target while commanded past the breakaway."""
        last = self._last or [0.0, 0.0]
        held = [False, False]
        for k in (0, 1):
            # Still while its command is past what starts a wheel (a deadband, a curved map at low speed): the
            # integrator must be free to find that command; beyond it, a still wheel is jammed.
            top = self.ranges[k][1] if targets[k] > 0.0 else -self.ranges[k][0]
            held[k] = abs(speeds[k]) < STILL_FRACTION * abs(targets[k]) and abs(last[k]) >= BREAKAWAY_FRACTION * top
        return held

    def _slew(self, u: list[float], dt_s: float) -> list[float]:
        """Each wheel's command at most max_step_rad_s2 * dt_s from the last one (module docstring)."""
        last = self._last
        if last is None or self._running_s > HANDOVER_S:
            return list(u)
        step = self.max_step_rad_s2 * dt_s
        # Toward zero only: a command growing is the limiter's ramp plus what the wheel lacks (a runaway
        # there is the wiring monitor's to name, and its names rest on how fast it grows).
        return [x if abs(x) >= abs(prev) and x * prev >= 0.0 else min(prev + step, max(prev - step, x))
                for prev, x in zip(last, u, strict=True)]

    def _hold(self, targets: tuple[float, float], pre_scaled: bool, fresh: bool) -> LoopResult:
        """No current measurement: the target plus the integrators' correction, per wheel scaled with the
        target against the one it was learnt at (up to 1: never more than it was; negative for a reversed
        target)."""
        u = []
        for k, correction in enumerate(self.wheel_integral()):
            learnt = self._learnt_at[k]
            ratio = max(-1.0, min(1.0, targets[k] / learnt)) if learnt != 0.0 else 0.0
            u.append(targets[k] + correction * ratio)
        command, saturated = self._limit(u, targets, pre_scaled)
        self._last = list(command)
        return LoopResult(WheelSpeeds(command[0], command[1]), saturated, fresh)

    def _limit(self, u: list[float], targets: tuple[float, float], pre_scaled: bool) -> tuple[list[float], bool]:
        """Never the other direction; both wheels scaled by one factor into their ranges (the curvature kept)."""
        for k in (0, 1):
            if targets[k] == 0.0 or (u[k] > 0.0) != (targets[k] > 0.0):
                u[k] = 0.0  # never the other direction: no reverse kick
        scale = 1.0
        for k, (lo, hi) in enumerate(self.ranges):
            if u[k] > hi:
                scale = min(scale, hi / u[k])
            elif u[k] < lo:
                scale = min(scale, lo / u[k])
        if scale < 1.0:
            u = [x * scale for x in u]
        return u, pre_scaled or scale < 1.0


@dataclass(frozen=True, slots=True)
class WiringFault:
    wheel: str  # "left", "right" or "both"
    kind: str  # "backwards", "still", "runaway" or "swapped"

    @property
    def texts(self) -> tuple[str, str]:
        """Two STATUSTEXT lines (50 characters each): what happened, what to check."""
        if self.kind == "swapped":
            return ("RB: FAULT wheels swapped (or both reversed)",
                    "RB: check output channels / encoder indices")
        if self.kind == "runaway":
            return (f"RB: FAULT {self.wheel} wheel runs away",
                    "RB: check swapped channels / encoder indices")
        if self.kind == "backwards":
            return (f"RB: FAULT {self.wheel} wheel turns backwards",
                    "RB: check motor / encoder reversed, channels")
        return (f"RB: FAULT {self.wheel} wheel does not turn",
                "RB: check channel, SERVOn_FUNCTION, encoder")


class WiringMonitor:
    """Watches commanded against measured wheel speeds for the bring-up wiring faults."""

    def __init__(self, params: ControlParams, left_range: tuple[float, float],
                 right_range: tuple[float, float]) -> None:
        self.top_rad_s = tuple(max(-lo, hi) for lo, hi in (left_range, right_range))
        self.min_rad_s = tuple(params.fault_min_fraction * top for top in self.top_rad_s)
        self.hold_s = params.fault_time_s
        self._since: dict[str, float] = {}  # condition -> when it began

    def reset(self) -> None:
        self._since.clear()

    def check(self, target: WheelSpeeds, measured: WheelSpeeds | None, now_s: float) -> WiringFault | None:
        if measured is None:
            self.reset()
            return None
        t = (target.left_rad_s, target.right_rad_s)
        m = (measured.left_rad_s, measured.right_rad_s)
        checked = [abs(t[k]) >= self.min_rad_s[k] for k in (0, 1)]
        conditions: list[tuple[str, str]] = []
        larger = max(abs(t[0]), abs(t[1]))
        backwards = [checked[k] and m[k] * t[k] < 0.0 and abs(m[k]) >= BACKWARDS_FRACTION * abs(t[k])
                     for k in (0, 1)]
        # Each wheel doing what the other was told, or (in a turn one way and the other) both running
        # backwards: the channels or the encoder indices are swapped (both motors reversed look the same
        # in a spin; the text says so).
        crossed = any(checked) and abs(t[0] - t[1]) >= SWAP_MIN_DIFFERENCE * larger and all(
            abs(m[k] - t[1 - k]) <= SWAP_TOLERANCE * larger for k in (0, 1))
        if crossed or (all(backwards) and t[0] * t[1] < 0.0):
            conditions.append(("both", "swapped"))
        for k, name in ((0, "left"), (1, "right")):
            if not checked[k]:
                continue
            if backwards[k]:
                conditions.append((name, "backwards"))
            elif abs(m[k]) < STILL_FRACTION * abs(t[k]):
                conditions.append((name, "still"))
            elif abs(m[k]) > RUNAWAY_FACTOR * abs(t[k]) + RUNAWAY_MARGIN * self.top_rad_s[k]:
                conditions.append((name, "runaway"))
        if not conditions:  # the common case: every wheel doing what it was told
            if self._since:
                self._since.clear()
            return None
        active = {f"{w}:{kind}" for w, kind in conditions}
        for key in list(self._since):
            if key not in active:
                del self._since[key]
        for w, kind in conditions:
            since = self._since.setdefault(f"{w}:{kind}", now_s)
            if now_s - since >= self.hold_s:
                if kind == "backwards" and ("both", "swapped") in conditions:
                    # One wheel's timer began first, but the two are crossed now: the name that says what to check.
                    return WiringFault("both", "swapped")
                return WiringFault(w, kind)
        return None
