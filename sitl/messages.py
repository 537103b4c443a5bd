"""The emulated autopilot's outgoing messages, built from its state and the physics.

``build`` makes one message of the streams (the builders moved here unchanged from sitl/autopilot.py);
``build_all`` adds the messages ArduPilot sends only sometimes: NAV_CONTROLLER_OUTPUT only in modes
that navigate (Rover's send_nav_controller_output), PID_TUNING per GCS_PID_MASK bit (1: steering,
axis 5, deg/s; 2: speed, axis 4, m/s: Rover's send_pid_tuning), HOME_POSITION once home is set,
DISTANCE_SENSOR per range sensor fitted (sitl/range_sensors.py).
"""

from __future__ import annotations

import math

from sitl import range_sensors
from sitl.autopilot_view import AutopilotView
from sitl.mav import MAVLinkMessage, mavlink
from sitl.mission import COMPLETE, RUNNING
from sitl.modes import AUTOPILOT_MODES, MODE_AUTO, MODE_GUIDED, MODE_HOLD
from sitl.physics import PhysicsState
from sitl.rc import NUM_RC
from sitl.sensors import G_M_S2, accel_reading_m_s2, fit_to_wire, fitted

_P = mavlink
PID_AXIS_SPEED = 4  # PID_TUNING_ACCZ, Rover's speed controller
PID_AXIS_STEER = 5  # PID_TUNING_STEER
# MISSION_STATE: no mission, not started, active, complete.
_NO_MISSION, _NOT_STARTED, _ACTIVE, _COMPLETE = 1, 2, 3, 5


@fitted  # every field saturates at its wire type's range, as the C conversions on the autopilot do
def build(ap: AutopilotView, msg_id: int, now_us: int, s: PhysicsState) -> MAVLinkMessage:
    """Build one message of a stream from the current state."""
    boot_ms = ap.time_boot_ms(now_us)
    boot_us = max(0, now_us - ap.boot_us)
    m = ap.mav
    if msg_id == _P.MAVLINK_MSG_ID_HEARTBEAT:
        base = _P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | _P.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if ap.mode == MODE_GUIDED:
            base |= _P.MAV_MODE_FLAG_GUIDED_ENABLED | _P.MAV_MODE_FLAG_STABILIZE_ENABLED
        elif ap.mode in AUTOPILOT_MODES:  # GCS_MAVLINK_Rover::base_mode: modes that navigate themselves
            base |= _P.MAV_MODE_FLAG_GUIDED_ENABLED
        if ap.armed:
            base |= _P.MAV_MODE_FLAG_SAFETY_ARMED
        # GCS_MAVLINK_Rover::vehicle_system_status: armed and not holding is ACTIVE; a failsafe, CRITICAL.
        status = _P.MAV_STATE_ACTIVE if ap.armed and ap.mode != MODE_HOLD else _P.MAV_STATE_STANDBY
        if ap.rover.failsafe.triggered:
            status = _P.MAV_STATE_CRITICAL
        return m.heartbeat_encode(
            _P.MAV_TYPE_GROUND_ROVER, _P.MAV_AUTOPILOT_ARDUPILOTMEGA, base, ap.mode, status, 3
        )
    if msg_id == _P.MAVLINK_MSG_ID_WHEEL_DISTANCE:
        d0, d1 = ap.wheel_distances_m(s)
        return m.wheel_distance_encode(boot_us, 2, [d0, d1] + [0.0] * 14)
    if msg_id == _P.MAVLINK_MSG_ID_ATTITUDE:
        return m.attitude_encode(boot_ms, 0.0, 0.0, ap.heading_rad(s), 0.0, 0.0, s.gyro_rad_s)
    if msg_id in (_P.MAVLINK_MSG_ID_RAW_IMU, _P.MAVLINK_MSG_ID_SCALED_IMU):
        # mG and mrad/s in FRD: x forward, y right, z down (gravity reads -1 g); the accelerometer
        # saturates at +-16 g, the gyro (already in its range) at int16 in mrad/s (sitl/sensors.py).
        ax = accel_reading_m_s2(s.accel_m_s2) / G_M_S2 * 1000.0
        ay = accel_reading_m_s2(s.v_m_s * s.yaw_rate_rad_s) / G_M_S2 * 1000.0
        gz = s.gyro_rad_s * 1000.0
        if msg_id == _P.MAVLINK_MSG_ID_RAW_IMU:
            return m.raw_imu_encode(boot_us, ax, ay, -1000, 0, 0, gz, 0, 0, 0)
        return m.scaled_imu_encode(boot_ms, ax, ay, -1000, 0, 0, gz, 0, 0, 0)
    if msg_id == _P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
        out = ap.servo_outputs()
        return m.servo_output_raw_encode(boot_us & 0xFFFFFFFF, 0, *[out[n] for n in range(1, 17)])
    if msg_id == _P.MAVLINK_MSG_ID_RC_CHANNELS:
        rc = ap.rc_inputs(now_us)
        return m.rc_channels_encode(boot_ms, NUM_RC, *[rc[ch] for ch in range(1, NUM_RC + 1)], 255)
    if msg_id == _P.MAVLINK_MSG_ID_SYSTEM_TIME:
        return m.system_time_encode(0, boot_ms)  # no GPS: no UNIX time, as ArduPilot
    if msg_id == _P.MAVLINK_MSG_ID_SYS_STATUS:
        return m.sys_status_encode(0, 0, 0, 0, 12000, -1, -1, 0, 0, 0, 0, 0, 0)
    if msg_id == _P.MAVLINK_MSG_ID_VFR_HUD:
        heading: int = round(math.degrees(s.ahrs_yaw_rad)) % 360
        return m.vfr_hud_encode(abs(s.v_m_s), abs(s.v_m_s), heading, 0, 0.0, 0.0)
    if msg_id == _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
        ext = ap.extnav.position() if ap.extnav_position_source else None
        if ext is not None:  # the EKF navigates on the companion's ODOMETRY
            return m.local_position_ned_encode(boot_ms, ext[0], ext[1], 0.0, ap.extnav.vel_n_m_s,
                                               ap.extnav.vel_e_m_s, 0.0)
        vx = s.v_m_s * math.cos(s.yaw_rad)
        vy = s.v_m_s * math.sin(s.yaw_rad)
        return m.local_position_ned_encode(boot_ms, s.x_m, s.y_m, 0.0, vx, vy, 0.0)
    if msg_id == _P.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
        lat_deg = lon_deg = 0.0  # no position yet: ArduPilot sends zeros
        if ap.has_position():
            ext = ap.extnav.position() if ap.extnav_position_source else None
            lat_deg, lon_deg = ap.lat_lon_of(*(ext if ext is not None else (s.x_m, s.y_m)))
        vn, ve = s.v_m_s * math.cos(s.yaw_rad), s.v_m_s * math.sin(s.yaw_rad)
        hdg = round(math.degrees(ap.heading_rad(s)) * 100.0) % 36000
        return m.global_position_int_encode(boot_ms, lat_deg * 1e7, lon_deg * 1e7, 584_000, 0,
                                            vn * 100.0, ve * 100.0, 0, hdg)
    if msg_id == _P.MAVLINK_MSG_ID_SIMSTATE:
        lat_deg, lon_deg = ap.lat_lon_of(s.x_m, s.y_m)
        lateral_m_s2 = s.v_m_s * s.yaw_rate_rad_s
        return m.simstate_encode(
            0.0,
            0.0,
            s.yaw_rad,
            s.accel_m_s2,
            lateral_m_s2,
            -9.80665,
            0.0,
            0.0,
            s.yaw_rate_rad_s,
            lat_deg * 1e7,
            lon_deg * 1e7,
        )
    raise ValueError(f"cannot build message id {msg_id}")


