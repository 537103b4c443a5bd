"""Fence geometry: the edges of polygons as walls, the circle fence, breached fences (hand-computed), and a property:
an oblique approach still stops the margin from every edge."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.command.fences import (
    CircleFence,
    FenceClearance,
    Fences,
    PolygonFence,
    edge_travel_m,
    fence_clearance,
    inside_polygon,
    ne_from_lat_lon,
    nearest_boundary_vector,
)

SQUARE = ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0))  # north 0..10, east 0..10
NORTH, EAST, SOUTH, WEST = 0.0, math.pi / 2, math.pi, -math.pi / 2


def test_point_in_polygon() -> None:
    assert inside_polygon(5.0, 5.0, SQUARE)
    assert not inside_polygon(12.0, 5.0, SQUARE)
    assert not inside_polygon(5.0, -0.1, SQUARE)
    concave = ((0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (5.0, 5.0), (0.0, 10.0))  # a notch from the east side
    assert not inside_polygon(2.0, 8.0, concave) and inside_polygon(8.0, 8.0, concave)


def test_edge_travel_takes_each_edge_as_a_wall_square_to_its_closest_point() -> None:
    assert edge_travel_m(5.0, 5.0, 1.0, 0.0, SQUARE, 1.0) == pytest.approx(4.0)
    assert edge_travel_m(2.0, 5.0, -1.0, 0.0, SQUARE, 0.0) == pytest.approx(2.0)
    c = math.sqrt(0.5)
    assert edge_travel_m(5.0, 5.0, c, c, SQUARE, 1.0) == pytest.approx(4.0 / c)  # the corner: 4 m square to each edge
    assert edge_travel_m(2.0, 5.0, c, c, SQUARE, 1.0) == pytest.approx(4.0 / c)  # east edge (5 m) before north (8 m)
    assert edge_travel_m(5.0, 0.5, 1.0, 0.0, SQUARE, 1.0) == pytest.approx(4.0)  # along the west edge: the north one
    assert edge_travel_m(5.0, 5.0, 1.0, 0.0, ((0.0, 0.0), (0.0, 10.0), (-1.0, 5.0)), 1.0) is None  # all behind
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
    # Passing east of it: its corner (20, 10) is a wall square to the line to it, 46.8 m of travel away: no cap
    # that matters (AC_Avoid's way; it never comes nearer than 15 m).
    p = math.hypot(15.0, 5.0)
    assert fence_clearance(fences, 5.0, 5.0, EAST) == FenceClearance(pytest.approx((p - 1.0) * p / 5.0))
    assert fence_clearance(fences, 22.0, 5.0, SOUTH) == FenceClearance(None, True)  # nearest way out
    assert fence_clearance(fences, 22.0, 5.0, NORTH) == FenceClearance(0.0, True)


def test_the_tightest_fence_wins() -> None:
    keep_out = PolygonFence(((6.0, -1.0), (8.0, -1.0), (8.0, 1.0), (6.0, 1.0)), inclusion=False)
    fences = Fences(margin_m=2.0, circle=CircleFence(12.0), polygons=(keep_out,))
    assert fence_clearance(fences, 0.0, 0.0, NORTH).distance_m == pytest.approx(4.0)
    assert fence_clearance(fences, 0.0, 0.0, SOUTH).distance_m == pytest.approx(10.0)
    assert fence_clearance(Fences(margin_m=1.0, polygons=(PolygonFence(((0.0, 0.0), (1.0, 1.0))),)),
                           0.0, 0.0, NORTH) == FenceClearance(None)


@settings(max_examples=400, deadline=None)
@given(st.floats(1.0, 9.0), st.floats(1.0, 9.0), st.floats(-math.pi, math.pi), st.floats(0.0, 1.0))
def test_travel_as_allowed_never_ends_inside_the_margin_of_a_convex_fence(north_m: float, east_m: float,
                                                                          heading: float, margin_m: float) -> None:
    fences = Fences(margin_m=margin_m, polygons=(PolygonFence(SQUARE),))
    clearance = fence_clearance(fences, north_m, east_m, heading)
    assert clearance.distance_m is not None  # inside a closed square every direction meets an edge
    end_n = north_m + clearance.distance_m * math.cos(heading)
    end_e = east_m + clearance.distance_m * math.sin(heading)
    start_gap = min(north_m, 10.0 - north_m, east_m, 10.0 - east_m)
    assert min(end_n, 10.0 - end_n, end_e, 10.0 - end_e) >= min(margin_m, start_gap) - 1e-6
