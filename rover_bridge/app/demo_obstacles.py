"""The demo's `obstacles` scenario (issue 43): a wall ahead and a post, ArduPilot's SITL proximity sensor (PRX1_TYPE
10: 8 sectors as DISTANCE_SENSOR), and a ground station that drives the rover at each in GUIDED with velocity
requests and keeps asking after it stopped. The emulator's Rover does not avoid by itself: what stops it
AVOID_MARGIN short is the bridge (docs/avoidance.md).

The obstacles are defined here once: the emulator gets them as its scenario's ``[[obstacles]]`` polygons, and
the report and the picture measure the truth against the same polygons (from the rover's centre, as
tests/test_avoidance_e2e.py does), with geometry of their own, not the bridge's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from rover_bridge.app.demo_route import Phase, body, toward
from rover_bridge.app.demo_series import Series
from rover_bridge.command.fences import nearest_boundary_vector

Point = tuple[float, float]  # north, east (m) in the autopilot's local frame: the start is 0, 0, facing north
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Obstacle:
    name: str
    polygon: tuple[Point, ...]


def _octagon(centre: Point, radius_m: float) -> tuple[Point, ...]:
    """A round post as the polygon the scenario TOML carries (a flat face toward every 45-degree bearing)."""
    return tuple((centre[0] + radius_m * math.cos(math.radians(22.5 + 45 * k)),
                  centre[1] + radius_m * math.sin(math.radians(22.5 + 45 * k))) for k in range(8))


WALL = Obstacle("wall", ((8.0, -3.0), (8.0, 5.0), (8.4, 5.0), (8.4, -3.0)))  # 8 m ahead, 8 m wide
# South-east of where the rover stops at the wall (about 6 m north): about 6 m from it, on its 135 deg bearing;
# 0.8 m across: the proximity sensor's forward sector is one ray (as ArduPilot's SITL), and the rover's heading
# on the way is 1-3 deg off the bearing asked for (the heading controller's standing error), 0.1-0.3 m at 6 m.
POST = Obstacle("post", _octagon((1.75, 4.25), 0.4))
OBSTACLES = (WALL, POST)
# ArduPilot's SITL proximity sensor (sitl/range_sensors.py): 8 sectors, 1 Hz until the bridge asks for 10 Hz.
VEHICLE_PARAMS = {"PRX1_TYPE": 10.0}
SPEED_M_S = 1.0  # what issue 43's runs ask for; the scenario's profile allows it ([limits] max_linear_m_s)
PROFILE_TOML = "[limits]\nmax_linear_m_s = 1.0\n"


def scenario_toml() -> str:
    """The emulator's scenario file: each obstacle as a ``[[obstacles]]`` polygon."""
    out = []
    for o in OBSTACLES:
        points = ", ".join(f"[{n:.4f}, {e:.4f}]" for n, e in o.polygon)
        out.append(f"# {o.name}\n[[obstacles]]\npolygon = [{points}]\n")
    return "\n".join(out)


def obstacle_route() -> list[Phase]:
    """GUIDED all along: at the wall and on asking after the rover stopped; turn in place to the post, at it
    and on asking; back away from it (motion away is never limited); stop. About 28 s."""
    post_centre = (sum(p[0] for p in POST.polygon) / 8, sum(p[1] for p in POST.polygon) / 8)
    return [Phase("standstill", 2.0, body(0.0, 0.0)),
            Phase("to the wall", 10.0, body(SPEED_M_S, 0.0)),
            Phase("turn to the post", 3.0, toward(0.0), aim_ne=post_centre),
            Phase("to the post", 7.5, toward(SPEED_M_S), aim_ne=post_centre),
            Phase("back away", 2.5, body(-0.4, 0.0)),
            Phase("stop", 1.0, body(0.0, 0.0))]


LEGS = {"to the wall": WALL, "to the post": POST}  # the phases that drive at an obstacle


