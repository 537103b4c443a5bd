"""Position targets ("go here") from ground stations and planners -> one frozen value (pure).

Read the way ArduPilot Rover reads them in GUIDED (Rover/GCS_MAVLink_Rover.cpp, GCS_Common.cpp):

- SET_POSITION_TARGET_LOCAL_NED with x and y used (a set ignore bit of either ignores the position):
  MAV_FRAME_LOCAL_NED (1): north/east in the autopilot's local frame; LOCAL_OFFSET_NED (7): a north/east
  offset from where the rover is; BODY_NED (8) and BODY_OFFSET_NED (9), taken alike: an offset forward/
  right, rotated by the rover's heading. z is never used. The MAVLink 2 FRD frames (LOCAL_FRD 20,
  BODY_FRD 12) ArduPilot ignores for positions: refused as an unsupported frame. A yaw, if used, is the
  heading to turn to on arrival (clockwise from north; for body frames relative to the heading now);
  a velocity, if used, gives the cruise speed (its magnitude). Acceleration is ignored.
- SET_POSITION_TARGET_GLOBAL_INT with lat/lon used (frames GLOBAL_INT 5, GLOBAL_RELATIVE_ALT_INT 6,
  GLOBAL_TERRAIN_ALT_INT 11, and their non-INT twins 0, 3, 10): altitude ignored (noted).
- MISSION_ITEM_INT / MISSION_ITEM with current = 2 (Mission Planner's "Fly to here", MAVProxy's
  `guided`): command NAV_WAYPOINT (16), frames GLOBAL* or MISSION; the answer is a MISSION_ACK with
  ArduPilot's result codes (UNSUPPORTED for another command, UNSUPPORTED_FRAME, INVALID_PARAM5_X/6_Y
  for a bad lat/lon). param4 (yaw at the waypoint) is ignored, as Rover does.
- COMMAND_INT MAV_CMD_DO_REPOSITION (QGroundControl, MAVSDK's goto_location): x/y lat/lon in degE7,
  param1 the speed when > 0, param4 the final yaw in radians (as PX4 and MAVSDK use it; NaN: none).
  Over COMMAND_LONG it is UNSUPPORTED (float lat/lon lose ~1 m), as ArduPilot answers.
- MAV_CMD_DO_CHANGE_SPEED (COMMAND_LONG or _INT): param1 0/1 (air/ground speed, both taken as ground
  speed), param2 the cruise speed in m/s (-1: no change, -2: back to the default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink

X_IGNORE, Y_IGNORE = 1, 2
VX_IGNORE, VY_IGNORE = 8, 16
AX_IGNORE, AY_IGNORE = 64, 128
YAW_IGNORE = 1024

LOCAL_NED = mavlink.MAV_FRAME_LOCAL_NED
LOCAL_OFFSET_NED = mavlink.MAV_FRAME_LOCAL_OFFSET_NED
BODY_NED = mavlink.MAV_FRAME_BODY_NED
BODY_OFFSET_NED = mavlink.MAV_FRAME_BODY_OFFSET_NED
LOCAL_FRAMES = frozenset({LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED})
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})
MISSION_FRAMES = GLOBAL_FRAMES | {mavlink.MAV_FRAME_MISSION}
MIN_SPEED_M_S = 0.05  # ArduPilot's AR_WPNAV_SPEED_MIN: DO_CHANGE_SPEED below it FAILED
MAX_SPEED_M_S = 100.0  # beyond any rover: garbage (the limits bound the rest)
MAX_OFFSET_M = 1e5  # beyond any rover's reach: a garbage value, refused (a distance limit refuses the rest)

# Why a target is refused (counters "rejected.<reason>" and the answers' wording).
BAD_VALUE = "bad_value"
UNSUPPORTED_FRAME = "unsupported_frame"
UNSUPPORTED_COMMAND = "unsupported_command"


@dataclass(frozen=True, slots=True)
class LocalTarget:
    """A target in a local frame: `frame` LOCAL_NED (north, east), LOCAL_OFFSET_NED (offset north,
    east) or BODY (offset forward, right). `yaw_cw_rad` is the heading on arrival (None: none)."""

    frame: str  # "local" | "offset" | "body"
    x_m: float
    y_m: float
    yaw_cw_rad: float | None = None
    speed_m_s: float | None = None
    notes: frozenset[str] = frozenset()


@dataclass(frozen=True, slots=True)
class GlobalTarget:
    lat_deg: float
    lon_deg: float
    yaw_cw_rad: float | None = None
    speed_m_s: float | None = None
    notes: frozenset[str] = frozenset()


@dataclass(frozen=True, slots=True)
class SpeedChange:
    """DO_CHANGE_SPEED: a new cruise speed; None with reset False: no change (-1), reset: the default (-2)."""

    speed_m_s: float | None
    reset: bool = False


@dataclass(frozen=True, slots=True)
class Refused:
    reason: str
    mission_result: int = mavlink.MAV_MISSION_ERROR  # what a MISSION_ACK says for it
    command_result: int = mavlink.MAV_RESULT_DENIED  # what a COMMAND_ACK says for it


Target = LocalTarget | GlobalTarget
Decoded = LocalTarget | GlobalTarget | SpeedChange | Refused

ALTITUDE_IGNORED = "altitude_ignored"
ACCELERATION_IGNORED = "acceleration_ignored"


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _lat_lon_ok(lat: float, lon: float) -> bool:
    return _finite(lat, lon) and abs(lat) <= 90.0 and abs(lon) <= 180.0


def uses_position(msg: MAVLinkMessage) -> bool:
    """A SET_POSITION_TARGET_* whose x and y (lat and lon) are both used: a position target."""
    mask = int(msg.type_mask)
    return not (mask & X_IGNORE or mask & Y_IGNORE)


def _speed_and_yaw(msg: MAVLinkMessage) -> tuple[float | None, float | None] | None:
    mask = int(msg.type_mask)
    speed = yaw = None
    if not (mask & VX_IGNORE and mask & VY_IGNORE):
        vx = float(msg.vx) if not mask & VX_IGNORE else 0.0
        vy = float(msg.vy) if not mask & VY_IGNORE else 0.0
        if not _finite(vx, vy):
            return None
        speed = math.hypot(vx, vy) or None
        if speed is not None and speed > MAX_SPEED_M_S:
            return None
    if not mask & YAW_IGNORE:
        yaw = float(msg.yaw)
        if not (math.isfinite(yaw) and abs(yaw) <= 2.0 * math.pi):
            return None
    return speed, yaw


def decode_position_target(msg: MAVLinkMessage) -> Decoded:
    """SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT with a position (see uses_position)."""
    extra = _speed_and_yaw(msg)
    if extra is None:
        return Refused(BAD_VALUE)
    speed, yaw = extra
    frame = int(msg.coordinate_frame)
    accel_used = int(msg.type_mask) & (AX_IGNORE | AY_IGNORE) != AX_IGNORE | AY_IGNORE
    notes = frozenset({ACCELERATION_IGNORED} if accel_used else set())
    if msg.get_type() == "SET_POSITION_TARGET_GLOBAL_INT":
        if frame not in GLOBAL_FRAMES:
            return Refused(UNSUPPORTED_FRAME)
        lat, lon = int(msg.lat_int) * 1e-7, int(msg.lon_int) * 1e-7
        if not _lat_lon_ok(lat, lon):
            return Refused(BAD_VALUE)
        return GlobalTarget(lat, lon, yaw, speed, notes | {ALTITUDE_IGNORED})
    if frame not in LOCAL_FRAMES:
        return Refused(UNSUPPORTED_FRAME)
    x, y = float(msg.x), float(msg.y)
    if not (_finite(x, y) and abs(x) <= MAX_OFFSET_M and abs(y) <= MAX_OFFSET_M):
        return Refused(BAD_VALUE)
    kind = {LOCAL_NED: "local", LOCAL_OFFSET_NED: "offset"}.get(frame, "body")
    return LocalTarget(kind, x, y, yaw, speed, notes)


def decode_mission_item(msg: MAVLinkMessage) -> Decoded:
    """MISSION_ITEM(_INT) with current = 2: a guided waypoint, answered by MISSION_ACK."""
    if int(msg.command) != mavlink.MAV_CMD_NAV_WAYPOINT:
        return Refused(UNSUPPORTED_COMMAND, mavlink.MAV_MISSION_UNSUPPORTED)
    if int(msg.frame) not in MISSION_FRAMES:
        return Refused(UNSUPPORTED_FRAME, mavlink.MAV_MISSION_UNSUPPORTED_FRAME)
    if msg.get_type() == "MISSION_ITEM_INT":
        lat, lon = int(msg.x) * 1e-7, int(msg.y) * 1e-7
    else:
        lat, lon = float(msg.x), float(msg.y)
    if not (math.isfinite(lat) and abs(lat) <= 90.0):
        return Refused(BAD_VALUE, mavlink.MAV_MISSION_INVALID_PARAM5_X)
    if not (math.isfinite(lon) and abs(lon) <= 180.0):
        return Refused(BAD_VALUE, mavlink.MAV_MISSION_INVALID_PARAM6_Y)
    return GlobalTarget(lat, lon, None, None, frozenset({ALTITUDE_IGNORED}))


def changes_mode(msg: MAVLinkMessage) -> bool:
    """DO_REPOSITION's MAV_DO_REPOSITION_FLAGS_CHANGE_MODE (param2): switch to GUIDED first."""
    flags = float(msg.param2)
    return math.isfinite(flags) and bool(int(flags) & mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE)


