"""The emulator's circular fence and GCS failsafe act as Rover 4.7's do (sitl/safety.py, sitl/rover.py).

The issue 29 measurements they follow: a breach switches the mode within about 80-100 ms
(FENCE_ACTION 2 = Hold, 1 = RTL or Hold); every mode change during a breach suspends fence checks for
10 s ("manual recovery"); with per-wheel overrides still arriving the rover kept driving out in HOLD.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sitl import Emulator, VehicleConfig, load_vehicle
from sitl.gcs import InProcessGcs
from sitl.mav import mavlink
from sitl.modes import MODE_AUTO, MODE_HOLD, MODE_MANUAL, MODE_RTL

P = mavlink
VEHICLES = Path(__file__).resolve().parents[1] / "sitl" / "vehicles"
ANCHOR = load_vehicle(VEHICLES / "ardupilot-skid-anchor.toml")
BRIDGE = load_vehicle(VEHICLES / "ardupilot-skid-bridge.toml")
RADIUS_M = 8.0


def fenced(vehicle: VehicleConfig, action: int) -> InProcessGcs:
    g = InProcessGcs(Emulator(vehicle, seed=4, record_sent=True))
    for name, value in (("FENCE_ENABLE", 1), ("FENCE_TYPE", 2), ("FENCE_RADIUS", RADIUS_M), ("FENCE_ACTION", action)):
        g.emu.set_param(name, value)
    g.heartbeat()
    g.run(0.2)
    assert g.arm() == P.MAV_RESULT_ACCEPTED
    return g


def from_home(g: InProcessGcs) -> float:
    return math.hypot(g.emu.truth.x_m, g.emu.truth.y_m)


def drive(g: InProcessGcs) -> None:
    """Sticks (anchor: RC3 throttle) or both wheel overrides (bridge: passthrough) forward."""
    g.override(ch1=1700 if g.emu.vehicle.left_function == 51 else 1500, ch3=1700)


def breach_latency(g: InProcessGcs, mode: int) -> float:
    """Drive out in MANUAL; seconds from the first loop outside the fence to the mode change."""
    g.set_mode(MODE_MANUAL)
    outside_at: list[float] = []

    def switched() -> bool:  # looked at after every 5 ms step
        if not outside_at and from_home(g) >= RADIUS_M:
            outside_at.append(g.emu.sim_time_s)
        return g.emu.mode == mode

    assert g.run_until(switched, 30.0, dt_s=0.005, each=lambda: drive(g))
    return g.emu.sim_time_s - outside_at[0]


@pytest.mark.parametrize(("action", "mode"), [(2, MODE_HOLD), (1, MODE_RTL)])
def test_a_breach_switches_the_mode_within_a_tenth_of_a_second(action: int, mode: int) -> None:
    g = fenced(ANCHOR, action)
    assert breach_latency(g, mode) <= 0.105
    assert "Manual recovery started" in g.texts()  # the action's own mode change, while breached
    if mode == MODE_HOLD:
        g.run(3.0)
        assert abs(g.emu.truth.v_m_s) < 0.01 and from_home(g) < RADIUS_M + 2.0  # the motors' outputs went to trim
    else:
        assert g.run_until(lambda: "Reached destination" in g.texts(), 40.0)
        g.run(2.0)
        assert from_home(g) < 1.0  # back inside, at home


def test_report_only_and_disarmed_breaches_change_nothing() -> None:
    g = fenced(ANCHOR, 0)
    g.set_mode(MODE_MANUAL)
    g.run_until(lambda: from_home(g) >= RADIUS_M + 2.0, 20.0, each=lambda: drive(g))
    g.run(0.5, each=lambda: drive(g))
    assert g.emu.mode == MODE_MANUAL
    assert g.emu.autopilot.rover.fence.breached
    g2 = fenced(ANCHOR, 2)
    g2.command(P.MAV_CMD_COMPONENT_ARM_DISARM, 0)
    g2.emu.teleport(RADIUS_M + 3.0, 0.0)
    g2.run(1.0)
    assert g2.emu.mode == MODE_MANUAL


def test_passthrough_overrides_keep_driving_in_hold_and_recovery_suspends_the_fence_for_10_s() -> None:
    g = fenced(BRIDGE, 2)
    breach_latency(g, MODE_HOLD)
    g.run(2.0, each=lambda: drive(g))  # HOLD cannot stop wheels on RC passthrough
    assert from_home(g) > RADIUS_M + 3.0 and g.emu.truth.v_m_s > 1.0
    assert g.set_mode(MODE_MANUAL) == P.MAV_RESULT_ACCEPTED  # the pilot takes over while breached
    recovery_s = g.emu.sim_time_s
    assert g.texts().count("Manual recovery started") == 2
    # Back inside, then out again within the 10 s: the new breach is recorded but ignored, so nothing
    # acts on it when the 10 s are over; the next action comes at the backup fence 20 m further out
    # (the "kept driving out to 28 m").
    g.run_until(lambda: from_home(g) < RADIUS_M - 1.0, 20.0, each=lambda: g.override(ch1=1300, ch3=1300))
    outside: list[float] = []

    def each() -> None:
        drive(g)
        if not outside and from_home(g) >= RADIUS_M:
            outside.append(g.emu.sim_time_s)

    assert g.run_until(lambda: g.emu.mode == MODE_HOLD, 20.0, each=each)
    assert outside[0] < recovery_s + 10.0 < g.emu.sim_time_s
    assert RADIUS_M + 20.0 <= from_home(g) <= RADIUS_M + 21.0
    assert g.emu.autopilot.rover.fence.breach_count == 3


def test_gcs_failsafe_holds_clears_overrides_and_clears_again() -> None:
    g = fenced(BRIDGE, 0)
    g.emu.set_param("FS_GCS_ENABLE", 1)
    g.set_mode(MODE_MANUAL)
    g.run(1.0, each=lambda: (g.heartbeat(), drive(g)))
    g.run_until(lambda: from_home(g) > 1.0, 10.0, each=lambda: (g.heartbeat(), drive(g)))
    quiet = g.emu.sim_time_s
    g.run_until(lambda: "GCS Failsafe" in g.texts(), 10.0)
    assert 6.5 <= g.emu.sim_time_s - quiet <= 6.8  # FS_GCS_TIMEOUT 5 s, then FS_TIMEOUT 1.5 s, at 10 Hz
    g.run(1.1)
    assert g.emu.mode == MODE_HOLD  # FS_ACTION 2
    assert g.of("HEARTBEAT")[-1].system_status == P.MAV_STATE_CRITICAL
    assert not g.emu.autopilot.has_override(1, g.emu.sim_time_us)  # RC overrides cleared
    g.heartbeat()
    g.run(0.3)
    assert "GCS Failsafe Cleared" in g.texts()


def test_gcs_failsafe_continues_auto_with_fs_gcs_enable_2() -> None:
    g = fenced(ANCHOR, 0)
    g.emu.set_param("FS_GCS_ENABLE", 2)
    items = [g.waypoint(0, 0.0, 0.0), g.waypoint(1, 40.0, 0.0)]
    assert g.upload(items) == P.MAV_MISSION_ACCEPTED
    g.set_mode(MODE_AUTO)
    g.run(8.0)
    assert "Failsafe - Continuing Auto Mode" in g.texts() and g.emu.mode == MODE_AUTO
