"""The skid-steer demand on ThrottleLeft/Right outputs, SERVO_OUTPUT_RAW's rate rules, home, and the
math of the emulator's navigation (property tests).

ArduPilot facts (issue 29, Rover 4.7): SERVO5/6 default to 1100-1900 while the motors use 1000-2000, so
80 % of the demand gets through; SERVO_OUTPUT_RAW comes at 1 Hz by default; SET_MESSAGE_INTERVAL is
DENIED below 1.25 loop periods ("Requested rate for message ID 36 too fast. Increase SCHED_LOOP_RATE"),
40 Hz is accepted at SCHED_LOOP_RATE 50, 50 Hz needs 100; message intervals reset when it reboots.
"""

from __future__ import annotations

import math
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from sitl import Emulator, VehicleConfig, load_vehicle
from sitl.gcs import InProcessGcs
from sitl.mav import mavlink
from sitl.modes import MODE_HOLD
from sitl.motors import SkidMotors, pwm_from_angle
from sitl.scurve import LegProfile

P = mavlink
SERVO_OUTPUT_RAW = P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
BRIDGE = load_vehicle(Path(__file__).resolve().parents[1] / "sitl" / "vehicles" / "ardupilot-skid-bridge.toml")


def rig(vehicle: VehicleConfig = BRIDGE) -> InProcessGcs:
    g = InProcessGcs(Emulator(vehicle, seed=5, record_sent=True))
    g.heartbeat()
    g.run(0.1)
    return g


def test_throttle_outputs_scale_full_demand_by_their_own_min_max_trim_and_reversal() -> None:
    g = rig()
    g.arm()
    full = {"ch1": 1500, "ch3": 2000}  # MANUAL: RC3 throttle full, RC1 steering centred
    g.run(0.1, each=lambda: g.override(**full))
    out = g.emu.servo_outputs
    assert (out[5], out[6]) == (1900, 1900)  # default 1100-1900: 80 % of a 1000-2000 range
    assert (out[1], out[3]) == (1500, 2000)  # the motors stay on their passthrough inputs
    g.emu.set_param("SERVO5_MAX", 2000)
    g.emu.set_param("SERVO6_REVERSED", 1)
    g.run(0.1, each=lambda: g.override(**full))
    assert (g.emu.servo_outputs[5], g.emu.servo_outputs[6]) == (2000, 1100)
    g.emu.set_param("SERVO5_TRIM", 1520)
    g.run(0.1, each=lambda: g.override(ch1=1500, ch3=1500))
    assert g.emu.servo_outputs[5] == 1520
    g.run(0.1, each=lambda: g.override(ch1=2000, ch3=1500))  # spin: left forward, right back
    assert g.emu.servo_outputs[5] > 1520 and g.emu.servo_outputs[6] > 1500  # right reversed: back reads high
    g.send(g.mav.command_long_encode(1, 1, P.MAV_CMD_REQUEST_MESSAGE, 0, SERVO_OUTPUT_RAW, 0, 0, 0, 0, 0, 0))
    raw = [m for m in g.run(0.01, each=lambda: g.override(ch1=2000, ch3=1500)) if m.get_type() == "SERVO_OUTPUT_RAW"]
    assert (raw[-1].servo5_raw, raw[-1].servo6_raw) == (g.emu.servo_outputs[5], g.emu.servo_outputs[6])


def test_disarmed_and_hold_put_throttle_outputs_at_trim() -> None:
    g = rig()
    g.run(0.1, each=lambda: g.override(ch1=1500, ch3=2000))
    assert g.emu.servo_outputs[5] == g.emu.servo_outputs[6] == 1500  # disarmed
    g.arm()
    g.set_mode(MODE_HOLD)
    g.run(0.1, each=lambda: g.override(ch1=1500, ch3=2000))
    assert g.emu.servo_outputs[5] == g.emu.servo_outputs[6] == 1500
    assert g.emu.servo_outputs[3] == 2000  # passthrough ignores the mode


def test_servo_output_raw_is_1_hz_until_asked_and_40_hz_is_the_fastest_at_loop_rate_50() -> None:
    g = rig()
    g.run(5.0)
    assert 4 <= len(g.of("SERVO_OUTPUT_RAW")) <= 6
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 20_000) == P.MAV_RESULT_DENIED
    assert "Requested rate for message ID 36 too fast. Increase SCHED_LOOP_RATE" in g.texts()
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 24_999) == P.MAV_RESULT_DENIED  # 24 ms
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 25_000, 1) == P.MAV_RESULT_DENIED  # param3
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, -2) == P.MAV_RESULT_DENIED
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 25_000) == P.MAV_RESULT_ACCEPTED
    before = len(g.of("SERVO_OUTPUT_RAW"))
    g.run(4.0, dt_s=0.005)
    assert 158 <= len(g.of("SERVO_OUTPUT_RAW")) - before <= 162
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 0) == P.MAV_RESULT_ACCEPTED  # default
    before = len(g.of("SERVO_OUTPUT_RAW"))
    g.run(4.0)
    assert 3 <= len(g.of("SERVO_OUTPUT_RAW")) - before <= 5


