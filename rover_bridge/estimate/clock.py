"""The autopilot's boot clock seen from the bridge's time line (pure: both times are arguments).

The filter runs on the autopilot's own stamps (WHEEL_DISTANCE.time_usec, ATTITUDE/SCALED_IMU
.time_boot_ms, RAW_IMU.time_usec, SYSTEM_TIME.time_boot_ms: one boot clock for every stream), so
network and scheduling jitter cannot shift the gyro against the wheels. Only publishing needs
"now" on that clock: one offset, the smallest arrival latency seen over every stream, maps the
caller's now_s onto it. The offset may creep up by CLOCK_DRIFT seconds per second, so an
autopilot clock that runs slow against ours is followed; one that fell behind at once (a SITL
starved on a busy machine re-bases its clock rather than bursting: 0.75 s measured in
`rover-bridge demo`) shows as a whole LATENCY_WINDOW_S whose smallest latency is STEP_S or more
above the offset, which then jumps to it: creeping, ODOMETRY was stamped that far ahead of its pose
for STEP / CLOCK_DRIFT seconds (15 s, 87 deg of heading error against the truth in a spin).

One mapping for all streams, not one per stream: separate offsets differ by arrival jitter (tens
of ms on a busy machine), which shifted the gyro against the wheels and cost degrees of heading
at every change of turn rate.

Discontinuities (never integrated step by step):
- every stream's stamps jumping back by more than REORDER_WINDOW_S is an autopilot reboot: the
  offset is learnt again ("reboot");
- a stamp that goes on from where the clock stood before that reboot (one that the re-learnt clock
  would call a jump) shows the "reboot" was one corrupted or forged stamp: the mapping from before it
  comes back ("restored"; the one it replaces is kept the same way, so a single stamp never fixes the
  clock for longer than the autopilot's next one);
- one stream's stamps far from where the clock says now is (more than JUMP_S ahead, or behind
  without going back on themselves, or returning from such a jump): that stream changed its epoch
  (MAVLink's time_usec is "UNIX epoch or time since boot", and some autopilots switch a stream to
  UNIX time when GPS time arrives) or sent garbage. Its stamps are re-based onto the boot clock
  from then on ("jump"); the other streams and the filter do not notice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# s/s: how fast the latency offset may creep up. Generous, so a sender's clock that runs slow
# against ours (an emulator behind real time on a loaded machine) is followed within seconds.
CLOCK_DRIFT = 0.05
LATENCY_WINDOW_S = 1.0  # a step of the latency is judged over whole windows of this length
STEP_S = 0.1  # a window's smallest latency this far above the offset: the autopilot's clock fell behind
REORDER_WINDOW_S = 0.5  # stamps further back than this are a restarted clock, not reordering
JUMP_S = 5.0  # a stamp this far from the clock's now (no link is that late) is another epoch

REBOOT = "reboot"
JUMP = "jump"
RESTORED = "restored"


@dataclass(frozen=True, slots=True)
class Stamp:
    """A measurement's time on the boot clock, and what the clock made of it."""

    t_s: float
    event: str | None = None  # None, REBOOT, RESTORED or JUMP
    jump_s: float = 0.0  # JUMP: how far this stream's stamps moved (its new shift minus the old)


