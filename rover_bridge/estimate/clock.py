"""The autopilot's boot clock seen from the bridge's time line (pure: both times are arguments).

The filter runs on the autopilot's own stamps (WHEEL_DISTANCE.time_usec, ATTITUDE/SCALED_IMU
.time_boot_ms, RAW_IMU.time_usec, SYSTEM_TIME.time_boot_ms: one boot clock for every stream), so
network and scheduling jitter cannot shift the gyro against the wheels. Only publishing needs
"now" on that clock: one offset, the smallest arrival latency seen over every stream, maps the
caller's now_s onto it. The offset may creep up by CLOCK_DRIFT seconds per second, so an
autopilot clock that runs slow against ours is followed; stamps jumping back by more than
REORDER_WINDOW_S (a reboot) re-learn it.

One mapping for all streams, not one per stream: separate offsets differ by arrival jitter (tens
of ms on a busy machine), which shifted the gyro against the wheels and cost degrees of heading
at every change of turn rate.
"""

from __future__ import annotations

# s/s: how fast the latency offset may creep up. Generous, so a sender's clock that runs slow
# against ours (an emulator behind real time on a loaded machine) is followed within seconds.
CLOCK_DRIFT = 0.05
REORDER_WINDOW_S = 0.5  # stamps further back than this are a restarted clock, not reordering


class AutopilotClock:
    """Maps the autopilot's boot clock onto the caller's time line (offset = smallest latency seen)."""

    def __init__(self) -> None:
        self.offset_s: float | None = None
        self._last_stamp_s: float | None = None
        self._last_now_s = 0.0

    def observe(self, stamp_s: float, now_s: float) -> bool:
        """Learn from one stamp that arrived at now_s; True when the stamps jumped back (the autopilot
        restarted its clock: the offset is learnt again from this stamp)."""
        restarted = self._last_stamp_s is not None and stamp_s < self._last_stamp_s - REORDER_WINDOW_S
        if restarted:
            self.offset_s = None
        self._last_stamp_s = stamp_s
        latency = now_s - stamp_s
        if self.offset_s is None:
            self.offset_s = latency
        else:
            self.offset_s = min(self.offset_s + CLOCK_DRIFT * max(0.0, now_s - self._last_now_s), latency)
        self._last_now_s = now_s
        return restarted

    def autopilot_time_s(self, now_s: float) -> float:
        """now_s on the autopilot's boot clock; now_s itself until the first stamp has arrived."""
        offset = self.offset_s
        return now_s if offset is None else now_s - offset

    def time_usec(self, now_s: float) -> int:
        """autopilot_time_s in whole microseconds (ODOMETRY.time_usec)."""
        return max(0, round(self.autopilot_time_s(now_s) * 1e6))
