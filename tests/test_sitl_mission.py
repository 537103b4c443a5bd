"""The emulator's mission protocol, as ArduPilot speaks it (sitl/mission_protocol.py), through sitl/gcs.py:
every message packed and decoded as on the wire, in simulated time."""

from __future__ import annotations

import math

from sitl import Emulator, VehicleConfig
from sitl.gcs import InProcessGcs
from sitl.geo import north_east_of
from sitl.mav import MAVLinkMessage, mavlink
from sitl.modes import MODE_AUTO

P = mavlink
V = VehicleConfig()


def rig(vehicle: VehicleConfig = V) -> InProcessGcs:
    g = InProcessGcs(Emulator(vehicle, seed=1, record_sent=True))
    g.heartbeat()
    g.run(0.1)
    return g


def square(g: InProcessGcs) -> list[MAVLinkMessage]:
    return [g.waypoint(0, 0.0, 0.0)] + [g.waypoint(i + 1, n, e) for i, (n, e) in enumerate([(6, 0), (6, 6), (0, 6)])]


def test_upload_is_asked_item_by_item_and_downloads_back_with_home_as_item_0() -> None:
    g = rig()
    items = square(g)
    assert g.upload(items) == P.MAV_MISSION_ACCEPTED
    requests = g.of("MISSION_REQUEST")
    assert [r.seq for r in requests] == [0, 1, 2, 3]  # ArduPilot asks with MISSION_REQUEST, not _INT
    assert all((r.target_system, r.target_component) == (255, 190) for r in requests)
    assert "Flight plan received" in g.texts()
    down = g.download()
    assert [m.seq for m in down] == [0, 1, 2, 3]
    home = down[0]
    v = g.emu.vehicle
    assert (home.x, home.y, home.frame) == (round(v.origin_lat_deg * 1e7), round(v.origin_lon_deg * 1e7), 0)
    for sent, got in zip(items[1:], down[1:], strict=True):
        assert (got.x, got.y, got.command) == (sent.x, sent.y, P.MAV_CMD_NAV_WAYPOINT)
        assert got.frame == P.MAV_FRAME_GLOBAL_RELATIVE_ALT  # the non-INT frame number, as ArduPilot returns it
    n, e = north_east_of(down[2].x * 1e-7, down[2].y * 1e-7, v.origin_lat_deg, v.origin_lon_deg)
    assert math.hypot(n - 6.0, e - 6.0) < 0.02


def test_legacy_mission_item_and_request_are_converted_and_warned_once() -> None:
    g = rig()
    items = [g.mav.mission_item_encode(1, 1, i, P.MAV_FRAME_GLOBAL_RELATIVE_ALT, P.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                       0, 0, 0, 0, -35.363261 + 1e-5 * i, 149.165230, 0.0) for i in range(3)]
    assert g.upload(items) == P.MAV_MISSION_ACCEPTED
    assert g.texts().count("got MISSION_ITEM; GCS should send MISSION_ITEM_INT") == 1
    g.send(g.mav.mission_request_encode(1, 1, 2, 0))
    g.send(g.mav.mission_request_encode(1, 1, 1, 0))
    g.run(0.02)
    got = g.of("MISSION_ITEM")
    assert [m.seq for m in got] == [2, 1]
    assert abs(got[0].x - (-35.363261 + 2e-5)) < 5e-6  # MISSION_ITEM's float32 latitude: about 0.2 m
    assert g.texts().count("got MISSION_REQUEST; use MISSION_REQUEST_INT!") == 1


def test_out_of_sequence_other_sender_outside_upload_and_bad_frame() -> None:
    g = rig()
    items = square(g)
    g.send(g.mav.mission_count_encode(1, 1, 4, 0))
    g.run(0.02)
    g.send(items[1])  # seq 1 while 0 is wanted
    g.run(0.02)
    assert g.of("MISSION_ACK")[-1].type == P.MAV_MISSION_INVALID_SEQUENCE
    other = InProcessGcs(g.emu, sysid=254)
    other.send(other.mav.mission_count_encode(1, 1, 2, 0))
    assert [a.type for a in other.run(0.02) if a.get_type() == "MISSION_ACK"] == [P.MAV_MISSION_DENIED]
    bad = g.mav.mission_item_int_encode(1, 1, 0, P.MAV_FRAME_LOCAL_NED, P.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                        0, 0, 0, 0, 0, 0, 0.0)
    g.send(bad)
    g.run(0.02)
    assert g.of("MISSION_ACK")[-1].type == P.MAV_MISSION_UNSUPPORTED_FRAME
    g.send(items[1])  # the upload ended with that error
    g.run(0.02)
    assert g.of("MISSION_ACK")[-1].type == P.MAV_MISSION_ERROR


