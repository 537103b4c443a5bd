"""The autopilot's local frame: LocalAnchor math, FrameAnchor's decisions, ODOMETRY in that frame."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_estimate_core import _attitude, _core, _feed, _from, _hb, _wheels

from rover_bridge.estimate.anchor import FrameAnchor
from rover_bridge.frames import LocalAnchor, NedPose
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Link
from rover_bridge.odometry import Pose2D
from rover_bridge.params import OdometryParams, Profile, profile_from_dict, profile_warnings

finite = st.floats(-1e4, 1e4, allow_nan=False)
angle = st.floats(-10.0, 10.0, allow_nan=False)


def test_anchor_facing_east_maps_forward_to_east_and_left_to_north() -> None:
    a = LocalAnchor.matching(0.0, 0.0, 0.0, NedPose(10.0, 20.0, math.pi / 2))
    fwd = a.to_ned(1.0, 0.0, 0.0)
    left = a.to_ned(0.0, 1.0, 0.0)
    assert (fwd.north_m, fwd.east_m) == pytest.approx((10.0, 21.0))
    assert (left.north_m, left.east_m) == pytest.approx((11.0, 20.0))
    assert a.to_ned(0.0, 0.0, 0.3).yaw_cw_rad == pytest.approx(math.pi / 2 - 0.3)  # a left turn: toward north


@given(finite, finite, angle, finite, finite, angle, finite, finite, angle)
def test_anchor_matches_the_pair_and_round_trips(x: float, y: float, yaw: float, n: float, e: float, psi: float,
                                                 px: float, py: float, pyaw: float) -> None:
    a = LocalAnchor.matching(x, y, yaw, NedPose(n, e, psi))
    here = a.to_ned(x, y, yaw)
    assert (here.north_m, here.east_m) == pytest.approx((n, e), abs=1e-6)
    assert math.remainder(here.yaw_cw_rad - psi, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    bx, by, byaw = a.from_ned(a.to_ned(px, py, pyaw))
    assert (bx, by) == pytest.approx((px, py), abs=1e-6)
    assert math.remainder(byaw - pyaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    # Distances are kept: a rigid motion.
    p, q = a.to_ned(px, py, 0.0), a.to_ned(x, y, 0.0)
    assert math.hypot(p.north_m - q.north_m, p.east_m - q.east_m) == pytest.approx(math.hypot(px - x, py - y),
                                                                                   rel=1e-9, abs=1e-6)


def _anchor(timeout_s: float = 3.0) -> FrameAnchor:
    return FrameAnchor(OdometryParams(targets="autopilot", anchor_timeout_s=timeout_s),
                       Reporter(Identity(learned_system_id=1)))


def test_frame_anchor_waits_for_the_local_position_then_matches_it() -> None:
    fa = _anchor()
    still = lambda _t: Pose2D(0.5, 0.0, 0.0)  # noqa: E731 - the estimate's pose at any stamp
    assert fa.decide(0.0, None) == [] and not fa.ready  # no wheel data yet
    fa.on_attitude(10.0, math.radians(30.0))
    assert fa.decide(1.0, still) == [] and not fa.ready  # waiting for LOCAL_POSITION_NED
    fa.on_local_position(10.2, 4.0, -2.0)
    out = fa.decide(1.5, still)
    assert fa.ready and fa.how == "local_position" and "autopilot frame" in out[0].msg.text
    assert fa.anchor is not None
    here = fa.anchor.to_ned(0.5, 0.0, 0.0)
    assert (here.north_m, here.east_m, here.yaw_cw_rad) == pytest.approx((4.0, -2.0, math.radians(30.0)))
    assert fa.internal(fa.published(Pose2D(1.0, 2.0, 0.3))) == Pose2D(pytest.approx(1.0), pytest.approx(2.0),
                                                                        pytest.approx(0.3))


def test_frame_anchor_cold_start_is_the_origin_north_aligned_and_without_attitude_the_start_frame() -> None:
    fa = _anchor(timeout_s=2.0)
    fa.on_attitude(5.0, math.radians(-90.0))
    fa.decide(0.0, lambda _t: Pose2D(0.0, 0.0, 0.0))
    assert not fa.ready
    fa.decide(2.0, lambda _t: Pose2D(0.0, 0.0, 0.0))
    assert fa.how == "origin" and fa.anchor == LocalAnchor(0.0, 0.0, pytest.approx(-math.pi / 2))
    bare = _anchor(timeout_s=0.5)
    bare.decide(0.0, lambda _t: Pose2D())
    bare.decide(0.6, lambda _t: Pose2D())
    assert bare.how == "start" and bare.anchor == LocalAnchor()


def test_garbage_positions_and_yaws_are_not_anchors() -> None:
    fa = _anchor()
    fa.on_local_position(1.0, math.nan, 0.0)
    fa.on_local_position(1.0, 1e9, 0.0)
    fa.on_attitude(1.0, math.inf)
    assert fa.local_position is None and fa.yaw is None


def _odometry(core: Any, now_s: float) -> list[Any]:
    return [o.msg for o in core.tick(now_s) if o.msg.get_type() == "ODOMETRY"]


def test_odometry_to_the_autopilot_is_held_back_until_anchored_then_in_its_frame() -> None:
    core = _core(odometry={"targets": "autopilot", "rate_hz": 20.0})
    assert core.frame.enabled
    _feed(core, _hb(), 0.0)
    t = 0.0
    for i in range(10):
        t = 0.05 * i
        _feed(core, _attitude(t, 0.0), t)
        _feed(core, _wheels(t, 0.0, 0.0), t)
        assert _odometry(core, t) == []  # no LOCAL_POSITION_NED yet, and the wait is not over
    yaw = _from(mavlink.MAVLink_attitude_message(round(t * 1000), 0, 0, math.pi / 2, 0, 0, 0))
    _feed(core, yaw, t)
    _feed(core, _from(mavlink.MAVLink_local_position_ned_message(round(t * 1000), 12.0, -3.0, 0, 0, 0, 0)), t)
    msgs = _odometry(core, t + 0.01)
    assert len(msgs) == 1
    odo = msgs[0]
    assert (odo.x, odo.y) == pytest.approx((12.0, -3.0), abs=1e-4)  # where the autopilot says it is
    assert 2.0 * math.atan2(odo.q[3], odo.q[0]) == pytest.approx(math.pi / 2, abs=1e-4)
    # The start frame's x variance (along the rover, facing east) is the east variance now: rotated.
    P = core.ekf.P  # noqa: N806
    assert odo.pose_covariance[6] == pytest.approx(float(P[0, 0]), rel=1e-3)
    assert odo.pose_covariance[0] == pytest.approx(float(P[1, 1]), rel=1e-3)
    assert odo.pose_covariance[11] == 0.01  # unobserved variance for the autopilot: its errors stay at the floors


def test_pose_reset_is_in_the_published_frame() -> None:
    core = _core(odometry={"targets": "autopilot", "anchor_timeout_s": 0.0})
    _feed(core, _hb(), 0.0)
    _feed(core, _from(mavlink.MAVLink_attitude_message(0, 0, 0, math.pi / 2, 0, 0, 0)), 0.0)
    _feed(core, _wheels(0.0, 0.0, 0.0), 0.0)
    core.tick(0.01)
    assert core.frame.how == "origin"
    cmd = mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, 5.0, 1.0, 0.0, 0, 0, 0, 0)
    core.handle(incoming_from_gcs(cmd), 0.02)
    odo = _odometry(core, 0.1)[0]
    assert (odo.x, odo.y) == pytest.approx((5.0, 1.0), abs=1e-4)  # north 5, east 1 as asked
    assert 2.0 * math.atan2(odo.q[3], odo.q[0]) == pytest.approx(0.0, abs=1e-4)


def incoming_from_gcs(msg: Any) -> Any:
    from rover_bridge.mavlink.wire import Incoming

    return Incoming(Link.GCS, _from(msg, 255, 190))


def test_frame_and_variance_resolve_by_target_and_warnings_name_the_bad_combinations() -> None:
    gcs, ap = OdometryParams(targets="gcs"), OdometryParams(targets="both")
    assert (gcs.resolved_frame, gcs.resolved_unobserved_variance) == ("start", 1e4)
    assert (ap.resolved_frame, ap.resolved_unobserved_variance) == ("autopilot", 0.01)
    assert OdometryParams(targets="both", unobserved_variance=5.0).resolved_unobserved_variance == 5.0
    assert profile_warnings(Profile()) == []
    bad = profile_warnings(profile_from_dict({"odometry": {"targets": "autopilot", "frame": "start",
                                                           "unobserved_variance": 1e4}}))
    assert len(bad) == 2 and "restarted" in bad[0] and "clamps" in bad[1]
