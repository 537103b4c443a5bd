"""The shell sleeps until `BridgeCore.next_deadline_s`; a deadline that `tick` leaves in the past makes it spin.

Invariant: right after `tick(now)`, the next deadline is strictly later than `now`, whatever came in
before (ACKs or none, silence, disarm, requests, a reboot). A queued stream request that waited for
another's ACK once broke this and kept a core busy until the autopilot answered.
"""

from __future__ import annotations

import dataclasses

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rover_bridge.app.composition import BridgeCore
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import Profile

AP = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
GCS = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)


def _wire(mav: mavlink.MAVLink, msg: MAVLinkMessage) -> MAVLinkMessage:
    return mav.decode(bytearray(msg.pack(mav)))


def _event(kind: str, t_s: float, value: int) -> Incoming:
    if kind == "ap_heartbeat":
        mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if value % 2 else 0)
        msg = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                mode, 15, mavlink.MAV_STATE_ACTIVE, 3)
        return Incoming(Link.AUTOPILOT, _wire(AP, msg))
    if kind == "interval_ack":
        result = (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED,
                  mavlink.MAV_RESULT_TEMPORARILY_REJECTED)[value % 4]
        msg = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, result, 0, 0, 255, 191)
        return Incoming(Link.AUTOPILOT, _wire(AP, msg))
    if kind == "wheels":
        d = value * 0.01
        msg = mavlink.MAVLink_wheel_distance_message(round(t_s * 1e6), 2, [d, 1.1 * d] + [0.0] * 14)
        return Incoming(Link.AUTOPILOT, _wire(AP, msg))
    if kind == "gyro":
        msg = mavlink.MAVLink_attitude_message(round(t_s * 1e3), 0.0, 0.0, 0.0, 0.0, 0.0, -0.01 * value)
        return Incoming(Link.AUTOPILOT, _wire(AP, msg))
    if kind == "system_time":
        return Incoming(Link.AUTOPILOT, _wire(AP, mavlink.MAVLink_system_time_message(0, round(t_s * 1e3))))
    if kind == "gcs_heartbeat":
        msg = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
        return Incoming(Link.GCS, _wire(GCS, msg))
    # a body-frame velocity request
    msg = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_BODY_OFFSET_NED, 1479, 0.0, 0.0, 0.0, 0.1 * (value % 5), 0.0, 0.0,
        0.0, 0.0, 0.0, 0.0, 0.1 * (value % 3 - 1))
    return Incoming(Link.GCS, _wire(GCS, msg))


KINDS = ("ap_heartbeat", "interval_ack", "wheels", "gyro", "system_time", "gcs_heartbeat", "request")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(events=st.lists(st.tuples(st.sampled_from(KINDS), st.floats(0.0, 2.5), st.integers(0, 40)),
                       min_size=1, max_size=60),
       servo=st.booleans(), calibrate=st.booleans())
def test_tick_always_moves_the_deadline_into_the_future(events: list[tuple[str, float, int]], servo: bool,
                                                         calibrate: bool) -> None:
    profile = Profile()
    if servo:
        profile = dataclasses.replace(profile, output=dataclasses.replace(profile.output, mode="servo"))
    if calibrate:
        profile = dataclasses.replace(profile, estimator=dataclasses.replace(profile.estimator, calibrate=True))
    core = BridgeCore(profile)
    t_s = 10.0
    for kind, gap_s, value in events:
        target = t_s + gap_s
        # Every deadline up to the next event is ticked, as the shell does after its sleep.
        while (deadline := core.next_deadline_s(t_s)) <= target:
            t_s = max(t_s, deadline)
            core.tick(t_s)
            after = core.next_deadline_s(t_s)
            assert after > t_s, f"deadline {after} not after the tick at {t_s} (after {kind})"
        t_s = target
        core.handle(_event(kind, t_s, value), t_s)
