"""The autopilot drives through the bridge (issue 29), end to end: a ground station (pymavlink) uploads a mission
THROUGH the bridge, the emulator's own navigation flies it in AUTO, RTL and SMART_RTL bring the rover home, a
fence breach while the GCS drives in MANUAL takes the fence's action, and every one of these is judged by the
emulator's ground truth against ArduPilot alone: the same emulator with SERVO1/3 = 73/74 (the anchor,
sitl/vehicles/ardupilot-skid-anchor.toml), no bridge, the same mission, in the same test.

The bridge side is set up as a rover owner would (tests/navrig.py: the shipped profile and .parm). Lockstep, UDP
loopback, one simulated clock (tests/lockstep.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from navmetrics import Point, RouteFigures, distance_to_path_m, distance_to_segment_m, route_figures
from navrig import ANCHOR, BRIDGE, WAYPOINTS, BridgeRig, shipped_parm

from rover_bridge.mavlink.dialect import mavlink
from sitl import Emulator, VehicleConfig
from sitl.gcs import InProcessGcs
from sitl.modes import MODE_AUTO, MODE_HOLD, MODE_MANUAL, MODE_RTL, MODE_SMART_RTL

pytestmark = pytest.mark.e2e

P = mavlink


def anchor_mission() -> RouteFigures:
    """ArduPilot alone (SERVO1/3 = 73/74, no bridge): the same mission, in process."""
    g = InProcessGcs(Emulator(ANCHOR, seed=29, record_sent=True))
    g.heartbeat()
    g.run(0.5)
    assert g.arm() == P.MAV_RESULT_ACCEPTED
    items = [g.waypoint(0, 0.0, 0.0)] + [g.waypoint(i + 1, n, e) for i, (n, e) in enumerate(WAYPOINTS)]
    assert g.upload(items) == P.MAV_MISSION_ACCEPTED
    track: list[Point] = []
    assert g.set_mode(MODE_AUTO) == P.MAV_RESULT_ACCEPTED
    start, at = g.emu.sim_time_s, (g.emu.truth.x_m, g.emu.truth.y_m)
    done = g.run_until(lambda: len(g.of("MISSION_ITEM_REACHED")) >= len(WAYPOINTS), 90.0,
                       each=lambda: track.append((g.emu.truth.x_m, g.emu.truth.y_m)))
    assert done
    return route_figures(track, at, WAYPOINTS, g.emu.sim_time_s - start)


def test_a_mission_uploaded_through_the_bridge_flies_as_ardupilot_alone_flies_it() -> None:
    anchor = anchor_mission()
    rig = BridgeRig()
    try:
        bridge = rig.fly_mission(WAYPOINTS)
        assert rig.reached() == [1, 2, 3]
        assert "RB: AUTO: the autopilot drives" in rig.texts() and "Mission Complete" in rig.texts()
        assert rig.ls.core.command.counters.get("demand.taken", 0) > 0  # the demand drove, through the bridge
    finally:
        rig.close()
    print(f"\nanchor | {anchor.row()}\nbridge | {bridge.row()}")
    assert max(bridge.closest_m) <= 0.5
    assert bridge.time_s <= 1.1 * anchor.time_s
    assert bridge.xtrack_max_m <= anchor.xtrack_max_m + 0.3


def drive_out(rig: BridgeRig, until: Callable[[], bool], v_m_s: float, yaw_rate_cw_rad_s: float = 0.0) -> None:
    """The GCS drives in MANUAL through the bridge (velocity requests at 10 Hz) until `until`, then stops."""
    assert rig.run_until(until, 30.0, rig.drive(v_m_s, yaw_rate_cw_rad_s))
    assert rig.run_until(rig.stopped, 10.0, rig.drive(0.0))


def home_and_stopped(rig: BridgeRig) -> float:
    assert rig.run_until(lambda: "Reached destination" in rig.texts(), 60.0)
    assert rig.run_until(rig.stopped, 10.0)
    rig.run(1.0)
    assert rig.stopped()
    return rig.from_home_m()


def test_rtl_from_eleven_metres_comes_home_through_the_bridge_and_stops() -> None:
    rig = BridgeRig()
    try:
        rig.set_mode(MODE_MANUAL)
        drive_out(rig, lambda: rig.from_home_m() >= 11.0, 1.5)
        rig.set_mode(MODE_RTL)
        final_m = home_and_stopped(rig)
        assert "RB: RTL: the autopilot drives" in rig.texts()
    finally:
        rig.close()
    print(f"\nRTL from 11 m: final {final_m:.2f} m from home")
    assert final_m <= 1.0


def test_smart_rtl_comes_home_along_the_path_it_came() -> None:
    rig = BridgeRig()
    try:
        rig.set_mode(MODE_MANUAL)
        yaw0 = rig.emu.truth.yaw_rad
        drive_out(rig, lambda: rig.from_home_m() >= 6.0, 1.5)
        corner = rig.track[-1]
        drive_out(rig, lambda: (rig.emu.truth.yaw_rad - yaw0) % (2 * math.pi) >= math.radians(85.0), 0.0, 0.8)
        drive_out(rig, lambda: math.hypot(rig.emu.truth.x_m - corner[0], rig.emu.truth.y_m - corner[1]) >= 6.0, 1.5)
        out = list(rig.track)
        rig.set_mode(MODE_SMART_RTL)
        back_from = len(rig.track)
        final_m = home_and_stopped(rig)
        back = rig.track[back_from:]
    finally:
        rig.close()
    off_path = max(distance_to_path_m(p, out) for p in back)
    at_corner = min(math.hypot(x - corner[0], y - corner[1]) for x, y in back)
    print(f"\nSMART_RTL: final {final_m:.2f} m, off the way out <= {off_path:.2f} m, "
          f"corner passed at {at_corner:.2f} m")
    assert final_m <= 1.0
    assert off_path <= 1.0 and at_corner <= 1.0  # back the way it came, not straight home (that misses by 4 m)


@pytest.mark.parametrize(("action", "mode"), [(1, MODE_RTL), (2, MODE_HOLD)])
def test_a_fence_breach_while_the_gcs_drives_takes_the_fences_action(action: int, mode: int) -> None:
    radius_m = 8.0
    rig = BridgeRig(FENCE_ENABLE=1, FENCE_TYPE=2, FENCE_RADIUS=radius_m, FENCE_ACTION=action)
    try:
        rig.set_mode(MODE_MANUAL)
        forward = rig.drive(1.5)
        # The GCS keeps asking to drive on, as a ground station that did not notice would.
        assert rig.run_until(lambda: rig.emu.mode == mode, 20.0, forward)
        breached_at_m = rig.from_home_m()
        if mode == MODE_HOLD:
            rig.run(3.0, forward)
            assert rig.stopped() and "RB: autopilot in HOLD, braking, then neutral" in rig.texts()
            final_m = rig.from_home_m()
            assert final_m <= radius_m + 1.5  # braked at once: 1.5 m/s stops well inside 1.5 m at 5 m/s^2
        else:
            assert rig.run_until(lambda: "Reached destination" in rig.texts(), 60.0, forward)
            assert rig.run_until(rig.stopped, 10.0, forward)
            final_m = rig.from_home_m()
            assert final_m <= 1.0  # back inside, at home
            assert rig.ls.core.command.counters.get("dropped.mode", 0) > 0  # the GCS's requests were refused
    finally:
        rig.close()
    print(f"\nfence {radius_m} m, action {action}: mode at {breached_at_m:.2f} m, ended {final_m:.2f} m from home")


# -- the figures' math ----------------------------------------------------------------------------------------

def test_distances_to_a_path_by_hand() -> None:
    assert distance_to_segment_m((1.0, 1.0), (0.0, 0.0), (2.0, 0.0)) == pytest.approx(1.0)
    assert distance_to_segment_m((3.0, 0.0), (0.0, 0.0), (2.0, 0.0)) == pytest.approx(1.0)  # past the end
    assert distance_to_segment_m((1.0, 1.0), (0.0, 0.0), (0.0, 0.0)) == pytest.approx(math.sqrt(2.0))
    assert distance_to_path_m((5.0, 5.0), [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)]) == pytest.approx(5.0)
    fig = route_figures([(0.0, 0.0), (5.0, 1.0), (10.0, 0.0)], (0.0, 0.0), [(10.0, 0.0)], 4.0)
    assert fig.closest_m == (0.0,) and fig.xtrack_max_m == pytest.approx(1.0)
    assert fig.xtrack_rms_m == pytest.approx(math.sqrt(1.0 / 3.0))


coord = st.floats(-100.0, 100.0)


@settings(derandomize=True, max_examples=200)
@given(coord, coord, coord, coord, coord, coord, st.floats(0.0, 1.0))
def test_a_segments_distance_is_the_nearest_of_its_points(px: float, py: float, ax: float, ay: float, bx: float,
                                                           by: float, t: float) -> None:
    d = distance_to_segment_m((px, py), (ax, ay), (bx, by))
    on = (ax + t * (bx - ax), ay + t * (by - ay))
    assert 0.0 <= d <= math.hypot(px - on[0], py - on[1]) + 1e-9  # no point of the segment is nearer
    assert d <= min(math.hypot(px - ax, py - ay), math.hypot(px - bx, py - by)) + 1e-9
    assert distance_to_segment_m(on, (ax, ay), (bx, by)) <= 1e-6  # a point on it is at 0


def test_the_fixtures_are_the_shipped_setup() -> None:
    parm = shipped_parm()
    assert (parm["SERVO1_FUNCTION"], parm["SERVO3_FUNCTION"], parm["SERVO5_FUNCTION"], parm["SERVO6_FUNCTION"]) \
        == (51, 53, 73, 74)
    assert isinstance(BRIDGE, VehicleConfig) and (BRIDGE.left_function, BRIDGE.right_function) == (51, 53)
    assert (ANCHOR.left_function, ANCHOR.right_function) == (73, 74)