def test_unanswered_request_is_repeated_then_the_upload_times_out() -> None:
    g = rig()
    g.send(g.mav.mission_count_encode(1, 1, 3, 0))
    g.run(9.0)
    assert len(g.of("MISSION_REQUEST")) == 8  # at once, then once a second
    assert "Mission upload timeout" in g.texts()
    assert g.of("MISSION_ACK")[-1].type == P.MAV_MISSION_OPERATION_CANCELLED


def test_clear_all_and_count_zero_empty_the_mission_and_auto_is_refused() -> None:
    g = rig(VehicleConfig(start_armed=True))
    assert g.upload(square(g)) == P.MAV_MISSION_ACCEPTED
    g.send(g.mav.mission_clear_all_encode(1, 1, 0))
    g.run(0.02)
    assert g.of("MISSION_ACK")[-1].type == P.MAV_MISSION_ACCEPTED
    assert g.download() == []  # AP_Mission::clear truncates to 0; home is written back when home next moves
    assert g.set_mode(MODE_AUTO) == P.MAV_RESULT_FAILED
    assert "No Mission. Can't set AUTO." in g.texts() and "Flight mode change failed" in g.texts()
    assert g.upload(square(g)) == P.MAV_MISSION_ACCEPTED
    assert g.upload([]) == P.MAV_MISSION_ACCEPTED
    assert g.download() == []


def test_clear_is_refused_while_the_mission_runs_armed() -> None:
    g = rig(VehicleConfig(start_armed=True))
    g.upload(square(g))
    assert g.set_mode(MODE_AUTO) == P.MAV_RESULT_ACCEPTED
    g.run(1.0)
    g.send(g.mav.mission_clear_all_encode(1, 1, 0))
    g.run(0.02)
    assert g.of("MISSION_ACK")[-1].type == P.MAV_MISSION_ERROR


def test_mission_current_streams_and_set_current_answers_with_it() -> None:
    g = rig()
    g.run(2.0)
    empty = g.of("MISSION_CURRENT")[-1]
    assert (empty.seq, empty.total, empty.mission_state) == (0, 0, P.MISSION_STATE_NO_MISSION)
    g.upload(square(g))
    g.send(g.mav.mission_set_current_encode(1, 1, 2))
    answer = [m for m in g.run(0.02) if m.get_type() == "MISSION_CURRENT"]
    assert answer and answer[0].seq == 2
    g.run(1.0)
    now = g.of("MISSION_CURRENT")[-1]
    assert (now.seq, now.total, now.mission_state, now.mission_mode) == (2, 3, P.MISSION_STATE_NOT_STARTED, 0)


def test_guided_go_here_items_are_not_mission_items() -> None:
    g = rig()
    go_here = g.mav.mission_item_int_encode(1, 1, 0, 6, P.MAV_CMD_NAV_WAYPOINT, 2, 0, 0, 0, 0, 0,
                                            -353632610, 1491652300, 0.0)
    g.send(go_here)
    out = g.run(0.05)
    assert not [m for m in out if m.get_type() in ("MISSION_ACK", "MISSION_REQUEST")]
    assert g.emu.counters["mission_guided_ignored"] == 1
    assert len(g.download()) == 1


def test_the_mission_survives_a_reboot_and_fence_and_rally_lists_are_empty() -> None:
    g = rig()
    g.upload(square(g))
    g.emu.reboot()
    g.run(2.0)
    assert len(g.download()) == 4
    g.send(g.mav.mission_request_list_encode(1, 1, P.MAV_MISSION_TYPE_FENCE))
    counts = [m for m in g.run(0.02) if m.get_type() == "MISSION_COUNT"]
    assert (counts[-1].count, counts[-1].mission_type) == (0, P.MAV_MISSION_TYPE_FENCE)
