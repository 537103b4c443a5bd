"""Setpoint decoding: frames, type masks, signs, non-finite values, MANUAL_CONTROL.

Expected values are worked out from the MAVLink spec (POSITION_TARGET_TYPEMASK: a set bit
means "ignore this field"; yaw and yaw_rate clockwise positive) and our convention (omega
counter-clockwise positive), never read back from the code.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rover_bridge.command.setpoints import (
    BodyVelocity,
    HeadingVelocity,
    Rejected,
    decode_manual_control,
    decode_position_target,
    decode_request,
)
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.params import CommandParams

# Type masks computed by hand from the bit values x=1 y=2 z=4 vx=8 vy=16 vz=32 ax=64 ay=128 az=256
# force=512 yaw=1024 yaw_rate=2048.
IGNORE_POS = 1 + 2 + 4
IGNORE_VEL = 8 + 16 + 32
IGNORE_ACC = 64 + 128 + 256
VEL_YAW_RATE = IGNORE_POS + IGNORE_ACC + 1024  # 1479
VEL_YAW = IGNORE_POS + IGNORE_ACC + 2048  # 2503
VEL_ONLY = IGNORE_POS + IGNORE_ACC + 1024 + 2048  # 3527
MAVPROXY_VELOCITY = 4039  # MAVProxy's `velocity` command
POSITION_ONLY = IGNORE_VEL + IGNORE_ACC + 1024 + 2048  # 3576
POSITION_AND_VEL = IGNORE_ACC + 1024 + 2048  # 3520
ACCEL_ONLY = IGNORE_POS + IGNORE_VEL + 1024 + 2048  # 3135
VEL_AND_ACCEL = IGNORE_POS + 1024 + 2048  # 3079
YAW_ONLY = IGNORE_POS + IGNORE_VEL + IGNORE_ACC + 2048  # 2559
YAW_RATE_ONLY = IGNORE_POS + IGNORE_VEL + IGNORE_ACC + 1024  # 1535
VEL_YAW_AND_RATE = IGNORE_POS + IGNORE_ACC  # 455
NOTHING_USED = 4095


def test_hand_computed_masks_match_the_spec_numbers() -> None:
    assert (VEL_YAW_RATE, VEL_YAW, VEL_ONLY, POSITION_ONLY, ACCEL_ONLY) == (1479, 2503, 3527, 3576, 3135)
    # 4039 = velocity only plus FORCE_SET (bit 9): position, acceleration, yaw and yaw rate ignored.
    assert MAVPROXY_VELOCITY == VEL_ONLY + mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET


def local(frame: int, mask: int, *, x: float = 0.0, y: float = 0.0, vx: float = 0.0, vy: float = 0.0,
          vz: float = 0.0, afx: float = 0.0, yaw: float = 0.0, yaw_rate: float = 0.0) -> MAVLinkMessage:
    return mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, frame, mask, x, y, 0.0, vx, vy, vz, afx, 0.0, 0.0, yaw, yaw_rate)


def global_int(frame: int, mask: int, *, vx: float = 0.0, vy: float = 0.0, yaw: float = 0.0,
               yaw_rate: float = 0.0) -> MAVLinkMessage:
    return mavlink.MAVLink_set_position_target_global_int_message(
        0, 1, 1, frame, mask, 0, 0, 0.0, vx, vy, 0.0, 0.0, 0.0, 0.0, yaw, yaw_rate)


def manual(x: int, r: int) -> MAVLinkMessage:
    return mavlink.MAVLink_manual_control_message(1, x, 0, 500, r, 0)


CMD = CommandParams(manual_linear_scale_m_s=0.5, manual_angular_scale_rad_s=1.5)


# ------------------------------------------------------------------ body frames


@pytest.mark.parametrize("frame", [8, 9, 12])
def test_body_frames_vx_forward_and_positive_yaw_rate_is_a_right_turn(frame: int) -> None:
    # MAVLink yaw_rate +0.3 (clockwise, right turn) is omega -0.3 counter-clockwise.
    assert decode_position_target(local(frame, VEL_YAW_RATE, vx=0.5, yaw_rate=0.3)) == BodyVelocity(0.5, -0.3)


def test_body_negative_vx_drives_backwards() -> None:
    assert decode_position_target(local(8, VEL_YAW_RATE, vx=-0.4, yaw_rate=-0.2)) == BodyVelocity(-0.4, 0.2)


def test_body_lateral_velocity_is_ignored_and_noted() -> None:
    got = decode_position_target(local(12, VEL_ONLY, vx=0.3, vy=0.7))
    assert got == BodyVelocity(0.3, 0.0, frozenset({"lateral_ignored"}))


def test_mavproxy_velocity_command_is_a_body_velocity_without_turn() -> None:
    assert decode_position_target(local(8, MAVPROXY_VELOCITY, vx=0.5)) == BodyVelocity(0.5, 0.0)


def test_force_set_bit_is_tolerated_with_yaw_rate() -> None:
    got = decode_position_target(local(8, VEL_YAW_RATE | 512, vx=0.2, yaw_rate=0.1))
    assert got == BodyVelocity(0.2, -0.1)


def test_body_yaw_target_is_relative_to_the_current_heading() -> None:
    got = decode_position_target(local(8, VEL_YAW, vx=0.2, yaw=0.5))
    assert got == HeadingVelocity(0.2, 0.5, relative=True)
    assert isinstance(got, HeadingVelocity)
    # facing 3.0 rad, turn 0.5 rad to the right: 3.5 rad, i.e. 3.5 - 2 pi = -2.7831853...
    assert got.absolute(3.0).heading_cw_rad == pytest.approx(3.5 - 2 * math.pi, abs=1e-12)
    assert got.absolute(3.0).relative is False


def test_yaw_rate_alone_spins_in_place() -> None:
    assert decode_position_target(local(8, YAW_RATE_ONLY, vx=9.0, yaw_rate=1.0)) == BodyVelocity(0.0, -1.0)


# ------------------------------------------------------------------ earth frames


@pytest.mark.parametrize("frame", [1, 7])
def test_local_earth_velocity_is_speed_and_heading(frame: int) -> None:
    got = decode_position_target(local(frame, VEL_ONLY, vx=0.0, vy=0.5))  # due east
    assert isinstance(got, HeadingVelocity)
    assert got.speed_m_s == pytest.approx(0.5)
    assert got.heading_cw_rad == pytest.approx(math.pi / 2)
    assert got.relative is False


@pytest.mark.parametrize("frame", [0, 3, 5, 6, 10, 11])
def test_global_frames_are_earth_frames(frame: int) -> None:
    got = decode_position_target(global_int(frame, VEL_ONLY, vx=-0.3, vy=-0.4))  # south-west, 0.5 m/s
    assert isinstance(got, HeadingVelocity)
    assert got.speed_m_s == pytest.approx(0.5)
    assert got.heading_cw_rad == pytest.approx(math.atan2(-0.4, -0.3))


def test_earth_velocity_behind_is_a_heading_not_a_reverse() -> None:
    got = decode_position_target(local(1, VEL_ONLY, vx=-0.5))  # due south
    assert isinstance(got, HeadingVelocity)
    assert got.speed_m_s == pytest.approx(0.5)  # never negative in an earth frame
    assert abs(got.heading_cw_rad) == pytest.approx(math.pi)


def test_earth_velocity_with_yaw_target_turns_to_the_yaw() -> None:
    got = decode_position_target(local(1, VEL_YAW, vx=0.3, vy=0.4, yaw=-1.0))
    assert got == HeadingVelocity(pytest.approx(0.5), -1.0)  # type: ignore[arg-type]


def test_earth_velocity_with_yaw_rate_uses_the_rate() -> None:
    got = decode_position_target(local(7, VEL_YAW_RATE, vx=0.3, vy=0.4, yaw_rate=0.25))
    assert got == BodyVelocity(pytest.approx(0.5), -0.25)  # type: ignore[arg-type]


def test_earth_yaw_only_turns_in_place() -> None:
    assert decode_position_target(local(1, YAW_ONLY, yaw=2.0)) == HeadingVelocity(0.0, 2.0)


def test_earth_zero_velocity_is_a_stop() -> None:
    assert decode_position_target(local(1, VEL_ONLY)) == BodyVelocity(0.0, 0.0)


def test_yaw_and_yaw_rate_together_yaw_wins_and_is_noted() -> None:
    got = decode_position_target(local(1, VEL_YAW_AND_RATE, vx=0.5, yaw=1.0, yaw_rate=0.5))
    assert got == HeadingVelocity(0.5, 1.0, notes=frozenset({"yaw_rate_ignored"}))


@pytest.mark.parametrize(("msg", "reason"), [
    (local(6, VEL_ONLY, vx=1.0), "unsupported_frame"),  # a global frame in the LOCAL_NED message
    (local(20, VEL_ONLY, vx=1.0), "unsupported_frame"),  # LOCAL_FRD
    (local(21, VEL_ONLY, vx=1.0), "unsupported_frame"),  # LOCAL_FLU
    (global_int(1, VEL_ONLY, vx=1.0), "unsupported_frame"),  # a local frame in the GLOBAL_INT message
    (global_int(8, VEL_ONLY, vx=1.0), "unsupported_frame"),
])
def test_unsupported_frames(msg: MAVLinkMessage, reason: str) -> None:
    assert decode_position_target(msg) == Rejected(reason)


# ------------------------------------------------------------------ masks


@pytest.mark.parametrize(("mask", "reason"), [
    (POSITION_ONLY, "position_only"),
    (POSITION_AND_VEL, "position_with_velocity"),
    (ACCEL_ONLY, "acceleration_only"),
    (NOTHING_USED, "no_velocity"),
    (NOTHING_USED - 32, "no_velocity"),  # only vz: nothing a rover can drive
])
def test_unsupported_masks_are_rejected(mask: int, reason: str) -> None:
    assert decode_position_target(local(8, mask, x=1.0, y=2.0, vx=0.5, afx=1.0)) == Rejected(reason)
    assert decode_position_target(local(1, mask, x=1.0, y=2.0, vx=0.5, afx=1.0)) == Rejected(reason)


def test_acceleration_with_velocity_is_followed_without_the_acceleration() -> None:
    got = decode_position_target(local(8, VEL_AND_ACCEL, vx=0.5, afx=3.0))
    assert got == BodyVelocity(0.5, 0.0, frozenset({"acceleration_ignored"}))


# ------------------------------------------------------------------ non-finite values


@pytest.mark.parametrize(("mask", "field"), [
    (VEL_YAW_RATE, "vx"), (VEL_YAW_RATE, "vy"), (VEL_YAW_RATE, "vz"), (VEL_YAW_RATE, "yaw_rate"),
    (VEL_YAW, "yaw"), (POSITION_ONLY, "x"), (VEL_AND_ACCEL, "afx"),
])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_used_field_rejects_the_request(mask: int, field: str, bad: float) -> None:
    msg = local(8, mask, vx=0.5)
    setattr(msg, field, bad)
    assert decode_position_target(msg) == Rejected("non_finite")


def test_non_finite_global_velocity_rejected() -> None:
    assert decode_position_target(global_int(5, VEL_ONLY, vx=math.nan)) == Rejected("non_finite")


def test_non_finite_ignored_field_is_not_inspected() -> None:
    # NaN marks "unset" for several senders; the mask says these fields carry nothing.
    msg = local(8, VEL_YAW_RATE, vx=0.5, yaw_rate=0.1)
    msg.x = msg.yaw = msg.afx = math.nan
    assert decode_position_target(msg) == BodyVelocity(0.5, -0.1)


def test_malformed_field_is_a_rejection_not_an_exception() -> None:
    msg = local(8, VEL_YAW_RATE, vx=0.5)
    msg.vx = "fast"
    assert decode_request(msg, CMD) == Rejected("malformed")


# ------------------------------------------------------------------ MANUAL_CONTROL


@pytest.mark.parametrize(("x", "r", "v", "omega"), [
    (1000, 0, 0.5, 0.0),
    (-1000, 0, -0.5, 0.0),
    (500, 1000, 0.25, -1.5),  # r > 0: right turn, clockwise
    (0, -400, 0.0, 0.6),
    (0x7FFF, 200, 0.0, -0.3),  # INT16_MAX: axis invalid, read as 0
    (1000, 0x7FFF, 0.5, 0.0),
])
def test_manual_control_scaling_and_sign(x: int, r: int, v: float, omega: float) -> None:
    got = decode_manual_control(manual(x, r), CMD)
    assert isinstance(got, BodyVelocity)
    assert got.v_m_s == pytest.approx(v)
    assert got.omega_rad_s == pytest.approx(omega)


@pytest.mark.parametrize(("x", "r", "reason"), [
    (1001, 0, "manual_out_of_range"), (0, -1001, "manual_out_of_range"), (-32768, 0, "manual_out_of_range"),
    (0x7FFF, 0x7FFF, "manual_no_axes"),
])
def test_manual_control_rejections(x: int, r: int, reason: str) -> None:
    assert decode_request(manual(x, r), CMD) == Rejected(reason)


# ------------------------------------------------------------------ heading controller


def test_heading_controller_turns_right_toward_a_heading_on_the_right() -> None:
    # target 45 deg right of north, facing north: error +pi/4 -> yaw rate cw 2 * pi/4, omega negative.
    twist = HeadingVelocity(0.5, math.pi / 4).twist(0.0, 2.0, 3.0)
    assert twist.omega_rad_s == pytest.approx(-math.pi / 2)
    assert twist.v_m_s == pytest.approx(0.5 * math.cos(math.pi / 4))


def test_heading_controller_rate_is_limited_and_facing_away_turns_in_place() -> None:
    twist = HeadingVelocity(0.5, -2.5).twist(0.5, 2.0, 1.0)  # target 3.0 rad to the left
    assert twist == Twist2D(0.0, 1.0)


def test_relative_heading_must_be_made_absolute_first() -> None:
    with pytest.raises(ValueError, match="absolute"):
        HeadingVelocity(0.1, 0.2, relative=True).twist(0.0, 1.0, 1.0)


finite = st.floats(min_value=-100.0, max_value=100.0, allow_nan=False)


@given(vx=finite, yaw_rate=finite, frame=st.sampled_from([8, 9, 12]))
def test_body_sign_convention_property(vx: float, yaw_rate: float, frame: int) -> None:
    assert decode_position_target(local(frame, VEL_YAW_RATE, vx=vx, yaw_rate=yaw_rate)) == BodyVelocity(
        vx, -yaw_rate)


@given(vn=finite, ve=finite)
def test_earth_speed_is_the_horizontal_magnitude_property(vn: float, ve: float) -> None:
    got = decode_position_target(local(1, VEL_ONLY, vx=vn, vy=ve))
    assert not isinstance(got, Rejected)
    speed = got.v_m_s if isinstance(got, BodyVelocity) else got.speed_m_s
    assert speed == pytest.approx(math.hypot(vn, ve))
    assert speed >= 0.0
