"""Simple avoidance end to end (issue 43 items 1, 2, 4): the real bridge and the emulator in lockstep, a wall
10 m ahead (sitl/scenarios/wall-ahead.toml), ArduPilot's SITL proximity sensor on (PRX1_TYPE 10: 8 sectors as
DISTANCE_SENSOR in EXTRA3, 1 Hz until the bridge asks for more), AVOID_* at ArduPilot's defaults (margin 2 m).
A GCS asks GUIDED for vx 1.0 m/s for 15 s: the rover must stop short of the wall, near the margin, and never
touch it. The emulator's Rover does no avoidance itself: what stops it is the bridge.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
from lockstep import Lockstep

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import Profile
from sitl import VehicleConfig, load_scenario

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]
GUIDED = 15


def drive_at_the_wall(prx: bool = True, avoid_enable: float = 3.0,
                      vehicle: VehicleConfig | None = None) -> dict[str, Any]:
    profile = Profile()
    profile = dataclasses.replace(profile, limits=dataclasses.replace(profile.limits, max_linear_m_s=1.0))
    params = (("PRX1_TYPE", 10.0),) if prx else ()
    vehicle = vehicle or VehicleConfig(params=params)
    rig = Lockstep(profile, vehicle, seed=5, scenario=load_scenario(REPO / "sitl/scenarios/wall-ahead.toml"))
    try:
        rig.emu.set_param("AVOID_ENABLE", avoid_enable)
        rig.run_for(1.0)
        rig.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                      mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED, 0, 0, 0, 0, 0)
        rig.run_for(0.5)
        nearest: list[float] = []
        rig.run_for(15.0, send=lambda: rig.send_body_velocity(1.0, 0.0),
                    after_step=lambda: nearest.append(rig.emu.nearest_obstacle_m() or 0.0))
        texts = [str(m.text) for _, m in rig.view.of("STATUSTEXT")]
        return {"closest": min(nearest), "rest": nearest[-1], "speed": rig.emu.truth.v_m_s,
                "collided": rig.emu.collided(), "texts": texts, "counters": dict(rig.core.command.counters),
                "top": max(abs(rig.emu.truth.v_m_s), 0.0), "x": rig.emu.truth.x_m}
    finally:
        rig.close()


def test_the_rover_stops_short_of_a_wall_the_proximity_sensor_sees() -> None:
    run = drive_at_the_wall()
    margin_m = 2.0  # AVOID_MARGIN, ArduPilot's default, as the emulator reports it
    # The rover's centre against the wall: never inside the margin by more than 0.3 m, at rest within 1 m of it.
    assert run["closest"] >= margin_m - 0.3, run
    assert run["rest"] <= margin_m + 1.0, run
    assert abs(run["speed"]) < 0.05, run
    assert not run["collided"]
    assert "RB: obstacle ahead: slowing to stop 2 m short" in run["texts"]
    assert run["counters"].get("avoid.obstacle_stop", 0) >= 1
    assert run["counters"].get("avoid.sensor_silent", 0) == 0  # asked at 10 Hz: never silent


@pytest.mark.parametrize("sensor", [
    VehicleConfig(params=(("RNGFND1_TYPE", 100.0), ("RNGFND1_ORIENT", 0.0), ("RNGFND1_MAX", 12.0))),
    VehicleConfig(obstacle_distance_hz=10.0, obstacle_distance_fov_deg=87.0, obstacle_distance_max_m=10.0),
], ids=["forward rangefinder", "companion depth camera (OBSTACLE_DISTANCE)"])
def test_a_forward_rangefinder_or_a_depth_camera_alone_stops_it_too(sensor: VehicleConfig) -> None:
    run = drive_at_the_wall(vehicle=sensor)
    assert run["closest"] >= 2.0 - 0.3, run
    assert run["rest"] <= 2.0 + 1.0, run
    assert not run["collided"], run
    assert run["counters"].get("avoid.obstacle_stop", 0) >= 1, run


def test_without_a_sensor_or_with_avoid_enable_0_it_drives_through_as_before() -> None:
    for run in (drive_at_the_wall(prx=False), drive_at_the_wall(avoid_enable=0.0)):
        assert run["collided"] or run["x"] > 10.5, run  # through the wall: nothing to stop it
        assert not any(k.startswith("avoid.obstacle") for k in run["counters"]), run


def test_a_proximity_sensor_that_goes_silent_slows_the_rover_to_a_crawl_and_says_so() -> None:
    profile = Profile()
    profile = dataclasses.replace(profile, limits=dataclasses.replace(profile.limits, max_linear_m_s=1.0))
    rig = Lockstep(profile, VehicleConfig(params=(("PRX1_TYPE", 10.0),)), seed=5,
                   scenario=load_scenario(REPO / "sitl/scenarios/wall-ahead.toml"))
    try:
        rig.run_for(1.0)
        rig.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                      mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED, 0, 0, 0, 0, 0)
        rig.run_for(0.5)
        rig.run_for(2.0, send=lambda: rig.send_body_velocity(1.0, 0.0))
        assert rig.emu.truth.v_m_s > 0.8  # the wall is still far: full speed
        rig.emu.set_param("PRX1_TYPE", 0.0)  # the sensor dies
        rig.run_for(2.0, send=lambda: rig.send_body_velocity(1.0, 0.0))
        assert rig.emu.truth.v_m_s == pytest.approx(0.2, abs=0.03)
        texts = [str(m.text) for _, m in rig.view.of("STATUSTEXT")]
        assert texts.count("RB: proximity sensor silent: crawling (0.2 m/s)") == 1
        assert rig.core.command.counters["avoid.sensor_silent"] == 1
    finally:
        rig.close()
