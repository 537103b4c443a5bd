"""The stored polygon fence (AC_PolyFence_loader's items) and its shapes in the emulator's world.

Read in ArduPilot (4.7): libraries/AC_Fence/AC_PolyFence_loader.cpp (write_fence: the vertices of a
polygon are consecutive items of one type, each giving the polygon's vertex count in param1, at least 3;
a circle's radius is param1), libraries/GCS_MAVLink/MissionItemProtocol_Fence.cpp (which MAV_CMDs are
fence items). Items keep x/y as lat/lon * 1e7 as uploaded; ``shapes`` turns them into NED metres about
the emulator's origin (sitl/geo.py). The store lives in "storage": a reboot keeps it, as the mission.
"""

from __future__ import annotations

from dataclasses import dataclass

from sitl.geo import north_east_of
from sitl.mav import mavlink
from sitl.obstacles import Circle, Polygon, Shape

_P = mavlink
RETURN_POINT: int = _P.MAV_CMD_NAV_FENCE_RETURN_POINT  # 5000
POLYGON_INCLUSION: int = _P.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION  # 5001
POLYGON_EXCLUSION: int = _P.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION  # 5002
CIRCLE_INCLUSION: int = _P.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION  # 5003
CIRCLE_EXCLUSION: int = _P.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION  # 5004
FENCE_COMMANDS = frozenset({RETURN_POINT, POLYGON_INCLUSION, POLYGON_EXCLUSION, CIRCLE_INCLUSION, CIRCLE_EXCLUSION})
MAX_ITEMS = 255  # the emulator's own limit (ArduPilot's depends on the board's fence storage)


@dataclass(frozen=True)
class FenceItem:
    command: int
    param1: float  # a polygon's vertex count, a circle's radius (m)
    x: int  # latitude * 1e7
    y: int  # longitude * 1e7


@dataclass(frozen=True)
class FenceShapes:
    inclusion: tuple[Shape, ...] = ()
    exclusion: tuple[Shape, ...] = ()

    @property
    def all(self) -> tuple[Shape, ...]:
        return self.inclusion + self.exclusion


def valid(items: tuple[FenceItem, ...]) -> bool:
    """write_fence's check: each polygon complete (count >= 3, as many vertices as it says), circles > 0."""
    i = 0
    while i < len(items):
        item = items[i]
        if item.command in (POLYGON_INCLUSION, POLYGON_EXCLUSION):
            count = int(item.param1)
            run = items[i:i + count]
            if count < 3 or len(run) != count or any(v.command != item.command or int(v.param1) != count for v in run):
                return False
            i += count
            continue
        if item.command in (CIRCLE_INCLUSION, CIRCLE_EXCLUSION) and not item.param1 > 0:
            return False
        i += 1
    return True


class FenceStore:
    """The fence items as stored (uploaded, downloaded and cleared through sitl/fence_protocol.py)."""

    def __init__(self) -> None:
        self.items: tuple[FenceItem, ...] = ()
        self.version = 0  # bumped on every write: a reader re-derives its shapes

    def write(self, items: tuple[FenceItem, ...]) -> bool:
        if not valid(items):
            return False
        self.items = items
        self.version += 1
        return True

    def shapes(self, lat0_deg: float, lon0_deg: float) -> FenceShapes:
        """The polygons and circles in NED metres about the origin (the return point is not a shape)."""
        inc: list[Shape] = []
        exc: list[Shape] = []
        i = 0
        items = self.items
        while i < len(items):
            item = items[i]
            ned = north_east_of(item.x * 1e-7, item.y * 1e-7, lat0_deg, lon0_deg)
            if item.command in (POLYGON_INCLUSION, POLYGON_EXCLUSION):
                count = int(item.param1)
                vertices = tuple(north_east_of(v.x * 1e-7, v.y * 1e-7, lat0_deg, lon0_deg) for v in items[i:i + count])
                (inc if item.command == POLYGON_INCLUSION else exc).append(Polygon(vertices))
                i += count
                continue
            if item.command == CIRCLE_INCLUSION:
                inc.append(Circle(ned, item.param1))
            elif item.command == CIRCLE_EXCLUSION:
                exc.append(Circle(ned, item.param1))
            i += 1
        return FenceShapes(tuple(inc), tuple(exc))
