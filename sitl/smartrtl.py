"""SmartRTL's breadcrumb path (AP_SmartRTL), simplified, as behaviour.

Read in ArduPilot (Rover 4.7): libraries/AP_SmartRTL/AP_SmartRTL.cpp (set_home, update, add_point,
pop_point, peek_point, request_thorough_cleanup, the simplification) and Rover/mode_smart_rtl.cpp.
What is kept:

- Home (set when home is set and again on arming) clears the path and saves the position as its first
  point; the path is then active. Three times a second, outside SMART_RTL, the position is saved when it
  is at least SRTL_ACCURACY from the last saved point. SRTL_POINTS (at most 500) bounds the path;
  SRTL_POINTS = 0 or SRTL_ACCURACY <= 0 disables SmartRTL.
- Cleanup: simplification (points within SRTL_ACCURACY / 2 of the line between their neighbours go)
  and loop pruning (where the path comes back within 0.99 * SRTL_ACCURACY of an older part of itself,
  the loop between is replaced by the midpoint of the two closest points). SMART_RTL first runs a
  "thorough cleanup", then drives back through the points, newest first, and stops at the last (home).
  A path that cannot shrink and stays full for 15 s deactivates SmartRTL ("SmartRTL deactivated:
  buffer full").
- Simplified: ArduPilot cleans up in the background, simplifying every 50 new points and pruning when
  fewer than 10 places are left; here both run when fewer than 10 places are left, at once.
"""

from __future__ import annotations

import math
from collections.abc import Callable

POINTS_MAX = 500  # SMARTRTL_POINTS_MAX
CLEANUP_START_MARGIN = 10  # SMARTRTL_CLEANUP_START_MARGIN
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


def _cross(o: Vec, a: Vec, b: Vec) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _closest_on_segment(p: Vec, a: Vec, b: Vec) -> Vec:
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return a[0] + t * dx, a[1] + t * dy


def segment_distance(a: Vec, b: Vec, c: Vec, d: Vec) -> tuple[float, Vec]:
    """(closest distance between segments ab and cd, the midpoint of their closest points)."""
    d1, d2, d3, d4 = _cross(c, d, a), _cross(c, d, b), _cross(a, b, c), _cross(a, b, d)
    if d1 * d2 < 0.0 and d3 * d4 < 0.0:  # they cross
        t = d1 / (d1 - d2)
        return 0.0, (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))
    best = (math.inf, a)
    for p, q in ((a, _closest_on_segment(a, c, d)), (b, _closest_on_segment(b, c, d)),
                 (_closest_on_segment(c, a, b), c), (_closest_on_segment(d, a, b), d)):
        dist = math.hypot(p[0] - q[0], p[1] - q[1])
        if dist < best[0]:
            best = (dist, (0.5 * (p[0] + q[0]), 0.5 * (p[1] + q[1])))
    return best


def prune_loops(points: list[Vec], delta_m: float) -> list[Vec]:
    """Replace each loop (a newer segment within ``delta_m`` of an older, non-adjacent one) by a midpoint."""
    out = list(points)
    i = len(out) - 1
    while i >= 3:
        for j in range(1, i - 1):  # segment (j-1, j) against the newer (i-1, i)
            dist, mid = segment_distance(out[i - 1], out[i], out[j - 1], out[j])
            if dist < delta_m:
                out[j:i] = [mid]
                i = j + 1
                break
        i -= 1
    return out


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
        if len(self.points) >= points_max - CLEANUP_START_MARGIN:
            self.cleanup()
        if len(self.points) >= points_max:
            if now_ms - self._last_save_ms > FULL_TIMEOUT_MS:
                self.active = False
                self._say("SmartRTL deactivated: buffer full")
            return
        self.points.append(pos)
        self._last_save_ms = now_ms

    def cleanup(self) -> None:
        """Simplify, then prune loops (SMART_RTL's thorough cleanup; also when the path fills up)."""
        _, accuracy = self._limits()
        self.points = prune_loops(simplify(self.points, 0.5 * accuracy), 0.99 * accuracy)

    def pop(self) -> Vec | None:
        return self.points.pop() if self.active and self.points else None

    def peek(self) -> Vec | None:
        return self.points[-1] if self.active and self.points else None
