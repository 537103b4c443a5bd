"""Every message the emulated autopilot takes, dispatched as ArduPilot's GCS_MAVLINK::handle_message does.

The behaviours are listed in sitl/autopilot.py's docstring; commands are in sitl/commands.py, mission
messages in sitl/mission_protocol.py. What counts as "the GCS seen" for the GCS failsafe
(GCS_Common.cpp sysid_mygcs_seen): a HEARTBEAT or MANUAL_CONTROL from MAV_GCS_SYSID, or an accepted
RC_CHANNELS_OVERRIDE.
"""

from __future__ import annotations

from sitl import commands
from sitl.autopilot_view import AutopilotView
from sitl.mav import MAVLinkMessage, mavlink
from sitl.mission_protocol import MISSION_IDS
from sitl.rc import NUM_RC
from sitl.streams import STREAM_GROUPS

_P = mavlink
UINT16_MAX = 65535


def for_us(ap: AutopilotView, msg: MAVLinkMessage) -> bool:
    """ArduPilot's routing rule: broadcast (0) or our ids."""
    ts = getattr(msg, "target_system", None)
    tc = getattr(msg, "target_component", None)
    if ts is None and hasattr(msg, "target"):
        ts = msg.target
    if ts is not None and ts not in (0, ap.system_id):
        return False
    return tc is None or tc in (0, ap.component_id)


def handle_message(ap: AutopilotView, msg: MAVLinkMessage, now_us: int) -> None:
    """Process one decoded message (ignored while rebooting)."""
    if ap.rebooting:
        ap.count("rx_while_rebooting")
        return
    ap.count("rx_messages")
    msg_id = msg.get_msgId()
    if msg_id < 0:
        ap.count("rx_bad_data")
        return
    if not for_us(ap, msg):
        ap.count("rx_not_for_us")
        if msg_id == _P.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE:
            ap.count("override_wrong_target")
        return
    now_ms = ap.time_boot_ms(now_us)
    from_gcs = msg.get_srcSystem() == int(ap.param("MAV_GCS_SYSID"))
    if from_gcs and msg_id in (_P.MAVLINK_MSG_ID_HEARTBEAT, _P.MAVLINK_MSG_ID_MANUAL_CONTROL):
        ap.rover.failsafe.seen(now_ms)
    if msg_id == _P.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE:
        _handle_override(ap, msg, now_us)
    elif msg_id == _P.MAVLINK_MSG_ID_COMMAND_LONG:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        commands.handle_command(ap, msg, msg.command, params, now_us)
    elif msg_id == _P.MAVLINK_MSG_ID_COMMAND_INT:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        commands.handle_command(ap, msg, msg.command, params, now_us)
    elif msg_id == _P.MAVLINK_MSG_ID_SET_MODE:
        commands.set_mode(ap, msg.base_mode, msg.custom_mode)
    elif msg_id == _P.MAVLINK_MSG_ID_REQUEST_DATA_STREAM:
        _handle_request_data_stream(ap, msg)
    elif msg_id == _P.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
        for name in ap.params:
            ap.outbox.append(ap.param_value_msg(name))
    elif msg_id == _P.MAVLINK_MSG_ID_PARAM_REQUEST_READ:
        _handle_param_read(ap, msg)
    elif msg_id == _P.MAVLINK_MSG_ID_PARAM_SET:
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
        if ap.set_param(name, float(msg.param_value)):
            ap.outbox.append(ap.param_value_msg(name))
        else:
            ap.count("param_set_unknown")
    elif msg_id == _P.MAVLINK_MSG_ID_ODOMETRY:
        ap.take_odometry(msg, now_us)
    elif msg_id in MISSION_IDS:
        ap.protocol.handle(msg, now_ms, ap.armed, ap.rover.nav, ap.mission_current_msg)
    elif msg_id == _P.MAVLINK_MSG_ID_HEARTBEAT:
        ap.count("rx_heartbeats")
    elif msg_id == _P.MAVLINK_MSG_ID_TIMESYNC and msg.tc1 == 0:
        # GCS_Common.cpp handle_timesync: a request (tc1 == 0) is answered while parsing, ts1 echoed,
        # so its reply proves every byte before it on this link was handled.
        ap.count("timesync_replies")
        ap.outbox.append(ap.mav.timesync_encode(max(1, now_us * 1000), msg.ts1))


def _handle_override(ap: AutopilotView, msg: MAVLinkMessage, now_us: int) -> None:
    if msg.get_srcSystem() != int(ap.param("MAV_GCS_SYSID")):
        ap.count("override_rejected_sysid")  # silently, as ArduPilot does
        return
    ap.count("override_accepted")
    ap.rover.failsafe.seen(ap.time_boot_ms(now_us))
    for ch in range(1, NUM_RC + 1):
        value = int(getattr(msg, f"chan{ch}_raw", UINT16_MAX if ch <= 8 else 0))
        if ch <= 8:
            if value != UINT16_MAX:
                ap._set_override(ch, value, now_us)  # 0 releases the channel
        elif value not in (0, UINT16_MAX):
            ap._set_override(ch, 0 if value == UINT16_MAX - 1 else value, now_us)


def _handle_param_read(ap: AutopilotView, msg: MAVLinkMessage) -> None:
    names = list(ap.params)
    if msg.param_index >= 0:
        if msg.param_index < len(names):
            ap.outbox.append(ap.param_value_msg(names[msg.param_index]))
        return
    name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
    if name in ap.params:
        ap.outbox.append(ap.param_value_msg(name))
    else:
        ap.count("param_read_unknown")


def _handle_request_data_stream(ap: AutopilotView, msg: MAVLinkMessage) -> None:
    if msg.start_stop == 0:
        hz = 0
    elif msg.start_stop == 1:
        hz = int(msg.req_message_rate)
    else:
        return
    if msg.req_stream_id == _P.MAV_DATA_STREAM_ALL:
        groups = list(STREAM_GROUPS)
    elif msg.req_stream_id in STREAM_GROUPS:
        groups = [msg.req_stream_id]
    else:
        return
    for group in groups:
        ap.set_param(STREAM_GROUPS[group][0], float(hz))
