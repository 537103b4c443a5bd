"""MAVLink velocity requests -> one frozen request value (pure): frames, type masks, signs.

Accepted (after ArduPilot Rover's handle_set_position_target_*, which is what GCSs expect):

- SET_POSITION_TARGET_LOCAL_NED in a body frame (BODY_NED 8, BODY_OFFSET_NED 9, BODY_FRD 12):
  vx is the forward speed (negative drives backwards); yaw_rate is clockwise positive, so a
  positive yaw_rate is a right turn; vy (sideways) cannot be driven by a differential drive and
  is ignored (noted); a yaw target is relative to the current heading.
- SET_POSITION_TARGET_LOCAL_NED in an earth frame (LOCAL_NED 1, LOCAL_OFFSET_NED 7) and
  SET_POSITION_TARGET_GLOBAL_INT (GLOBAL 0, GLOBAL_RELATIVE_ALT 3, GLOBAL_INT 5,
  GLOBAL_RELATIVE_ALT_INT 6, GLOBAL_TERRAIN_ALT 10, GLOBAL_TERRAIN_ALT_INT 11): speed = the
  horizontal magnitude, heading = its direction. This is a heading request: a velocity pointing
  behind the rover turns it round (it never reverses; unlike ArduPilot, the sign of vx does not
  pick the direction in an earth frame). A yaw target overrides the direction; a yaw rate
  replaces the heading controller (speed = magnitude, turn = that rate).
- MANUAL_CONTROL: x forward and r (yaw, clockwise +: r > 0 is a right turn), each in
  [-1000, 1000], scaled by command.manual_*_scale; INT16_MAX marks an axis as invalid (MAVLink),
  read as 0.

Type mask: FORCE_SET (bit 9) and unknown high bits are tolerated (MAVProxy's `velocity`
command sends 4039 = use vx, vy, vz only, FORCE_SET set). Only horizontal position (x/y,
lat/lon) and horizontal acceleration count: altitude and vz mean nothing to a rover. A message with
x and y (lat and lon) both used is a position target, which the command core hands to
rover_bridge.command.targets before it gets here; one with only x or only y used is rejected here,
with or without velocity (following only the velocity of a half position would drive past it).
Acceleration with velocity is a feed-forward and is ignored (noted); acceleration alone is rejected.

Non-finite values: a NaN or infinity in any field the type mask marks as used rejects the
whole request. So does a finite value no sender can mean (OUT_OF_RANGE): a speed component beyond
MAX_REQUEST_SPEED_M_S, a yaw rate beyond MAX_REQUEST_RATE_RAD_S or a yaw angle outside +-2 pi; such
values come from corrupted frames or unit mistakes (degrees for radians), and saturating them at
the limits would drive at full speed on garbage. Requests above the profile's limits but within
these bounds are still accepted and limited as before. Fields the mask marks as ignored carry no
value, and several MAVLink senders fill them with NaN for exactly that reason, so they are not
inspected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rover_bridge import frames
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage
from rover_bridge.params import CommandParams

# POSITION_TARGET_TYPEMASK bits (set = ignore that field).
X_IGNORE = 1
Y_IGNORE = 2
Z_IGNORE = 4
VX_IGNORE = 8
VY_IGNORE = 16
VZ_IGNORE = 32
AX_IGNORE = 64
AY_IGNORE = 128
AZ_IGNORE = 256
FORCE_SET = 512
YAW_IGNORE = 1024
YAW_RATE_IGNORE = 2048

BODY_FRAMES = frozenset({8, 9, 12})
LOCAL_EARTH_FRAMES = frozenset({1, 7})
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})

MANUAL_AXIS_INVALID = 0x7FFF  # INT16_MAX: "this axis is invalid" (MANUAL_CONTROL)
MANUAL_FULL_SCALE = 1000

# Rejection reasons: stable keys, used in counters ("rejected.<reason>") and reports.
NON_FINITE = "non_finite"
POSITION_ONLY = "position_only"
POSITION_UNSUPPORTED = "position_with_velocity"
ACCELERATION_ONLY = "acceleration_only"
UNSUPPORTED_FRAME = "unsupported_frame"
NO_VELOCITY = "no_velocity"
MANUAL_OUT_OF_RANGE = "manual_out_of_range"
MANUAL_NO_AXES = "manual_no_axes"
MALFORMED = "malformed"
OUT_OF_RANGE = "out_of_range"

REJECTION_REASONS = (NON_FINITE, POSITION_ONLY, POSITION_UNSUPPORTED, ACCELERATION_ONLY, UNSUPPORTED_FRAME,
                     NO_VELOCITY, MANUAL_OUT_OF_RANGE, MANUAL_NO_AXES, MALFORMED, OUT_OF_RANGE)

# Plausibility bounds (not limits: the limiter does that): beyond them a value is garbage.
MAX_REQUEST_SPEED_M_S = 100.0  # per component; ArduPilot's WP_SPEED tops out at 100 m/s
MAX_REQUEST_RATE_RAD_S = 100.0
MAX_REQUEST_YAW_RAD = 2.0 * math.pi

# Notes on accepted requests: something in it was not followed, said once per source.
LATERAL_IGNORED = "lateral_ignored"
ACCELERATION_IGNORED = "acceleration_ignored"
YAW_RATE_IGNORED = "yaw_rate_ignored"  # yaw and yaw_rate both given: the yaw target wins


@dataclass(frozen=True, slots=True)
class BodyVelocity:
    """Drive at `v_m_s` (forward +) turning at `omega_rad_s` (counter-clockwise +)."""

    v_m_s: float
    omega_rad_s: float
    notes: frozenset[str] = frozenset()

    def twist(self) -> Twist2D:
        return Twist2D(v_m_s=self.v_m_s, omega_rad_s=self.omega_rad_s)


@dataclass(frozen=True, slots=True)
class HeadingVelocity:
    """Drive at `speed_m_s` (negative: backwards) while turning to `heading_cw_rad`.

    The heading is clockwise from north (as ATTITUDE.yaw), or, with `relative`, clockwise from
    the heading the rover has when the request arrives (body-frame yaw targets).
    """

    speed_m_s: float
    heading_cw_rad: float
    relative: bool = False
    notes: frozenset[str] = frozenset()

    def absolute(self, current_yaw_cw_rad: float) -> HeadingVelocity:
        """The same request with its heading made absolute, given the rover's heading now."""
        if not self.relative:
            return self
        heading = frames.heading_from_body_yaw_rad(current_yaw_cw_rad, self.heading_cw_rad)
        return HeadingVelocity(self.speed_m_s, heading, relative=False, notes=self.notes)

    def twist(self, yaw_cw_rad: float, kp_1_s: float, max_angular_rad_s: float) -> Twist2D:
        """Heading controller: P on the heading error, yaw rate limited.

        The speed is scaled by cos(error), clipped at 0: a rover facing away from the requested
        direction turns in place first instead of driving a wide arc the wrong way.
        """
        if self.relative:
            raise ValueError("make the heading absolute (HeadingVelocity.absolute) before following it")
        error = frames.heading_error_rad(self.heading_cw_rad, yaw_cw_rad)
        omega = frames.omega_toward_heading(self.heading_cw_rad, yaw_cw_rad, kp_1_s, max_angular_rad_s)
        return Twist2D(v_m_s=self.speed_m_s * max(0.0, math.cos(error)), omega_rad_s=omega)


