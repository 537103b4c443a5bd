"""COMMAND_LONG / COMMAND_INT as the emulated ArduPilot answers them (each gets one COMMAND_ACK).

Read in ArduPilot: libraries/GCS_MAVLink/GCS_Common.cpp (handle_command_*), Rover/GCS_MAVLink_Rover.cpp,
libraries/AP_ServoRelayEvents, Rover/AP_Arming_Rover.cpp. Arm (param2 21196 forces past pre-arm checks) and
disarm ("Throttle armed" / "Throttle disarmed" on a change); DO_SET_MODE (custom mode in param2);
DO_SET_SERVO; SET_MESSAGE_INTERVAL; REQUEST_MESSAGE; REQUEST_AUTOPILOT_CAPABILITIES; GET_HOME_POSITION
(FAILED before home is set); PREFLIGHT_REBOOT_SHUTDOWN (refused while armed; param1 1 or 3; the ACK goes
out before the board falls silent). Anything else: MAV_RESULT_UNSUPPORTED.
"""

from __future__ import annotations

from sitl.autopilot_view import AutopilotView
from sitl.mav import MAVLinkMessage, mavlink
from sitl.modes import MODE_AUTO
from sitl.motors import FUNC_THROTTLE_LEFT, FUNC_THROTTLE_RIGHT
from sitl.rc import NUM_SERVOS
from sitl.sensors import wire_int
from sitl.streams import MAPPED

_P = mavlink
ACCEPTED: int = _P.MAV_RESULT_ACCEPTED
DENIED: int = _P.MAV_RESULT_DENIED
FAILED: int = _P.MAV_RESULT_FAILED
UNSUPPORTED: int = _P.MAV_RESULT_UNSUPPORTED
FORCE_ARM_MAGIC = 21196  # ArduPilot's param2 to skip pre-arm checks


def handle_command(ap: AutopilotView, msg: MAVLinkMessage, command: int, params: tuple[float, ...],
                   now_us: int) -> None:
    """Act on one command and queue its COMMAND_ACK (a reboot starts after the ACK is queued)."""
    ap.count("commands")
    p1, p2, p3 = params[0], params[1], params[2]
    result = UNSUPPORTED
    reboot = False
    if command == _P.MAV_CMD_COMPONENT_ARM_DISARM:
        if p1 == 1.0:
            result = arm(ap, force=int(p2) == FORCE_ARM_MAGIC)
        elif p1 == 0.0:
            result = disarm(ap)
    elif command == _P.MAV_CMD_DO_SET_MODE:
        result = ACCEPTED if set_mode(ap, int(p1), int(p2)) else FAILED
    elif command == _P.MAV_CMD_DO_SET_SERVO:
        result = do_set_servo(ap, wire_int(p1, "uint8_t"), wire_int(p2, "uint16_t"))  # C's casts
    elif command == _P.MAV_CMD_SET_MESSAGE_INTERVAL:
        result = set_message_interval(ap, int(p1), p2, p3)
    elif command == _P.MAV_CMD_REQUEST_MESSAGE:
        result = request_message(ap, int(p1))
    elif command == _P.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
        ap.outbox.append(autopilot_version(ap))
        result = ACCEPTED
    elif command == _P.MAV_CMD_GET_HOME_POSITION:
        result = request_message(ap, _P.MAVLINK_MSG_ID_HOME_POSITION) if ap.rover.nav.home is not None else FAILED
    elif command == _P.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
        if ap.armed:
            result = FAILED  # ArduPilot refuses to reboot when armed
        elif p1 in (1.0, 3.0):
            result = ACCEPTED
            reboot = True
    if result == UNSUPPORTED:
        ap.count("commands_unsupported")
    ap.outbox.append(
        ap.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
    )
    if reboot:
        ap.start_reboot(now_us)  # after the ACK is queued, as ArduPilot sends it first


def set_mode(ap: AutopilotView, base_mode: int, custom_mode: int) -> bool:
    """SET_MODE / DO_SET_MODE: only custom modes (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) are taken."""
    if not base_mode & _P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return False
    return ap.rover.set_mode(custom_mode)


def arm(ap: AutopilotView, force: bool) -> int:
    if ap.armed:
        return ACCEPTED
    no_motors = not ap.rc.functions() & {FUNC_THROTTLE_LEFT, FUNC_THROTTLE_RIGHT}
    if ap.vehicle.strict_prearm and not force and no_motors:
        ap.send_text(_P.MAV_SEVERITY_CRITICAL, "PreArm: no motor, sail or scripting outputs defined")
        return FAILED
    ap.armed = True
    ap.send_text(_P.MAV_SEVERITY_INFO, "Throttle armed")
    return ACCEPTED


def disarm(ap: AutopilotView) -> int:
    """AP_Arming_Rover::disarm: outside AUTO the mission starts from its first item next time."""
    if ap.armed:
        ap.armed = False
        if ap.rover.mode != MODE_AUTO:
            ap.mission.reset_cursor()
        ap.send_text(_P.MAV_SEVERITY_INFO, "Throttle disarmed")
    return ACCEPTED


def do_set_servo(ap: AutopilotView, n: int, pwm: int) -> int:
    if not 1 <= n <= NUM_SERVOS:
        return FAILED
    if not ap.rc.do_set_servo(n, pwm):
        ap.send_text(_P.MAV_SEVERITY_INFO, f"ServoRelayEvent: Channel {n} is already in use")
        return FAILED
    ap.count("servo_commands")
    return ACCEPTED


def mapped(ap: AutopilotView, msg_id: int) -> bool:
    """Whether ArduPilot has an internal id for the message (4.7 has none for WHEEL_DISTANCE)."""
    if msg_id == _P.MAVLINK_MSG_ID_WHEEL_DISTANCE and ap.vehicle.deny_wheel_distance_interval:
        return False
    return msg_id in MAPPED


def set_message_interval(ap: AutopilotView, msg_id: int, interval_us: float, param3: float) -> int:
    if param3 != 0:
        return DENIED
    if not mapped(ap, msg_id):
        ap.send_text(_P.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msg_id})")
        return DENIED
    result, text = ap.streams.set_interval(msg_id, interval_us, param3, ap.rover.loop_period_us, ap.now_us)
    if text is not None:
        ap.send_text(_P.MAV_SEVERITY_INFO, text)
    return result


def request_message(ap: AutopilotView, msg_id: int) -> int:
    if msg_id == _P.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
        ap.outbox.append(autopilot_version(ap))
        return ACCEPTED
    if not mapped(ap, msg_id):
        return FAILED
    ap.streams.pending.append(msg_id)
    return ACCEPTED


def autopilot_version(ap: AutopilotView) -> MAVLinkMessage:
    caps = (
        _P.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | _P.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | _P.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
        | _P.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    )
    version = (4 << 24) | (7 << 16) | (0 << 8) | 255  # "4.7.0 official", emulated
    zeros8 = [0] * 8
    return ap.mav.autopilot_version_encode(caps, version, 0, 0, 0, zeros8, zeros8, zeros8, 0, 0, ap.system_id)
