"""The emulator's obstacles, fence transfers and range sensors (sitl/obstacles.py, sitl/fence_protocol.py,
sitl/range_sensors.py): geometry by hand, readings against a wall placed by hand, the messages' fields and
rates as ArduPilot's SITL sends them, and the parameters a bridge reads."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sitl import Emulator, VehicleConfig
from sitl.config import ConfigError
from sitl.fence_store import CIRCLE_EXCLUSION, POLYGON_EXCLUSION, POLYGON_INCLUSION
from sitl.gcs import InProcessGcs
from sitl.mav import MAVLinkMessage, mavlink, mavutil
from sitl.obstacles import Circle, Polygon, inside, obstacle_distance_m, ray_m, ray_segment_m
from sitl.physics import PhysicsState
from sitl.range_sensors import proximity_sectors_m, sitl_bisection_m
from sitl.scenario import Scenario, load_scenario

_P = mavlink
# A wall 10 m north of the origin, 20 m wide, 0.5 m thick.
WALL = Polygon(((10.0, -10.0), (10.0, 10.0), (10.5, 10.0), (10.5, -10.0)))
FENCE = mavlink.MAV_MISSION_TYPE_FENCE


def at(x_m: float = 0.0, y_m: float = 0.0, yaw_deg: float = 0.0) -> PhysicsState:
    return PhysicsState(x_m=x_m, y_m=y_m, yaw_rad=math.radians(yaw_deg))


# ------------------------------------------------------------------ geometry by hand
def test_ray_casting_by_hand() -> None:
    assert ray_segment_m((0.0, 0.0), 0.0, (10.0, -1.0), (10.0, 1.0)) == pytest.approx(10.0)
    assert ray_segment_m((0.0, 0.0), math.pi, (10.0, -1.0), (10.0, 1.0)) is None  # behind
    assert ray_segment_m((0.0, 0.0), math.pi / 2, (10.0, -1.0), (10.0, 1.0)) is None  # east: misses
    # 45 deg (north-east) to the wall x = 10: sqrt(2) * 10.
    assert ray_m((0.0, 0.0), math.pi / 4, [WALL]) == pytest.approx(10.0 * math.sqrt(2.0))
    assert ray_m((0.0, 0.0), math.pi / 2, [WALL]) is None
    # The nearest of several: a post at 5 m in front of the wall.
    post = Circle((5.0, 0.0), 0.5)
    assert ray_m((0.0, 0.0), 0.0, [WALL, post]) == pytest.approx(4.5)
    # From inside a circle (an inclusion fence) to its edge.
    assert ray_m((0.0, 0.0), 1.0, [Circle((0.0, 0.0), 12.0)]) == pytest.approx(12.0)
    # From inside a square (an inclusion polygon) to its edge.
    square = Polygon(((-5.0, -5.0), (-5.0, 5.0), (5.0, 5.0), (5.0, -5.0)))
    assert ray_m((1.0, 0.0), 0.0, [square]) == pytest.approx(4.0)
    assert ray_m((1.0, 0.0), -math.pi / 2, [square]) == pytest.approx(5.0)


def test_inside_and_distance_to_the_nearest_obstacle() -> None:
    assert inside((10.2, 0.0), WALL) and not inside((9.9, 0.0), WALL) and not inside((10.2, 11.0), WALL)
    assert obstacle_distance_m((0.0, 0.0), [WALL]) == pytest.approx(10.0)
    assert obstacle_distance_m((10.2, 3.0), [WALL]) == 0.0
    assert obstacle_distance_m((10.25, 13.0), [WALL]) == pytest.approx(3.0)  # past its end
    assert obstacle_distance_m((0.0, 0.0), [Circle((3.0, 4.0), 1.0)]) == pytest.approx(4.0)
    assert obstacle_distance_m((0.0, 0.0), []) is None


# ------------------------------------------------------------------ scenario
def test_a_scenario_file_places_obstacles_and_refuses_bad_ones(tmp_path: Path) -> None:
    good = tmp_path / "wall.toml"
    good.write_text('[[obstacles]]\npolygon = [[10, -10], [10, 10], [10.5, 10], [10.5, -10]]\n\n'
                    '[[obstacles]]\ncircle = [4.0, 3.0]\nradius_m = 0.5\n')
    sc = load_scenario(good)
    assert sc.obstacles == (WALL, Circle((4.0, 3.0), 0.5))
    bad = tmp_path / "bad.toml"
    bad.write_text('[[obstacles]]\npolygon = [[0, 0], [1, 1]]\n\n[[obstacles]]\ncircle = [1, 2]\n')
    with pytest.raises(ConfigError) as info:
        load_scenario(bad)
    assert len(info.value.problems) == 2 and "3 vertices" in info.value.problems[0]


def test_the_emulator_reports_the_truth_distance_and_a_collision() -> None:
    emu = Emulator(VehicleConfig(start_armed=True), Scenario(obstacles=(WALL,)))
    assert emu.nearest_obstacle_m() == pytest.approx(10.0) and not emu.collided()
    emu.teleport(10.3, 0.0)
    assert emu.nearest_obstacle_m() == 0.0 and emu.collided()
    assert Emulator().nearest_obstacle_m() is None


# ------------------------------------------------------------------ proximity sectors
def test_sitl_bisection_reads_short_by_less_than_its_accuracy() -> None:
    for true_m in (0.05, 1.0, 2.16, 10.0, 123.4):
        assert true_m - 0.1 < sitl_bisection_m(true_m) <= true_m
    assert sitl_bisection_m(None) == pytest.approx(200.0, abs=0.1)


def test_sectors_of_a_wall_ahead_to_the_side_and_after_a_turn() -> None:
    ahead = proximity_sectors_m(at(), [WALL])
    assert ahead[0] == pytest.approx(10.0, abs=0.1)
    assert ahead[1] == pytest.approx(10.0 * math.sqrt(2.0), abs=0.1) and ahead[7] == pytest.approx(ahead[1])
    assert all(d == pytest.approx(200.0, abs=0.1) for d in ahead[2:7])  # nothing right, behind, left
    # Facing east the wall is on the left (sector 6, 270 deg clockwise from forward).
    turned = proximity_sectors_m(at(yaw_deg=90.0), [WALL])
    assert turned[6] == pytest.approx(10.0, abs=0.1) and turned[0] == pytest.approx(200.0, abs=0.1)
    assert turned[5] == pytest.approx(10.0 * math.sqrt(2.0), abs=0.1)
    # Facing west: on the right (sector 2).
    assert proximity_sectors_m(at(yaw_deg=-90.0), [WALL])[2] == pytest.approx(10.0, abs=0.1)
    # Closer: 2 m from the wall.
    assert proximity_sectors_m(at(x_m=8.0), [WALL])[0] == pytest.approx(2.0, abs=0.1)


def _distance_sensors(gcs: InProcessGcs, seconds: float) -> list[MAVLinkMessage]:
    return [m for m in gcs.run(seconds) if m.get_type() == "DISTANCE_SENSOR"]


def test_proximity_sends_eight_sectors_and_the_upward_distance_at_the_extra3_rate() -> None:
    vehicle = VehicleConfig(start_armed=True, params=(("PRX1_TYPE", 10.0),))
    emu = Emulator(vehicle, Scenario(obstacles=(WALL,)), record_sent=True)
    gcs = InProcessGcs(emu)
    gcs.run(0.5)
    msgs = _distance_sensors(gcs, 10.0)
    assert len(msgs) == 90  # 9 per second at SR0_EXTRA3 = 1 Hz, as on ArduPilot's SITL
    first = msgs[:9]
    assert [m.id for m in first] == [10 + k for k in range(8)] + [19]
    assert [m.orientation for m in first] == [*range(8), _P.MAV_SENSOR_ROTATION_PITCH_90]
    assert all(m.min_distance == 0 and m.max_distance == 20000 and m.covariance == 0 for m in first)
    assert all(m.type == _P.MAV_DISTANCE_SENSOR_LASER for m in first)
    assert 990 <= first[0].current_distance <= 1000 and first[4].current_distance >= 19990
    assert first[8].current_distance == 10000
    # A faster EXTRA3 stream is a faster sensor.
    gcs.send(gcs.mav.param_set_encode(1, 1, b"SR0_EXTRA3", 10.0, _P.MAV_PARAM_TYPE_INT16))
    gcs.run(0.1)
    assert 85 <= len(_distance_sensors(gcs, 1.0)) <= 95


def test_no_sensor_fitted_sends_no_distance_sensor_and_no_walls_send_only_the_upward_one() -> None:
    emu = Emulator(VehicleConfig(start_armed=True), Scenario(obstacles=(WALL,)), record_sent=True)
    assert _distance_sensors(InProcessGcs(emu), 3.0) == []
    emu = Emulator(VehicleConfig(params=(("PRX1_TYPE", 10.0),)), record_sent=True)
    msgs = _distance_sensors(InProcessGcs(emu), 3.0)
    assert msgs and {m.id for m in msgs} == {19}


def test_the_proximity_sensor_sees_the_inclusion_fence_as_walls() -> None:
    # As ArduPilot's PRX1_TYPE 10: a fence square 10 m around the origin, no scenario obstacle, FENCE_ENABLE 0.
    emu = Emulator(VehicleConfig(start_armed=True, params=(("PRX1_TYPE", 10.0),)), record_sent=True)
    gcs = InProcessGcs(emu)
    corners = [(10.0, -10.0), (10.0, 10.0), (-10.0, 10.0), (-10.0, -10.0)]
    items = [gcs.fence_item(i, POLYGON_INCLUSION, n, e, 4) for i, (n, e) in enumerate(corners)]
    assert gcs.upload(items, mission_type=FENCE) == _P.MAV_MISSION_ACCEPTED
    emu.teleport(4.0, 0.0, math.radians(90.0))  # facing east, 6 m from the north edge
    msgs = _distance_sensors(gcs, 1.5)[:9]
    by_id = {m.id: m.current_distance for m in msgs}
    assert 980 <= by_id[10] <= 1000  # ahead (east): 10 m
    assert 590 <= by_id[16] <= 600  # left (north): 6 m
    assert 1390 <= by_id[12] <= 1400  # right (south): 14 m


def test_a_forward_rangefinder_reports_with_its_orientation_and_range() -> None:
    params = (("RNGFND1_TYPE", 100.0), ("RNGFND1_ORIENT", 0.0))
    emu = Emulator(VehicleConfig(start_armed=True, params=params), Scenario(obstacles=(WALL,)), record_sent=True)
    emu.teleport(5.0, 0.0)
    gcs = InProcessGcs(emu)
    gcs.run(0.5)
    msgs = _distance_sensors(gcs, 3.0)
    assert len(msgs) == 3
    m = msgs[0]
    assert (m.id, m.orientation, m.min_distance, m.max_distance) == (0, 0, 20, 700)
    assert m.type == _P.MAV_DISTANCE_SENSOR_UNKNOWN and m.current_distance == 500
    emu.teleport(0.0, 0.0)  # 10 m: beyond its 7 m
    assert _distance_sensors(gcs, 1.0)[0].current_distance == 800
    emu.teleport(5.0, 0.0, math.radians(90.0))  # facing along the wall: nothing
    assert _distance_sensors(gcs, 1.0)[0].current_distance == 800


# ------------------------------------------------------------------ OBSTACLE_DISTANCE
def test_the_depth_camera_sends_obstacle_distance_from_its_own_component() -> None:
    vehicle = VehicleConfig(start_armed=True, obstacle_distance_hz=10.0, obstacle_distance_fov_deg=90.0,
                            obstacle_distance_max_m=20.0)
    emu = Emulator(vehicle, Scenario(obstacles=(WALL,)), record_sent=True)
    emu.teleport(5.0, 0.0)
    msgs = [m for m in InProcessGcs(emu).run(2.0) if m.get_type() == "OBSTACLE_DISTANCE"]
    assert 19 <= len(msgs) <= 21
    m = msgs[-1]
    assert m.get_srcComponent() == _P.MAV_COMP_ID_OBSTACLE_AVOIDANCE and m.get_srcSystem() == 1
    assert (m.increment, m.increment_f, m.angle_offset, m.frame) == (5, 5.0, 0.0, _P.MAV_FRAME_BODY_FRD)
    assert (m.min_distance, m.max_distance) == (20, 2000)
    d = list(m.distances)
    assert len(d) == 72 and d[0] == 500
    assert d[9] == int(5.0 / math.cos(math.radians(45.0)) * 100.0)  # 45 deg right
    assert d[8] == int(5.0 / math.cos(math.radians(40.0)) * 100.0) and d[64] == d[8]  # 40 deg left
    assert all(x == 65535 for x in d[10:63])  # outside the 90 deg field of view: unknown
    emu.teleport(5.0, 0.0, math.pi)  # facing away: in view, no obstacle = max + 1
    last = [m for m in InProcessGcs(emu).run(0.2) if m.get_type() == "OBSTACLE_DISTANCE"][-1]
    assert last.distances[0] == 2001


# ------------------------------------------------------------------ fence transfers
def test_fence_upload_and_download_keep_every_item() -> None:
    emu = Emulator(VehicleConfig(), record_sent=True)
    gcs = InProcessGcs(emu)
    items = [gcs.fence_item(i, POLYGON_INCLUSION, n, e, 3) for i, (n, e) in enumerate([(0, 0), (20, 0), (0, 20)])]
    items += [gcs.fence_item(3 + i, POLYGON_EXCLUSION, n, e, 3) for i, (n, e) in enumerate([(5, 5), (6, 5), (5, 6)])]
    items.append(gcs.fence_item(6, CIRCLE_EXCLUSION, 2.0, 2.0, 1.5))
    assert gcs.upload(items, mission_type=FENCE) == _P.MAV_MISSION_ACCEPTED
    requests = [m for m in gcs.received if m[1].get_type() == "MISSION_REQUEST"]
    assert requests and all(m.mission_type == FENCE for _, m in requests)
    got = gcs.download(mission_type=FENCE)
    assert [(m.seq, m.command, m.param1, m.x, m.y, m.mission_type) for m in got] == [
        (i.seq, i.command, i.param1, i.x, i.y, FENCE) for i in items]
    assert len(gcs.download()) == 1  # the mission is untouched: home only
    shapes = emu.autopilot.fence.shapes(emu.vehicle.origin_lat_deg, emu.vehicle.origin_lon_deg)
    assert len(shapes.inclusion) == 1 and len(shapes.exclusion) == 2
    assert isinstance(shapes.inclusion[0], Polygon)
    assert shapes.inclusion[0].vertices[1] == pytest.approx((20.0, 0.0), abs=0.02)
    # Cleared with MISSION_CLEAR_ALL of type FENCE; kept across a reboot before that.
    emu.reboot()
    gcs.run(2.0)
    assert len(gcs.download(mission_type=FENCE)) == 7
    gcs.send(gcs.mav.mission_clear_all_encode(1, 1, FENCE))
    gcs.run(0.05)
    assert gcs.download(mission_type=FENCE) == []


def test_a_bad_fence_is_refused_and_the_old_one_kept() -> None:
    emu = Emulator(VehicleConfig(), record_sent=True)
    gcs = InProcessGcs(emu)
    good = [gcs.fence_item(i, POLYGON_INCLUSION, n, e, 3) for i, (n, e) in enumerate([(0, 0), (20, 0), (0, 20)])]
    assert gcs.upload(good, mission_type=FENCE) == _P.MAV_MISSION_ACCEPTED
    short = [gcs.fence_item(i, POLYGON_INCLUSION, n, e, 4) for i, (n, e) in enumerate([(0, 0), (20, 0), (0, 20)])]
    assert gcs.upload(short, mission_type=FENCE) == _P.MAV_MISSION_ERROR  # says 4 vertices, has 3
    waypoint = gcs.mav.mission_item_int_encode(1, 1, 0, _P.MAV_FRAME_GLOBAL_INT, _P.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0,
                                               0.0, 0.0, 0.0, 0, 0, 0.0, FENCE)
    assert gcs.upload([waypoint], mission_type=FENCE) == _P.MAV_MISSION_UNSUPPORTED
    assert len(gcs.download(mission_type=FENCE)) == 3


# ------------------------------------------------------------------ parameters
def test_avoidance_fence_and_sensor_parameters_are_readable_with_ardupilots_defaults() -> None:
    emu = Emulator(VehicleConfig(), record_sent=True)
    gcs = InProcessGcs(emu)
    expected = {"AVOID_ENABLE": 3.0, "AVOID_MARGIN": 2.0, "AVOID_BACKUP_SPD": 0.75, "AVOID_BEHAVE": 1.0,
                "FENCE_ENABLE": 0.0, "FENCE_RADIUS": 300.0, "FENCE_MARGIN": 2.0, "FENCE_TYPE": 6.0,
                "FENCE_ACTION": 1.0, "PRX1_TYPE": 0.0, "RNGFND1_TYPE": 0.0, "RNGFND1_ORIENT": 25.0,
                "RNGFND1_MIN": 0.2, "RNGFND1_MAX": 7.0}
    for name in expected:
        gcs.send(gcs.mav.param_request_read_encode(1, 1, name.encode(), -1))
    got = {m.param_id: m.param_value for m in gcs.run(0.05) if m.get_type() == "PARAM_VALUE"}
    assert got == pytest.approx(expected)
    gcs.send(gcs.mav.param_request_list_encode(1, 1))
    listed = {m.param_id for m in gcs.run(0.05) if m.get_type() == "PARAM_VALUE"}
    assert set(expected) <= listed


# ------------------------------------------------------------------ on the wire
def test_over_udp_the_sectors_come_from_the_autopilot_and_the_scan_from_the_camera_component() -> None:
    vehicle = VehicleConfig(start_armed=True, params=(("PRX1_TYPE", 10.0),), obstacle_distance_hz=10.0)
    with Emulator(vehicle, Scenario(obstacles=(WALL,))) as emu:
        emu.open("udpin:127.0.0.1:0")
        client = mavutil.mavlink_connection(f"udpout:127.0.0.1:{emu.local_address[1]}", source_system=255)
        try:
            client.mav.heartbeat_send(_P.MAV_TYPE_GCS, _P.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            seen: dict[str, set[int]] = {"DISTANCE_SENSOR": set(), "OBSTACLE_DISTANCE": set()}
            for _ in range(300):  # 3 s of simulated time, lockstep: no wall-clock timing in the assertion
                emu.step(0.01)
                while (m := client.recv_match(blocking=False)) is not None:
                    if m.get_type() in seen:
                        seen[m.get_type()].add(m.get_srcComponent())
        finally:
            client.close()
    assert seen == {"DISTANCE_SENSOR": {1}, "OBSTACLE_DISTANCE": {_P.MAV_COMP_ID_OBSTACLE_AVOIDANCE}}


def test_a_stalled_fence_upload_times_out_and_legacy_items_are_scaled() -> None:
    emu = Emulator(VehicleConfig(), record_sent=True)
    gcs = InProcessGcs(emu)
    gcs.send(gcs.mav.mission_count_encode(1, 1, 3, FENCE))
    sent = gcs.run(9.0)
    requests = [m for m in sent if m.get_type() == "MISSION_REQUEST"]
    assert len(requests) >= 8 and all(m.seq == 0 and m.mission_type == FENCE for m in requests)  # re-asked each second
    assert "Fence upload timeout" in gcs.texts()
    acks = [m for m in sent if m.get_type() == "MISSION_ACK"]
    assert [(m.type, m.mission_type) for m in acks] == [(_P.MAV_MISSION_OPERATION_CANCELLED, FENCE)]
    # MISSION_ITEM (float degrees) is taken as ArduPilot converts it: lat/lon * 1e7.
    lat, lon = emu.vehicle.origin_lat_deg, emu.vehicle.origin_lon_deg
    gcs.send(gcs.mav.mission_count_encode(1, 1, 1, FENCE))
    gcs.run(0.02)
    gcs.send(gcs.mav.mission_item_encode(1, 1, 0, _P.MAV_FRAME_GLOBAL, CIRCLE_EXCLUSION, 0, 1, 5.0, 0.0, 0.0, 0.0,
                                         lat, lon, 0.0, FENCE))
    assert gcs.run(0.02)[-1].type == _P.MAV_MISSION_ACCEPTED
    item = emu.autopilot.fence.items[0]
    # (MISSION_ITEM's float32 keeps about 1.5e-5 deg of a longitude of 149 deg.)
    assert (item.x, item.y, item.param1) == pytest.approx((round(lat * 1e7), round(lon * 1e7), 5.0), abs=200)


def test_only_the_proximity_sensor_sees_the_fence_the_rangefinder_and_camera_see_things() -> None:
    emu = Emulator(VehicleConfig(start_armed=True, params=(("RNGFND1_TYPE", 100.0), ("RNGFND1_ORIENT", 0.0)),
                                 obstacle_distance_hz=10.0), record_sent=True)
    gcs = InProcessGcs(emu)
    items = [gcs.fence_item(i, POLYGON_INCLUSION, n, e, 3) for i, (n, e) in enumerate([(3, -3), (3, 3), (-3, 0)])]
    assert gcs.upload(items, mission_type=FENCE) == _P.MAV_MISSION_ACCEPTED
    sent = gcs.run(1.5)
    assert {m.current_distance for m in sent if m.get_type() == "DISTANCE_SENSOR"} == {800}  # clear: max + 1 m
    scans = [m for m in sent if m.get_type() == "OBSTACLE_DISTANCE"]
    assert scans and all(set(m.distances) == {2001} for m in scans)  # 360 deg, nothing within 20 m