def test_a_stream_group_faster_than_0_8_of_the_loop_rate_is_capped_not_refused() -> None:
    # ArduPilot's set_ap_message_interval caps every interval, a group's too, at 0.8 x SCHED_LOOP_RATE
    # (GCS_Common.cpp cap_message_interval): EXTRA1 asked at 50 Hz streams at 40 Hz at loop rate 50.
    g = rig()
    g.send(g.mav.request_data_stream_encode(1, 1, P.MAV_DATA_STREAM_EXTRA1, 50, 1))
    g.run(1.0, dt_s=0.005)
    before = len(g.of("ATTITUDE"))
    g.run(4.0, dt_s=0.005)
    assert 158 <= len(g.of("ATTITUDE")) - before <= 162
    g.send(g.mav.request_data_stream_encode(1, 1, P.MAV_DATA_STREAM_EXTRA1, 25, 1))  # below the cap: as asked
    g.run(1.0, dt_s=0.005)
    before = len(g.of("ATTITUDE"))
    g.run(4.0, dt_s=0.005)
    assert 98 <= len(g.of("ATTITUDE")) - before <= 102


def test_intervals_reset_on_reboot_and_a_faster_loop_takes_effect_after_one() -> None:
    g = rig()
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 25_000) == P.MAV_RESULT_ACCEPTED
    g.emu.set_param("SCHED_LOOP_RATE", 100)
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 20_000) == P.MAV_RESULT_DENIED  # not yet
    assert g.command(P.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == P.MAV_RESULT_ACCEPTED
    g.run(2.0)
    before = len(g.of("SERVO_OUTPUT_RAW"))
    g.run(4.0)
    assert 3 <= len(g.of("SERVO_OUTPUT_RAW")) - before <= 5  # the 40 Hz interval did not survive
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 20_000) == P.MAV_RESULT_ACCEPTED
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, SERVO_OUTPUT_RAW, 12_000) == P.MAV_RESULT_DENIED


def test_home_is_set_at_the_first_fix_follows_the_rover_while_disarmed_and_is_sent_on_request() -> None:
    g = rig()
    assert any(t.startswith("Set HOME to -35.363261 149.165230") for t in g.texts())
    assert g.of("HOME_POSITION")  # sent when set
    g.emu.teleport(0.3, 0.0)
    g.run(0.1)
    assert g.command(P.MAV_CMD_GET_HOME_POSITION) == P.MAV_RESULT_ACCEPTED
    assert abs(g.of("HOME_POSITION")[-1].x) < 1e-6  # moved less than 0.5 m: home stays
    g.emu.teleport(2.0, 1.0)
    g.run(0.1)
    home = g.of("HOME_POSITION")[-1]
    assert (home.x, home.y) == (2.0, 1.0)
    g.arm()
    g.emu.teleport(5.0, 5.0)
    g.run(0.1)
    g.send(g.mav.command_long_encode(1, 1, P.MAV_CMD_REQUEST_MESSAGE, 0, P.MAVLINK_MSG_ID_HOME_POSITION,
                                     0, 0, 0, 0, 0, 0))
    g.run(0.05)
    assert (g.of("HOME_POSITION")[-1].x, g.of("HOME_POSITION")[-1].y) == (2.0, 1.0)  # armed: home holds
    assert g.texts().count("Set HOME to -35.363261 149.165230 at 584.00m") == 1


@given(st.floats(-1500, 1500), st.integers(800, 1400), st.integers(1600, 2200), st.integers(1450, 1550))
def test_pwm_from_angle_is_monotonic_bounded_and_trim_at_zero(value: float, lo: int, hi: int, trim: int) -> None:
    pwm = pwm_from_angle(value, lo, hi, trim, False)
    assert lo <= pwm <= hi
    assert pwm_from_angle(0.0, lo, hi, trim, False) == trim
    assert pwm_from_angle(value + 1.0, lo, hi, trim, False) >= pwm
    assert pwm_from_angle(-value, lo, hi, trim, True) == pwm  # reversed mirrors the value


@given(st.floats(-150, 150), st.floats(-6000, 6000), st.floats(0.0, 1.0))
def test_skid_mixer_stays_in_range_and_keeps_the_turn_direction(throttle: float, steering: float, mix: float) -> None:
    params = {"MOT_THR_MAX": 100.0, "MOT_SLEWRATE": 0.0, "MOT_STR_THR_MIX": mix}
    motors = SkidMotors(params.__getitem__)
    motors.set_throttle(throttle, armed=True)
    motors.set_steering(steering)
    left, right = motors.output(True, 0.02)
    assert -1.0 - 1e-9 <= left <= 1.0 + 1e-9 and -1.0 - 1e-9 <= right <= 1.0 + 1e-9
    if steering > 1.0:  # never turns the other way (MOT_STR_THR_MIX < 0.5 may drop the turn at full throttle)
        assert left >= right
    elif steering < -1.0:
        assert left <= right
    assert motors.output(False, 0.02) == (0.0, 0.0)


@settings(max_examples=200)
@given(st.floats(0.1, 50.0), st.floats(0.2, 5.0), st.floats(0.2, 3.0), st.floats(0.2, 3.0), st.floats(0.0, 5.0),
       st.floats(0.0, 5.0))
def test_leg_profile_ends_at_the_end_never_speeds_past_the_limit_and_never_goes_back(
        length: float, speed_max: float, accel: float, jerk: float, start: float, end: float) -> None:
    leg = LegProfile(length, speed_max, accel, jerk, min(start, speed_max), end)
    s_end, v_end, _ = leg.at(leg.duration_s)
    assert s_end == length and v_end == leg.end_m_s <= end + 1e-9
    last = 0.0
    steps = 200
    for i in range(steps + 1):
        s, v, a = leg.at(leg.duration_s * i / steps)
        assert s >= last - 1e-9 and 0.0 <= s <= length + 1e-9
        assert -1e-9 <= v <= max(speed_max, start) + 1e-9 and abs(a) <= accel + 1e-9
        last = s
    assert math.isfinite(leg.duration_s)
