"""The fence's wiring (issue 43 item 3): the download (rover_bridge.command.fence_download), the stored fence's items
as fences (fences.stored_fences), where the rover is on them (fence_watch.FenceWatch.query), and the command core
acting on them: FENCE_* read from the autopilot, home asked for, a crawl while the rover cannot be placed, a new
download when another client's upload is accepted, the parameters read again when the fence is switched."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from navsupport import LAT0, LON0, FakeSource, lat_lon
from test_command_core import overrides, profile, texts
from test_proximity_core import AvoidRig

from rover_bridge.command.core import CommandCore
from rover_bridge.command.fence_download import ATTEMPTS, RESEND_S, RETRY_S, TYPE_FENCE, FenceDownload
from rover_bridge.command.fence_watch import FenceConfig, FenceWatch
from rover_bridge.command.fences import (
    CIRCLE_EXCLUSION,
    CIRCLE_INCLUSION,
    POLYGON_EXCLUSION,
    POLYGON_INCLUSION,
    CircleFence,
    Fences,
    fence_clearance,
    stored_fences,
)
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.wire import Link, Outgoing
from rover_bridge.odometry import Pose2D

AP = (1, 1)
US = (1, 191)
GUIDED, MANUAL = 15, 0


def item(seq: int, command: int, param1: float, lat_e7: int = 0, lon_e7: int = 0) -> MAVLinkMessage:
    return mavlink.MAVLink_mission_item_int_message(*US, seq, 0, command, 0, 1, param1, 0.0, 0.0, 0.0, lat_e7,
                                                    lon_e7, 0.0, TYPE_FENCE)


def kinds(msgs: list[MAVLinkMessage]) -> list[tuple[str, int]]:
    return [(m.get_type(), int(getattr(m, "seq", -1))) for m in msgs]


# ----------------------------------------------------------------- the download


def test_a_download_asks_for_the_list_then_each_item_and_acks_at_the_end() -> None:
    d = FenceDownload()
    d.start(0.0)
    assert kinds(d.requests(0.0, AP)) == [("MISSION_REQUEST_LIST", -1)]
    count = mavlink.MAVLink_mission_count_message(*US, 2, TYPE_FENCE)
    assert kinds(d.on_message(count, 0.1, AP)) == [("MISSION_REQUEST_INT", 0)]
    assert d.on_message(item(1, POLYGON_INCLUSION, 2), 0.2, AP) == []  # out of turn: ignored
    assert kinds(d.on_message(item(0, POLYGON_INCLUSION, 2), 0.2, AP)) == [("MISSION_REQUEST_INT", 1)]
    done = d.on_message(item(1, POLYGON_INCLUSION, 2), 0.3, AP)
    assert [(m.get_type(), m.type, m.mission_type) for m in done] == [("MISSION_ACK", 0, TYPE_FENCE)]
    assert d.items is not None and len(d.items) == 2 and d.version == 1 and not d.running


def test_an_unanswered_step_is_asked_again_then_the_download_waits_and_begins_afresh() -> None:
    d = FenceDownload()
    d.start(0.0)
    asked = [t for t in (k * RESEND_S for k in range(ATTEMPTS + 1)) if d.due(t) and d.requests(t, AP)]
    assert len(asked) == ATTEMPTS  # the sixth due time gives up
    assert not d.due(ATTEMPTS * RESEND_S + RETRY_S - 0.01) and d.due(ATTEMPTS * RESEND_S + RETRY_S)
    assert kinds(d.requests(ATTEMPTS * RESEND_S + RETRY_S, AP)) == [("MISSION_REQUEST_LIST", -1)]


def test_a_denied_download_keeps_the_last_fence_and_tries_again_later() -> None:
    d = FenceDownload()
    d.start(0.0)
    d.on_message(mavlink.MAVLink_mission_count_message(*US, 0, TYPE_FENCE), 0.1, AP)
    assert d.items == () and d.version == 1
    d.start(1.0)  # the fence changed
    d.requests(1.0, AP)
    denied = mavlink.MAVLink_mission_ack_message(*US, mavlink.MAV_MISSION_DENIED, TYPE_FENCE)
    assert d.on_message(denied, 1.1, AP) == []
    assert d.items == () and d.running and d.due(1.1 + RETRY_S)


# ----------------------------------------------------------------- items -> fences


def test_stored_items_become_polygons_and_circles_about_home() -> None:
    def ll(n: float, e: float) -> tuple[float, float]:
        return lat_lon(n, e)

    square = [ll(10, -10), ll(10, 10), ll(-10, 10), ll(-10, -10)]
    items = [(POLYGON_INCLUSION, 4.0, *p) for p in square]
    items += [(POLYGON_EXCLUSION, 3.0, *ll(5, 0)), (POLYGON_EXCLUSION, 3.0, *ll(5, 1))]  # broken: 2 of 3
    items += [(5000, 0.0, *ll(0, 0)), (CIRCLE_EXCLUSION, 2.0, *ll(0, 5)), (CIRCLE_INCLUSION, 0.0, *ll(0, 0))]
    polygons, circles = stored_fences(items, LAT0, LON0)
    assert len(polygons) == 1 and polygons[0].inclusion
    assert [(round(n, 3), round(e, 3)) for n, e in polygons[0].points_ne] == [(10, -10), (10, 10), (-10, 10),
                                                                               (-10, -10)]
    assert len(circles) == 1 and not circles[0].inclusion and circles[0].radius_m == 2.0
    assert (round(circles[0].center_north_m, 3), round(circles[0].center_east_m, 3)) == (0.0, 5.0)


@settings(max_examples=300, deadline=None)
@given(st.floats(0.0, 2 * math.pi), st.floats(3.5, 40.0), st.floats(0.0, 2 * math.pi), st.floats(0.0, 3.0))
def test_an_exclusion_circles_clearance_never_leads_inside_its_margin(bearing: float, dist_m: float,
                                                                        heading: float, margin_m: float) -> None:
    circle = CircleFence(3.0, 1.0, -2.0, inclusion=False)
    n, e = 1.0 + dist_m * math.cos(bearing), -2.0 + dist_m * math.sin(bearing)
    clearance = fence_clearance(Fences(margin_m, circles=(circle,)), n, e, heading)
    if clearance.distance_m is None:
        return
    end_n, end_e = n + clearance.distance_m * math.cos(heading), e + clearance.distance_m * math.sin(heading)
    assert math.hypot(end_n - 1.0, end_e + 2.0) >= min(3.0 + margin_m, dist_m) - 1e-6


# ----------------------------------------------------------------- where the rover is


@dataclass
class MovedSince:
    """A GPS fix 0.5 s old at north 3 m / east 4 m of home; the estimate has moved 2 m along x since, its x axis
    pointing east (ATTITUDE: 90 deg)."""

    now: float = 10.0

    def nav_pose(self, now_s: float) -> Pose2D | None:
        return Pose2D(2.0, 0.0, 0.0)

    def nav_pose_at(self, stamp_s: float) -> Pose2D:
        return Pose2D(0.0, 0.0, 0.0)

    def autopilot_time_s(self, now_s: float) -> float:
        return now_s

    @property
    def heading(self) -> tuple[float, float] | None:
        return self.now, math.pi / 2

    @property
    def gps(self) -> tuple[float, float, float, float] | None:
        return self.now - 0.5, self.now - 0.5, *lat_lon(3.0, 4.0)

    position_fixes: tuple[()] = ()
    reset_counter: int = 0


def test_the_rover_is_placed_at_the_fix_plus_the_estimates_travel_since() -> None:
    watch = FenceWatch(Identity(learned_system_id=1), MovedSince(), 2.0, 1.0)
    watch.configure(FenceConfig(True, 2, 12.0, 2.0), 10.0)
    assert watch.query(10.0) is None  # no home yet
    watch.on_home(mavlink.MAVLink_home_position_message(round(LAT0 * 1e7), round(LON0 * 1e7), 0, 0, 0, 0,
                                                         [1, 0, 0, 0], 0, 0, 0))
    q = watch.query(10.0)
    assert q is not None
    assert (q.north_m, q.east_m, q.heading_cw_rad) == pytest.approx((3.0, 6.0, math.pi / 2), abs=1e-3)
    assert watch.query(12.6) is None  # the fix is older than gps_timeout_s: unknown


# ----------------------------------------------------------------- the command core


class FenceRig(AvoidRig):
    def __init__(self, fence_params: dict[str, float] | None = None, source: FakeSource | None = None) -> None:
        super().__init__(profile(limits={"max_linear_decel_m_s2": 100.0}))
        self.source = source or FakeSource()
        self.core = CommandCore(self.profile, self.identity, self.reporter, pose_source=self.source)
        self.heartbeat(0.0, mode=GUIDED)
        self.tick(0.01)
        params = {"AVOID_ENABLE": 1.0, "AVOID_MARGIN": 2.0, "AVOID_BACKUP_SPD": 0.75, "FENCE_ENABLE": 1.0,
                  "FENCE_TYPE": 2.0, "FENCE_RADIUS": 12.0, "FENCE_MARGIN": 2.0, **(fence_params or {})}
        for name, value in params.items():
            self.param(0.02, name, value)

    def home(self, t: float) -> None:
        msg = mavlink.MAVLink_home_position_message(round(LAT0 * 1e7), round(LON0 * 1e7), 0, 0, 0, 0, [1, 0, 0, 0],
                                                    0, 0, 0)
        self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def at(self, north_m: float, t: float) -> None:
        self.source.pose = Pose2D(north_m, 0.0, 0.0)
        self.source.now_s = t
        self.attitude(t, 0.0)


def home_requests(out: list[Outgoing]) -> int:
    return sum(1 for o in out if o.msg.get_type() == "COMMAND_LONG" and o.msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE
               and o.msg.param1 == mavlink.MAVLINK_MSG_ID_HOME_POSITION)


def test_the_circle_fence_caps_the_bridges_drivers_once_home_is_known_and_crawls_before() -> None:
    rig = FenceRig()
    assert home_requests(rig.tick(0.05)) == 1  # the fence is on: home asked for
    rig.at(0.0, 0.1)
    assert overrides(rig.local(0.11, vx=0.5, mask=3527).out) != [(1739, 1739)]  # not placed: a crawl
    assert rig.core.commanded.v_m_s == pytest.approx(0.2)
    assert "RB: fence on, no home yet: crawling (0.2 m/s)" in texts(rig.sent)
    assert home_requests(rig.tick(2.1)) == 1  # asked again until it comes
    ack = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED, 0, 0,
                                              *US)
    assert rig.feed(Link.AUTOPILOT, rig.wire(rig.ap, ack), 2.15).consumed  # its answer is the bridge's own
    rig.home(2.2)
    rig.at(0.0, 2.3)
    assert overrides(rig.local(2.31, vx=0.5, mask=3527).out) == [(1739, 1739)]  # 10 m of room: full speed
    rig.at(9.95, 2.4)
    rig.local(2.41, vx=0.5, mask=3527)
    assert rig.core.commanded.v_m_s == 0.0  # at FENCE_RADIUS - FENCE_MARGIN: stop
    assert "RB: fence ahead: slowing to stop 2 m inside" in texts(rig.sent)
    assert rig.local(2.42, vx=-0.5, mask=3527) and rig.core.commanded.v_m_s == pytest.approx(-0.5)  # back in
    rig.heartbeat(2.5, mode=MANUAL)
    rig.manual(2.51, 1000, 0)
    assert rig.core.commanded.v_m_s > 0.0  # MANUAL: not avoided (ArduPilot neither)
    assert rig.core.counters["avoid.fence_stop"] >= 1 and rig.core.counters["avoid.fence_unknown"] == 1


def test_without_a_fresh_gps_fix_the_rover_crawls() -> None:
    rig = FenceRig()
    rig.home(0.05)
    rig.source.gps_on = False
    rig.at(0.0, 0.1)
    rig.local(0.11, vx=0.5, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(0.2)
    assert "RB: fence on, no GPS fix: crawling (0.2 m/s)" in texts(rig.sent)


def test_fence_enable_0_or_avoid_enable_without_bit_0_changes_nothing() -> None:
    for params in ({"FENCE_ENABLE": 0.0}, {"AVOID_ENABLE": 2.0}):
        rig = FenceRig(params)
        assert home_requests(rig.tick(0.05)) == 0
        rig.at(11.0, 0.1)
        assert overrides(rig.local(0.11, vx=0.5, mask=3527).out) == [(1739, 1739)]
        assert rig.core.avoid.fence.fences is None


def test_another_clients_accepted_fence_upload_starts_a_download_and_ours_are_consumed() -> None:
    rig = FenceRig({"FENCE_TYPE": 4.0})
    first = [o.msg for o in rig.tick(0.05) if o.msg.get_type() == "MISSION_REQUEST_LIST"]
    assert len(first) == 1 and first[0].mission_type == TYPE_FENCE
    count = mavlink.MAVLink_mission_count_message(*US, 0, TYPE_FENCE)
    reaction = rig.feed(Link.AUTOPILOT, rig.wire(rig.ap, count), 0.06)
    assert reaction.consumed and [o.msg.get_type() for o in reaction.out] == ["MISSION_ACK"]
    assert rig.core.avoid.fence.download.items == ()
    theirs = mavlink.MAVLink_mission_ack_message(255, 190, mavlink.MAV_MISSION_ACCEPTED, TYPE_FENCE)
    reaction = rig.feed(Link.AUTOPILOT, rig.wire(rig.ap, theirs), 1.0)
    assert not reaction.consumed  # the GCS's answer goes on to it
    assert [o.msg.get_type() for o in rig.tick(1.01)].count("MISSION_REQUEST_LIST") == 1


def test_a_fence_switched_by_command_is_read_again() -> None:
    rig = FenceRig()
    rig.tick(3.0)
    ack = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_FENCE_ENABLE, mavlink.MAV_RESULT_ACCEPTED, 0, 0,
                                              255, 190)
    rig.feed(Link.AUTOPILOT, rig.wire(rig.ap, ack), 3.1)
    asked = [o.msg.param_id for o in rig.tick(3.2) if o.msg.get_type() == "PARAM_REQUEST_READ"]
    assert {"FENCE_ENABLE", "FENCE_TYPE", "FENCE_RADIUS", "FENCE_MARGIN"} <= set(asked)
    assert rig.core.avoid.fence.config is not None and rig.core.avoid.fence.config.enabled  # kept meanwhile


def test_a_lone_fence_enable_0_does_not_switch_the_fence_off_until_the_autopilot_says_it() -> None:
    rig = FenceRig()
    rig.home(0.05)
    rig.tick(2.5)  # all answered
    rig.param(2.6, "FENCE_ENABLE", 0.0)  # one frame: forged, corrupted, or a GCS's PARAM_SET
    rig.at(9.95, 2.61)
    rig.local(2.62, vx=0.5, mask=3527)
    assert rig.core.commanded.v_m_s == 0.0  # still kept: at the margin
    assert "FENCE_ENABLE" in [o.msg.param_id for o in rig.tick(2.8) if o.msg.get_type() == "PARAM_REQUEST_READ"]
    rig.param(2.81, "FENCE_ENABLE", 0.0)  # the autopilot's word
    rig.local(2.82, vx=0.5, mask=3527)
    assert rig.core.commanded.v_m_s == pytest.approx(0.5)
