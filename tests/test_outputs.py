"""Wheel speed -> PWM -> RC_CHANNELS_OVERRIDE / DO_SET_SERVO, with hand-computed values.

RC_CHANNELS_OVERRIDE (common.xml): ch1-8 65535 = leave alone, 0 = release; ch9-18 0 or 65535 =
leave alone, 65534 = release.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from rover_bridge.command.outputs import OutputMap, WheelPwm
from rover_bridge.kinematics import WheelSpeeds
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.params import Profile

MAX = 20.0  # rad/s at full PWM, a round number for hand computation


def omap(**kw: object) -> OutputMap:
    args: dict[str, object] = {"mode": "rc_override", "left_channel": 1, "right_channel": 3, "pwm_min": 1000,
                               "pwm_trim": 1500, "pwm_max": 2000, "max_wheel_rad_s": MAX}
    args.update(kw)
    return OutputMap(**args)  # type: ignore[arg-type]


def channels(msg: MAVLinkMessage) -> list[int]:
    return [int(getattr(msg, f"chan{i}_raw")) for i in range(1, 19)]


@pytest.mark.parametrize(("rad_s", "pwm"), [
    (0.0, 1500), (20.0, 2000), (-20.0, 1000), (10.0, 1750), (-5.0, 1375), (1.0, 1525),
    (40.0, 2000), (-1e9, 1000),  # beyond full scale: clamped
])
def test_linear_map_with_clamp(rad_s: float, pwm: int) -> None:
    assert omap().wheel_pwm_us(rad_s, False) == pwm


def test_reversed_wheel_mirrors_around_trim() -> None:
    assert omap().wheel_pwm_us(10.0, True) == 1250
    assert omap().wheel_pwm_us(-5.0, True) == 1625


def test_off_centre_trim_uses_each_half_span() -> None:
    m = omap(pwm_min=1100, pwm_trim=1520, pwm_max=1900)
    assert m.wheel_pwm_us(10.0, False) == 1710  # 1520 + 0.5 * 380
    assert m.wheel_pwm_us(-10.0, False) == 1310  # 1520 - 0.5 * 420
    assert m.wheel_pwm_us(0.0, False) == 1520


def test_to_pwm_applies_each_wheels_reversal() -> None:
    m = omap(right_reversed=True)
    assert m.to_pwm(WheelSpeeds(10.0, 10.0)) == WheelPwm(1750, 1250)
    assert m.neutral == WheelPwm(1500, 1500)


def test_non_finite_wheel_speed_is_a_programming_error() -> None:
    with pytest.raises(ValueError):
        omap().wheel_pwm_us(math.nan, False)


@given(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6), st.booleans())
def test_pwm_always_in_range_and_monotone_sign(rad_s: float, rev: bool) -> None:
    pwm = omap().wheel_pwm_us(rad_s, rev)
    assert 1000 <= pwm <= 2000
    forward = rad_s > 0 if not rev else rad_s < 0
    if pwm != 1500:
        assert (pwm > 1500) == forward


def test_rc_override_ch1_8_exact() -> None:
    (msg,) = omap().command(WheelPwm(1600, 1400), 1, 1)
    assert msg.get_type() == "RC_CHANNELS_OVERRIDE"
    assert (msg.target_system, msg.target_component) == (1, 1)
    assert channels(msg) == [1600, 65535, 1400, 65535, 65535, 65535, 65535, 65535] + [0] * 10


def test_rc_override_ch9_18_exact() -> None:
    (msg,) = omap(left_channel=9, right_channel=12).command(WheelPwm(1600, 1400), 7, 1)
    assert channels(msg) == [65535] * 8 + [1600, 0, 0, 1400, 0, 0, 0, 0, 0, 0]
    assert msg.target_system == 7


def test_release_ch1_8_and_ch9_18_exact() -> None:
    (low,) = omap(left_channel=2, right_channel=4).release(1, 1)
    assert channels(low) == [65535, 0, 65535, 0, 65535, 65535, 65535, 65535] + [0] * 10
    (mixed,) = omap(left_channel=2, right_channel=10).release(1, 1)
    assert channels(mixed) == [65535, 0] + [65535] * 6 + [0, 65534] + [0] * 8


def test_override_survives_mavlink2_packing() -> None:
    (msg,) = omap(left_channel=16, right_channel=1).command(WheelPwm(1234, 1876), 1, 1)
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=191)
    back = mav.decode(bytearray(msg.pack(mav)))
    assert channels(back) == [1876] + [65535] * 7 + [0] * 7 + [1234, 0, 0]


def test_servo_mode_sends_one_do_set_servo_per_wheel() -> None:
    left, right = omap(mode="servo", left_channel=1, right_channel=3).command(WheelPwm(1600, 1400), 1, 1)
    for msg, servo, pwm in ((left, 1.0, 1600.0), (right, 3.0, 1400.0)):
        assert msg.get_type() == "COMMAND_LONG"
        assert msg.command == mavlink.MAV_CMD_DO_SET_SERVO == 183
        assert (msg.target_system, msg.target_component, msg.confirmation) == (1, 1, 0)
        assert (msg.param1, msg.param2) == (servo, pwm)
        assert (msg.param3, msg.param4, msg.param5, msg.param6, msg.param7) == (0.0,) * 5


def test_servo_mode_release_is_trim() -> None:
    msgs = omap(mode="servo").release(1, 1)
    assert [(m.param1, m.param2) for m in msgs] == [(1.0, 1500.0), (3.0, 1500.0)]


def test_from_profile_uses_max_wheel_rpm() -> None:
    m = OutputMap.from_profile(Profile())
    assert m.max_wheel_rad_s == pytest.approx(200 * 2 * math.pi / 60)
    assert (m.left_channel, m.right_channel, m.pwm_trim, m.mode) == (1, 3, 1500, "rc_override")


@pytest.mark.parametrize("kw", [{"mode": "pwm"}, {"pwm_trim": 2000}, {"right_channel": 1},
                                {"left_channel": 19}, {"max_wheel_rad_s": 0.0}])
def test_invalid_maps_are_refused(kw: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        omap(**kw)
