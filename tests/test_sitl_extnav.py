"""The emulator's model of ArduPilot navigating on the companion's ODOMETRY (sitl/extnav.py)."""

from __future__ import annotations

import math

import pytest

from sitl import Emulator, VehicleConfig
from sitl.extnav import POS_ERR_MAX_M, ExtNavConsumer, folded_errors
from sitl.mav import mavlink


def odometry(x: float, y: float, yaw_cw: float = 0.0, vx: float = 0.0, var: float = 1e-4, unobserved: float = 0.01,
             reset_counter: int = 0, frame: int = 20, child: int = 12) -> mavlink.MAVLink_odometry_message:
    cov = [0.0] * 21
    cov[0] = cov[6] = var
    cov[11] = cov[15] = cov[18] = unobserved
    cov[20] = var
    q = [math.cos(yaw_cw / 2), 0.0, 0.0, math.sin(yaw_cw / 2)]
    return mavlink.MAVLink_odometry_message(0, frame, child, x, y, 0.0, q, vx, 0.0, 0.0, 0.0, 0.0, 0.0, cov,
                                            [0.0] * 21, reset_counter, 0, 100)


def feed(c: ExtNavConsumer, frames: list[mavlink.MAVLink_odometry_message], t0_us: int = 0,
         dt_us: int = 33_333) -> int:
    t = t0_us
    for msg in frames:
        c.predict(dt_us / 1e6, 0.0)
        c.odometry(msg, t, 0.0)
        c.update(t)
        t += dt_us
    return t


def test_only_local_frd_with_body_frd_is_taken() -> None:
    c = ExtNavConsumer()
    feed(c, [odometry(1, 2, frame=1), odometry(1, 2, child=8)])
    assert c.started_us is None and c.counters["dropped_frame"] == 2


def test_errors_are_folded_and_clamped_as_ardupilot_does() -> None:
    assert folded_errors(odometry(0, 0, var=0.01, unobserved=1e4).pose_covariance)[0] == pytest.approx(
        math.cbrt(2 * 0.01**2 + 1e8))
    c = ExtNavConsumer()
    feed(c, [odometry(0, 0, unobserved=1e4)])
    assert c.last_errors == (POS_ERR_MAX_M, 1.5)  # the old default: position and yaw effectively unweighted
    feed(c, [odometry(0, 0, unobserved=0.01)], t0_us=100_000)
    assert c.last_errors == (pytest.approx(0.2), pytest.approx(0.2))  # at the VISO_*_M_NSE floors


def test_uses_the_data_two_seconds_after_the_first_frame() -> None:
    c = ExtNavConsumer()
    t = feed(c, [odometry(0.0, 0.0)] * 50)
    assert c.position() is None and t < 2_000_000
    feed(c, [odometry(0.0, 0.0)] * 20, t0_us=t)
    assert c.position() == (pytest.approx(0.0), pytest.approx(0.0))


def test_a_jump_is_rejected_a_reset_counter_change_is_taken_and_rejections_end_after_10_s() -> None:
    c = ExtNavConsumer()
    t = feed(c, [odometry(5.0, 5.0)] * 100)
    t = feed(c, [odometry(0.0, 0.0)] * 30, t0_us=t)  # a new frame, same reset_counter
    assert c.position() == (pytest.approx(5.0, abs=0.01), pytest.approx(5.0, abs=0.01))
    assert c.counters["pos_rejected"] == 30
    t = feed(c, [odometry(0.0, 0.0)] * 300, t0_us=t)  # still rejected ... then, after 10 s, snapped
    assert c.counters["pos_timeout_resets"] == 1 and c.position() == (pytest.approx(0.0), pytest.approx(0.0))
    feed(c, [odometry(3.0, -1.0, reset_counter=1)], t0_us=t)
    assert c.position() == (3.0, -1.0) and c.counters["pos_resets"] == 1


def test_velocity_is_rotated_by_the_frames_own_quaternion() -> None:
    c = ExtNavConsumer()
    t = feed(c, [odometry(0.0, 0.0, yaw_cw=math.pi / 2, vx=1.0)] * 80)  # facing east at 1 m/s, frame says (0, 0)
    assert c.vel_e_m_s == pytest.approx(1.0, abs=0.01) and abs(c.vel_n_m_s) < 0.01
    assert c.position() is not None and t > 2_000_000


def test_the_emulator_sends_its_extnav_position_and_heading_and_none_before() -> None:
    emu = Emulator(VehicleConfig(external_nav=True, start_armed=True, rate_position_hz=10.0, rate_extra1_hz=10.0),
                   record_sent=True)
    emu.step(1.0)
    assert emu.sent_log is not None
    assert not [m for _, m in emu.sent_log if m.get_type() == "LOCAL_POSITION_NED"]  # no position yet
    for _ in range(90):  # 3 s of ODOMETRY at 30 Hz, the rover said to be at (2, 3) facing 60 deg
        emu.handle_message(odometry(2.0, 3.0, yaw_cw=math.radians(60)), src_system=1, src_component=191)
        emu.step(1 / 30)
    sent = emu.sent_log
    local = [m for _, m in sent if m.get_type() == "LOCAL_POSITION_NED"]
    assert local and (local[-1].x, local[-1].y) == (pytest.approx(2.0, abs=0.01), pytest.approx(3.0, abs=0.01))
    att = [m for _, m in sent if m.get_type() == "ATTITUDE"]
    assert att[-1].yaw == pytest.approx(math.radians(60), abs=0.02)
    assert "EKF3 IMU0 is using external nav data" in emu.statustexts_sent
