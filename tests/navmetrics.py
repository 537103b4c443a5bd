"""How well a rover flew a route, from its true track: the figures issue 29 compares between the bridge and
ArduPilot alone (closest approach to each waypoint, cross-track error, mission time). Planar NED metres;
shared by the emulator's end-to-end tests and the optional real-SITL ones."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

Point = tuple[float, float]


def distance_to_segment_m(p: Point, a: Point, b: Point) -> float:
    """Distance from p to the segment a-b (to a when a == b)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0.0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2))
    return math.hypot(p[0] - a[0] - t * dx, p[1] - a[1] - t * dy)


def distance_to_path_m(p: Point, path: list[Point]) -> float:
    """Distance from p to the nearest point of the polyline `path` (one point: to that point)."""
    if len(path) == 1:
        return math.hypot(p[0] - path[0][0], p[1] - path[0][1])
    return min(distance_to_segment_m(p, a, b) for a, b in itertools.pairwise(path))


@dataclass(frozen=True)
class RouteFigures:
    """A mission flown: its time, the closest approach to each waypoint and the cross-track error (the
    track's largest and RMS distance from the planned legs, start -> WP 1 -> ... -> WP n)."""

    time_s: float
    closest_m: tuple[float, ...]
    xtrack_max_m: float
    xtrack_rms_m: float
    xtrack_max_at: Point = (math.nan, math.nan)  # where on the track the largest error was (north, east)

    def row(self) -> str:
        return (f"{self.time_s:.1f} s | " + " / ".join(f"{c:.2f}" for c in self.closest_m)
                + f" m | {self.xtrack_max_m:.2f} / {self.xtrack_rms_m:.2f} m"
                + f" (largest at {self.xtrack_max_at[0]:.1f}, {self.xtrack_max_at[1]:.1f})")


def route_figures(track: list[Point], start: Point, waypoints: list[Point], time_s: float) -> RouteFigures:
    legs = [start, *waypoints]
    closest = tuple(min(math.hypot(x - n, y - e) for x, y in track) for n, e in waypoints)
    xt = [distance_to_path_m(p, legs) for p in track]
    worst = max(range(len(xt)), key=xt.__getitem__)
    return RouteFigures(time_s, closest, xt[worst], math.sqrt(sum(d * d for d in xt) / len(xt)), track[worst])