def build_all(ap: AutopilotView, msg_id: int, now_us: int, s: PhysicsState) -> list[MAVLinkMessage]:
    """The messages one due stream slot (or request) of ``msg_id`` produces (none, one or two), each
    fitted to its wire types as ``build``'s are."""
    return [fit_to_wire(msg) for msg in _build_all(ap, msg_id, now_us, s)]


def _build_all(ap: AutopilotView, msg_id: int, now_us: int, s: PhysicsState) -> list[MAVLinkMessage]:
    m = ap.mav
    rover = ap.rover
    if msg_id == _P.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT:
        if rover.mode not in AUTOPILOT_MODES:
            return []
        nav_deg, target_deg, dist_m, xtrack_m = rover.nav.nav_output(rover.mode)
        return [m.nav_controller_output_encode(0.0, 0.0, int(nav_deg), int(target_deg), int(min(dist_m, 65535.0)),
                                               0.0, 0.0, xtrack_m)]
    if msg_id == _P.MAVLINK_MSG_ID_PID_TUNING:
        mask = int(ap.param("GCS_PID_MASK"))
        out = []
        atc = rover.nav.atc
        if mask & 1:
            i = atc.steer_pid.info
            out.append(m.pid_tuning_encode(PID_AXIS_STEER, math.degrees(i.target), math.degrees(i.actual),
                                           i.ff, i.p, i.i, i.d, 0.0, 1.0))
        if mask & 2:
            i = atc.speed_info
            out.append(m.pid_tuning_encode(PID_AXIS_SPEED, i.target, i.actual, i.ff, i.p, i.i, i.d, 0.0, 1.0))
        return out
    if msg_id == _P.MAVLINK_MSG_ID_MISSION_CURRENT:
        return [mission_current(ap, ap.mission.current_nav_index())]
    if msg_id == _P.MAVLINK_MSG_ID_HOME_POSITION:
        home = rover.nav.home
        if home is None:
            return []
        lat, lon = ap.lat_lon_of(*home)
        nan = float("nan")
        return [m.home_position_encode(round(lat * 1e7), round(lon * 1e7), HOME_ALT_MM, home[0], home[1], 0.0,
                                       [nan] * 4, 0.0, 0.0, 0.0, max(0, now_us - ap.boot_us))]
    if msg_id == _P.MAVLINK_MSG_ID_DISTANCE_SENSOR:
        return range_sensors.distance_sensors(ap, now_us, s)
    if msg_id == _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not ap.has_position():
        return []  # ArduPilot sends no local position before its EKF has one
    return [build(ap, msg_id, now_us, s)]


HOME_ALT_MM = 584_000  # the altitude GLOBAL_POSITION_INT reports


def mission_current(ap: AutopilotView, seq: int) -> MAVLinkMessage:
    """MISSION_CURRENT (GCS_Common.cpp send_mission_current): ``seq``, items without home, state, AUTO or not."""
    mission = ap.mission
    state = (_NO_MISSION if not mission.present() else _ACTIVE if mission.state == RUNNING
             else _COMPLETE if mission.state == COMPLETE else _NOT_STARTED)
    return ap.mav.mission_current_encode(seq, max(0, mission.count() - 1), state,
                                         1 if ap.rover.mode == MODE_AUTO else 0)
