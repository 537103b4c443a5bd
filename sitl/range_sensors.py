"""Range sensors on the emulated rover: ArduPilot's SITL proximity sensor and rangefinder (DISTANCE_SENSOR
from the autopilot) and a depth camera on the companion computer (OBSTACLE_DISTANCE from another component).

Read in ArduPilot (4.7): libraries/AP_Proximity/AP_Proximity_SITL.cpp, AP_Proximity.h,
libraries/AP_RangeFinder/AP_RangeFinder_SITL.h, libraries/GCS_MAVLink/GCS_Common.cpp (send_distance_sensor,
send_proximity), Rover/GCS_MAVLink_Rover.cpp (DISTANCE_SENSOR is in the EXTRA3 stream); OBSTACLE_DISTANCE as
common.xml defines it. Distances are measured on the truth (position and heading), as SITL's sensors are.

- Proximity, PRX1_TYPE 10 (SITL): 8 sectors, sector k facing k * 45 deg clockwise from the body's forward,
  each one ray at the sector's middle (not a sweep of its 45 deg) to the first boundary it meets. ArduPilot's
  SITL sees only the stored fence (its inclusion and exclusion polygons and circles, whether or not
  FENCE_ENABLE is set); the emulator's also sees the scenario's obstacles. Its bisection over 0..200 m to
  0.1 m is kept: a reading is short of the truth by less than 0.1 m, and 200 m when nothing is nearer.
  With neither a fence inclusion boundary nor an obstacle the sensor has no data and no sector is sent.
  Each EXTRA3 slot sends, after the rangefinder, the 8 sectors (DISTANCE_SENSOR min 0, max 20000 cm,
  type LASER, id 10 + k (PROXIMITY_SENSOR_ID_START), orientation k, covariance 0) and the upward distance
  (id 19, orientation PITCH_90 = 24, FENCE_ALT_MAX's default 100 m above the ground): 9 messages at the
  default 1 Hz. PRX1_YAW_CORR turns the sectors (deg clockwise); PRX1_ORIENT is not emulated.
- Rangefinder, RNGFND1_TYPE 100 (SITL): one ray along RNGFND1_ORIENT (0..7: k * 45 deg clockwise from
  forward) against the scenario's obstacles (not the fence, which is not a thing to see), reported as
  DISTANCE_SENSOR id 0 (the instance), orientation RNGFND1_ORIENT, min/max RNGFND1_MIN/MAX in cm, type
  UNKNOWN (SITL's), covariance 0. Nothing within RNGFND1_MAX reads RNGFND1_MAX + 1 m (out of range).
  Other orientations (25, down: the ground) are not emulated: nothing is sent.
- Depth camera (vehicle ``obstacle_distance_hz`` > 0): OBSTACLE_DISTANCE at that rate from component
  ``obstacle_distance_component`` (196, MAV_COMP_ID_OBSTACLE_AVOIDANCE) of the autopilot's system, as a
  companion's camera script sends it: 72 sectors of 5 deg (increment 5, increment_f 5.0, angle_offset 0:
  sector i faces i * 5 deg clockwise from forward, frame BODY_FRD), distances in cm to the scenario's
  obstacles; sectors outside ``obstacle_distance_fov_deg`` (centred forward) are UINT16_MAX (unknown),
  no obstacle within ``obstacle_distance_max_m`` is max + 1 cm, as common.xml says.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

from sitl.autopilot_view import AutopilotView
from sitl.config import VehicleConfig
from sitl.mav import MAVLinkMessage, mavlink
from sitl.obstacles import Shape, ray_m
from sitl.physics import PhysicsState

_P = mavlink
PRX_TYPE_SITL = 10
RNGFND_TYPE_SITL = 100
PROXIMITY_SENSOR_ID_START = 10  # AP_Proximity.h
PROXIMITY_SECTORS = 8
PROXIMITY_MAX_M = 200.0  # AP_Proximity_SITL's PROXIMITY_MAX_RANGE
PROXIMITY_ACCURACY_M = 0.1  # and PROXIMITY_ACCURACY: where its bisection stops
UPWARD_DISTANCE_M = 100.0  # FENCE_ALT_MAX's default minus a rover's height above ground (0)
UINT16_MAX = 65535
OBSTACLE_SECTORS = 72
OBSTACLE_INCREMENT_DEG = 5


def sitl_bisection_m(true_m: float | None) -> float:
    """What AP_Proximity_SITL's bisection over 0..200 m reports for a boundary at ``true_m`` (None: none)."""
    low, high = 0.0, PROXIMITY_MAX_M
    while high - low > PROXIMITY_ACCURACY_M:
        test = 0.5 * (low + high)
        if true_m is not None and test >= true_m:
            high = test
        else:
            low = test
    return low


def proximity_sectors_m(s: PhysicsState, walls: Sequence[Shape], yaw_corr_deg: float = 0.0) -> list[float]:
    """The 8 sector readings (m) of a SITL proximity sensor at the truth's position and heading."""
    origin = (s.x_m, s.y_m)
    return [sitl_bisection_m(ray_m(origin, s.yaw_rad + math.radians(k * 45.0 + yaw_corr_deg), walls))
            for k in range(PROXIMITY_SECTORS)]


