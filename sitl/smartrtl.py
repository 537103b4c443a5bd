"""SmartRTL's breadcrumb path (AP_SmartRTL), simplified, as behaviour.

Read in ArduPilot (Rover 4.7): libraries/AP_SmartRTL/AP_SmartRTL.cpp (set_home, update, add_point,
pop_point, peek_point, request_thorough_cleanup, the simplification) and Rover/mode_smart_rtl.cpp.
What is kept:

- Home (set when home is set and again on arming) clears the path and saves the position as its first
  point; the path is then active. Three times a second, outside SMART_RTL, the position is saved when it
  is at least SRTL_ACCURACY from the last saved point. SRTL_POINTS (at most 500) bounds the path;
  SRTL_POINTS = 0 or SRTL_ACCURACY <= 0 disables SmartRTL.
- SMART_RTL first asks for a "thorough cleanup", then drives back through the points, newest first,
  and stops at the last (home).
- Simplified: the cleanup is only the Ramer-Douglas-Peucker simplification with SRTL_ACCURACY / 2
  (ArduPilot also prunes loops where the path comes back within SRTL_ACCURACY of itself, and runs
  routine cleanups when the path fills up); a full path here stops taking points and, after 15 s,
  deactivates SmartRTL ("SmartRTL deactivated: buffer full").
"""

from __future__ import annotations

import math
from collections.abc import Callable

POINTS_MAX = 500  # SMARTRTL_POINTS_MAX
FULL_TIMEOUT_MS = 15_000  # SMARTRTL_TIMEOUT
SAVE_INTERVAL_MS = 333  # the 3 Hz save_position task

Vec = tuple[float, float]


def _distance_to_segment(p: Vec, a: Vec, b: Vec) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    if length2 == 0.0:
        return math.hypot(p[0] - a[0], p[1] - a[1])
    t = max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


def simplify(points: list[Vec], epsilon_m: float) -> list[Vec]:
    """Ramer-Douglas-Peucker: drop points within ``epsilon_m`` of the line between kept neighbours."""
    if len(points) < 3:
        return list(points)
    keep = [False] * len(points)
    keep[0] = keep[-1] = True
    stack = [(0, len(points) - 1)]
    while stack:
        first, last = stack.pop()
        worst, worst_i = -1.0, -1
        for i in range(first + 1, last):
            d = _distance_to_segment(points[i], points[first], points[last])
            if d > worst:
                worst, worst_i = d, i
        if worst_i >= 0 and worst > epsilon_m:
            keep[worst_i] = True
            stack += [(first, worst_i), (worst_i, last)]
    return [p for p, k in zip(points, keep, strict=True) if k]


class SmartRtlPath:
    """The breadcrumbs (NED metres from the EKF origin); see the module docstring."""

    def __init__(self, param: Callable[[str], float], say: Callable[[str], None]) -> None:
        self._param = param
        self._say = say
        self.points: list[Vec] = []
        self.active = False
        self._home_saved = False
        self._last_save_ms = 0
        self._next_save_ms = 0

    def _limits(self) -> tuple[int, float]:
        return int(max(0, min(POINTS_MAX, self._param("SRTL_POINTS")))), self._param("SRTL_ACCURACY")

    def set_home(self, pos: Vec | None, now_ms: int) -> None:
        points_max, accuracy = self._limits()
        self.points = []
        if pos is None or points_max == 0 or accuracy <= 0.0:
            return
        self.points = [pos]
        self.active = self._home_saved = True
        self._last_save_ms = now_ms

    def save(self, pos: Vec | None, now_ms: int, saving: bool) -> None:
        """The 3 Hz task: call every loop; it acts every third of a second."""
        if now_ms < self._next_save_ms:
            return
        self._next_save_ms = now_ms + SAVE_INTERVAL_MS
        if pos is not None and not self._home_saved:
            self.set_home(pos, now_ms)
        if not self.active or not saving or pos is None:
            return
        points_max, accuracy = self._limits()
        last = self.points[-1] if self.points else None
        if last is not None and math.hypot(pos[0] - last[0], pos[1] - last[1]) < accuracy:
            self._last_save_ms = now_ms
            return
        if len(self.points) >= points_max:
            if now_ms - self._last_save_ms > FULL_TIMEOUT_MS:
                self.active = False
                self._say("SmartRTL deactivated: buffer full")
            return
        self.points.append(pos)
        self._last_save_ms = now_ms

    def cleanup(self) -> None:
        """The thorough cleanup requested when SMART_RTL starts."""
        _, accuracy = self._limits()
        self.points = simplify(self.points, 0.5 * accuracy)

    def pop(self) -> Vec | None:
        return self.points.pop() if self.active and self.points else None

    def peek(self) -> Vec | None:
        return self.points[-1] if self.active and self.points else None