@dataclass(frozen=True, slots=True)
class Rejected:
    """A request that is not followed; `reason` is one of REJECTION_REASONS."""

    reason: str


Request = BodyVelocity | HeadingVelocity
Decoded = BodyVelocity | HeadingVelocity | Rejected

REQUEST_TYPES = frozenset({"SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT",
                           "MANUAL_CONTROL"})


_LOCAL_FRAMES = BODY_FRAMES | LOCAL_EARTH_FRAMES
_CHECKED_REST = (("vx", VX_IGNORE), ("vy", VY_IGNORE), ("vz", VZ_IGNORE), ("afx", AX_IGNORE), ("afy", AY_IGNORE),
                 ("afz", AZ_IGNORE), ("yaw", YAW_IGNORE), ("yaw_rate", YAW_RATE_IGNORE))
_CHECKED_GLOBAL = (("lat_int", X_IGNORE), ("lon_int", Y_IGNORE), ("alt", Z_IGNORE), *_CHECKED_REST)
_CHECKED_LOCAL = (("x", X_IGNORE), ("y", Y_IGNORE), ("z", Z_IGNORE), *_CHECKED_REST)
_BOUNDED = (("vx", VX_IGNORE, MAX_REQUEST_SPEED_M_S), ("vy", VY_IGNORE, MAX_REQUEST_SPEED_M_S),
            ("yaw_rate", YAW_RATE_IGNORE, MAX_REQUEST_RATE_RAD_S), ("yaw", YAW_IGNORE, MAX_REQUEST_YAW_RAD))


def _used(mask: int, bit: int) -> bool:
    return not mask & bit


