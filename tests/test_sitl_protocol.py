"""MAVLink behaviour of the sitl emulator, with a pymavlink client over UDP loopback in lockstep.

The client sends, then the test calls ``emu.step``; loopback UDP delivers before sendto()
returns, so each step sees everything sent before it. The client then drains its socket.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from sitl import Emulator, VehicleConfig
from sitl.mav import MAVLinkMessage, mavlink, mavutil

GCS_SYSID = 255


class Rig:
    """An emulator on an ephemeral UDP port and a pymavlink 'GCS' talking to it."""

    def __init__(self, vehicle: VehicleConfig | None = None, sysid: int = GCS_SYSID) -> None:
        self.emu = Emulator(vehicle=vehicle or VehicleConfig(), seed=3)
        self.emu.open("udpin:127.0.0.1:0")
        self.port = self.emu.local_address[1]
        self.gcs = self.client(sysid)
        self.log: list[tuple[float, MAVLinkMessage]] = []
        self.gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        self.run(0.01)

    def client(self, sysid: int) -> Any:
        return mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{self.port}", source_system=sysid, source_component=190
        )

    def drain(self) -> None:
        while True:
            msg = self.gcs.recv_match(blocking=False)
            if msg is None:
                return
            self.log.append((self.emu.sim_time_s, msg))

    def run(self, seconds: float, dt_s: float = 0.01) -> list[MAVLinkMessage]:
        """Step the emulator; return the messages received meanwhile."""
        start = len(self.log)
        for _ in range(max(1, round(seconds / dt_s))):
            self.emu.step(dt_s)
            self.drain()
        return [m for _, m in self.log[start:]]

    def command(self, command: int, *params: float) -> int:
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        self.gcs.mav.command_long_send(1, 1, command, 0, *p)
        acks = [m for m in self.run(0.02) if m.get_type() == "COMMAND_ACK" and m.command == command]
        assert len(acks) == 1, acks
        result: int = acks[0].result
        return result

    def override(self, target_system: int = 1, target_component: int = 1, **channels: int) -> None:
        values = [channels.get(f"ch{i}", 65535 if i <= 8 else 0) for i in range(1, 19)]
        self.gcs.mav.rc_channels_override_send(target_system, target_component, *values)

    def stream(self, stream_id: int, hz: int) -> None:
        self.gcs.mav.request_data_stream_send(1, 1, stream_id, hz, 1)

    def close(self) -> None:
        self.gcs.close()
        self.emu.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    yield r
    r.close()


@pytest.fixture
def armed_rig() -> Iterator[Rig]:
    r = Rig(VehicleConfig(start_armed=True))
    yield r
    r.close()


def of(msgs: list[MAVLinkMessage], type_name: str) -> list[MAVLinkMessage]:
    return [m for m in msgs if m.get_type() == type_name]


def test_heartbeat_contents_and_rate(rig: Rig) -> None:
    msgs = rig.run(3.0)
    beats = of(msgs, "HEARTBEAT")
    assert len(beats) == 3  # 1 Hz
    hb = beats[-1]
    assert hb.type == mavlink.MAV_TYPE_GROUND_ROVER
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.custom_mode == 0  # MANUAL
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.get_msgbuf()[0] == 0xFD  # MAVLink 2 framing


def test_arm_and_mode_commands_acknowledged_and_reflected(rig: Rig) -> None:
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert rig.emu.armed
    assert rig.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4) == (
        mavlink.MAV_RESULT_ACCEPTED
    )
    hb = of(rig.run(1.0), "HEARTBEAT")[-1]
    assert hb.custom_mode == 4
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert rig.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15) == (
        mavlink.MAV_RESULT_ACCEPTED
    )
    assert rig.emu.mode == 15
    assert rig.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 99) == (
        mavlink.MAV_RESULT_FAILED
    )
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_ACCEPTED
    assert not rig.emu.armed
    assert rig.command(mavlink.MAV_CMD_DO_FLIGHTTERMINATION, 1) == mavlink.MAV_RESULT_UNSUPPORTED


def test_override_values_reach_servo_output_raw_and_turn_the_wheels(armed_rig: Rig) -> None:
    rig = armed_rig
    rig.stream(mavlink.MAV_DATA_STREAM_RC_CHANNELS, 10)
    for _ in range(10):
        rig.override(ch1=1700, ch3=1300)
        rig.run(0.1)
    servo = of(rig.run(0.2), "SERVO_OUTPUT_RAW")[-1]
    assert (servo.servo1_raw, servo.servo3_raw) == (1700, 1300)
    rc = of(rig.log and [m for _, m in rig.log], "RC_CHANNELS")[-1]
    assert (rc.chan1_raw, rc.chan3_raw) == (1700, 1300)
    truth = rig.emu.truth
    assert truth.left_wheel_rad_s > 5.0 and truth.right_wheel_rad_s < -5.0
    assert truth.yaw_rate_rad_s > 0.5  # left forward, right back: clockwise


def test_release_and_ignore_semantics(armed_rig: Rig) -> None:
    rig = armed_rig
    rig.override(ch1=1700, ch3=1700, ch9=1800)
    rig.run(0.05)
    assert [rig.emu.rc_inputs[c] for c in (1, 3, 9)] == [1700, 1700, 1800]
    # ch1 65535 = leave alone; ch3 0 = release to the radio (trim, no radio); ch9 0 = leave alone.
    rig.override(ch1=65535, ch3=0, ch9=0)
    rig.run(0.05)
    assert [rig.emu.rc_inputs[c] for c in (1, 3, 9)] == [1700, 1500, 1800]
    rig.override(ch9=65535)
    rig.run(0.05)
    assert rig.emu.rc_inputs[9] == 1800
    rig.override(ch9=65534)  # ch9-18: 65534 releases
    rig.run(0.05)
    assert rig.emu.rc_inputs[9] == 1500
    assert rig.emu.rc_inputs[1] == 1700


def test_overrides_from_other_sysid_or_for_other_targets_are_ignored(armed_rig: Rig) -> None:
    rig = armed_rig
    other = rig.client(200)
    other.mav.rc_channels_override_send(1, 1, 1900, 65535, 1900, 65535, 65535, 65535, 65535, 65535)
    rig.run(0.5)
    other.close()
    assert rig.emu.rc_inputs[1] == 1500
    assert rig.emu.truth.left_wheel_rad_s == 0.0
    assert rig.emu.counters["override_rejected_sysid"] == 1
    rig.override(target_system=7, ch1=1900)
    rig.override(target_system=1, target_component=50, ch1=1900)
    rig.run(0.1)
    assert rig.emu.rc_inputs[1] == 1500
    rig.override(target_system=0, target_component=0, ch1=1900)  # broadcast is for us
    rig.run(0.1)
    assert rig.emu.rc_inputs[1] == 1900


def test_override_timeout_returns_to_trim_and_stops_the_wheels(armed_rig: Rig) -> None:
    rig = armed_rig
    for _ in range(10):
        rig.override(ch1=1800, ch3=1800)
        rig.run(0.1)
    assert rig.emu.truth.v_m_s > 0.5
    last_sent_s = rig.emu.sim_time_s - 0.1  # the last override was handled one run(0.1) ago
    rig.run(2.85)
    assert rig.emu.sim_time_s == pytest.approx(last_sent_s + 2.95)
    assert rig.emu.rc_inputs[1] == 1800  # still alive just before RC_OVERRIDE_TIME (3 s)
    rig.run(0.1)
    assert rig.emu.rc_inputs[1] == 1500
    assert rig.emu.servo_outputs[1] == 1500
    rig.run(1.0)
    assert abs(rig.emu.truth.v_m_s) < 1e-3
    assert abs(rig.emu.truth.left_wheel_rad_s) < 0.01


def test_do_set_servo_refused_on_motor_function_output(armed_rig: Rig) -> None:
    rig = armed_rig
    rig.gcs.mav.param_set_send(1, 1, b"SERVO1_FUNCTION", 73, mavlink.MAV_PARAM_TYPE_INT16)
    rig.run(0.02)
    assert rig.command(mavlink.MAV_CMD_DO_SET_SERVO, 1, 1800) == mavlink.MAV_RESULT_FAILED
    texts = [m.text for m in of([m for _, m in rig.log], "STATUSTEXT")]
    assert any("Channel 1 is already in use" in t for t in texts)
    assert rig.emu.servo_outputs[1] == 1500


def test_do_set_servo_on_passthrough_holds_without_timeout_until_rc_moves(armed_rig: Rig) -> None:
    rig = armed_rig
    assert rig.command(mavlink.MAV_CMD_DO_SET_SERVO, 1, 1800) == mavlink.MAV_RESULT_ACCEPTED
    assert rig.command(mavlink.MAV_CMD_DO_SET_SERVO, 3, 1800) == mavlink.MAV_RESULT_ACCEPTED
    rig.run(10.0)  # far beyond RC_OVERRIDE_TIME: a dead companion leaves the wheels turning
    assert rig.emu.servo_outputs[1] == 1800
    assert rig.emu.truth.v_m_s > 0.5
    rig.override(ch1=1520)  # within RC1's 30 us dead zone of the last radio value: still held
    rig.run(0.05)
    assert rig.emu.servo_outputs[1] == 1800
    rig.override(ch1=1600)
    rig.run(0.05)
    assert rig.emu.servo_outputs[1] == 1600
    assert rig.emu.servo_outputs[3] == 1800  # the other output is still held


def test_set_message_interval_changes_measured_rate(rig: Rig) -> None:
    before = of(rig.run(4.0), "ATTITUDE")
    assert 3 <= len(before) <= 5  # EXTRA1 at 1 Hz by default
    assert rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, 50_000) == (
        mavlink.MAV_RESULT_ACCEPTED
    )
    after = of(rig.run(4.0), "ATTITUDE")
    assert 78 <= len(after) <= 82  # 20 Hz
    assert rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, -1) == (
        mavlink.MAV_RESULT_ACCEPTED
    )
    assert of(rig.run(2.0), "ATTITUDE") == []


def test_wheel_distance_interval_denied_but_extra1_stream_works(rig: Rig) -> None:
    result = rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE, 20_000)
    assert result == mavlink.MAV_RESULT_DENIED
    assert "No ap_message for mavlink id (9000)" in rig.emu.statustexts_sent
    assert len(of(rig.run(4.0), "WHEEL_DISTANCE")) <= 5  # still the 1 Hz default
    rig.stream(mavlink.MAV_DATA_STREAM_EXTRA1, 10)
    msgs = of(rig.run(4.0), "WHEEL_DISTANCE")
    assert 38 <= len(msgs) <= 42
    assert msgs[-1].count == 2
    assert rig.emu.get_param("SR0_EXTRA1") == 10


def test_wheel_distance_interval_allowed_when_configured() -> None:
    r = Rig(VehicleConfig(deny_wheel_distance_interval=False))
    try:
        assert r.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 9000, 100_000) == mavlink.MAV_RESULT_ACCEPTED
        assert 38 <= len(of(r.run(4.0), "WHEEL_DISTANCE")) <= 42
    finally:
        r.close()


def test_wheel_distance_sign_order_and_reboot_reset(armed_rig: Rig) -> None:
    rig = armed_rig
    rig.stream(mavlink.MAV_DATA_STREAM_EXTRA1, 10)
    for _ in range(20):  # spin in place: left forward, right back
        rig.override(ch1=1800, ch3=1200)
        rig.run(0.1)
    wd = of([m for _, m in rig.log], "WHEEL_DISTANCE")[-1]
    assert wd.distance[0] > 0.3 and wd.distance[1] < -0.3  # index 0 left, index 1 right
    assert wd.time_usec == pytest.approx(rig.emu.sim_time_s * 1e6, abs=0.2e6)
    assert rig.command(mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == mavlink.MAV_RESULT_FAILED  # armed
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_ACCEPTED
    assert rig.command(mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert rig.run(1.4) == []  # the link is silent while the board reboots
    msgs = rig.run(1.0)
    first = of(msgs, "WHEEL_DISTANCE")[0]
    assert first.distance[0] == pytest.approx(0.0, abs=0.01)
    assert first.distance[1] == pytest.approx(0.0, abs=0.01)
    assert first.time_usec < 200_000  # time since boot restarted
    assert rig.emu.rc_inputs[1] == 1500  # overrides cleared
    assert of(msgs, "HEARTBEAT")


def test_param_set_read_round_trip_and_list(rig: Rig) -> None:
    rig.gcs.mav.param_set_send(1, 1, b"RC_OVERRIDE_TIME", 1.5, mavlink.MAV_PARAM_TYPE_REAL32)
    reply = of(rig.run(0.02), "PARAM_VALUE")
    assert [(m.param_id, m.param_value) for m in reply] == [("RC_OVERRIDE_TIME", 1.5)]
    rig.gcs.mav.param_request_read_send(1, 1, b"RC_OVERRIDE_TIME", -1)
    assert of(rig.run(0.02), "PARAM_VALUE")[0].param_value == 1.5
    rig.gcs.mav.param_set_send(1, 1, b"SERVO3_FUNCTION", 74.4, mavlink.MAV_PARAM_TYPE_INT16)
    assert of(rig.run(0.02), "PARAM_VALUE")[0].param_value == 74.0
    rig.gcs.mav.param_set_send(1, 1, b"NO_SUCH_PARAM", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert of(rig.run(0.02), "PARAM_VALUE") == []
    rig.gcs.mav.param_request_list_send(1, 1)
    values = of(rig.run(0.02), "PARAM_VALUE")
    assert len(values) == values[0].param_count
    names = {m.param_id for m in values}
    assert {"SERVO1_FUNCTION", "MAV_GCS_SYSID", "WENC_CPR", "WENC2_RADIUS", "SR0_EXTRA1"} <= names
    assert sorted(m.param_index for m in values) == list(range(len(values)))


def test_shorter_override_time_parameter_takes_effect(armed_rig: Rig) -> None:
    rig = armed_rig
    rig.gcs.mav.param_set_send(1, 1, b"RC_OVERRIDE_TIME", 0.5, mavlink.MAV_PARAM_TYPE_REAL32)
    rig.override(ch1=1800)
    rig.run(0.4)
    assert rig.emu.rc_inputs[1] == 1800
    rig.run(0.2)
    assert rig.emu.rc_inputs[1] == 1500


def test_odometry_is_kept_for_inspection(rig: Rig) -> None:
    rig.gcs.mav.odometry_send(
        123,
        mavlink.MAV_FRAME_LOCAL_FRD,
        mavlink.MAV_FRAME_BODY_FRD,
        1.25,
        -0.5,
        0.0,
        [1, 0, 0, 0],
        0.3,
        0.0,
        0.0,
        0.0,
        0.0,
        0.1,
        [float("nan")] * 21,
        [float("nan")] * 21,
        0,
        0,
        0,
    )
    rig.run(0.02)
    assert len(rig.emu.received_odometry) == 1
    got = rig.emu.received_odometry[0]
    assert (got.message.x, got.message.y, got.message.time_usec) == (1.25, -0.5, 123)
    assert got.time_s == pytest.approx(0.01, abs=0.011)


@pytest.mark.parametrize("passthrough_when_disarmed", [False, True])
def test_disarmed_passthrough_option(passthrough_when_disarmed: bool) -> None:
    r = Rig(VehicleConfig(passthrough_when_disarmed=passthrough_when_disarmed))
    try:
        for _ in range(10):
            r.override(ch1=1800, ch3=1800)
            r.run(0.1)
        if passthrough_when_disarmed:  # the measured ArduPilot hazard: disarmed wheels turn
            assert r.emu.servo_outputs[1] == 1800
            assert r.emu.truth.v_m_s > 0.5
        else:
            assert r.emu.servo_outputs[1] == 1500
            assert r.emu.truth.v_m_s == 0.0
    finally:
        r.close()


def test_strict_prearm_refuses_passthrough_only_vehicle() -> None:
    r = Rig(VehicleConfig(strict_prearm=True))
    try:
        assert r.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_FAILED
        assert any("no motor, sail or scripting outputs" in t for t in r.emu.statustexts_sent)
        assert r.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196) == mavlink.MAV_RESULT_ACCEPTED
    finally:
        r.close()


def test_motor_functions_mix_throttle_and_steering_in_manual(armed_rig: Rig) -> None:
    rig = armed_rig
    rig.emu.set_param("SERVO1_FUNCTION", 73)
    rig.emu.set_param("SERVO3_FUNCTION", 74)
    rig.override(ch1=1700, ch3=1500)  # steering right, no throttle: spin clockwise
    rig.run(1.0)
    assert rig.emu.servo_outputs[1] > 1600 and rig.emu.servo_outputs[3] < 1400
    assert rig.emu.truth.yaw_rate_rad_s > 0.5


def test_tcp_endpoint_answers_heartbeat() -> None:
    emu = Emulator()
    emu.open("tcpin:127.0.0.1:0")
    port = emu.local_address[1]
    client = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
    try:
        got: list[MAVLinkMessage] = []
        for _ in range(150):
            emu.step(0.01)
            while (m := client.recv_match(blocking=False)) is not None:
                got.append(m)
        assert [m.get_type() for m in got].count("HEARTBEAT") == 2
    finally:
        client.close()
        emu.close()


def test_tcp_endpoint_serves_a_client_that_reconnects() -> None:
    """`rover-sitl` listens on TCP like ArduPilot SITL: a bridge that is restarted connects again and is
    served (the new client replaces the old, as on a serial port), its commands answered."""
    emu = Emulator()
    emu.open("tcpin:127.0.0.1:0")
    port = emu.local_address[1]
    first = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
    second = None
    try:
        for _ in range(120):
            emu.step(0.01)
        assert first.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0) is not None
        first.close()
        second = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255)
        second.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        got: list[MAVLinkMessage] = []
        for _ in range(150):
            emu.step(0.01)
            while (m := second.recv_match(blocking=False)) is not None:
                got.append(m)
        assert [m.get_type() for m in got].count("HEARTBEAT") >= 1
        acks = [m for m in got if m.get_type() == "COMMAND_ACK"]
        assert [(a.command, a.result) for a in acks] == [(mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                                                          mavlink.MAV_RESULT_ACCEPTED)]
        assert emu.armed
    finally:
        if second is not None:
            second.close()
        emu.close()
