"""Fence avoidance end to end (issue 43 item 3): the real bridge and the emulator in lockstep. The emulator keeps
FENCE_* and the stored fence as ArduPilot does (its breach takes FENCE_ACTION, here 0: report only, so a crossing
shows) and does no avoidance itself: what stops the rover short of the fence is the bridge, on its own position
(the estimate anchored to GLOBAL_POSITION_INT) against home (HOME_POSITION) and the fence it downloads.

- The circle: FENCE_RADIUS 12 around home, FENCE_MARGIN 2, AVOID_ENABLE 1 (fence only), GUIDED vx 1.5 m/s north
  for 15 s (the issue's real-SITL run: ArduPilot alone went 10.05 m from home; the bridge before this 18.1 m).
- A polygon a ground station uploads through the bridge while it runs (FENCE_TYPE 4): the bridge sees the
  autopilot accept the upload, downloads the new fence, and stops FENCE_MARGIN inside its edge; the ground station
  never sees the bridge's own transfer; one stored over another link is downloaded within the refresh.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest
from lockstep import Lockstep

from rover_bridge.command.fence_watch import STORED_REFRESH_S
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import Profile
from sitl import VehicleConfig
from sitl.fence_store import FenceItem
from sitl.geo import lat_lon_of

pytestmark = pytest.mark.e2e

GUIDED = 15
RADIUS_M, MARGIN_M = 12.0, 2.0
FENCE_OFF_ACTION = (("FENCE_ENABLE", 1.0), ("FENCE_MARGIN", MARGIN_M), ("FENCE_ACTION", 0.0))


def rig_with(params: tuple[tuple[str, float], ...], max_speed_m_s: float = 1.5) -> Lockstep:
    profile = Profile()
    profile = dataclasses.replace(profile, limits=dataclasses.replace(profile.limits, max_linear_m_s=max_speed_m_s))
    return Lockstep(profile, VehicleConfig(params=params), seed=5)


def guided(rig: Lockstep) -> None:
    rig.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                  GUIDED, 0, 0, 0, 0, 0)
    rig.run_for(0.5)


def drive_north(rig: Lockstep, v_m_s: float, seconds: float) -> dict[str, Any]:
    """GUIDED body velocity for `seconds`: the farthest and last distance from home (the emulator's truth)."""
    far: list[float] = []
    norths: list[float] = []

    def sample() -> None:
        far.append(math.hypot(rig.emu.truth.x_m, rig.emu.truth.y_m))
        norths.append(rig.emu.truth.x_m)

    rig.run_for(seconds, send=lambda: rig.send_body_velocity(v_m_s, 0.0), after_step=sample)
    return {"farthest": max(far), "rest": far[-1], "north_max": max(norths), "speed": rig.emu.truth.v_m_s,
            "texts": [str(m.text) for _, m in rig.view.of("STATUSTEXT")],
            "counters": {k: v for k, v in rig.core.command.counters.items() if k.startswith("avoid.")}}


def circle_run(avoid_enable: float) -> dict[str, Any]:
    rig = rig_with((*FENCE_OFF_ACTION, ("FENCE_TYPE", 2.0), ("FENCE_RADIUS", RADIUS_M), ("AVOID_ENABLE", avoid_enable)))
    try:
        rig.run_for(2.0)
        guided(rig)
        return drive_north(rig, 1.5, 15.0)
    finally:
        rig.close()


def test_the_circle_fence_is_never_crossed_the_rover_stops_fence_margin_inside() -> None:
    run = circle_run(avoid_enable=1.0)
    inner_m = RADIUS_M - MARGIN_M
    assert run["farthest"] < RADIUS_M, run  # never crossed
    assert inner_m - 0.7 <= run["farthest"] <= inner_m + 0.3, run  # where ArduPilot stops (10.05 m), not timid
    assert abs(run["speed"]) < 0.05, run
    assert "RB: fence ahead: slowing to stop 2 m inside" in run["texts"], run
    assert run["counters"].get("avoid.fence_stop", 0) >= 1, run


def test_without_the_fence_bit_of_avoid_enable_the_rover_drives_past_the_circle() -> None:
    run = circle_run(avoid_enable=2.0)  # proximity only: ArduPilot would not avoid the fence either
    assert run["farthest"] > RADIUS_M + 2.0, run
    assert not any(k.startswith("avoid.fence") for k in run["counters"]), run


def upload_through_the_bridge(rig: Lockstep, items: list[Any]) -> int | None:
    """The GCS uploads a fence via the bridge (MISSION_COUNT, each item asked for, the autopilot's MISSION_ACK)."""
    seen = {kind: len(rig.view.of(kind)) for kind in ("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK")}
    rig.gcs.mav.mission_count_send(1, 1, len(items), mavlink.MAV_MISSION_TYPE_FENCE)
    for _ in range(300):
        rig.step()
        for kind in ("MISSION_REQUEST", "MISSION_REQUEST_INT"):
            for _t, m in rig.view.of(kind)[seen[kind]:]:
                rig.gcs.mav.send(items[m.seq])
            seen[kind] = len(rig.view.of(kind))
        acks = rig.view.of("MISSION_ACK")[seen["MISSION_ACK"]:]
        if acks:
            return int(acks[-1][1].type)
    return None


def polygon_items(rig: Lockstep, corners: list[tuple[float, float]]) -> list[tuple[float, float]]:
    v = rig.emu.vehicle
    return [lat_lon_of(n, e, v.origin_lat_deg, v.origin_lon_deg) for n, e in corners]


def test_a_polygon_stored_over_another_link_is_downloaded_within_the_refresh() -> None:
    # A ground station on a radio straight to the autopilot: its upload passes no MISSION_ACK through the bridge.
    rig = rig_with((*FENCE_OFF_ACTION, ("FENCE_TYPE", 4.0), ("AVOID_ENABLE", 1.0)))
    try:
        rig.run_for(2.0)
        corners = [(8.0, -5.0), (8.0, 5.0), (-5.0, 5.0), (-5.0, -5.0)]
        vertices = polygon_items(rig, corners)
        assert rig.emu.autopilot.fence.write(tuple(
            FenceItem(mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 4.0, round(lat * 1e7), round(lon * 1e7))
            for lat, lon in vertices))
        rig.run_for(STORED_REFRESH_S + 1.0)
        fences = rig.core.command.avoid.fence.fences
        assert fences is not None and len(fences.polygons) == 1
        guided(rig)
        run = drive_north(rig, 1.5, 12.0)
        assert 8.0 - MARGIN_M - 0.7 < run["north_max"] < 8.0 - MARGIN_M + 0.3, run
    finally:
        rig.close()


def test_a_polygon_uploaded_while_the_bridge_runs_is_downloaded_and_kept() -> None:
    rig = rig_with((*FENCE_OFF_ACTION, ("FENCE_TYPE", 4.0), ("AVOID_ENABLE", 1.0)))
    try:
        rig.run_for(2.0)
        avoid = rig.core.command.avoid
        assert avoid.fence.download.items == ()  # nothing stored yet: downloaded, empty
        corners = [(8.0, -5.0), (8.0, 5.0), (-5.0, 5.0), (-5.0, -5.0)]  # its north edge 8 m ahead
        items = []
        for seq, (lat, lon) in enumerate(polygon_items(rig, corners)):
            items.append(rig.gcs.mav.mission_item_int_encode(
                1, 1, seq, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 0, 1,
                float(len(corners)), 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7), 0.0,
                mavlink.MAV_MISSION_TYPE_FENCE))
        assert upload_through_the_bridge(rig, items) == mavlink.MAV_MISSION_ACCEPTED
        rig.run_for(1.0)
        assert avoid.fence.download.items is not None and len(avoid.fence.download.items) == 4
        fences = avoid.fence.fences
        assert fences is not None and len(fences.polygons) == 1
        guided(rig)
        run = drive_north(rig, 1.5, 12.0)
        assert run["north_max"] < 8.0 - MARGIN_M + 0.3, run
        assert run["north_max"] > 8.0 - MARGIN_M - 0.7, run
        assert run["counters"].get("avoid.fence_stop", 0) >= 1, run
        # The bridge's own transfer is consumed: the GCS saw only its own (the ACK to its upload, the requests).
        theirs = [m for kind in ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK") for _t, m in rig.view.of(kind)
                  if m.target_component == rig.core.identity.component_id]
        assert theirs == []
    finally:
        rig.close()
