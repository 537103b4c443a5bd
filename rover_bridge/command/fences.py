"""Fence geometry for avoidance (pure): how far the rover may drive along its direction of travel before it has to
have stopped FENCE_MARGIN inside its fences, as ArduPilot's AC_Avoid works it out in BEHAVE 1 (stop, Rover's
default): adjust_velocity_circle_fence and adjust_velocity_polygon.

Positions are local north/east metres from the fence origin (home); directions are headings clockwise from
north (ATTITUDE.yaw; reversing is the heading + pi). Polygons may be given as lat/lon and are flattened about an
origin as the bridge's navigation does (an equirectangular patch: fences are hundreds of metres, not more).

- circle (FENCE_RADIUS around home): inside radius - margin, the distance along the ray to the circle of radius
  - margin; beyond it, motion outward stops and motion inward is free up to the inner circle's far side
  (ArduPilot leaves a rover outside the circle to its fence failsafe; here only motion back inside passes);
- inclusion polygon, rover inside: each edge is a wall square to the line to its closest point, as AC_Avoid takes
  it; the travel allowed is the least (distance - margin) / cos(angle off the travel) over the edges ahead (at or
  inside the margin: stop), so an oblique approach still stops the margin from the edge measured square to it;
  exclusion polygon, rover outside: the same for its edges;
- outside an inclusion polygon or inside an exclusion one (breached): only motion toward the nearest point of
  its boundary passes (the way back), anything else stops.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from rover_bridge.frames import ne_from_lat_lon

_EPS = 1e-9
ALONG_COS = 1e-3  # an edge or obstacle this close to abeam of the travel does not limit it (the cap would be huge)

Point = tuple[float, float]  # (north m, east m)


@dataclass(frozen=True, slots=True)
class CircleFence:
    """FENCE_RADIUS around home (the origin), or a circle of the stored fence: inclusion (stay inside) or
    exclusion (stay outside)."""

    radius_m: float
    center_north_m: float = 0.0
    center_east_m: float = 0.0
    inclusion: bool = True


@dataclass(frozen=True, slots=True)
class PolygonFence:
    """An inclusion (stay inside) or exclusion (stay outside) polygon, vertices in order, not closed."""

    points_ne: tuple[Point, ...]
    inclusion: bool = True

    @classmethod
    def from_lat_lon(cls, points_deg: Sequence[tuple[float, float]], origin_lat_deg: float,
                     origin_lon_deg: float, inclusion: bool = True) -> PolygonFence:
        return cls(tuple(ne_from_lat_lon(origin_lat_deg, origin_lon_deg, lat, lon) for lat, lon in points_deg),
                   inclusion)


@dataclass(frozen=True, slots=True)
class Fences:
    """Every fence the autopilot has (FENCE_TYPE's circle and polygons) and FENCE_MARGIN."""

    margin_m: float
    circle: CircleFence | None = None
    polygons: tuple[PolygonFence, ...] = ()
    circles: tuple[CircleFence, ...] = ()  # the stored fence's inclusion and exclusion circles


@dataclass(frozen=True, slots=True)
class FenceClearance:
    """How far the rover may still travel along its direction before it must be at rest (the margin already
    taken off; 0 = stop now; None = no fence in the way) and whether it is outside a fence already."""

    distance_m: float | None
    breached: bool = False


def _edges(points: Sequence[Point]) -> list[tuple[Point, Point]]:
    return [(points[i], points[(i + 1) % len(points)]) for i in range(len(points))]


def inside_polygon(north_m: float, east_m: float, points: Sequence[Point]) -> bool:
    """Even-odd ray casting (AC_Fence's Polygon_outside, negated)."""
    inside = False
    for (n1, e1), (n2, e2) in _edges(points):
        if (e1 > east_m) != (e2 > east_m):
            n_cross = n1 + (east_m - e1) * (n2 - n1) / (e2 - e1)
            if north_m < n_cross:
                inside = not inside
    return inside


def _closest_on_edge(north_m: float, east_m: float, p1: Point, p2: Point) -> Point:
    """From the point to the closest point of the segment p1-p2."""
    (n1, e1), (n2, e2) = p1, p2
    sn, se = n2 - n1, e2 - e1
    length_sq = sn * sn + se * se
    u = 0.0 if length_sq < _EPS else max(0.0, min(1.0, ((north_m - n1) * sn + (east_m - e1) * se) / length_sq))
    return n1 + u * sn - north_m, e1 + u * se - east_m


def nearest_boundary_vector(north_m: float, east_m: float, points: Sequence[Point]) -> Point:
    """From the point to the closest point of the polygon's boundary."""
    vectors = [_closest_on_edge(north_m, east_m, p1, p2) for p1, p2 in _edges(points)]
    return min(vectors, key=lambda v: math.hypot(*v))


def edge_travel_m(north_m: float, east_m: float, dn: float, de: float, points: Sequence[Point],
                  margin_m: float) -> float | None:
    """How far the rover may travel along the unit direction before it is `margin_m` from an edge, each edge taken
    as a wall square to the line to its closest point (AC_Avoid::adjust_velocity_polygon's way): (p - margin) /
    cos(theta) for an edge p away at theta off the travel; edges beside or behind do not limit (None: none does)."""
    best: float | None = None
    for p1, p2 in _edges(points):
        vn, ve = _closest_on_edge(north_m, east_m, p1, p2)
        p = math.hypot(vn, ve)
        if p < _EPS:
            return 0.0  # on the edge
        cos_theta = (vn * dn + ve * de) / p
        if cos_theta <= ALONG_COS:
            continue
        travel = max(p - margin_m, 0.0) / cos_theta
        best = travel if best is None else min(best, travel)
    return best


def ray_circle_exit_m(north_m: float, east_m: float, dir_north: float, dir_east: float, radius_m: float) -> float:
    """Distance along the unit ray to where it leaves a circle about the origin (the far crossing)."""
    b = north_m * dir_north + east_m * dir_east
    c = north_m * north_m + east_m * east_m - radius_m * radius_m
    return -b + math.sqrt(max(b * b - c, 0.0))


def _circle(fence: CircleFence, margin_m: float, north_m: float, east_m: float, dn: float,
            de: float) -> FenceClearance:
    if not fence.inclusion:
        return _exclusion_circle(fence, margin_m, north_m, east_m, dn, de)
    if margin_m > fence.radius_m:
        return FenceClearance(None)  # as AC_Avoid: a margin wider than the fence disables it
    pn, pe = north_m - fence.center_north_m, east_m - fence.center_east_m
    dist = math.hypot(pn, pe)
    outward = pn * dn + pe * de >= 0.0
    inner_m = fence.radius_m - margin_m
    if dist < inner_m:
        return FenceClearance(ray_circle_exit_m(pn, pe, dn, de, inner_m))
    breached = dist > fence.radius_m
    if outward:
        return FenceClearance(0.0, breached)
    # inward: free until the far side of the inner circle, if the ray crosses it at all
    b = pn * dn + pe * de
    if b * b - (dist * dist - inner_m * inner_m) < 0.0:
        return FenceClearance(None, breached)
    return FenceClearance(ray_circle_exit_m(pn, pe, dn, de, inner_m), breached)


def _exclusion_circle(fence: CircleFence, margin_m: float, north_m: float, east_m: float, dn: float,
                      de: float) -> FenceClearance:
    """Stay outside the circle widened by the margin: the distance along the ray to where it enters that; inside the
    circle itself (breached) only motion away from the centre passes, inside the margin's ring the same stops."""
    pn, pe = north_m - fence.center_north_m, east_m - fence.center_east_m
    dist = math.hypot(pn, pe)
    b = pn * dn + pe * de
    outer_m = fence.radius_m + margin_m
    if dist <= outer_m:
        return FenceClearance(None if b > 0.0 else 0.0, breached=dist < fence.radius_m)
    disc = b * b - (dist * dist - outer_m * outer_m)
    if b >= 0.0 or disc < 0.0:
        return FenceClearance(None)  # moving away, or the ray misses it
    return FenceClearance(-b - math.sqrt(disc))


def _polygon(fence: PolygonFence, margin_m: float, north_m: float, east_m: float, dn: float,
             de: float) -> FenceClearance:
    if len(fence.points_ne) < 3:
        return FenceClearance(None)
    if inside_polygon(north_m, east_m, fence.points_ne) != fence.inclusion:
        vn, ve = nearest_boundary_vector(north_m, east_m, fence.points_ne)
        return FenceClearance(None if vn * dn + ve * de > 0.0 else 0.0, breached=True)
    return FenceClearance(edge_travel_m(north_m, east_m, dn, de, fence.points_ne, margin_m))


def fence_clearance(fences: Fences, north_m: float, east_m: float, travel_cw_rad: float) -> FenceClearance:
    """The tightest clearance over every fence for travel from (north, east) toward `travel_cw_rad`."""
    dn, de = math.cos(travel_cw_rad), math.sin(travel_cw_rad)
    parts = [_polygon(p, fences.margin_m, north_m, east_m, dn, de) for p in fences.polygons]
    circles = fences.circles if fences.circle is None else (fences.circle, *fences.circles)
    parts += [_circle(c, fences.margin_m, north_m, east_m, dn, de) for c in circles]
    distances = [p.distance_m for p in parts if p.distance_m is not None]
    return FenceClearance(min(distances) if distances else None, any(p.breached for p in parts))


POLYGON_INCLUSION = 5001  # MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION: param1 = the polygon's vertex count
POLYGON_EXCLUSION = 5002
CIRCLE_INCLUSION = 5003  # MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION: param1 = radius m
CIRCLE_EXCLUSION = 5004


def stored_fences(items: Sequence[tuple[int, float, float, float]], origin_lat_deg: float,
                  origin_lon_deg: float) -> tuple[tuple[PolygonFence, ...], tuple[CircleFence, ...]]:
    """The polygons and circles of a downloaded fence, items as (command, param1, lat deg, lon deg), flattened about
    the origin (home). A polygon is its first vertex's param1 items of the same command in a row (as ArduPilot's
    AC_PolyFence_loader reads them); a short or broken run is dropped; the return point (5000) is not a fence."""
    polygons: list[PolygonFence] = []
    circles: list[CircleFence] = []
    i = 0
    while i < len(items):
        command, param1, lat, lon = items[i]
        if command in (CIRCLE_INCLUSION, CIRCLE_EXCLUSION):
            if param1 > 0.0:
                north, east = ne_from_lat_lon(origin_lat_deg, origin_lon_deg, lat, lon)
                circles.append(CircleFence(param1, north, east, inclusion=command == CIRCLE_INCLUSION))
            i += 1
            continue
        if command not in (POLYGON_INCLUSION, POLYGON_EXCLUSION):
            i += 1
            continue
        count = int(param1)
        run = items[i:i + count]
        if count >= 3 and len(run) == count and all(item[0] == command for item in run):
            polygons.append(PolygonFence.from_lat_lon([(item[2], item[3]) for item in run], origin_lat_deg,
                                                      origin_lon_deg, inclusion=command == POLYGON_INCLUSION))
            i += count
        else:
            i += 1
    return tuple(polygons), tuple(circles)
