"""Which gyro stream the estimator listens to, and which of its samples are new (pure).

[estimator] gyro_source names one of ATTITUDE.yawspeed (rad/s), SCALED_IMU.zgyro (mrad/s) or
RAW_IMU.zgyro (assumed mrad/s: ArduPilot fills RAW_IMU with scaled values, not ADC counts);
'auto' uses the highest-priority one that is arriving (ATTITUDE, SCALED_IMU, RAW_IMU in that
order) and falls back to a lower one after GYRO_SILENT_S without the current one.

Only the sources worth decoding now are read (`reads`): the one in use and those 'auto' would
switch to at once; every source while none is in use or it fell silent. A lower-priority IMU stream
at 50 Hz is then forwarded without being decoded.
"""

from __future__ import annotations

import logging
import math

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import EstimatorParams

log = logging.getLogger("rover_bridge.estimate.gyro")

GYRO_MESSAGES = {  # source name -> (message id, stream group), in 'auto' priority order
    "attitude": (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAV_DATA_STREAM_EXTRA1),
    "scaled_imu": (mavlink.MAVLINK_MSG_ID_SCALED_IMU, mavlink.MAV_DATA_STREAM_RAW_SENSORS),
    "raw_imu": (mavlink.MAVLINK_MSG_ID_RAW_IMU, mavlink.MAV_DATA_STREAM_RAW_SENSORS),
}
GYRO_PRIORITY = tuple(GYRO_MESSAGES)
ALL_GYRO_IDS = frozenset(msg_id for msg_id, _group in GYRO_MESSAGES.values())
GYRO_SILENT_S = 3.0  # 'auto' falls back to a lower-priority source after this long without the current one
REORDER_WINDOW_S = 0.5  # older stamps within this are reordering or duplicates, further back a reboot


class GyroSelector:
    """The gyro source in use, the message ids worth decoding, and per-source reorder checks."""

    def __init__(self, params: EstimatorParams) -> None:
        self.auto = params.gyro_source == "auto"
        self.source: str | None = None if self.auto else params.gyro_source
        self.switches = 0
        self._last_seen: dict[str, float] = {}  # arrival time per source
        self._last_stamp_s: dict[str, float] = {}  # newest sender stamp (s) fused per source
        self.reads = frozenset(GYRO_MESSAGES[name][0] for name in GYRO_PRIORITY)
        self.update_reads(0.0)

    @property
    def source_id(self) -> int | None:
        return None if self.source is None else GYRO_MESSAGES[self.source][0]

    @property
    def request_name(self) -> str:
        """The source whose stream is asked for: ATTITUDE under 'auto'."""
        return "attitude" if self.auto else str(self.source)

    def update_reads(self, now_s: float) -> None:
        """Recompute `reads` (a source that fell silent opens the others again)."""
        current = self.source
        if not self.auto and current is not None:
            names: tuple[str, ...] = (current,)
        elif current is None or now_s - self._last_seen.get(current, -math.inf) > GYRO_SILENT_S:
            names = GYRO_PRIORITY
        else:
            names = GYRO_PRIORITY[: GYRO_PRIORITY.index(current) + 1]
        reads = frozenset(GYRO_MESSAGES[name][0] for name in names)
        if reads != self.reads:
            self.reads = reads

    def accept_source(self, source: str, now_s: float) -> bool:
        """A sample of `source` arrived: is it the one to fuse (switching to it if 'auto' prefers it)?"""
        self._last_seen[source] = now_s
        if not self.auto:
            return source == self.source
        current = self.source
        if current == source:
            return True
        rank = GYRO_PRIORITY.index
        silent = current is None or now_s - self._last_seen.get(current, -math.inf) > GYRO_SILENT_S
        if current is None or rank(source) < rank(current) or silent:
            if current is not None:
                self.switches += 1
                log.info("gyro source %s -> %s", current, source)
            self.source = source
            self.update_reads(now_s)
            return True
        return False

    def is_stale(self, source: str, stamp_s: float) -> bool:
        """Reordered or duplicated (UDP), judged on the sender's own stamps (further back is a reboot)."""
        last = self._last_stamp_s.get(source)
        return last is not None and last - REORDER_WINDOW_S <= stamp_s <= last

    def fused(self, source: str, stamp_s: float) -> None:
        self._last_stamp_s[source] = stamp_s

    @property
    def tracked_sources(self) -> int:
        """Entries kept per source (bounded by the number of sources; the soak test checks)."""
        return max(len(self._last_seen), len(self._last_stamp_s))