def decode_position_target(msg: MAVLinkMessage) -> Decoded:
    """SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT -> request or rejection."""
    is_global = msg.get_type() == "SET_POSITION_TARGET_GLOBAL_INT"
    frame = int(msg.coordinate_frame)
    mask = int(msg.type_mask)
    if is_global:
        if frame not in GLOBAL_FRAMES:
            return Rejected(UNSUPPORTED_FRAME)
        body = False
        checked = _CHECKED_GLOBAL
    else:
        if frame not in _LOCAL_FRAMES:
            return Rejected(UNSUPPORTED_FRAME)
        body = frame in BODY_FRAMES
        checked = _CHECKED_LOCAL
    isfinite = math.isfinite
    for name, bit in checked:  # a loop, not any(genexpr): this runs for every request
        if not mask & bit and not isfinite(float(getattr(msg, name))):
            return Rejected(NON_FINITE)
    for name, bit, bound in _BOUNDED:
        if not mask & bit and abs(float(getattr(msg, name))) > bound:
            return Rejected(OUT_OF_RANGE)

    vx_used, vy_used = _used(mask, VX_IGNORE), _used(mask, VY_IGNORE)
    velocity_used = vx_used or vy_used
    yaw_used, yaw_rate_used = _used(mask, YAW_IGNORE), _used(mask, YAW_RATE_IGNORE)
    position_used = _used(mask, X_IGNORE) or _used(mask, Y_IGNORE)
    accel_used = _used(mask, AX_IGNORE) or _used(mask, AY_IGNORE)
    if position_used:
        return Rejected(POSITION_UNSUPPORTED if velocity_used else POSITION_ONLY)
    if not (velocity_used or yaw_used or yaw_rate_used):
        return Rejected(ACCELERATION_ONLY if accel_used else NO_VELOCITY)

    notes: set[str] = set()
    if accel_used:
        notes.add(ACCELERATION_IGNORED)
    if yaw_used and yaw_rate_used:
        notes.add(YAW_RATE_IGNORED)
    vx = float(msg.vx) if vx_used else 0.0
    vy = float(msg.vy) if vy_used else 0.0

    if body:
        if vy != 0.0:
            notes.add(LATERAL_IGNORED)
        if yaw_used:
            return HeadingVelocity(vx, float(msg.yaw), relative=True, notes=frozenset(notes))
        omega = frames.omega_from_mavlink_yaw_rate(float(msg.yaw_rate)) if yaw_rate_used else 0.0
        return BodyVelocity(vx, omega, frozenset(notes))

    # Earth frame (NED): vx north, vy east.
    speed = math.hypot(vx, vy)
    if yaw_used:
        return HeadingVelocity(speed, float(msg.yaw), notes=frozenset(notes))
    if yaw_rate_used:
        return BodyVelocity(speed, frames.omega_from_mavlink_yaw_rate(float(msg.yaw_rate)), frozenset(notes))
    if speed == 0.0:
        return BodyVelocity(0.0, 0.0, frozenset(notes))  # a stop: no direction to turn to
    return HeadingVelocity(speed, frames.ned_heading_rad(vx, vy), notes=frozenset(notes))


def _manual_axis(value: int) -> float | None:
    """One MANUAL_CONTROL axis as a fraction of full scale; None if out of range."""
    if value == MANUAL_AXIS_INVALID:
        return 0.0
    if -MANUAL_FULL_SCALE <= value <= MANUAL_FULL_SCALE:
        return value / MANUAL_FULL_SCALE
    return None


def decode_manual_control(msg: MAVLinkMessage, command: CommandParams) -> Decoded:
    """MANUAL_CONTROL x (forward) and r (yaw, clockwise +) -> body velocity."""
    x, r = int(msg.x), int(msg.r)
    if x == MANUAL_AXIS_INVALID and r == MANUAL_AXIS_INVALID:
        return Rejected(MANUAL_NO_AXES)
    fx, fr = _manual_axis(x), _manual_axis(r)
    if fx is None or fr is None:
        return Rejected(MANUAL_OUT_OF_RANGE)
    yaw_rate_cw = fr * command.manual_angular_scale_rad_s
    return BodyVelocity(fx * command.manual_linear_scale_m_s, frames.omega_from_mavlink_yaw_rate(yaw_rate_cw))


def decode_request(msg: MAVLinkMessage, command: CommandParams) -> Decoded:
    """Any of REQUEST_TYPES -> request or rejection. Malformed field values come back as MALFORMED."""
    try:
        if msg.get_type() == "MANUAL_CONTROL":
            return decode_manual_control(msg, command)
        return decode_position_target(msg)
    except (AttributeError, TypeError, ValueError, OverflowError):
        # A message object missing a field or holding a non-number: the network's fault, never ours.
        return Rejected(MALFORMED)

