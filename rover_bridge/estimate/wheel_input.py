"""WHEEL_DISTANCE ingestion (pure): cumulative distances -> checked per-interval wheel increments.

- Which distance index is which wheel and which way it counts come from [encoders]; distances
  are scaled by the profile's per-wheel radius over the nominal one (the autopilot integrates
  with its own WENC_RADIUS, assumed to be robot.wheel_radius_m).
- Time is the message's time_usec (the autopilot's sample time), never the arrival time.
- Reboots re-base: time going backwards by more than REORDER_WINDOW_S, both distances restarting
  near zero from a distance far away, or `count` changing. The next reading after a re-base is a
  new baseline, so the pose never jumps; the caller decides what a re-base means (reset_counter).
- A step that implies more than twice the fastest wheel surface speed is a spike: rejected,
  counted, and the old baseline kept (the next good reading spans both intervals). Spikes that
  persist (MAX_SPIKES_IN_ROW) are accepted as a new baseline (a resync), never integrated.
- Slightly older or duplicate stamps (UDP reordering) are dropped and counted.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

from rover_bridge.params import EncoderParams, RobotParams

REORDER_WINDOW_S = 0.5  # older stamps within this are reordering, beyond it a reboot
NEAR_ZERO_M = 0.02  # a freshly booted autopilot's distances are within this of zero ...
FAR_FROM_ZERO_M = 0.5  # ... and the previous ones were at least this far from zero
SPIKE_SLACK_M = 0.005  # quantisation and timestamp jitter allowance on top of the speed bound
MAX_SPIKES_IN_ROW = 5
GAP_S = 0.5  # an interval longer than this is counted as a gap (still integrated: distances are cumulative)


class StepKind(enum.Enum):
    BASELINE = "baseline"  # first reading (or first after a re-base): nothing to integrate yet
    STEP = "step"  # a good interval: integrate d_left_m, d_right_m over dt_s
    REBOOT = "reboot"  # the autopilot restarted: this reading is the new baseline
    RESYNC = "resync"  # persistent spikes: this reading is the new baseline
    SPIKE = "spike"  # rejected, baseline kept
    STALE = "stale"  # out of order or duplicate, dropped
    BAD = "bad"  # malformed (missing index, not finite), dropped


@dataclass(frozen=True, slots=True)
class WheelStep:
    kind: StepKind
    stamp_s: float
    dt_s: float = 0.0
    d_left_m: float = 0.0
    d_right_m: float = 0.0
    reason: str = ""


class WheelInput:
    """Turns successive WHEEL_DISTANCE messages into checked increments (robot convention: + forward)."""

    def __init__(self, encoders: EncoderParams, robot: RobotParams) -> None:
        self.encoders = encoders
        nominal = robot.wheel_radius_m
        self._left_scale = (-1.0 if encoders.left_reversed else 1.0) * robot.left_radius_m / nominal
        self._right_scale = (-1.0 if encoders.right_reversed else 1.0) * robot.right_radius_m / nominal
        # Fastest plausible surface speed of either wheel, in the units of the (scaled) readings.
        self.max_surface_m_s = robot.max_wheel_rad_s * max(robot.left_radius_m, robot.right_radius_m)
        self._last: tuple[float, float, float, int] | None = None  # stamp_s, left_m, right_m, count
        self._spikes_in_row = 0
        self.counters = {"wheel_samples": 0, "wheel_steps": 0, "wheel_spikes": 0, "wheel_reboots": 0,
                         "wheel_resyncs": 0, "wheel_stale": 0, "wheel_bad": 0, "wheel_gaps": 0}

    def reset(self) -> None:
        """Forget the baseline (the next reading is a new one)."""
        self._last = None
        self._spikes_in_row = 0

    def ingest(self, time_usec: int, count: int, distance: Sequence[float]) -> WheelStep:
        self.counters["wheel_samples"] += 1
        stamp_s = time_usec * 1e-6
        e = self.encoders
        if count <= max(e.left_index, e.right_index) or len(distance) <= max(e.left_index, e.right_index):
            self.counters["wheel_bad"] += 1
            return WheelStep(StepKind.BAD, stamp_s, reason=f"count {count} has no index "
                             f"{max(e.left_index, e.right_index)}")
        left = float(distance[e.left_index]) * self._left_scale
        right = float(distance[e.right_index]) * self._right_scale
        if not (math.isfinite(left) and math.isfinite(right)):
            self.counters["wheel_bad"] += 1
            return WheelStep(StepKind.BAD, stamp_s, reason="distance not finite")
        last = self._last
        if last is None:
            self._last = (stamp_s, left, right, count)
            return WheelStep(StepKind.BASELINE, stamp_s)
        last_s, last_l, last_r, last_count = last
        restarted = (max(abs(left), abs(right)) < NEAR_ZERO_M
                     and max(abs(last_l), abs(last_r)) > FAR_FROM_ZERO_M)
        reason = ""
        if count != last_count:
            reason = f"count {last_count} -> {count}"
        elif stamp_s < last_s - REORDER_WINDOW_S:
            reason = f"time back {last_s - stamp_s:.3f} s"
        elif restarted:
            reason = "distances restarted at zero"
        if reason:
            self._rebase(stamp_s, left, right, count)
            self.counters["wheel_reboots"] += 1
            return WheelStep(StepKind.REBOOT, stamp_s, reason=reason)
        dt = stamp_s - last_s
        if dt <= 0.0:
            self.counters["wheel_stale"] += 1
            return WheelStep(StepKind.STALE, stamp_s, reason="stamp not newer")
        dl, dr = left - last_l, right - last_r
        limit = 2.0 * self.max_surface_m_s * dt + SPIKE_SLACK_M
        if abs(dl) > limit or abs(dr) > limit:
            self._spikes_in_row += 1
            if self._spikes_in_row >= MAX_SPIKES_IN_ROW:
                self._rebase(stamp_s, left, right, count)
                self.counters["wheel_resyncs"] += 1
                return WheelStep(StepKind.RESYNC, stamp_s, reason="persistent spikes")
            self.counters["wheel_spikes"] += 1
            return WheelStep(StepKind.SPIKE, stamp_s, dt, dl, dr,
                             reason=f"step {max(abs(dl), abs(dr)):.3f} m in {dt:.3f} s")
        self._spikes_in_row = 0
        self._last = (stamp_s, left, right, count)
        self.counters["wheel_steps"] += 1
        if dt > GAP_S:
            self.counters["wheel_gaps"] += 1
        return WheelStep(StepKind.STEP, stamp_s, dt, dl, dr)

    def _rebase(self, stamp_s: float, left: float, right: float, count: int) -> None:
        self._last = (stamp_s, left, right, count)
        self._spikes_in_row = 0
