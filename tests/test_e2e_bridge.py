"""End to end over UDP loopback: scripted GCS -> bridge (real shell + core) -> sitl emulator.

Lockstep tests share one simulated clock (deterministic, faster than real time); the SIGTERM
test runs the real `rover-bridge run` process against the emulator in wall-clock time.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from lockstep import GCS_COMPID, GCS_SYSID, Lockstep, circle_fit_radius, free_udp_port, step_wall

from rover_bridge.mavlink.dialect import mavlink, mavutil
from rover_bridge.params import Profile
from sitl import Emulator, VehicleConfig

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def rig() -> Any:
    ls = Lockstep(Profile(), VehicleConfig(), seed=3)
    ls.run_for(1.0)  # heartbeats exchanged, vehicle sysid learned, streams requested
    yield ls
    ls.close()


def test_body_ned_right_turn_drives_a_clockwise_circle_of_the_requested_radius(rig: Lockstep) -> None:
    # vx 0.5 m/s with yaw_rate +0.3 rad/s (MAVLink: clockwise) -> radius 0.5 / 0.3 = 1.667 m, turning right.
    start_yaw = rig.emu.truth.yaw_rad
    points: list[tuple[float, float]] = []
    for i in range(100):
        rig.send_body_velocity(0.5, 0.3)
        if i % 10 == 0:
            rig.gcs_heartbeat()
        for _ in range(10):
            rig.step()
        if i >= 10:  # after the limiter's ramp-up
            points.append((rig.emu.truth.x_m, rig.emu.truth.y_m))
    radius = circle_fit_radius(points)
    assert radius == pytest.approx(0.5 / 0.3, rel=0.05)
    # Clockwise seen from above: yaw (clockwise from north) has grown by about 0.3 rad/s * ~10 s.
    turned = rig.emu.truth.yaw_rad - start_yaw
    assert math.remainder(turned, 2 * math.pi) == pytest.approx(math.remainder(3.0 - 0.15, 2 * math.pi), abs=0.35)
    # The first steps of a right turn from heading north go east (y east > 0).
    assert points[5][1] > 0.0


def test_local_ned_velocity_east_turns_the_rover_to_east(rig: Lockstep) -> None:
    assert abs(rig.emu.truth.yaw_rad) < 0.05  # starts facing north
    rig.run_for(8.0, send=lambda: rig.send_local_ned_velocity(0.0, 0.4))
    assert math.degrees(rig.emu.truth.yaw_rad) == pytest.approx(90.0, abs=8.0)
    assert rig.emu.truth.v_m_s == pytest.approx(0.4, abs=0.06)
    assert rig.emu.truth.y_m > 1.5  # it went east


def test_stopping_the_requests_stops_the_wheels_within_timeout_plus_braking(rig: Lockstep) -> None:
    profile = rig.core.profile
    rig.run_for(3.0, send=lambda: rig.send_body_velocity(0.6, 0.0))
    assert rig.emu.truth.v_m_s == pytest.approx(0.6, abs=0.05)
    # No more requests: timeout, then braking through the limiter, plus the motors' own lag.
    budget_s = (profile.command.setpoint_timeout_s + 0.6 / profile.limits.max_linear_decel_m_s2
                + 1.0 / profile.command.rate_hz + 0.5)
    rig.run_for(budget_s)
    assert abs(rig.emu.truth.v_m_s) < 0.01
    assert rig.emu.truth.left_wheel_rad_s == pytest.approx(0.0, abs=0.2)
    trim = profile.output.pwm_trim
    assert rig.emu.servo_outputs[profile.output.left_channel] == trim
    assert rig.emu.servo_outputs[profile.output.right_channel] == trim


def test_nothing_moves_before_the_first_request_and_overrides_come_from_the_gcs_sysid(rig: Lockstep) -> None:
    rig.run_for(2.0)
    assert abs(rig.emu.truth.v_m_s) < 1e-6
    assert rig.emu.counters.get("override_rejected_sysid", 0) == 0
    rig.run_for(1.0, send=lambda: rig.send_body_velocity(0.3, 0.0))
    assert rig.emu.counters.get("override_accepted", 0) > 0
    assert rig.emu.truth.v_m_s > 0.1


def test_gcs_sees_the_vehicle_through_the_bridge(rig: Lockstep) -> None:
    rig.run_for(2.0)
    vehicle_beats = [m for _, m in rig.view.of("HEARTBEAT") if m.get_srcSystem() == 1 and m.get_srcComponent() == 1]
    bridge_beats = [m for _, m in rig.view.of("HEARTBEAT") if m.get_srcComponent() == 191]
    assert vehicle_beats and vehicle_beats[-1].type == mavlink.MAV_TYPE_GROUND_ROVER
    assert bridge_beats and bridge_beats[-1].type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert bridge_beats[-1].autopilot == mavlink.MAV_AUTOPILOT_INVALID


def test_autopilot_over_tcp_drives_and_estimates_like_udp() -> None:
    """ArduPilot SITL serves TCP: a stream, so frames arrive split across reads and several per read."""
    ls = Lockstep(Profile(), VehicleConfig(), seed=3, autopilot_tcp=True)
    try:
        ls.run_for(1.0)
        ls.run_for(4.0, every_s=0.1, send=lambda: ls.send_body_velocity(0.5, 0.0))
        assert ls.emu.truth.x_m > 1.0  # driven north by the overrides
        odometry = [m for _, m in ls.view.of("ODOMETRY")]
        assert len(odometry) > 50
        # The estimate follows the truth (x forward = north here), and the telemetry got through.
        assert odometry[-1].x == pytest.approx(ls.emu.truth.x_m, abs=0.15)
        assert ls.view.of("WHEEL_DISTANCE") and ls.view.of("HEARTBEAT")
        assert ls.autopilot.rx_bad == 0
    finally:
        ls.close()


def _drive_emulator(emu: Emulator, seconds: float, gcs: Any = None, request: bool = False) -> None:
    """Step the emulator in wall-clock time, the GCS sending a forward request at 10 Hz."""
    end = time.monotonic() + seconds
    last = time.monotonic()
    next_req = 0.0
    while (now := time.monotonic()) < end:
        if gcs is not None and request and now >= next_req:
            gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            gcs.mav.set_position_target_local_ned_send(0, 1, 1, 8, 0b0101_1100_0111, 0, 0, 0, 0.5, 0, 0, 0, 0, 0,
                                                       0, 0.0)
            next_req = now + 0.1
        step_wall(emu, now - last)
        last = now
        if gcs is not None:
            while gcs.recv_msg() is not None:
                pass
        time.sleep(0.005)


def test_sigterm_during_motion_releases_the_overrides(tmp_path: Path) -> None:
    ap_port, gcs_port = free_udp_port(), free_udp_port()
    emu = Emulator(VehicleConfig(start_armed=True), seed=5)
    emu.open(f"udpin:127.0.0.1:{ap_port}")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "run", "--params", str(REPO / "params" / "default.toml"),
         "--autopilot", f"udpout:127.0.0.1:{ap_port}", "--gcs", f"udpin:127.0.0.1:{gcs_port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    gcs: Any = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=GCS_SYSID,
                                          source_component=GCS_COMPID, dialect="ardupilotmega")
    try:
        # Wait (bounded) until the bridge is up and has forwarded the vehicle's heartbeat: start-up
        # takes seconds on a loaded machine, and the bridge sends nothing before it knows the vehicle.
        deadline = time.monotonic() + 30.0
        seen = set()
        last = time.monotonic()
        while {"bridge", "vehicle"} - seen:
            assert time.monotonic() < deadline, f"bridge not up: {seen}"
            gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            now = time.monotonic()
            step_wall(emu, now - last)
            last = now
            while (m := gcs.recv_msg()) is not None:
                if m.get_type() == "HEARTBEAT":
                    seen.add("bridge" if m.get_srcComponent() == 191 else "vehicle")
            time.sleep(0.01)
        _drive_emulator(emu, 3.0, gcs, request=True)
        now_us = emu.sim_time_us
        assert emu.autopilot.has_override(1, now_us) and emu.autopilot.has_override(3, now_us)
        assert emu.truth.v_m_s > 0.3  # moving
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=5.0)
        _drive_emulator(emu, 0.3)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert code == 0, out
        now_us = emu.sim_time_us
        # Released at once (0 on ch1-8), not left to the 3 s override timeout.
        assert not emu.autopilot.has_override(1, now_us)
        assert not emu.autopilot.has_override(3, now_us)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        gcs.close()
        emu.close()


def test_a_ground_station_switching_to_hold_stops_the_rover_until_a_fresh_request(rig: Lockstep) -> None:
    # Per-wheel RC passthrough ignores the autopilot's mode: without the bridge's stop modes the
    # wheels would keep turning in HOLD. The GCS's Hold button sends DO_SET_MODE (HOLD = 4).
    rig.run_for(2.0, send=lambda: rig.send_body_velocity(0.5, 0.0))
    assert rig.emu.truth.v_m_s > 0.45
    rig.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                  mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 0, 0, 0, 0, 0)
    speeds = []
    for _ in range(200):  # 2 s, the planner still streaming its request
        if len(speeds) % 10 == 0:
            rig.send_body_velocity(0.5, 0.0)
        rig.step()
        speeds.append(rig.emu.truth.v_m_s)
    assert rig.emu.mode == 4
    assert rig.core.command.state.value == "hold"
    assert speeds[-1] < 0.01 and rig.emu.servo_outputs[1] == 1500  # stopped, and held at neutral
    # At once (the bridge saw the GCS's request pass, it does not wait for the next 1 Hz heartbeat) and
    # braked, not cut: 0.5 m/s at 2 m/s^2 is 0.25 s, plus the motors' lag.
    stopped_s = next(i for i, v in enumerate(speeds) if v < 0.02) * rig.dt_s
    assert 0.2 < stopped_s < 0.7, stopped_s
    assert any("HOLD" in m.text for _, m in rig.view.of("STATUSTEXT"))
    # Back to GUIDED: the old request does not resume by itself ...
    rig.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                  mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15, 0, 0, 0, 0, 0)
    rig.run_for(1.5)
    assert rig.emu.mode == 15 and abs(rig.emu.truth.v_m_s) < 0.01
    # ... a fresh one drives.
    rig.run_for(1.5, send=lambda: rig.send_body_velocity(0.5, 0.0))
    assert rig.emu.truth.v_m_s > 0.45