class AutopilotClock:
    """Maps the autopilot's boot clock onto the caller's time line (offset = smallest latency seen)."""

    def __init__(self) -> None:
        self.offset_s: float | None = None
        self._last_now_s = 0.0
        self._last_stamp_s: dict[str, float] = {}  # per stream, raw (as sent)
        self._shift_s: dict[str, float] = {}  # per stream: raw stamp - boot clock time
        self._window: tuple[float, float] | None = None  # (start, smallest latency) of the current window
        # The mapping a reboot replaced (offset, shifts, last stamps): back if the stamps go on from it.
        self._before: tuple[float, dict[str, float], dict[str, float]] | None = None

    def observe(self, stamp_s: float, now_s: float, stream: str = "") -> Stamp:
        """One stamp of `stream` that arrived at now_s: its time on the boot clock (see the module doc)."""
        if not math.isfinite(stamp_s):
            return Stamp(self.autopilot_time_s(now_s), JUMP)
        last = self._last_stamp_s.get(stream)
        self._last_stamp_s[stream] = stamp_s
        shift = self._shift_s.get(stream, 0.0)
        event: str | None = None
        jump = 0.0
        if self.offset_s is not None:
            boot_now = now_s - self.offset_s
            went_back = last is not None and stamp_s < last - REORDER_WINDOW_S
            if went_back and shift != 0.0 and abs(stamp_s - boot_now) < JUMP_S:
                event, jump, shift = JUMP, -shift, 0.0  # back from another epoch to the boot clock
            elif went_back:
                event = REBOOT  # the autopilot restarted its clock: every stream starts again
                self._keep_before(stream, last)
                self.offset_s = None
                self._shift_s.clear()
                self._last_stamp_s = {stream: stamp_s}
                shift = 0.0
            elif self._goes_on_from_before(stamp_s, now_s, stream):
                event, shift = RESTORED, self._restore(stream, stamp_s, last)
            elif abs(stamp_s - shift - boot_now) > JUMP_S:
                jump = stamp_s - shift - boot_now  # this stream is on another epoch (or garbage)
                event, shift = JUMP, shift + jump
            if shift != 0.0 or stream in self._shift_s:
                self._shift_s[stream] = shift
        t = stamp_s - shift
        latency = now_s - t
        if self.offset_s is None:
            self.offset_s = latency
            self._window = None
        else:
            self.offset_s = min(self.offset_s + CLOCK_DRIFT * max(0.0, now_s - self._last_now_s), latency)
        self._last_now_s = now_s
        self._follow_step(now_s, latency)
        return Stamp(t, event, jump)

    def _keep_before(self, stream: str, last: float | None) -> None:
        """A reboot: keep the mapping it replaces (the stamps as they were before this one)."""
        assert self.offset_s is not None
        self._before = (self.offset_s, dict(self._shift_s), self._lasts_before(stream, last))

    def _lasts_before(self, stream: str, last: float | None) -> dict[str, float]:
        """The last stamps as they were before this one of `stream` (observe has already noted it)."""
        lasts = dict(self._last_stamp_s)
        if last is None:
            lasts.pop(stream, None)
        else:
            lasts[stream] = last
        return lasts

    def _goes_on_from_before(self, stamp_s: float, now_s: float, stream: str) -> bool:
        """The stamp is far from the clock's now but where the mapping before the last reboot says now is."""
        before = self._before
        offset = self.offset_s
        if before is None or offset is None:
            return False
        if abs(stamp_s - self._shift_s.get(stream, 0.0) - (now_s - offset)) <= JUMP_S:
            return False
        old_offset, old_shift, _ = before
        return abs(stamp_s - old_shift.get(stream, 0.0) - (now_s - old_offset)) <= JUMP_S

    def _restore(self, stream: str, stamp_s: float, last: float | None) -> float:
        """Back to the mapping before the last reboot (the replaced one kept in its place); this stream's shift."""
        assert self._before is not None and self.offset_s is not None
        offset, shifts, lasts = self._before
        lasts = dict(lasts)
        lasts[stream] = stamp_s
        self._before = (self.offset_s, self._shift_s, self._lasts_before(stream, last))
        self.offset_s, self._shift_s, self._last_stamp_s = offset, dict(shifts), lasts
        self._window = None
        return self._shift_s.get(stream, 0.0)

    def _follow_step(self, now_s: float, latency_s: float) -> None:
        """A whole window's smallest latency STEP_S above the offset: the offset jumps to it (module doc)."""
        window = self._window
        if window is None or now_s < window[0]:
            self._window = (now_s, latency_s)
            return
        start, smallest = window[0], min(window[1], latency_s)
        if now_s - start < LATENCY_WINDOW_S:
            self._window = (start, smallest)
            return
        if self.offset_s is not None and smallest > self.offset_s + STEP_S:
            self.offset_s = smallest
        self._window = (now_s, latency_s)

    def rebase(self, stamp_s: float, stream: str = "") -> float:
        """A stamp of `stream` on the boot clock, without learning from it (see observe)."""
        return stamp_s - self._shift_s.get(stream, 0.0)

    def autopilot_time_s(self, now_s: float) -> float:
        """now_s on the autopilot's boot clock; now_s itself until the first stamp has arrived."""
        offset = self.offset_s
        return now_s if offset is None else now_s - offset

    def time_usec(self, now_s: float) -> int:
        """autopilot_time_s in whole microseconds, clamped to ODOMETRY.time_usec's uint64 range."""
        t = self.autopilot_time_s(now_s)
        if not t > 0.0:  # also NaN
            return 0
        return min(UINT64_MAX, round(t * 1e6)) if t < UINT64_MAX_S else UINT64_MAX


UINT64_MAX = 2**64 - 1
UINT64_MAX_S = UINT64_MAX * 1e-6
