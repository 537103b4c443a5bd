"""The emulated autopilot's parameters: names, boot values (ArduPilot Rover 4.7's defaults unless the
vehicle profile says otherwise) and PARAM_SET's rounding of integer parameters.

Defaults read in ArduPilot: Rover/Parameters.cpp, Rover/config.h, libraries/AR_WPNav (WP_*),
libraries/APM_Control/AR_AttitudeControl.cpp (ATC_*), libraries/AR_Motors/AP_MotorsUGV.cpp (MOT_*),
libraries/SRV_Channel/SRV_Channel.cpp (SERVOn_MIN 1100, MAX 1900, TRIM 1500), libraries/AC_Fence
(FENCE_*: Rover's FENCE_TYPE default is circle + polygon = 6), libraries/AP_SmartRTL (SRTL_*),
libraries/AP_Scheduler (SCHED_LOOP_RATE 50 for Rover), libraries/AC_Avoidance/AC_Avoid.cpp (AVOID_*: ENABLE 3 =
fence + proximity, MARGIN 2, BEHAVE 1 = stop for Rover, BACKUP_SPD 0.75, ACCEL_MAX 3, BACKUP_DZ 0.1),
libraries/AP_Proximity/AP_Proximity_Params.cpp (PRX1_*), libraries/AP_RangeFinder/AP_RangeFinder_Params.cpp
(RNGFND1_*: 4.7's MIN/MAX in metres, 0.2/7, ORIENT 25 = down). The vehicle's two motor outputs boot with
MIN/MAX = the vehicle's pwm_min/pwm_max (as ArduPilot's SITL rover.parm sets SERVO1/3 to 1000-2000).
The profile's ``params`` table sets any other boot value (e.g. SERVO5_FUNCTION = 73).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.config import ConfigError, VehicleConfig
from sitl.mav import mavlink

_INT = mavlink.MAV_PARAM_TYPE_INT16
_INT8 = mavlink.MAV_PARAM_TYPE_INT8
_REAL = mavlink.MAV_PARAM_TYPE_REAL32
REAL_TYPE: int = _REAL
NUM_SERVOS = 16
WHEEL_PARAM_PREFIXES = ("WENC", "WENC2")

# Navigation, control and safety defaults (name: (value, type)).
_ROVER_DEFAULTS: dict[str, tuple[float, int]] = {
    "SCHED_LOOP_RATE": (50.0, _INT), "GCS_PID_MASK": (0.0, _INT),
    "WP_SPEED": (2.0, _REAL), "WP_RADIUS": (2.0, _REAL), "WP_ACCEL": (0.0, _REAL), "WP_JERK": (0.0, _REAL),
    "WP_PIVOT_ANGLE": (60.0, _INT), "WP_PIVOT_RATE": (60.0, _INT), "WP_PIVOT_DELAY": (0.0, _REAL),
    "RTL_SPEED": (0.0, _REAL), "CRUISE_SPEED": (2.0, _REAL), "CRUISE_THROTTLE": (50.0, _INT8),
    "TURN_RADIUS": (0.9, _REAL), "MIS_DONE_BEHAVE": (0.0, _INT8), "MIS_RESTART": (0.0, _INT8),
    "ATC_STR_RAT_P": (0.2, _REAL), "ATC_STR_RAT_I": (0.2, _REAL), "ATC_STR_RAT_D": (0.0, _REAL),
    "ATC_STR_RAT_FF": (0.2, _REAL), "ATC_STR_RAT_IMAX": (1.0, _REAL), "ATC_STR_RAT_FLTE": (10.0, _REAL),
    "ATC_STR_RAT_MAX": (120.0, _REAL), "ATC_STR_ACC_MAX": (120.0, _REAL), "ATC_STR_DEC_MAX": (0.0, _REAL),
    "ATC_STR_ANG_P": (2.0, _REAL), "ATC_SPEED_P": (0.2, _REAL), "ATC_SPEED_I": (0.2, _REAL),
    "ATC_SPEED_D": (0.0, _REAL), "ATC_SPEED_FF": (0.0, _REAL), "ATC_SPEED_IMAX": (1.0, _REAL),
    "ATC_SPEED_FLTE": (10.0, _REAL), "ATC_ACCEL_MAX": (1.0, _REAL), "ATC_DECEL_MAX": (0.0, _REAL),
    "ATC_BRAKE": (1.0, _INT8), "ATC_STOP_SPEED": (0.1, _REAL), "ATC_TURN_MAX_G": (0.6, _REAL),
    "MOT_SLEWRATE": (100.0, _INT), "MOT_THR_MAX": (100.0, _INT8), "MOT_STR_THR_MIX": (0.5, _REAL),
    "SRTL_ACCURACY": (2.0, _REAL), "SRTL_POINTS": (300.0, _INT),
    "FENCE_ENABLE": (0.0, _INT8), "FENCE_TYPE": (6.0, _INT8), "FENCE_ACTION": (1.0, _INT8),
    "FENCE_RADIUS": (300.0, _REAL), "FENCE_MARGIN": (2.0, _REAL),
    "FS_ACTION": (2.0, _INT8), "FS_TIMEOUT": (1.5, _REAL), "FS_GCS_ENABLE": (0.0, _INT8),
    "FS_GCS_TIMEOUT": (5.0, _REAL), "FS_OPTIONS": (0.0, _INT),
    # Simple avoidance (AC_Avoid): fence and proximity by default, Rover stops (BEHAVE 1).
    "AVOID_ENABLE": (3.0, _INT8), "AVOID_MARGIN": (2.0, _REAL), "AVOID_BEHAVE": (1.0, _INT8),
    "AVOID_BACKUP_SPD": (0.75, _REAL), "AVOID_ACCEL_MAX": (3.0, _REAL), "AVOID_BACKUP_DZ": (0.1, _REAL),
    # Range sensors (sitl/range_sensors.py): none fitted; PRX1_TYPE 10 = SITL, RNGFND1_TYPE 100 = SITL.
    "PRX1_TYPE": (0.0, _INT8), "PRX1_ORIENT": (0.0, _INT8), "PRX1_YAW_CORR": (0.0, _INT),
    "RNGFND1_TYPE": (0.0, _INT8), "RNGFND1_ORIENT": (25.0, _INT8), "RNGFND1_MIN": (0.2, _REAL),
    "RNGFND1_MAX": (7.0, _REAL),
}


@dataclass
class Param:
    value: float
    type: int


def default_params(v: VehicleConfig, system_id: int) -> dict[str, Param]:
    """Every parameter with its boot value, in PARAM_REQUEST_LIST order."""
    p: dict[str, Param] = {
        "SYSID_THISMAV": Param(float(system_id), _INT),
        "MAV_GCS_SYSID": Param(float(v.gcs_sysid), _INT),
        "RC_OVERRIDE_TIME": Param(v.rc_override_time_s, _REAL),
    }
    for n in range(1, NUM_SERVOS + 1):
        func = v.left_function if n == v.left_servo else v.right_function if n == v.right_servo else 0
        motor = n in (v.left_servo, v.right_servo)
        p[f"SERVO{n}_FUNCTION"] = Param(float(func), _INT)
        p[f"SERVO{n}_TRIM"] = Param(float(v.pwm_trim), _INT)
        p[f"SERVO{n}_MIN"] = Param(float(v.pwm_min if motor else 1100), _INT)
        p[f"SERVO{n}_MAX"] = Param(float(v.pwm_max if motor else 1900), _INT)
        p[f"SERVO{n}_REVERSED"] = Param(0.0, _INT8)
    for ch in range(1, 17):
        # Rover gives its steering (RC1) and throttle (RC3) channels a 30 us dead zone.
        p[f"RC{ch}_DZ"] = Param(30.0 if ch in (1, 3) else 0.0, _INT)
    order = ("left", "right") if v.wheel_distance_order == "left_right" else ("right", "left")
    for prefix, wheel in zip(WHEEL_PARAM_PREFIXES, order, strict=True):
        p[f"{prefix}_TYPE"] = Param(1.0, _INT8)
        p[f"{prefix}_CPR"] = Param(float(v.encoder_cpr), _INT)
        p[f"{prefix}_RADIUS"] = Param(v.wheel_radius_m, _REAL)
        p[f"{prefix}_POS_Y"] = Param(-0.5 * v.track_width_m if wheel == "left" else 0.5 * v.track_width_m, _REAL)
    rates = {"SR0_RAW_SENS": v.rate_raw_sensors_hz, "SR0_EXT_STAT": v.rate_ext_status_hz,
             "SR0_RC_CHAN": v.rate_rc_channels_hz, "SR0_POSITION": v.rate_position_hz,
             "SR0_EXTRA1": v.rate_extra1_hz, "SR0_EXTRA2": v.rate_extra2_hz, "SR0_EXTRA3": v.rate_extra3_hz}
    for name, hz in rates.items():
        p[name] = Param(float(hz), _INT)
    # External navigation from ODOMETRY (AP_VisualOdom, EKF3 sources): off unless the vehicle says so.
    ext = v.external_nav
    p["VISO_TYPE"] = Param(1.0 if ext else 0.0, _INT8)
    for name in ("EK3_SRC1_POSXY", "EK3_SRC1_VELXY"):
        p[name] = Param(6.0 if ext else 3.0, _INT8)  # 6 ExtNav, 3 GPS
    p["EK3_SRC1_YAW"] = Param(6.0 if ext else 1.0, _INT8)  # 6 ExtNav, 1 Compass
    p["VISO_POS_M_NSE"] = Param(0.2, _REAL)
    p["VISO_YAW_M_NSE"] = Param(0.2, _REAL)
    p["EK3_POS_I_GATE"] = Param(500.0, _INT)
    p["EK3_YAW_I_GATE"] = Param(300.0, _INT)
    p.update({name: Param(value, kind) for name, (value, kind) in _ROVER_DEFAULTS.items()})
    unknown = [name for name, _ in v.params if name not in p]
    if unknown:
        raise ConfigError("vehicle params", [f"unknown parameter {name!r}" for name in unknown])
    for name, value in v.params:
        set_value(p[name], value)
    return p


def set_value(entry: Param, value: float) -> bool:
    """PARAM_SET semantics: integer parameters are rounded; non-finite values are refused."""
    if not math.isfinite(value):
        return False
    entry.value = float(round(value)) if entry.type != _REAL else float(value)
    return True