def _cm(m: float) -> int:
    return max(0, min(UINT16_MAX, int(m * 100.0)))


def distance_sensors(ap: AutopilotView, now_us: int, s: PhysicsState) -> list[MAVLinkMessage]:
    """The DISTANCE_SENSOR messages of one EXTRA3 slot: the rangefinder's, then the proximity sensor's."""
    out: list[MAVLinkMessage] = []
    boot_ms = ap.time_boot_ms(now_us)
    m = ap.mav
    obstacles = ap.obstacles
    orient = int(ap.param("RNGFND1_ORIENT"))
    if int(ap.param("RNGFND1_TYPE")) == RNGFND_TYPE_SITL and 0 <= orient < 8:
        lo, hi = ap.param("RNGFND1_MIN"), ap.param("RNGFND1_MAX")
        hit = ray_m((s.x_m, s.y_m), s.yaw_rad + math.radians(orient * 45.0), obstacles)
        reading = hit if hit is not None and hit <= hi else hi + 1.0
        out.append(m.distance_sensor_encode(boot_ms, _cm(lo), _cm(hi), _cm(reading), _P.MAV_DISTANCE_SENSOR_UNKNOWN,
                                            0, orient, 0))
    if int(ap.param("PRX1_TYPE")) != PRX_TYPE_SITL:
        return out
    fence = ap.fence.shapes(ap.vehicle.origin_lat_deg, ap.vehicle.origin_lon_deg)
    max_cm = _cm(PROXIMITY_MAX_M)
    if fence.inclusion or obstacles:
        readings = proximity_sectors_m(s, fence.all + obstacles, ap.param("PRX1_YAW_CORR"))
        for k, reading in enumerate(readings):
            out.append(m.distance_sensor_encode(boot_ms, 0, max_cm, _cm(reading), _P.MAV_DISTANCE_SENSOR_LASER,
                                                PROXIMITY_SENSOR_ID_START + k, k, 0))
    out.append(m.distance_sensor_encode(boot_ms, 0, max_cm, _cm(UPWARD_DISTANCE_M), _P.MAV_DISTANCE_SENSOR_LASER,
                                        PROXIMITY_SENSOR_ID_START + PROXIMITY_SECTORS + 1,
                                        _P.MAV_SENSOR_ROTATION_PITCH_90, 0))
    return out


def obstacle_distances_cm(s: PhysicsState, obstacles: Sequence[Shape], fov_deg: float, min_m: float,
                          max_m: float) -> list[int]:
    """OBSTACLE_DISTANCE's 72 distances (cm): UINT16_MAX outside the field of view, max + 1 when clear."""
    out: list[int] = []
    max_cm = _cm(max_m)
    for i in range(OBSTACLE_SECTORS):
        angle = i * OBSTACLE_INCREMENT_DEG
        off_axis = min(angle, 360 - angle)
        if off_axis > 0.5 * fov_deg:
            out.append(UINT16_MAX)
            continue
        hit = ray_m((s.x_m, s.y_m), s.yaw_rad + math.radians(angle), obstacles)
        out.append(max_cm + 1 if hit is None or hit > max_m else max(_cm(min_m), _cm(hit)))
    return out


class Writer(Protocol):
    def write(self, data: bytes) -> None: ...


class DepthCamera:
    """A companion's depth camera: OBSTACLE_DISTANCE at ``obstacle_distance_hz`` from its own component."""

    def __init__(self, vehicle: VehicleConfig, out: Writer, system_id: int) -> None:
        self.vehicle = vehicle
        # Its own sender: the packets carry its component id and sequence numbers (``out`` collects them).
        self.mav = mavlink.MAVLink(out, srcSystem=system_id, srcComponent=vehicle.obstacle_distance_component)
        hz = vehicle.obstacle_distance_hz
        self.interval_us = round(1e6 / hz) if hz > 0 else 0
        self._next_us = 0

    def due(self, now_us: int, s: PhysicsState, obstacles: Sequence[Shape]) -> list[MAVLinkMessage]:
        if self.interval_us <= 0 or now_us < self._next_us:
            return []
        self._next_us += self.interval_us  # keeps the average rate
        if self._next_us <= now_us:  # fell behind (a big step): skip, do not burst
            self._next_us = now_us + self.interval_us
        v = self.vehicle
        distances = obstacle_distances_cm(s, obstacles, v.obstacle_distance_fov_deg, v.obstacle_distance_min_m,
                                          v.obstacle_distance_max_m)
        return [self.mav.obstacle_distance_encode(now_us, _P.MAV_DISTANCE_SENSOR_LASER, distances,
                                                  OBSTACLE_INCREMENT_DEG, _cm(v.obstacle_distance_min_m),
                                                  _cm(v.obstacle_distance_max_m), float(OBSTACLE_INCREMENT_DEG), 0.0,
                                                  _P.MAV_FRAME_BODY_FRD)]
