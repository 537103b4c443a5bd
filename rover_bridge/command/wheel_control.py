"""Closed-loop wheel speeds (pure): the speed each wheel was asked for, on real motors.

Between the kinematics and the PWM map ([control] mode = closed_loop). Per wheel, every output:

    u = target + kp * e + I,    e = r - measured,    I += ki * e * dt

in wheel speed units (rad/s); u then goes through the PWM map (the measured curve where the profile
has one: the feedforward). The measured speed comes from WHEEL_DISTANCE (the estimate flow's checked
increments, differentiated on the autopilot's own stamps), low-pass filtered (speed_filter_hz).

r is the reference: the target through a first-order lag of reference_s, the response to expect of
a wheel (motor lag, the encoder interval's half-period, the filter). Correcting the error against the
target itself would count the wheel's own lag in every ramp as a deficit and wind the integrator up
(an overshoot of 20 % on a 0 -> 0.5 m/s step in the emulator with a weak, curved motor); against r
only what the feedforward gets wrong is corrected (1.7 % there).

- Desaturation: when a wheel's u is beyond what its motor can do (its map's range), both wheels' u
  are scaled by one common factor, as the open-loop clamp does, so the path's curvature is kept.
- Anti-windup: while the output is saturated, or the kinematics already scaled the targets down,
  the integrators may only shrink; they are clamped to integrator_max_fraction of the top speed. A wheel
  held at zero by the direction rule (below) is saturated too: a rover that coasts down slower than the
  limiter ramps (a handover from 2.7 m/s to a 0.5 m/s request) would otherwise wind its integrator
  backwards and hold the wheel at zero far below the target (0.19 m/s in the emulator).
- Handover slew: for HANDOVER_S after the loop (re)starts, a wheel's command shrinks by at most
  max_step_rad_s2 per second, the wheel acceleration the limiter's own limits allow (linear plus
  angular): a loop taking over a moving rover (from the autopilot's own demand, which it does not close)
  does not cut a wheel faster than the limiter would (a real Rover SITL, AUTO -> MANUAL at 2.7 m/s: 118
  us in one 50 ms period against the limiter's 63 us, the rover lagging the limiter's braking ramp).
  Only then: a loop that has been driving brakes along the ramp as hard as its correction asks, as it
  always has (every other closed-loop behaviour unchanged). A growing command is not slewed (the ramp
  plus what a weak wheel lacks; how fast a miswired loop runs away is what the wiring monitor tells
  faults apart by), nor a stop: a zero target is neutral at once.
- Resets: targets of zero (neutral, idle, timeout done, link lost, disarmed, refused, stopped) clear
  the integrators and give zero: a stop never kicks a wheel backwards. A non-zero target is never
  answered with the opposite direction either (braking is the limiter's ramp, not reverse thrust).
- Missing samples: the loop acts only on a current measurement, one no older than OVERDUE_INTERVALS
  of the encoder's own sample interval. Without one it holds: u = target + the correction the
  integrator had learnt, scaled with the target (never more than it was, and none for a target of the
  other sign), the integrator frozen, no P term (an old measurement against a moving reference would
  push harder the longer the silence lasts). The speed the wheels had is kept: a weak motor stays
  compensated instead of dropping to the bare map. A sample that spans more than encoder_timeout_s
  (the first after a silence) is the mean over the silence, not the wheel's speed: the loop waits for
  the next. Encoders silent for encoder_timeout_s are stale (`closed` False: the core says so once).
- Slip (the estimator's verdict): the integrators are frozen (slipping wheels read too fast).
- Stall handling: a wheel below STILL_FRACTION of its target for STALL_S is held (a stalled or
  jammed wheel): its integrator stops and its reference follows the measured speed, so when it is
  released it spins up to the steady command instead of a wound-up one.

A D term is left out: at 20-50 Hz encoder rates a derivative of a differentiated distance is
noise, and the motor's own lag already damps the loop.

WiringMonitor: at bring-up the most common failure of per-wheel control is wiring (a swapped
channel, a reversed motor or encoder, swapped encoder indices). A wheel commanded above
fault_min_fraction of its top speed that turns the wrong way, or not at all, for fault_time_s is
a fault; it says which wheel, what it did and what to check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
from rover_bridge.params import ControlParams

STILL_FRACTION = 0.1  # measured below this fraction of the target: the wheel does not turn
STALL_S = 0.25  # ... for this long: the loop treats it as stalled (integrator held, reference reseeded)
BACKWARDS_FRACTION = 0.2  # measured at least this fraction of the target, opposite sign: wrong way
SWAP_TOLERANCE = 0.3  # each wheel within this fraction of the other's target: swapped
SWAP_MIN_DIFFERENCE = 0.3  # the two targets must differ by this fraction of the larger to tell a swap
RUNAWAY_FACTOR = 1.5  # measured beyond this times the target (plus a margin of the top speed): runs away,
RUNAWAY_MARGIN = 0.1  # what a closed loop does to a wheel whose encoder is another wheel's
# A measurement is current while no older than this many of the encoder's sample intervals: one lost
# sample (two intervals) is not a silence yet.
OVERDUE_INTERVALS = 2.5
HANDOVER_S = 1.0  # the slew's window after the loop (re)starts (docstring)


class SpeedFilter:
    """First-order low-pass of the measured wheel speeds, on the samples' own stamps."""

    def __init__(self, cutoff_hz: float, max_interval_s: float = 1.0) -> None:
        self.tau_s = 1.0 / (2.0 * math.pi * cutoff_hz)
        self.max_interval_s = max_interval_s
        self.value: WheelSpeeds | None = None
        self.interval_s: float | None = None  # between the last two samples' stamps
        self._stamp_s: float | None = None

    def update(self, sample: MeasuredWheels) -> WheelSpeeds | None:
        """The filtered speeds; None for a sample that spans more than max_interval_s (the mean over a
        silence, not the wheels' speed): the filter starts again from the next one."""
        s = sample.speeds
        last, stamp = self.value, self._stamp_s
        self._stamp_s = sample.stamp_s
        if stamp is not None and sample.stamp_s - stamp > self.max_interval_s:
            self.value, self.interval_s = None, None
            return None
        if last is None or stamp is None or not sample.stamp_s > stamp:
            self.value = s  # first sample, or after a silence or a clock restart: start from it
        else:
            a = 1.0 - math.exp(-(sample.stamp_s - stamp) / self.tau_s)
            self.value = WheelSpeeds(last.left_rad_s + a * (s.left_rad_s - last.left_rad_s),
                                     last.right_rad_s + a * (s.right_rad_s - last.right_rad_s))
        self.interval_s = sample.stamp_s - stamp if stamp is not None and sample.stamp_s > stamp else None
        return self.value

    def reset(self) -> None:
        self.value, self.interval_s, self._stamp_s = None, None, None


