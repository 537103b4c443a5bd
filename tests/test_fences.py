"""Fence geometry: ray casting against polygons, the circle fence, breached fences (hand-computed)."""

from __future__ import annotations

import math

import pytest

from rover_bridge.command.fences import (
    CircleFence,
    FenceClearance,
    Fences,
    PolygonFence,
    fence_clearance,
    inside_polygon,
    ne_from_lat_lon,
    nearest_boundary_vector,
    ray_polygon_distance_m,
)

SQUARE = ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0))  # north 0..10, east 0..10
NORTH, EAST, SOUTH, WEST = 0.0, math.pi / 2, math.pi, -math.pi / 2


def test_point_in_polygon() -> None:
    assert inside_polygon(5.0, 5.0, SQUARE)
    assert not inside_polygon(12.0, 5.0, SQUARE)
    assert not inside_polygon(5.0, -0.1, SQUARE)
    concave = ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (5.0, 5.0), (0.0, 10.0))  # a notch from the east side
    assert not inside_polygon(2.0, 8.0, concave) and inside_polygon(8.0, 8.0, concave)


def test_ray_polygon_distances() -> None:
    assert ray_polygon_distance_m(5.0, 5.0, 1.0, 0.0, SQUARE) == pytest.approx(5.0)
    assert ray_polygon_distance_m(2.0, 5.0, -1.0, 0.0, SQUARE) == pytest.approx(2.0)
    c = math.sqrt(0.5)
    assert ray_polygon_distance_m(5.0, 5.0, c, c, SQUARE) == pytest.approx(5.0 * math.sqrt(2.0))
    assert ray_polygon_distance_m(2.0, 5.0, c, c, SQUARE) == pytest.approx(5.0 * math.sqrt(2.0))  # hits east side
    assert ray_polygon_distance_m(-5.0, 5.0, 1.0, 0.0, SQUARE) == pytest.approx(5.0)  # from outside: entering
    assert ray_polygon_distance_m(-5.0, 5.0, -1.0, 0.0, SQUARE) is None
    assert ray_polygon_distance_m(5.0, 0.0, 1.0, 0.0, SQUARE) is not None  # along the west edge: the north edge
    assert nearest_boundary_vector(5.0, 2.0, SQUARE) == pytest.approx((0.0, -2.0))
    assert nearest_boundary_vector(12.0, 12.0, SQUARE) == pytest.approx((-2.0, -2.0))


def test_lat_lon_flattened_about_the_origin() -> None:
    north, east = ne_from_lat_lon(0.0, 0.0, 0.001, 0.0)
    assert north == pytest.approx(111.319, abs=1e-3) and east == 0.0
    north, east = ne_from_lat_lon(60.0, 10.0, 60.0, 10.001)
    assert east == pytest.approx(55.66, abs=1e-2) and north == 0.0
    poly = PolygonFence.from_lat_lon([(60.0, 10.0), (60.001, 10.0), (60.001, 10.001)], 60.0, 10.0)
    assert poly.points_ne[1] == pytest.approx((111.319, 0.0), abs=1e-3) and poly.inclusion


def test_circle_fence_stops_the_margin_inside() -> None:
    fences = Fences(margin_m=2.0, circle=CircleFence(12.0))
    assert fence_clearance(fences, 0.0, 0.0, 1.234) == FenceClearance(pytest.approx(10.0))
    assert fence_clearance(fences, 5.0, 0.0, NORTH).distance_m == pytest.approx(5.0)
    assert fence_clearance(fences, 5.0, 0.0, SOUTH).distance_m == pytest.approx(15.0)
    assert fence_clearance(fences, 0.0, 6.0, NORTH).distance_m == pytest.approx(8.0)  # sqrt(10^2 - 6^2)
    # inside the margin: outward stops, inward runs to the far side of the inner circle
    assert fence_clearance(fences, 11.0, 0.0, NORTH) == FenceClearance(0.0, False)
    assert fence_clearance(fences, 11.0, 0.0, SOUTH).distance_m == pytest.approx(21.0)
    assert fence_clearance(fences, 11.0, 0.0, EAST) == FenceClearance(0.0, False)  # tangent is outward
    # outside the fence: only the way back in
    assert fence_clearance(fences, 13.0, 0.0, NORTH) == FenceClearance(0.0, True)
    assert fence_clearance(fences, 13.0, 0.0, SOUTH) == FenceClearance(pytest.approx(23.0), True)
    assert fence_clearance(Fences(margin_m=13.0, circle=CircleFence(12.0)), 0.0, 0.0, NORTH).distance_m is None


def test_circle_fence_about_a_centre() -> None:
    fences = Fences(margin_m=1.0, circle=CircleFence(5.0, center_north_m=100.0, center_east_m=-50.0))
    assert fence_clearance(fences, 100.0, -50.0, EAST).distance_m == pytest.approx(4.0)


def test_inclusion_polygon() -> None:
    fences = Fences(margin_m=1.0, polygons=(PolygonFence(SQUARE),))
    assert fence_clearance(fences, 5.0, 5.0, NORTH) == FenceClearance(pytest.approx(4.0))
    assert fence_clearance(fences, 9.5, 5.0, NORTH) == FenceClearance(0.0)
    assert fence_clearance(fences, 9.5, 5.0, SOUTH).distance_m == pytest.approx(8.5)
    assert fence_clearance(fences, 9.5, 5.0, EAST).distance_m == pytest.approx(4.0)  # along the edge: east side
    assert fence_clearance(fences, 12.0, 5.0, SOUTH) == FenceClearance(None, True)
    assert fence_clearance(fences, 12.0, 5.0, NORTH) == FenceClearance(0.0, True)
    assert fence_clearance(fences, 12.0, 5.0, EAST) == FenceClearance(0.0, True)


def test_exclusion_polygon() -> None:
    keep_out = PolygonFence(tuple((n + 20.0, e) for n, e in SQUARE), inclusion=False)  # north 20..30
    fences = Fences(margin_m=1.0, polygons=(keep_out,))
    assert fence_clearance(fences, 5.0, 5.0, NORTH) == FenceClearance(pytest.approx(14.0))
    assert fence_clearance(fences, 5.0, 5.0, SOUTH) == FenceClearance(None)
    assert fence_clearance(fences, 5.0, 5.0, EAST) == FenceClearance(None)
    assert fence_clearance(fences, 22.0, 5.0, SOUTH) == FenceClearance(None, True)  # nearest way out
    assert fence_clearance(fences, 22.0, 5.0, NORTH) == FenceClearance(0.0, True)


def test_the_tightest_fence_wins() -> None:
    keep_out = PolygonFence(((6.0, -1.0), (8.0, -1.0), (8.0, 1.0), (6.0, 1.0)), inclusion=False)
    fences = Fences(margin_m=2.0, circle=CircleFence(12.0), polygons=(keep_out,))
    assert fence_clearance(fences, 0.0, 0.0, NORTH).distance_m == pytest.approx(4.0)
    assert fence_clearance(fences, 0.0, 0.0, SOUTH).distance_m == pytest.approx(10.0)
    assert fence_clearance(Fences(margin_m=1.0, polygons=(PolygonFence(((0.0, 0.0), (1.0, 1.0))),)),
                           0.0, 0.0, NORTH) == FenceClearance(None)
