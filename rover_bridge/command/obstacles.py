"""The obstacle picture around the rover, as ArduPilot's AP_Proximity builds it (pure: time is an argument).

Eight 45-degree sectors in the body frame, sector k centred k * 45 degrees clockwise from forward (MAVLink's
MAV_SENSOR_ROTATION_NONE .. YAW_315 are exactly the sector ids: AP_Proximity_Boundary_3D's faces). Inside the
picture bearings are ours (counter-clockwise +, 0 = forward); frames.py turns MAVLink's clockwise angles round.

- DISTANCE_SENSOR (AP_Proximity_MAV::handle_distance_sensor_msg): orientation 0..7 marks that sector at its
  centre bearing; a reading inside [min, max] is an obstacle, one above max says nothing is within max (the
  sector is clear), one below min (or 0) is invalid: ArduPilot resets that face, so it says nothing. Other
  orientations (pitch and roll rotations: a downward rangefinder, CUSTOM) are ignored and counted.
- OBSTACLE_DISTANCE (handle_obstacle_distance_msg): up to 72 elements, `increment_f` if set else `increment`
  degrees apart from `angle_offset`, folded into the sectors: each sector keeps its closest valid element at
  that element's own bearing. 0, UINT16_MAX (unknown) and values below min are skipped, as ArduPilot does
  (the sector keeps what it had until it ages out); a value above max (max + 1 = nothing there) marks the
  sector clear if no element in it saw anything. `frame` MAV_FRAME_BODY_FRD is body-relative; GLOBAL and
  LOCAL_NED are north-relative (MAVLink's definition) and need the heading; any other frame is ignored and
  counted. ArduPilot 4.x itself ignores `frame` and reads every scan as body-relative: a sender that
  sets frame 0 but means the body is the one case where the two differ.
- A sector's reading older than `face_timeout_s` (PROXIMITY_FACE_RESET_MS, 1 s) is unknown; several sensors
  on one sector: the closest fresh obstacle wins (set_face_attributes keeps a shorter recent distance).
- A sensor that was seen and has sent nothing for `sensor_timeout_s` (PROXIMITY_MAV_TIMEOUT_MS, 0.5 s) is
  reported as silent, so the caller can slow to a crawl and say so.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

from rover_bridge.frames import yaw_flu_from_yaw_frd
from rover_bridge.mavlink.dialect import MAVLinkMessage

SECTOR_COUNT = 8
SECTOR_WIDTH_DEG = 360.0 / SECTOR_COUNT
FACE_TIMEOUT_S = 1.0  # AP_Proximity_Boundary_3D PROXIMITY_FACE_RESET_MS
SENSOR_TIMEOUT_S = 0.5  # AP_Proximity_MAV PROXIMITY_MAV_TIMEOUT_MS
MAV_SENSOR_ROTATION_YAW_315 = 7
OBSTACLE_DISTANCE_LEN = 72
UINT16_MAX = 65535
MAV_FRAME_GLOBAL = 0
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
EARTH_FRAMES = frozenset({MAV_FRAME_GLOBAL, MAV_FRAME_LOCAL_NED})

SensorKey = tuple[int, int, int]  # (system id, component id, sensor id) of the sender


class SectorState(enum.Enum):
    OBSTACLE = "obstacle"
    CLEAR = "clear"  # a fresh reading said nothing is within the sensor's max range
    UNKNOWN = "unknown"  # no fresh valid reading


@dataclass(frozen=True, slots=True)
class Sector:
    """One sector as seen at a time: its state, the closest obstacle's distance and bearing, the reading's age."""

    index: int
    state: SectorState
    bearing_ccw_rad: float  # the obstacle's bearing if any, else the sector's centre
    distance_m: float | None = None
    age_s: float | None = None


@dataclass(frozen=True, slots=True)
class ObstacleView:
    """The picture at one time: what the limiter reads and what the caller reports."""

    sectors: tuple[Sector, ...]
    silent_sensors: tuple[SensorKey, ...] = ()

    @property
    def obstacles(self) -> tuple[Sector, ...]:
        return tuple(s for s in self.sectors if s.state is SectorState.OBSTACLE)

    @property
    def blind(self) -> bool:
        """A sensor that was seen has gone silent."""
        return bool(self.silent_sensors)


@dataclass(frozen=True, slots=True)
class PictureCounts:
    """What was fed and what was not used, for --stats-json."""

    readings: int = 0
    out_of_range_high: int = 0
    below_min: int = 0
    ignored_orientation: int = 0
    ignored_frame: int = 0
    no_heading: int = 0
    bad_increment: int = 0


@dataclass(frozen=True, slots=True)
class _Entry:
    t_s: float
    state: SectorState  # OBSTACLE or CLEAR; an invalid reading removes the entry
    bearing_ccw_rad: float
    distance_m: float | None


def sector_bearing_ccw_rad(index: int) -> float:
    """Centre of sector `index` (MAVLink's clockwise k * 45 degrees) as our counter-clockwise bearing."""
    return math.remainder(yaw_flu_from_yaw_frd(math.radians(index * SECTOR_WIDTH_DEG)), 2.0 * math.pi)


_BEARINGS = tuple(sector_bearing_ccw_rad(k) for k in range(SECTOR_COUNT))


def sector_of_cw_deg(angle_cw_deg: float) -> int:
    """The sector holding a clockwise angle from forward (AP_Proximity_Boundary_3D::get_face)."""
    return int(((angle_cw_deg + 0.5 * SECTOR_WIDTH_DEG) % 360.0) // SECTOR_WIDTH_DEG) % SECTOR_COUNT


class ObstaclePicture:
    """Fed DISTANCE_SENSOR and OBSTACLE_DISTANCE fields with their arrival time; `view(now_s)` says what is where."""

    def __init__(self, face_timeout_s: float = FACE_TIMEOUT_S, sensor_timeout_s: float = SENSOR_TIMEOUT_S) -> None:
        self.face_timeout_s = face_timeout_s
        self.sensor_timeout_s = sensor_timeout_s
        self._entries: dict[tuple[SensorKey, int], _Entry] = {}
        self._last_seen_s: dict[SensorKey, float] = {}
        self._counts = dict.fromkeys(PictureCounts.__dataclass_fields__, 0)
        # Each sector's winning entry, kept from one reading to the next (the limiter asks every output): valid
        # until a reading changes the entries or the oldest fresh one ages out.
        self._best: dict[int, _Entry] = {}
        self._best_until_s = -math.inf

    @property
    def counts(self) -> PictureCounts:
        return PictureCounts(**self._counts)

    def _count(self, **more: int) -> None:
        counts = self._counts
        for name, n in more.items():
            counts[name] += n

    def distance_sensor(self, now_s: float, sensor: SensorKey, orientation: int, current_distance_cm: int,
                        min_distance_cm: int, max_distance_cm: int) -> None:
        """One DISTANCE_SENSOR: the sector `orientation` (0..7) gets this reading, others are ignored."""
        if not 0 <= orientation <= MAV_SENSOR_ROTATION_YAW_315:
            self._count(ignored_orientation=1)
            return
        self._last_seen_s[sensor] = now_s
        self._best_until_s = -math.inf
        key = (sensor, orientation)
        self._counts["readings"] += 1  # 80 a second from ArduPilot's 8 sectors: the plain increment
        if current_distance_cm > max_distance_cm:
            self._count(out_of_range_high=1)
            self._entries[key] = _Entry(now_s, SectorState.CLEAR, _BEARINGS[orientation], None)
        elif current_distance_cm < min_distance_cm or current_distance_cm <= 0:
            self._count(below_min=1)
            self._entries.pop(key, None)  # ArduPilot resets the face: no distance from this sensor
        else:
            self._entries[key] = _Entry(now_s, SectorState.OBSTACLE, _BEARINGS[orientation], current_distance_cm * 0.01)

    def obstacle_distance(self, now_s: float, sensor: SensorKey, distances_cm: Sequence[int], increment_deg: int,
                          increment_f_deg: float, angle_offset_deg: float, min_distance_cm: int,
                          max_distance_cm: int, frame: int, heading_cw_rad: float | None) -> None:
        """One OBSTACLE_DISTANCE scan folded into the sectors. `heading_cw_rad` (ATTITUDE.yaw) for earth frames."""
        increment = increment_f_deg if increment_f_deg != 0.0 else float(increment_deg)
        if increment == 0.0 or not math.isfinite(increment):
            self._count(bad_increment=1)
            return
        if frame == MAV_FRAME_BODY_FRD:
            to_body_deg = 0.0
        elif frame in EARTH_FRAMES:
            if heading_cw_rad is None:
                self._count(no_heading=1)
                return
            to_body_deg = -math.degrees(heading_cw_rad)
        else:
            self._count(ignored_frame=1)
            return
        self._last_seen_s[sensor] = now_s
        self._best_until_s = -math.inf
        count = min(int(360.0 / abs(increment) + 0.5), OBSTACLE_DISTANCE_LEN, len(distances_cm))
        closest: dict[int, tuple[float, float]] = {}  # sector -> (distance m, clockwise body angle deg)
        clear: set[int] = set()
        high = low = 0
        for j in range(count):
            d_cm = distances_cm[j]
            angle_cw_deg = (j * increment + angle_offset_deg + to_body_deg) % 360.0
            sector = sector_of_cw_deg(angle_cw_deg)
            if d_cm == UINT16_MAX or d_cm <= 0:
                continue  # unknown: the sector keeps what it had until it ages out
            if d_cm > max_distance_cm:
                high += 1
                clear.add(sector)
            elif d_cm < min_distance_cm:
                low += 1
            elif sector not in closest or d_cm * 0.01 < closest[sector][0]:
                closest[sector] = (d_cm * 0.01, angle_cw_deg)
        self._count(readings=1, out_of_range_high=high, below_min=low)
        for sector, (distance_m, angle_cw_deg) in closest.items():
            bearing = math.remainder(yaw_flu_from_yaw_frd(math.radians(angle_cw_deg)), 2.0 * math.pi)
            self._entries[(sensor, sector)] = _Entry(now_s, SectorState.OBSTACLE, bearing, distance_m)
        for sector in clear - closest.keys():
            self._entries[(sensor, sector)] = _Entry(now_s, SectorState.CLEAR, _BEARINGS[sector], None)

    def handle(self, msg: MAVLinkMessage, now_s: float, heading_cw_rad: float | None = None) -> bool:
        """Feed a DISTANCE_SENSOR or OBSTACLE_DISTANCE (others: False). The sender's (system, component, id)
        is the sensor; `heading_cw_rad` (ATTITUDE.yaw) for earth-frame scans."""
        kind = msg.get_type()
        if kind == "DISTANCE_SENSOR":
            self.distance_sensor(now_s, (msg.get_srcSystem(), msg.get_srcComponent(), int(msg.id)),
                                 int(msg.orientation), int(msg.current_distance), int(msg.min_distance),
                                 int(msg.max_distance))
            return True
        if kind == "OBSTACLE_DISTANCE":
            self.obstacle_distance(now_s, (msg.get_srcSystem(), msg.get_srcComponent(), 0), list(msg.distances),
                                   int(msg.increment), float(getattr(msg, "increment_f", 0.0) or 0.0),
                                   float(getattr(msg, "angle_offset", 0.0) or 0.0), int(msg.min_distance),
                                   int(msg.max_distance), int(getattr(msg, "frame", MAV_FRAME_GLOBAL)),
                                   heading_cw_rad)
            return True
        return False

    def _fresh_best(self, now_s: float) -> dict[int, _Entry]:
        """Each sector's winning fresh entry (an obstacle beats clear, the nearer obstacle wins)."""
        if now_s <= self._best_until_s:
            return self._best
        best: dict[int, _Entry] = {}
        oldest = math.inf
        for (_, sector), entry in self._entries.items():
            if now_s - entry.t_s > self.face_timeout_s:
                continue
            oldest = min(oldest, entry.t_s)
            held = best.get(sector)
            if held is None or _closer(entry, held):
                best[sector] = entry
        self._best, self._best_until_s = best, oldest + self.face_timeout_s
        return best

    def _silent(self, now_s: float) -> tuple[SensorKey, ...]:
        limit, seen = self.sensor_timeout_s, self._last_seen_s
        if not seen or now_s - min(seen.values()) <= limit:
            return ()
        return tuple(sorted(k for k, t in seen.items() if now_s - t > limit))

    def view(self, now_s: float) -> ObstacleView:
        """Every sector's state at `now_s`, and the sensors that went silent."""
        best = self._fresh_best(now_s)
        sectors = []
        for index in range(SECTOR_COUNT):
            found = best.get(index)
            if found is None:
                sectors.append(Sector(index, SectorState.UNKNOWN, _BEARINGS[index]))
            else:
                sectors.append(Sector(index, found.state, found.bearing_ccw_rad, found.distance_m,
                                      now_s - found.t_s))
        return ObstacleView(tuple(sectors), self._silent(now_s))

    def near(self, now_s: float, closing_m_s: float) -> ObstacleView:
        """What the limiter reads, every output: only the sectors with an obstacle, each taken `closing_m_s * age`
        nearer (the rover may have driven that far toward it since the reading), and the silent sensors."""
        sectors = tuple(Sector(index, SectorState.OBSTACLE, e.bearing_ccw_rad,
                               e.distance_m - closing_m_s * (now_s - e.t_s), now_s - e.t_s)
                        for index, e in self._fresh_best(now_s).items() if e.distance_m is not None)
        return ObstacleView(sectors, self._silent(now_s))


def _closer(entry: _Entry, held: _Entry) -> bool:
    """An obstacle beats a clear reading; of two obstacles the nearer wins."""
    if entry.state is not SectorState.OBSTACLE:
        return False
    if held.state is not SectorState.OBSTACLE:
        return True
    assert entry.distance_m is not None and held.distance_m is not None
    return entry.distance_m < held.distance_m