@dataclass(frozen=True, slots=True)
class LoopResult:
    command: WheelSpeeds  # what goes to the PWM map
    saturated: bool  # the common factor scaled the command down (or the targets were already scaled)
    closed: bool  # the encoders are fresh (a sample within encoder_timeout_s); False: stale, the loop holds


class WheelSpeedLoop:
    """Per-wheel feedforward + PI with anti-windup and a shared desaturation (see the module docstring)."""

    def __init__(self, params: ControlParams, left_range: tuple[float, float],
                 right_range: tuple[float, float], max_step_rad_s2: float = math.inf) -> None:
        self.kp = params.kp
        self.max_step_rad_s2 = max_step_rad_s2  # the most a wheel's command may change per second (docstring)
        self._last: list[float] | None = None  # the last command, while the loop runs
        self._running_s = 0.0  # since the loop (re)started: the slew's window (docstring)
        self.ki = params.ki_1_s
        self.timeout_s = params.encoder_timeout_s
        self.ranges = (left_range, right_range)  # (fastest reverse, fastest forward), rad/s
        self.i_max = tuple(params.integrator_max_fraction * max(-lo, hi) for lo, hi in self.ranges)
        self.reference_s = params.reference_s
        self.filter = SpeedFilter(params.speed_filter_hz, params.encoder_timeout_s)
        self.integral = [0.0, 0.0]
        self._learnt_at = [0.0, 0.0]  # the targets the integrators last learnt at (what a hold scales by)
        self.reference: list[float] | None = None  # None: starts from the measured speeds
        self._still_since: list[float | None] = [None, None]
        self.measured: WheelSpeeds | None = None
        self._measured_s: float | None = None  # arrival time of the last sample (the caller's clock)

    def measure(self, sample: MeasuredWheels, now_s: float) -> None:
        if not sample.speeds.is_finite():
            return
        value = self.filter.update(sample)
        if value is not None:  # None: the mean over a silence, not a measurement
            self.measured = value
            self._measured_s = now_s

    def fresh(self, now_s: float) -> bool:
        return self._measured_s is not None and now_s - self._measured_s < self.timeout_s

    def current(self, now_s: float) -> bool:
        """Fresh, and no older than OVERDUE_INTERVALS sample intervals: a measurement the loop acts on."""
        interval = self.filter.interval_s
        if not self.fresh(now_s) or self._measured_s is None:
            return False
        return interval is None or now_s - self._measured_s <= OVERDUE_INTERVALS * interval

    def reset(self) -> None:
        self.integral = [0.0, 0.0]
        self.reference = None  # set from the measured speeds on the next command
        self._last = None
        self._running_s = 0.0
        self._still_since = [None, None]

    def command(self, target: WheelSpeeds, dt_s: float, now_s: float, pre_scaled: bool = False,
                freeze: bool = False) -> LoopResult:
        targets = (target.left_rad_s, target.right_rad_s)
        if targets == (0.0, 0.0):
            self.reset()
            return LoopResult(target, False, False)
        self._running_s += dt_s
        follow = 1.0 - math.exp(-dt_s / self.reference_s) if dt_s > 0.0 else 0.0
        measured = self.measured
        if measured is None or not self.current(now_s):
            return self._hold(targets, follow, pre_scaled, self.fresh(now_s))
        speeds = (measured.left_rad_s, measured.right_rad_s)
        if self.reference is None:
            self.reference = list(speeds)  # the wheels are where they are: no error to correct yet
        reference = self.reference
        held = [False, False]
        for k in (0, 1):
            if abs(speeds[k]) < STILL_FRACTION * abs(targets[k]):
                since = self._still_since[k]
                self._still_since[k] = since = now_s if since is None else since
                held[k] = now_s - since >= STALL_S
            else:
                self._still_since[k] = None
            if held[k]:
                reference[k] = speeds[k]
            else:
                reference[k] += follow * (targets[k] - reference[k])
        errors = (reference[0] - speeds[0], reference[1] - speeds[1])
        asked = [t + self.kp * e + i for t, e, i in zip(targets, errors, self.integral, strict=True)]
        raw = self._slew(asked, dt_s)
        u, saturated = self._limit(list(raw), targets, pre_scaled)
        if not freeze and dt_s > 0.0:
            for k in (0, 1):
                if held[k]:
                    continue  # a stalled wheel: integrating its error only winds up
                step = self.ki * errors[k] * dt_s
                if saturated and (step > 0.0) == (targets[k] > 0.0):
                    continue  # saturated: the integrator may only unwind
                if (raw[k] > 0.0) != (targets[k] > 0.0) and (step > 0.0) != (targets[k] > 0.0):
                    continue  # held at zero (never the other direction): nor may it wind up backwards
                if raw[k] != asked[k] and (step > 0.0) == (asked[k] > raw[k]):
                    continue  # slew-limited: the same
                self.integral[k] = max(-self.i_max[k], min(self.i_max[k], self.integral[k] + step))
        self._learnt_at = list(targets)
        self._last = list(u)
        return LoopResult(WheelSpeeds(u[0], u[1]), saturated, True)

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

    def _hold(self, targets: tuple[float, float], follow: float, pre_scaled: bool, fresh: bool) -> LoopResult:
        """No current measurement: the target plus the integrator's correction, scaled with the target
        against the one it was learnt at (up to 1: never more than it was; negative for a reversed target)."""
        u = []
        for k in (0, 1):
            learnt = self._learnt_at[k]
            ratio = max(-1.0, min(1.0, targets[k] / learnt)) if learnt != 0.0 else 0.0
            u.append(targets[k] + self.integral[k] * ratio)
        if self.reference is not None:  # keeps following the target: no error piles up for the return
            for k in (0, 1):
                self.reference[k] += follow * (targets[k] - self.reference[k])
        self._still_since = [None, None]
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
                return WiringFault(w, kind)
        return None
