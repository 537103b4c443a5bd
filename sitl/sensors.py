"""What the emulated autopilot can report: sensor ranges and the wire types' ranges.

A real IMU saturates, and so does the flight controller's conversion to MAVLink's integers:
- ArduPilot's Invensense drivers (AP_InertialSensor_Invensense*) set the accelerometers to +-16 g
  and the gyros to +-2000 deg/s; a reading never leaves that range.
- GCS_MAVLINK::send_raw_imu and the other senders hand floats to int16/int32 fields in C; on the
  flight controller's FPU (ARM's VCVT) an out-of-range conversion saturates at the type's limit.
  So +-2000 deg/s (34,907 mrad/s) reads 32,767 in RAW_IMU's int16 zgyro.
``fit_to_wire`` applies the second rule to every field of a built message, so no state of the
physics (a tiny step, a stall, a slip, a reboot) can make a message fail to pack.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ParamSpec

if TYPE_CHECKING:  # the physics imports this module; it needs no MAVLink
    from sitl.mav import MAVLinkMessage

P = ParamSpec("P")

G_M_S2 = 9.80665
ACCEL_RANGE_M_S2 = 16.0 * G_M_S2
GYRO_RANGE_RAD_S = math.radians(2000.0)
FLOAT32_MAX = 3.4028234663852886e38

INT_RANGES: dict[str, tuple[int, int]] = {
    "int8_t": (-(2**7), 2**7 - 1),
    "uint8_t": (0, 2**8 - 1),
    "int16_t": (-(2**15), 2**15 - 1),
    "uint16_t": (0, 2**16 - 1),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1),
    "uint64_t": (0, 2**64 - 1),
}


def clamp(value: float, limit: float) -> float:
    """``value`` limited to [-limit, limit] (NaN stays NaN)."""
    return max(-limit, min(limit, value)) if not math.isnan(value) else value


def accel_reading_m_s2(value: float) -> float:
    """An accelerometer axis as the IMU reports it: saturated at +-16 g."""
    return clamp(value, ACCEL_RANGE_M_S2)


def gyro_reading_rad_s(value: float) -> float:
    """A gyro axis as the IMU reports it: saturated at +-2000 deg/s."""
    return clamp(value, GYRO_RANGE_RAD_S)


def wire_int(value: float, type_name: str) -> int:
    """A number as C's saturating conversion puts it in an integer field (NaN reads 0, as VCVT gives)."""
    low, high = INT_RANGES[type_name]
    if math.isnan(value):
        return 0
    if value >= high:
        return high
    if value <= low:
        return low
    return round(value) if isinstance(value, float) else int(value)


def wire_float(value: float) -> float:
    """A double as a float32 field holds it: beyond float32's range it is infinite (IEEE rounding)."""
    if math.isfinite(value) and abs(value) > FLOAT32_MAX:
        return math.copysign(math.inf, value)
    return value


def _fit(value: Any, type_name: str) -> Any:
    if type_name in INT_RANGES:
        return wire_int(value, type_name)
    if type_name == "float":
        return wire_float(value)
    return value  # char (text), double: already what the wire carries


def fit_to_wire(msg: MAVLinkMessage) -> MAVLinkMessage:
    """Every numeric field of ``msg`` (arrays too) saturated to its wire type's range, in place."""
    for name, type_name in zip(msg.fieldnames, msg.fieldtypes, strict=True):
        value = getattr(msg, name)
        if isinstance(value, list):
            setattr(msg, name, [_fit(v, type_name) for v in value])
        elif isinstance(value, int | float):
            setattr(msg, name, _fit(value, type_name))
    return msg


def fitted(build: Callable[P, MAVLinkMessage]) -> Callable[P, MAVLinkMessage]:
    """Decorate a message builder so that everything it builds fits the wire (``fit_to_wire``)."""

    @functools.wraps(build)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> MAVLinkMessage:
        return fit_to_wire(build(*args, **kwargs))

    return wrapper