def decode_command(msg: MAVLinkMessage) -> Decoded | None:
    """DO_REPOSITION / DO_CHANGE_SPEED in a COMMAND_INT or COMMAND_LONG; None for another command."""
    command = int(msg.command)
    is_int = msg.get_type() == "COMMAND_INT"
    if command == mavlink.MAV_CMD_DO_REPOSITION:
        if not is_int:
            return Refused(UNSUPPORTED_COMMAND, command_result=mavlink.MAV_RESULT_UNSUPPORTED)
        if int(msg.frame) not in GLOBAL_FRAMES:
            return Refused(UNSUPPORTED_FRAME)
        lat, lon = int(msg.x) * 1e-7, int(msg.y) * 1e-7
        if not _lat_lon_ok(lat, lon) or (int(msg.x) == 0 and int(msg.y) == 0):
            return Refused(BAD_VALUE)
        speed = float(msg.param1)
        yaw = float(msg.param4)
        return GlobalTarget(lat, lon, yaw if math.isfinite(yaw) and abs(yaw) <= 2.0 * math.pi else None,
                            speed if math.isfinite(speed) and speed > 0.0 else None,
                            frozenset({ALTITUDE_IGNORED}))
    if command == mavlink.MAV_CMD_DO_CHANGE_SPEED:
        kind, speed = float(msg.param1), float(msg.param2)
        if kind not in (0.0, 1.0) or not math.isfinite(speed):
            return Refused(BAD_VALUE)
        if speed == -2.0:
            return SpeedChange(None, reset=True)
        if speed == -1.0:
            return SpeedChange(None)
        if speed < MIN_SPEED_M_S or speed > MAX_SPEED_M_S:
            return Refused(BAD_VALUE, command_result=mavlink.MAV_RESULT_FAILED)
        return SpeedChange(speed)
    return None
