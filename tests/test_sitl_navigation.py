"""The emulator drives itself as Rover 4.7 does: AUTO over NAV_WAYPOINTs, RTL, SMART_RTL, HOLD, pivots,
NAV_CONTROLLER_OUTPUT, PID_TUNING, and the skid-steer demand that winds up when nobody forwards it.

Figures are bounded around the issue 29 anchor (a real Rover 4.7 SITL, rover-skid, three waypoints 10 m
apart, WP_SPEED 3: done in 28.6 s, closest 0.14-0.20 m, pivots at ~60 deg/s; RTL from 5 m within 3 m in
7 s, 0.32 m from home at the end); benchmarks/bench_sitl_anchor.py prints the full comparison.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import pytest

from sitl import Emulator, VehicleConfig, load_vehicle
from sitl.gcs import InProcessGcs
from sitl.mav import MAVLinkMessage, mavlink
from sitl.modes import MODE_AUTO, MODE_GUIDED, MODE_HOLD, MODE_MANUAL, MODE_RTL, MODE_SMART_RTL

P = mavlink
VEHICLES = Path(__file__).resolve().parents[1] / "sitl" / "vehicles"
ANCHOR = load_vehicle(VEHICLES / "ardupilot-skid-anchor.toml")
BRIDGE = load_vehicle(VEHICLES / "ardupilot-skid-bridge.toml")
SQUARE = [(10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]


def rig(vehicle: VehicleConfig = ANCHOR) -> InProcessGcs:
    g = InProcessGcs(Emulator(vehicle, seed=2, record_sent=True))
    g.heartbeat()
    g.run(0.2)
    assert g.arm() == P.MAV_RESULT_ACCEPTED
    return g


def mission(g: InProcessGcs, points: list[tuple[float, float]]) -> None:
    items = [g.waypoint(0, 0.0, 0.0)] + [g.waypoint(i + 1, n, e) for i, (n, e) in enumerate(points)]
    assert g.upload(items) == P.MAV_MISSION_ACCEPTED


def dist(g: InProcessGcs, north: float, east: float) -> float:
    return math.hypot(g.emu.truth.x_m - north, g.emu.truth.y_m - east)


def drive_out(g: InProcessGcs, north: float) -> None:
    """MANUAL, throttle stick up (RC3) until ``north`` metres out, then sticks centred until stopped."""
    g.set_mode(MODE_MANUAL)
    g.run_until(lambda: g.emu.truth.x_m >= north, 20.0, each=lambda: g.override(ch1=1500, ch3=1750))
    g.run_until(lambda: abs(g.emu.truth.v_m_s) < 0.01, 10.0, each=lambda: g.override(ch1=1500, ch3=1500))


def test_auto_reaches_every_item_in_order_and_completes_as_the_anchor_does() -> None:
    g = rig()
    mission(g, SQUARE)
    closest = [math.inf] * 3
    max_rate = 0.0

    def watch() -> None:
        nonlocal max_rate
        for i, (n, e) in enumerate(SQUARE):
            closest[i] = min(closest[i], dist(g, n, e))
        max_rate = max(max_rate, abs(g.emu.truth.yaw_rate_rad_s))

    assert g.set_mode(MODE_AUTO) == P.MAV_RESULT_ACCEPTED
    beat = g.of("HEARTBEAT")[-1]  # sent at once with the change
    assert beat.custom_mode == MODE_AUTO and beat.base_mode & P.MAV_MODE_FLAG_GUIDED_ENABLED
    start = g.emu.sim_time_s
    assert g.run_until(lambda: "Mission Complete" in g.texts(), 60.0, each=watch)
    elapsed = g.emu.sim_time_s - start
    reached = g.of("MISSION_ITEM_REACHED")
    assert [m.seq for m in reached] == [1, 2, 3]
    # The texts in the order a real Rover 4.7 SITL sends them for this mission.
    texts = g.texts()
    assert texts[texts.index("Throttle armed"):] == ["Throttle armed", "Flight plan received", "Mission: 1 WP",
                                                     "Reached waypoint #1", "Mission: 2 WP", "Reached waypoint #2",
                                                     "Mission: 3 WP", "Reached waypoint #3", "Mission Complete"]
    assert 25.0 <= elapsed <= 32.0, elapsed  # measured 28.6 s
    assert max(closest) <= 0.3, closest  # measured 0.14 / 0.17 / 0.20 m
    assert 50.0 <= math.degrees(max_rate) <= 70.0  # pivots at WP_PIVOT_RATE 60 deg/s
    g.run(3.0)
    assert g.emu.mode == MODE_AUTO and abs(g.emu.truth.v_m_s) < 0.01  # MIS_DONE_BEHAVE 0: stopped in AUTO
    current = g.of("MISSION_CURRENT")[-1]
    assert (current.seq, current.total, current.mission_state, current.mission_mode) == (3, 3, 5, 1)


def test_nav_controller_output_while_navigating_and_not_in_manual() -> None:
    g = rig()
    mission(g, [(12.0, 0.0)])
    g.emu.set_param("SR0_EXT_STAT", 10)
    g.run(1.0)
    assert g.of("NAV_CONTROLLER_OUTPUT") == []
    g.set_mode(MODE_AUTO)
    g.run(2.0)
    out = g.of("NAV_CONTROLLER_OUTPUT")[-1]
    assert out.target_bearing in (0, 359)
    assert 0 < out.wp_dist <= 12 and abs(out.xtrack_error) < 0.1
    assert abs(out.wp_dist - dist(g, 12.0, 0.0)) <= 1.0


def test_mode_change_mid_mission_stops_and_auto_resumes_the_current_item() -> None:
    g = rig()
    mission(g, SQUARE)
    g.set_mode(MODE_AUTO)
    assert g.run_until(lambda: len(g.of("MISSION_ITEM_REACHED")) == 1, 30.0)
    g.run(2.0)
    assert g.set_mode(MODE_HOLD) == P.MAV_RESULT_ACCEPTED
    g.run(1.0)
    assert g.emu.servo_outputs[1] == g.emu.servo_outputs[3] == 1500  # HOLD: motor outputs at trim
    g.run(3.0)
    assert abs(g.emu.truth.v_m_s) < 0.05
    g.set_mode(MODE_AUTO)
    assert g.run_until(lambda: "Mission Complete" in g.texts(), 40.0)
    assert [m.seq for m in g.of("MISSION_ITEM_REACHED")] == [1, 2, 3]
    assert dist(g, 0.0, 10.0) < 1.0


def test_disarmed_outside_auto_the_mission_starts_again_from_its_first_item() -> None:
    g = rig()
    mission(g, SQUARE)
    g.set_mode(MODE_AUTO)
    assert g.run_until(lambda: len(g.of("MISSION_ITEM_REACHED")) == 1, 30.0)
    g.set_mode(MODE_HOLD)
    g.run(3.0)
    assert g.command(P.MAV_CMD_COMPONENT_ARM_DISARM, 0) == P.MAV_RESULT_ACCEPTED
    assert "Throttle disarmed" in g.texts()
    g.arm()
    g.set_mode(MODE_AUTO)
    g.run(0.5)
    assert g.texts()[-1] == "Mission: 1 WP"


@pytest.mark.parametrize(("restart", "first"), [(0, "Mission: 2 WP"), (1, "Mission: 1 WP")])
def test_back_in_auto_the_mission_resumes_or_restarts_per_mis_restart(restart: int, first: str) -> None:
    g = rig()
    g.emu.set_param("MIS_RESTART", restart)
    mission(g, SQUARE)
    g.set_mode(MODE_AUTO)
    assert g.run_until(lambda: len(g.of("MISSION_ITEM_REACHED")) == 1, 30.0)
    g.run(1.0)
    g.set_mode(MODE_HOLD)
    g.run(2.0)
    g.set_mode(MODE_AUTO)
    g.run(0.5)
    assert g.texts()[-1] == first


def test_a_hold_time_delays_the_item_reached_and_the_next_leg() -> None:
    g = rig()
    items = [g.waypoint(0, 0.0, 0.0), g.waypoint(1, 8.0, 0.0, hold_s=3.0), g.waypoint(2, 16.0, 0.0)]
    assert g.upload(items) == P.MAV_MISSION_ACCEPTED
    g.set_mode(MODE_AUTO)
    assert g.run_until(lambda: "Reached waypoint #1. Loiter for 3 seconds" in g.texts(), 30.0)
    said = g.emu.sim_time_s
    assert g.run_until(lambda: bool(g.of("MISSION_ITEM_REACHED")), 10.0)
    assert 2.9 <= g.emu.sim_time_s - said <= 3.1
    assert abs(g.emu.truth.v_m_s) < 0.05 and dist(g, 8.0, 0.0) < 0.5  # stopped there meanwhile
    assert g.run_until(lambda: "Mission Complete" in g.texts(), 30.0)


def test_rtl_drives_home_at_rtl_speed_and_stops_within_wp_radius_of_it() -> None:
    g = rig()
    drive_out(g, 5.0)
    assert g.set_mode(MODE_RTL) == P.MAV_RESULT_ACCEPTED
    start = g.emu.sim_time_s
    assert g.run_until(lambda: dist(g, 0.0, 0.0) < 3.0, 20.0)
    within_s = g.emu.sim_time_s - start
    assert g.run_until(lambda: "Reached destination" in g.texts(), 20.0)
    g.run(3.0)
    assert 5.0 <= within_s <= 9.0, within_s  # measured 7.0 s
    assert dist(g, 0.0, 0.0) < 1.0 and abs(g.emu.truth.v_m_s) < 0.01  # measured 0.32 m


def test_rtl_is_refused_before_home_and_rtl_speed_sets_the_speed() -> None:
    g = rig()
    g.emu.set_param("RTL_SPEED", 1.0)
    drive_out(g, 12.0)
    g.set_mode(MODE_RTL)
    peak = 0.0

    def watch() -> None:
        nonlocal peak
        peak = max(peak, abs(g.emu.truth.v_m_s))

    assert g.run_until(lambda: "Reached destination" in g.texts(), 40.0, each=watch)
    assert 0.9 <= peak <= 1.15, peak
    home_less = InProcessGcs(Emulator(dataclasses.replace(ANCHOR, external_nav=True), seed=2, record_sent=True))
    assert home_less.set_mode(MODE_RTL) == P.MAV_RESULT_FAILED  # no position, no home


def test_smart_rtl_comes_back_along_the_way_it_went() -> None:
    g = rig()
    g.set_mode(MODE_MANUAL)
    g.run_until(lambda: g.emu.truth.x_m >= 8.0, 20.0, each=lambda: g.override(ch1=1500, ch3=1750))
    g.run_until(lambda: g.emu.truth.yaw_rad >= math.radians(80), 10.0, each=lambda: g.override(ch1=1650, ch3=1500))
    g.run_until(lambda: g.emu.truth.y_m >= 8.0, 20.0, each=lambda: g.override(ch1=1500, ch3=1750))
    g.run_until(lambda: abs(g.emu.truth.v_m_s) < 0.01, 10.0, each=lambda: g.override(ch1=1500, ch3=1500))
    corner = (g.emu.truth.x_m, 0.0)
    near_corner = math.inf

    def watch() -> None:
        nonlocal near_corner
        near_corner = min(near_corner, dist(g, *corner))

    assert g.set_mode(MODE_SMART_RTL) == P.MAV_RESULT_ACCEPTED
    assert g.run_until(lambda: "Reached destination" in g.texts(), 60.0, each=watch)
    g.run(3.0)
    assert near_corner < 2.5, near_corner  # came back round the corner, not straight across
    assert dist(g, 0.0, 0.0) < 1.0  # measured 0.14 m


def test_smart_rtl_needs_its_path_and_hold_and_guided_stop() -> None:
    g = rig()
    g.emu.set_param("SRTL_POINTS", 0)
    g.emu.reboot()
    g.run(2.0)
    g.arm()
    assert g.set_mode(MODE_SMART_RTL) == P.MAV_RESULT_FAILED
    drive_out(g, 3.0)
    g.set_mode(MODE_MANUAL)
    g.run(0.5, each=lambda: g.override(ch1=1500, ch3=1800))
    assert g.set_mode(MODE_GUIDED) == P.MAV_RESULT_ACCEPTED
    g.run(3.0)
    assert abs(g.emu.truth.v_m_s) < 0.05  # GUIDED without a target stops


def test_passthrough_rover_does_not_move_and_the_unforwarded_demand_winds_up() -> None:
    g = rig(BRIDGE)
    mission(g, SQUARE)
    g.emu.set_param("GCS_PID_MASK", 3)
    g.set_mode(MODE_AUTO)
    servo5 = []

    def watch() -> None:
        servo5.append((g.emu.sim_time_s, g.emu.servo_outputs[5]))

    g.run(12.0, each=watch)
    assert g.emu.truth.x_m == 0.0 and g.emu.servo_outputs[1] == g.emu.servo_outputs[3] == 1500
    at_limit = [t for t, pwm in servo5 if pwm >= 1899]
    assert at_limit and at_limit[0] - servo5[0][0] <= 10.0  # measured: at its limit within 7 s
    speed = [m for m in g.of("PID_TUNING") if m.axis == 4][-1]
    # The speed integrator wound up (from 0) until the output saturated, then stopped growing.
    assert speed.achieved == 0.0 and speed.desired > 0.3 and speed.I >= 0.4


def test_pid_tuning_reports_turn_rate_in_deg_s_and_speed_and_freezes_in_hold() -> None:
    g = rig()
    mission(g, [(0.0, 10.0)])  # east: a pivot first
    g.emu.set_param("GCS_PID_MASK", 3)
    g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, P.MAVLINK_MSG_ID_PID_TUNING, 25_000)
    g.set_mode(MODE_AUTO)
    g.run(1.5)
    steer = [m for m in g.of("PID_TUNING") if m.axis == 5]
    assert max(m.desired for m in steer) == pytest.approx(60.0, abs=2.0)  # clockwise +, WP_PIVOT_RATE
    assert abs(steer[-1].achieved - math.degrees(g.emu.truth.yaw_rate_rad_s)) < 5.0
    g.run(4.0)
    speed = [m for m in g.of("PID_TUNING") if m.axis == 4]
    assert max(m.desired for m in speed) > 1.0
    g.set_mode(MODE_HOLD)
    g.run(0.5)
    frozen = [(m.axis, m.desired, m.achieved, m.I) for m in g.of("PID_TUNING")[-2:]]
    g.run(1.0)
    assert [(m.axis, m.desired, m.achieved, m.I) for m in g.of("PID_TUNING")[-2:]] == frozen


def test_forwarding_servo5_and_6_into_the_wheel_overrides_flies_the_mission() -> None:
    """The issue's copy loop: each SERVO_OUTPUT_RAW's servo5/6 into the overrides of channels 1/3 (40 Hz,
    SERVO5/6 range 1000-2000): measured 29.0 s, closest 0.18 / 0.20 / 0.21 m on the real SITL."""
    g = rig(BRIDGE)
    for n in (5, 6):
        g.emu.set_param(f"SERVO{n}_MIN", 1000)
        g.emu.set_param(f"SERVO{n}_MAX", 2000)
    assert g.command(P.MAV_CMD_SET_MESSAGE_INTERVAL, P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, 25_000) == P.MAV_RESULT_ACCEPTED
    mission(g, SQUARE)
    seen: list[MAVLinkMessage] = []
    closest = [math.inf] * 3

    def copy() -> None:
        raw = g.of("SERVO_OUTPUT_RAW")
        if raw and (not seen or raw[-1] is not seen[-1]):
            seen.append(raw[-1])
            g.override(ch1=raw[-1].servo5_raw, ch3=raw[-1].servo6_raw)
        for i, (n, e) in enumerate(SQUARE):
            closest[i] = min(closest[i], dist(g, n, e))

    g.set_mode(MODE_AUTO)
    start = g.emu.sim_time_s
    assert g.run_until(lambda: "Mission Complete" in g.texts(), 60.0, each=copy)
    assert 25.0 <= g.emu.sim_time_s - start <= 32.0
    assert max(closest) <= 0.3, closest


@pytest.mark.parametrize("skid", [True, False])
def test_only_a_rover_with_throttle_left_and_right_outputs_pivots(skid: bool) -> None:
    g = rig(BRIDGE)  # nothing forwards the demand: the rover stands still either way
    if not skid:
        g.emu.set_param("SERVO5_FUNCTION", 0)
        g.emu.set_param("SERVO6_FUNCTION", 0)
    g.emu.set_param("GCS_PID_MASK", 3)
    g.emu.set_param("SR0_EXTRA1", 10)
    mission(g, [(0.0, 10.0)])  # east, the rover faces north
    g.set_mode(MODE_AUTO)
    g.run(2.0)
    pid: list[MAVLinkMessage] = g.of("PID_TUNING")
    pairs = [(a.desired, b.desired) for a, b in itertools.pairwise(pid) if (a.axis, b.axis) == (5, 4)]
    turning_on_the_spot = [turn for turn, speed in pairs if abs(turn) > 20.0 and speed == 0.0]
    if skid:  # a pivot: stopped, turning at WP_PIVOT_RATE
        assert turning_on_the_spot and max(turning_on_the_spot) == pytest.approx(60.0, abs=2.0)
    else:  # a steering rover turns only while it drives (TURN_RADIUS)
        assert pairs and not turning_on_the_spot
