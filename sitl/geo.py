"""Latitude/longitude <-> north/east metres about the emulator's origin (its EKF origin).

A sphere of the WGS-84 equatorial radius and a flat earth at the origin's latitude: the conversion
GLOBAL_POSITION_INT, SIMSTATE, HOME_POSITION and mission items share (ArduPilot's Location uses the
same flat-earth scaling over a few kilometres).
"""

from __future__ import annotations

import math

EARTH_RADIUS_M = 6378137.0


def lat_lon_of(north_m: float, east_m: float, lat0_deg: float, lon0_deg: float) -> tuple[float, float]:
    """A point north/east of the origin, in degrees."""
    lat = lat0_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon = lon0_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))))
    return lat, lon


def north_east_of(lat_deg: float, lon_deg: float, lat0_deg: float, lon0_deg: float) -> tuple[float, float]:
    """The inverse of ``lat_lon_of``."""
    north = math.radians(lat_deg - lat0_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - lon0_deg) * EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))
    return north, east
