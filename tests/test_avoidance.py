"""The avoidance limiter: ArduPilot's stop-at-the-margin rule, by hand and as properties (fixed seeds)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

import pytest
from hypothesis import given, seed, settings
from hypothesis import strategies as st

from rover_bridge.command.avoidance import (
    AvoidReason,
    AvoidSettings,
    FenceQuery,
    Limited,
    cap_speed_m_s,
    limit_velocity,
    stopping_speed_m_s,
)
from rover_bridge.command.fences import CircleFence, Fences
from rover_bridge.command.obstacles import ObstaclePicture, ObstacleView, Sector, SectorState

S = AvoidSettings(margin_m=2.0, decel_m_s2=1.0, delay_s=0.0, crawl_speed_m_s=0.2, backup_speed_m_s=0.75)
LIDAR = (1, 195, 0)


def one(bearing_ccw_rad: float, distance_m: float) -> ObstacleView:
    sectors = [Sector(i, SectorState.UNKNOWN, 0.0) for i in range(8)]
    sectors[0] = Sector(0, SectorState.OBSTACLE, bearing_ccw_rad, distance_m, 0.0)
    return ObstacleView(tuple(sectors))


def test_stopping_speed_is_sqrt_2ad_less_what_the_delay_eats() -> None:
    assert stopping_speed_m_s(2.0, 1.0) == pytest.approx(2.0)
    v = stopping_speed_m_s(2.0, 1.0, 0.5)
    assert v == pytest.approx(-0.5 + math.sqrt(4.25))
    assert v * 0.5 + v * v / 2.0 == pytest.approx(2.0)  # run at v for the delay, then brake: exactly 2 m
    assert stopping_speed_m_s(0.0, 1.0) == 0.0 and stopping_speed_m_s(-1.0, 1.0) == 0.0
    # the cap keeps a * delay^2 / 2 for the commands already on their way
    assert cap_speed_m_s(2.0, 1.0, 0.5) == pytest.approx(stopping_speed_m_s(2.0 - 0.125, 1.0, 0.5))
    assert cap_speed_m_s(0.1, 1.0, 0.5) == 0.0


def test_wall_ahead_caps_forward_speed_and_leaves_reverse_alone() -> None:
    view = one(0.0, 4.0)
    assert limit_velocity(3.0, 0.4, S, view) == Limited(pytest.approx(2.0), 0.4, AvoidReason.OBSTACLE_SLOW,
                                                        pytest.approx(2.0))
    assert limit_velocity(1.0, 0.0, S, view).reason is AvoidReason.PASS
    assert limit_velocity(1.0, 0.0, S, view).v_m_s == 1.0
    assert limit_velocity(-3.0, 0.0, S, view) == Limited(-3.0, 0.0)


def test_oblique_obstacle_limits_the_component_toward_it() -> None:
    out = limit_velocity(5.0, 0.0, S, one(math.pi / 4, 4.0))  # YAW_315: front left
    assert out.v_m_s == pytest.approx(2.0 / math.cos(math.pi / 4))
    assert limit_velocity(5.0, 0.0, S, one(-math.pi / 2, 0.5)).v_m_s == 5.0  # abeam, inside the margin: along


def test_inside_the_margin_stops_toward_and_lets_back_away() -> None:
    view = one(0.0, 1.5)
    stop = limit_velocity(1.0, 0.3, S, view)
    assert stop.v_m_s == 0.0 and stop.reason is AvoidReason.OBSTACLE_STOP and stop.omega_rad_s == 0.3
    back = limit_velocity(-0.5, 0.0, S, view)
    assert back.v_m_s == -0.5 and back.reason is AvoidReason.PASS
    # what ArduPilot would back away at: sqrt(2 * 0.4 a * breach), breach 0.5 m > deadzone 0.1 m
    assert stop.backup_m_s == pytest.approx(-math.sqrt(2 * 0.4 * 0.5))
    assert limit_velocity(0.0, 0.0, S, one(0.0, 0.1)).backup_m_s == -0.75  # AVOID_BACKUP_SPD
    assert limit_velocity(0.0, 0.0, S, one(0.0, 1.95)).backup_m_s == 0.0  # inside the deadzone


def test_obstacle_behind_caps_reverse() -> None:
    out = limit_velocity(-3.0, 0.0, S, one(math.pi, 4.0))
    assert out.v_m_s == pytest.approx(-2.0) and out.reason is AvoidReason.OBSTACLE_SLOW
    assert limit_velocity(3.0, 0.0, S, one(math.pi, 2.1)).v_m_s == 3.0


def test_a_silent_sensor_slows_to_a_crawl() -> None:
    pic = ObstaclePicture()
    pic.distance_sensor(0.0, LIDAR, 0, 1300, 20, 1200)
    assert limit_velocity(1.0, 0.0, S, pic.view(0.1)).v_m_s == 1.0
    out = limit_velocity(1.0, 0.0, S, pic.view(2.0))
    assert out.v_m_s == 0.2 and out.reason is AvoidReason.BLIND_CRAWL
    assert limit_velocity(-0.1, 0.0, S, pic.view(2.0)).v_m_s == -0.1


def test_fence_caps_and_breaches() -> None:
    fences = Fences(margin_m=2.0, circle=CircleFence(12.0))
    out = limit_velocity(10.0, 0.0, S, fence=FenceQuery(fences, 0.0, 0.0, 0.0))
    assert out.v_m_s == pytest.approx(math.sqrt(20.0)) and out.reason is AvoidReason.FENCE_SLOW
    # heading north at 11 m north: forward is outward (stop), reverse is inward (free)
    assert limit_velocity(1.0, 0.0, S, fence=FenceQuery(fences, 11.0, 0.0, 0.0)).reason is AvoidReason.FENCE_STOP
    assert limit_velocity(-1.0, 0.0, S, fence=FenceQuery(fences, 11.0, 0.0, 0.0)).v_m_s == -1.0
    out = limit_velocity(1.0, 0.0, S, fence=FenceQuery(fences, 13.0, 0.0, 0.0))
    assert out.v_m_s == 0.0 and out.reason is AvoidReason.FENCE_BREACHED
    assert limit_velocity(1.0, 0.0, S, fence=FenceQuery(fences, 13.0, 0.0, math.pi)).v_m_s == 1.0


def test_tightest_of_obstacle_and_fence_wins() -> None:
    fences = Fences(margin_m=2.0, circle=CircleFence(12.0))
    out = limit_velocity(9.0, 0.0, S, one(0.0, 3.0), FenceQuery(fences, 0.0, 0.0, 0.0))
    assert out.v_m_s == pytest.approx(math.sqrt(2.0)) and out.reason is AvoidReason.OBSTACLE_SLOW


# ------------------------------------------------------------------ properties

sector_st = st.builds(
    lambda i, b, d: Sector(i, SectorState.OBSTACLE, b, d, 0.0),
    st.integers(0, 7), st.floats(-math.pi, math.pi), st.floats(0.01, 50.0))
view_st = st.builds(lambda ss, blind: ObstacleView(tuple(ss), ((1, 1, 1),) if blind else ()),
                    st.lists(sector_st, max_size=8), st.booleans())
settings_st = st.builds(AvoidSettings, st.floats(0.0, 5.0), st.floats(0.1, 5.0), st.floats(0.0, 0.5),
                        st.floats(0.0, 1.0))
request_st = st.floats(-5.0, 5.0)


@seed(43)
@settings(max_examples=300, deadline=None)
@given(request_st, view_st, settings_st, st.floats(-30.0, 30.0), st.floats(-30.0, 30.0), st.floats(-4.0, 4.0))
def test_never_increases_never_flips(v: float, view: ObstacleView, s: AvoidSettings, n: float, e: float,
                                     heading: float) -> None:
    fence = FenceQuery(Fences(1.0, CircleFence(20.0)), n, e, heading)
    out = limit_velocity(v, 0.7, s, view, fence)
    assert abs(out.v_m_s) <= abs(v)
    assert out.v_m_s * v >= 0.0
    assert out.omega_rad_s == 0.7
    assert (out.v_m_s == v) == (out.reason is AvoidReason.PASS)


@seed(43)
@settings(max_examples=300, deadline=None)
@given(request_st, st.floats(-math.pi, math.pi), st.floats(0.0, 30.0), st.floats(0.0, 30.0), settings_st)
def test_monotone_in_distance(v: float, bearing: float, d1: float, d2: float, s: AvoidSettings) -> None:
    near, far = min(d1, d2), max(d1, d2)
    assert abs(limit_velocity(v, 0.0, s, one(bearing, near)).v_m_s) <= abs(limit_velocity(v, 0.0, s,
                                                                                           one(bearing, far)).v_m_s)


@seed(43)
@settings(max_examples=300, deadline=None)
@given(request_st, st.lists(st.tuples(st.floats(-math.pi, math.pi), st.floats(0.01, 30.0)), max_size=8), settings_st)
def test_motion_away_or_along_is_untouched(v: float, obstacles: list[tuple[float, float]], s: AvoidSettings) -> None:
    direction = 1.0 if v >= 0.0 else -1.0
    away = [Sector(0, SectorState.OBSTACLE, b, d, 0.0) for b, d in obstacles if direction * math.cos(b) <= 0.0]
    assert limit_velocity(v, 0.0, s, ObstacleView(tuple(away))).v_m_s == v


DT_S = 0.05


def approach(gap0_m: float, v_req: float, s: AvoidSettings, lag_steps: int,
             limit: Callable[[float, float], float]) -> tuple[float, float]:
    """A rover driving straight at an edge: each 50 ms `limit(t, gap)` caps the request, the command reaches the
    wheels lag_steps later, and the wheels change speed no faster than the deceleration.
    Returns (closest gap, final gap)."""
    pending: deque[float] = deque([0.0] * lag_steps)
    x = v = 0.0
    closest = gap0_m
    for k in range(int(200.0 / DT_S)):
        gap = gap0_m - x
        if k > lag_steps and abs(v) < 1e-4 and max(pending, default=0.0) < 1e-4 and gap < s.margin_m + 0.3:
            break  # at rest (a creep of under 0.1 mm/s left)
        pending.append(limit(k * DT_S, gap))
        cmd = pending.popleft()
        dv = max(-s.decel_m_s2 * DT_S, min(s.decel_m_s2 * DT_S, cmd - v))
        x += (v + 0.5 * dv) * DT_S
        v += dv
        closest = min(closest, gap0_m - x)
    return closest, gap0_m - x


def wall(v_req: float, s: AvoidSettings) -> Callable[[float, float], float]:
    """A wall straight ahead seen by DISTANCE_SENSOR sector 0, in centimetres as the message carries it."""
    pic = ObstaclePicture()

    def limit(t_s: float, gap_m: float) -> float:
        pic.distance_sensor(t_s, LIDAR, 0, round(gap_m * 100.0), 20, 5000)
        return limit_velocity(v_req, 0.0, s, pic.view(t_s)).v_m_s
    return limit


def circle_fence(v_req: float, s: AvoidSettings, radius_m: float) -> Callable[[float, float], float]:
    """Driving north from home toward a circle fence: gap is the distance to the fence, margin = FENCE_MARGIN."""
    fences = Fences(margin_m=s.margin_m, circle=CircleFence(radius_m))

    def limit(t_s: float, gap_m: float) -> float:
        return limit_velocity(v_req, 0.0, s, fence=FenceQuery(fences, radius_m - gap_m, 0.0, 0.0)).v_m_s
    return limit


@seed(43)
@settings(max_examples=40, deadline=None)
@given(st.floats(0.5, 15.0), st.floats(0.2, 3.0), st.floats(0.5, 3.0), st.floats(0.3, 3.0), st.integers(0, 6))
def test_a_simulated_approach_stops_at_the_margin(extra_m: float, v_req: float, margin_m: float, decel: float,
                                                  lag_steps: int) -> None:
    # the delay the limiter is told: the command's lag plus one control period (the output is held that long)
    s = AvoidSettings(margin_m=margin_m, decel_m_s2=decel, delay_s=(lag_steps + 1) * DT_S)
    rest_m = margin_m + 0.5 * decel * s.delay_s ** 2 + 0.05  # the reserve (a tau^2 / 2) and a little creep left
    closest, final = approach(margin_m + extra_m, v_req, s, lag_steps, wall(v_req, s))
    assert closest >= margin_m - 0.01  # the picture's centimetres
    assert final <= rest_m  # not timid
    closest, final = approach(margin_m + extra_m, v_req, s, lag_steps, circle_fence(v_req, s, margin_m + extra_m))
    assert closest >= margin_m - 1e-3  # exact position: only the integration's rounding
    assert final <= rest_m


def test_a_fence_the_rover_cannot_be_placed_on_caps_at_the_crawl_and_a_nearer_obstacle_still_wins() -> None:
    out = limit_velocity(1.0, 0.3, S, fence_unplaced=True)
    assert (out.v_m_s, out.omega_rad_s, out.reason) == (S.crawl_speed_m_s, 0.3, AvoidReason.FENCE_UNKNOWN)
    assert limit_velocity(-0.1, 0.0, S, fence_unplaced=True).v_m_s == -0.1  # under the crawl: as asked
    near = limit_velocity(1.0, 0.0, S, one(0.0, S.margin_m + 0.01), fence_unplaced=True)
    assert near.reason is AvoidReason.OBSTACLE_SLOW and near.v_m_s < S.crawl_speed_m_s
