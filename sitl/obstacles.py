"""Obstacles in the emulator's world, and the plane geometry its range sensors need (pure, no state).

World NED metres (x north, y east); a bearing is clockwise from north in radians. A polygon is its
vertices in order (either winding, closed implicitly, at least 3); a circle is a centre and a radius.
The same shapes describe a scenario's obstacles and the fence's polygons and circles (sitl/fence_store.py):
a range sensor sees the first boundary its ray crosses, whichever side it starts on, so a ray from inside
an inclusion fence stops at its edge as a ray from outside an obstacle stops at the obstacle's.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

Point = tuple[float, float]
_EPS = 1e-12


@dataclass(frozen=True)
class Polygon:
    vertices: tuple[Point, ...]

    def __post_init__(self) -> None:
        if len(self.vertices) < 3:
            raise ValueError(f"a polygon needs at least 3 vertices, got {len(self.vertices)}")

    def edges(self) -> Iterable[tuple[Point, Point]]:
        n = len(self.vertices)
        return ((self.vertices[i], self.vertices[(i + 1) % n]) for i in range(n))


@dataclass(frozen=True)
class Circle:
    centre: Point
    radius_m: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius_m) and self.radius_m > 0.0):
            raise ValueError(f"a circle needs a positive radius, got {self.radius_m!r}")


Shape = Polygon | Circle


def ray_segment_m(origin: Point, bearing_rad: float, a: Point, b: Point) -> float | None:
    """Distance along the ray from ``origin`` at ``bearing_rad`` to segment a-b, or None if it misses."""
    dx, dy = math.cos(bearing_rad), math.sin(bearing_rad)
    ex, ey = b[0] - a[0], b[1] - a[1]
    denom = dx * ey - dy * ex
    if abs(denom) < _EPS:
        return None  # parallel (a ray along an edge meets its ends through the neighbouring edges)
    wx, wy = a[0] - origin[0], a[1] - origin[1]
    t = (wx * ey - wy * ex) / denom
    u = (wx * dy - wy * dx) / denom
    if t < 0.0 or u < -1e-9 or u > 1.0 + 1e-9:  # a ray through a vertex hits (rounding must not miss it)
        return None
    return t


def ray_circle_m(origin: Point, bearing_rad: float, c: Circle) -> float | None:
    """Distance along the ray to the circle's boundary (the exit point when starting inside)."""
    dx, dy = math.cos(bearing_rad), math.sin(bearing_rad)
    fx, fy = origin[0] - c.centre[0], origin[1] - c.centre[1]
    b = fx * dx + fy * dy
    disc = b * b - (fx * fx + fy * fy - c.radius_m * c.radius_m)
    if disc < 0.0:
        return None
    root = math.sqrt(disc)
    for t in (-b - root, -b + root):
        if t >= 0.0:
            return t
    return None


def ray_m(origin: Point, bearing_rad: float, shapes: Iterable[Shape]) -> float | None:
    """Distance to the first boundary the ray crosses among ``shapes`` (None: nothing in that direction)."""
    best: float | None = None
    for shape in shapes:
        if isinstance(shape, Circle):
            hits = [ray_circle_m(origin, bearing_rad, shape)]
        else:
            hits = [ray_segment_m(origin, bearing_rad, a, b) for a, b in shape.edges()]
        for t in hits:
            if t is not None and (best is None or t < best):
                best = t
    return best


def inside(point: Point, shape: Shape) -> bool:
    """The point is inside the shape (even-odd rule for a polygon; on a boundary counts as inside a circle)."""
    if isinstance(shape, Circle):
        return math.hypot(point[0] - shape.centre[0], point[1] - shape.centre[1]) <= shape.radius_m
    x, y = point
    result = False
    for (x1, y1), (x2, y2) in shape.edges():
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            result = not result
    return result


def _segment_distance_m(p: Point, a: Point, b: Point) -> float:
    ex, ey = b[0] - a[0], b[1] - a[1]
    length2 = ex * ex + ey * ey
    t = 0.0 if length2 < _EPS else max(0.0, min(1.0, ((p[0] - a[0]) * ex + (p[1] - a[1]) * ey) / length2))
    return math.hypot(p[0] - (a[0] + t * ex), p[1] - (a[1] + t * ey))


def boundary_distance_m(point: Point, shape: Shape) -> float:
    """Distance from the point to the shape's boundary (from either side)."""
    if isinstance(shape, Circle):
        return abs(math.hypot(point[0] - shape.centre[0], point[1] - shape.centre[1]) - shape.radius_m)
    return min(_segment_distance_m(point, a, b) for a, b in shape.edges())


def obstacle_distance_m(point: Point, shapes: Sequence[Shape]) -> float | None:
    """Distance from the point to the nearest obstacle: 0 inside one; None without obstacles."""
    if not shapes:
        return None
    return min(0.0 if inside(point, s) else boundary_distance_m(point, s) for s in shapes)


def parse_obstacle(raw: object) -> Shape | str:
    """A scenario's ``[[obstacles]]`` table as a shape, or the problem with it:
    ``polygon = [[x, y], ...]`` or ``circle = [x, y]`` with ``radius_m``."""
    if not isinstance(raw, dict):
        return "must be a table"
    keys = set(raw)
    try:
        if keys == {"polygon"}:
            pts = raw["polygon"]
            if not isinstance(pts, list) or not all(_is_point(p) for p in pts):
                return "polygon must be a list of [x, y] pairs of numbers"
            return Polygon(tuple((float(p[0]), float(p[1])) for p in pts))
        if keys == {"circle", "radius_m"}:
            c, r = raw["circle"], raw["radius_m"]
            if not _is_point(c) or not _is_number(r):
                return "circle must be [x, y] and radius_m a number"
            return Circle((float(c[0]), float(c[1])), float(r))
    except ValueError as exc:
        return str(exc)
    return f"needs polygon = [[x, y], ...] or circle = [x, y] with radius_m, got keys {sorted(keys)}"


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _is_point(p: object) -> bool:
    return isinstance(p, list | tuple) and len(p) == 2 and all(_is_number(v) for v in p)