def clearance_m(north: FloatArray, east: FloatArray, polygon: Sequence[Point]) -> FloatArray:
    """Distance from each point to the polygon's boundary, 0 inside it (even-odd rule): the arithmetic of
    rover_bridge.command.fences on numpy arrays, for a whole path or the picture's grid at once."""
    best = np.full(np.shape(north), np.inf)
    inside = np.zeros(np.shape(north), dtype=bool)
    for (n1, e1), (n2, e2) in zip(polygon, [*polygon[1:], polygon[0]], strict=True):
        dn, de = n2 - n1, e2 - e1
        u = np.clip(((north - n1) * dn + (east - e1) * de) / (dn * dn + de * de), 0.0, 1.0)
        best = np.minimum(best, np.hypot(north - (n1 + u * dn), east - (e1 + u * de)))
        if e1 != e2:  # an edge along the east axis crosses no east = const line
            crosses = (e1 > east) != (e2 > east)
            n_cross = n1 + (east - e1) * dn / de
            inside ^= crosses & (north < n_cross)
    return np.where(inside, 0.0, best)


def nearest_point(north: float, east: float, polygon: Sequence[Point]) -> Point:
    """The polygon boundary's point nearest (north, east): where the picture draws the distance to."""
    dn, de = nearest_boundary_vector(north, east, polygon)
    return north + dn, east + de


@dataclass(frozen=True)
class ObstacleLeg:
    """One phase that drove at an obstacle, by ground truth (the rover's centre)."""

    phase: str
    obstacle: str
    margin_m: float  # AVOID_MARGIN as the autopilot reported it
    closest_m: float  # nearest the rover came to the obstacle during the phase
    rest_m: float  # from it at the phase's end, the ground station still asking to go on
    rest_speed_m_s: float  # how fast the rover still went then
    rest_ne: Point  # where it stopped

    @property
    def touched(self) -> bool:
        return self.closest_m <= 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"phase": self.phase, "obstacle": self.obstacle, "margin_m": self.margin_m,
                "closest_m": self.closest_m, "rest_m": self.rest_m, "rest_speed_m_s": self.rest_speed_m_s,
                "touched": self.touched}

    @staticmethod
    def table(legs: Sequence[ObstacleLeg]) -> str:
        out = [f"{'driven at':18s} {'AVOID_MARGIN':>12s} {'closest approach':>17s} {'at rest':>8s} "
               f"{'speed then':>11s} {'touched':>8s}"]
        out += [f"{leg.obstacle + ' (' + leg.phase + ')':18s} {leg.margin_m:10.2f} m {leg.closest_m:15.2f} m "
                f"{leg.rest_m:6.2f} m {leg.rest_speed_m_s:7.2f} m/s {'YES' if leg.touched else 'no':>8s}"
                for leg in legs]
        return "\n".join(out)


def obstacle_legs(series: Series, margin_m: float) -> list[ObstacleLeg]:
    """Each leg of LEGS that the run drove: its closest approach and rest distance by the truth."""
    if not series.truth:
        return []
    t = np.array([p[0] for p in series.truth])
    north, east = np.array([p[1] for p in series.truth]), np.array([p[2] for p in series.truth])
    end = series.truth[-1][0]
    legs = []
    for k, (name, t0) in enumerate(series.segments):
        obstacle = LEGS.get(name)
        t1 = series.segments[k + 1][1] if k + 1 < len(series.segments) else end
        span = (t >= t0) & (t <= t1)
        if obstacle is None or not span.any():
            continue
        d = clearance_m(north[span], east[span], obstacle.polygon)
        i = int(np.flatnonzero(span)[-1])
        legs.append(ObstacleLeg(name, obstacle.name, margin_m, float(d.min()), float(d[-1]),
                                speed_at(series, series.truth[i][0]), (float(north[i]), float(east[i]))))
    return legs


def speed_at(series: Series, t: float) -> float:
    """The truth's speed sample at or just before t (0 if none)."""
    before = [v for ts, v in series.speed if ts <= t]
    return before[-1] if before else 0.0
