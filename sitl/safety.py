"""Rover's circular fence and GCS failsafe, as behaviour (both run at 10 Hz in Rover's scheduler).

Read in ArduPilot (Rover 4.7): libraries/AC_Fence/AC_Fence.cpp (check, check_fence_circle,
record_breach, manual_recovery_start, update), Rover/fence.cpp (fence_check), Rover/failsafe.cpp
(gcs_failsafe_check, failsafe_trigger), Rover/system.cpp (set_mode calls manual_recovery_start) and
GCS_Common.cpp (what counts as the GCS being seen). What is kept:

- Fence: enabled while FENCE_ENABLE = 1 with the circle in FENCE_TYPE (bit 2). Distance from home >=
  FENCE_RADIUS is a breach; a new one only when not already breached or beyond the backup fence (20 m
  further out than where the last breach was seen). Back inside clears the breach. Every mode change
  while breached starts a 10 s "manual recovery" ("Manual recovery started") during which breaches are
  ignored, the fence action's own mode change included. Armed only, a new breach takes FENCE_ACTION:
  0 report only, 1 RTL (else HOLD), 2 HOLD, 3 SMART_RTL (else RTL, else HOLD), 4 SMART_RTL (else
  HOLD), 5 disarm, 6 LOITER (else HOLD); more than 100 m outside: HOLD. (The check and the action
  run in one 10 Hz task here; ArduPilot checks in a 10 Hz IO task and acts in the next 10 Hz main-loop
  pass, 80-100 ms after the breach as measured.)
- GCS failsafe (FS_GCS_ENABLE 1 or 2): once the GCS has been seen (HEARTBEAT, RC_CHANNELS_OVERRIDE or
  MANUAL_CONTROL from MAV_GCS_SYSID), nothing from it for FS_GCS_TIMEOUT s is a failsafe; after
  FS_TIMEOUT s more, outside RTL and HOLD (HOLD too with FS_OPTIONS bit 0): "GCS Failsafe", RC
  overrides cleared, then FS_ACTION (the same numbers as FENCE_ACTION), or with FS_GCS_ENABLE 2 in AUTO
  "Failsafe - Continuing Auto Mode". Seen again: "GCS Failsafe Cleared".
"""

from __future__ import annotations

import math
from collections.abc import Callable

from sitl.modes import MODE_AUTO, MODE_HOLD, MODE_RTL

FENCE_TYPE_CIRCLE = 2
BACKUP_DISTANCE_M = 20.0  # AC_FENCE_CIRCLE_RADIUS_BACKUP_DISTANCE (not Plane)
MANUAL_RECOVERY_MS = 10_000
GIVE_UP_DISTANCE_M = 100.0  # AC_FENCE_GIVE_UP_DISTANCE


class CircleFence:
    """AC_Fence's circle (see the module docstring). Positions are NED metres."""

    def __init__(self, param: Callable[[str], float], say: Callable[[str], None]) -> None:
        self._param = param
        self._say = say
        self.breached = False
        self.breach_count = 0
        self.breach_distance_m = 0.0
        self._backup_radius_m = 0.0
        self._recovery_start_ms: int | None = None

    def enabled(self) -> bool:
        return self._param("FENCE_ENABLE") == 1 and int(self._param("FENCE_TYPE")) & FENCE_TYPE_CIRCLE != 0

    def manual_recovery_start(self, now_ms: int) -> None:
        """A mode change: while breached, breaches are ignored for 10 s."""
        if self.breached:
            self._recovery_start_ms = now_ms
            self._say("Manual recovery started")

    def check(self, pos: tuple[float, float] | None, home: tuple[float, float] | None, now_ms: int) -> bool:
        """True on a new breach that is not being ignored."""
        if not self.enabled():
            self.breached, self._backup_radius_m = False, 0.0
            return False
        new = False
        if pos is not None and home is not None:
            distance = math.hypot(pos[0] - home[0], pos[1] - home[1])
            radius = self._param("FENCE_RADIUS")
            self.breach_distance_m = distance - radius
            if distance >= radius:
                if not self.breached or (self._backup_radius_m > 0.0 and distance >= self._backup_radius_m):
                    self.breached, new = True, True
                    self.breach_count += 1
                    self._backup_radius_m = distance + BACKUP_DISTANCE_M
            elif self.breached:
                self.breached, self._backup_radius_m = False, 0.0
        if self._recovery_start_ms is not None:
            if now_ms - self._recovery_start_ms < MANUAL_RECOVERY_MS:
                return False
            self._recovery_start_ms = None
        return new


class GcsFailsafe:
    """Rover's GCS failsafe (see the module docstring)."""

    def __init__(self, param: Callable[[str], float]) -> None:
        self._param = param
        self.last_seen_ms: int | None = None
        self._start_ms: int | None = None
        self.triggered = False

    def seen(self, now_ms: int) -> None:
        self.last_seen_ms = now_ms

    def check(self, now_ms: int, mode: int) -> str | None:
        """'trigger', 'continue' (AUTO carries on), 'cleared' or None."""
        enable = int(self._param("FS_GCS_ENABLE"))
        if enable == 0 or self.last_seen_ms is None:
            return None
        on = now_ms - self.last_seen_ms >= self._param("FS_GCS_TIMEOUT") * 1000.0
        if not on:
            self._start_ms = None
            if self.triggered:
                self.triggered = False
                return "cleared"
            return None
        if self._start_ms is None:
            self._start_ms = now_ms
        in_hold_ok = int(self._param("FS_OPTIONS")) & 1 != 0
        if (not self.triggered and now_ms - self._start_ms > self._param("FS_TIMEOUT") * 1000.0
                and mode != MODE_RTL and (mode != MODE_HOLD or in_hold_ok)):
            self.triggered = True
            return "continue" if mode == MODE_AUTO and enable == 2 else "trigger"
        return None
