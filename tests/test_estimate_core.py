"""EstimateCore protocol tests: messages + times in, exact messages out (no sockets, no clock)."""

from __future__ import annotations

import math
import random
from typing import Any

import pytest
from synthetic_drive import TrueGeometry, drive

from rover_bridge.estimate.core import EstimateCore
from rover_bridge.estimate.publish import upper_triangle_21
from rover_bridge.estimate.resets import POSE_RESET_COMMAND
from rover_bridge.frames import covariance_frd_from_flu
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.odometry import Pose2D
from rover_bridge.params import Profile, profile_from_dict

L = 0.30


def _core(**sections: dict[str, Any]) -> EstimateCore:
    # The drives here send at 20 Hz: that is the rate these tests ask for unless they say otherwise.
    sections = {**sections, "estimator": {"stream_rate_hz": 20.0, **sections.get("estimator", {})}}
    profile: Profile = profile_from_dict(sections)
    identity = Identity.from_profile(profile)
    return EstimateCore(profile, identity, Reporter(identity))


def _from(msg: MAVLinkMessage, sysid: int = 1, compid: int = 1) -> MAVLinkMessage:
    msg._header = mavlink.MAVLink_header(msg.id, srcSystem=sysid, srcComponent=compid)
    return msg


def _hb() -> MAVLinkMessage:
    return _from(mavlink.MAVLink_heartbeat_message(type=mavlink.MAV_TYPE_GROUND_ROVER,
                                                   autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode=0,
                                                   custom_mode=0, system_status=4, mavlink_version=3))


def _wheels(t_s: float, left_m: float, right_m: float, count: int = 2) -> MAVLinkMessage:
    return _from(mavlink.MAVLink_wheel_distance_message(time_usec=round(t_s * 1e6), count=count,
                                                        distance=[left_m, right_m] + [0.0] * 14))


def _attitude(t_s: float, yaw_rate_cw: float) -> MAVLinkMessage:
    return _from(mavlink.MAVLink_attitude_message(time_boot_ms=round(t_s * 1e3), roll=0, pitch=0, yaw=0,
                                                  rollspeed=0, pitchspeed=0, yawspeed=yaw_rate_cw))


def _ack(result: int) -> MAVLinkMessage:
    return _from(mavlink.MAVLink_command_ack_message(command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, result=result,
                                                     progress=0, result_param2=0, target_system=1,
                                                     target_component=191))


def _feed(core: EstimateCore, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
    reaction = core.handle(Incoming(Link.AUTOPILOT, msg), now_s)
    return list(reaction.out)


def _drive_twist(core: EstimateCore, v: float, w: float, seconds: float, t0: float = 0.0,
                 start: tuple[float, float] = (0.0, 0.0)) -> tuple[float, tuple[float, float]]:
    """Feed exact wheels and gyro for a constant body twist (CCW omega) at 20 Hz; return (t, distances)."""
    left, right = start
    t = t0
    _feed(core, _attitude(t, -w), t)  # already turning at t0: a steady twist, not a step
    _feed(core, _wheels(t, left, right), t)
    for _ in range(round(seconds * 20)):
        t += 0.05
        left += (v - w * L / 2) * 0.05
        right += (v + w * L / 2) * 0.05
        _feed(core, _attitude(t, -w), t)
        _feed(core, _wheels(t, left, right), t)
    return t, (left, right)


# ---------------------------------------------------------------- covariance packing

def test_upper_triangle_of_a_known_matrix() -> None:
    m = [[10.0 * (min(i, j) + 1) + (max(i, j) + 1) for j in range(6)] for i in range(6)]
    assert upper_triangle_21(m) == [11, 12, 13, 14, 15, 16, 22, 23, 24, 25, 26, 33, 34, 35, 36, 44, 45, 46,
                                    55, 56, 66]


def test_flu_to_frd_flips_the_cross_terms_of_y_z_pitch_yaw_with_x_roll() -> None:
    m = [[10.0 * (min(i, j) + 1) + (max(i, j) + 1) for j in range(6)] for i in range(6)]
    # signs (x, y, z, roll, pitch, yaw) = (+, -, -, +, -, -)
    assert upper_triangle_21(covariance_frd_from_flu(m)) == [
        11, -12, -13, 14, -15, -16,
        22, 23, -24, 25, 26,
        33, -34, 35, 36,
        44, -45, -46,
        55, 56,
        66]


# ---------------------------------------------------------------- ODOMETRY

def _odometry(core: EstimateCore, now_s: float) -> Any:
    out = core.tick(now_s)
    odom = [o for o in out if o.msg.get_type() == "ODOMETRY"]
    assert len(odom) == 1
    assert odom[0].dest is Link.GCS and (odom[0].src_system, odom[0].src_component) == (1, 191)
    return odom[0].msg


def test_odometry_signs_for_a_right_turn() -> None:
    core = _core()
    t, _ = _drive_twist(core, v=0.5, w=-0.5, seconds=2.0)  # right turn: omega CCW negative
    msg = _odometry(core, t)
    assert msg.frame_id == mavlink.MAV_FRAME_LOCAL_FRD and msg.child_frame_id == mavlink.MAV_FRAME_BODY_FRD
    # 1 m along a right-hand arc of radius 1 m: x = sin 1, y right = 1 - cos 1, yaw CW = 1 rad
    assert msg.x == pytest.approx(math.sin(1.0), abs=0.01)
    assert msg.y == pytest.approx(1.0 - math.cos(1.0), abs=0.01)
    assert msg.z == 0.0
    assert msg.q[0] == pytest.approx(math.cos(0.5), abs=0.01) and msg.q[3] == pytest.approx(math.sin(0.5), abs=0.01)
    assert msg.vx == pytest.approx(0.5, abs=0.01) and msg.vy == 0.0
    assert msg.yawspeed == pytest.approx(0.5, abs=0.01)


def test_odometry_signs_for_a_clockwise_spin_in_place() -> None:
    core = _core()
    t, _ = _drive_twist(core, v=0.0, w=-1.0, seconds=1.0)
    msg = _odometry(core, t)
    assert msg.x == pytest.approx(0.0, abs=1e-3) and msg.y == pytest.approx(0.0, abs=1e-3)
    assert msg.yawspeed == pytest.approx(1.0, abs=0.01)
    assert 2 * math.atan2(msg.q[3], msg.q[0]) == pytest.approx(1.0, abs=0.01)  # CW + in FRD


def test_odometry_covariances_are_filled_and_honest() -> None:
    core = _core(odometry={"unobserved_variance": 1234.0})
    t, _ = _drive_twist(core, v=0.5, w=-0.5, seconds=2.0)
    msg = _odometry(core, t)
    pose, vel = list(msg.pose_covariance), list(msg.velocity_covariance)
    diag = (0, 6, 11, 15, 18, 20)
    for i in (0, 6, 20):  # x, y, yaw: from the filter, small but never zero
        assert 0.0 < pose[i] < 1.0
    for i in (11, 15, 18):  # z, roll, pitch: unobserved
        assert pose[i] == pytest.approx(1234.0, rel=1e-6)
    assert 0.0 < vel[0] < 1.0 and 0.0 < vel[20] < 1.0  # vx, yawspeed
    assert 0.0 < vel[6] < 1.0  # vy: finite (nonholonomic), not certain
    assert all(vel[i] == pytest.approx(1234.0, rel=1e-6) for i in (11, 15, 18))
    assert all(math.isfinite(c) for c in pose + vel) and all(pose[i] > 0 and vel[i] > 0 for i in diag)
    assert msg.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_UNKNOWN
    assert 1 <= msg.quality <= 100


def test_no_odometry_before_wheel_data_and_none_for_targets_none() -> None:
    core = _core()
    assert [o for o in core.tick(0.0) if o.msg.get_type() == "ODOMETRY"] == []
    quiet = _core(odometry={"targets": "none"})
    t, _ = _drive_twist(quiet, 0.3, 0.0, 1.0)
    assert [o for o in quiet.tick(t) if o.msg.get_type() == "ODOMETRY"] == []


def test_odometry_to_both_targets_at_the_configured_rate() -> None:
    core = _core(odometry={"targets": "both", "rate_hz": 10.0, "frame": "start"})
    t, _ = _drive_twist(core, 0.3, 0.0, 1.0)
    sent = []
    now = t
    while now < t + 2.0 - 1e-9:
        sent += [o.dest for o in core.tick(now) if o.msg.get_type() == "ODOMETRY"]
        now = max(now + 0.001, core.next_deadline_s(now))
    assert sent.count(Link.GCS) == 20 and sent.count(Link.AUTOPILOT) == 20


def test_time_usec_follows_system_time_when_known() -> None:
    core = _core()
    assert core.odometry_time_usec(5.0) == 5_000_000
    # SYSTEM_TIME says 100 s since boot, received at now = 5 s (least delayed sample wins)
    _feed(core, _from(mavlink.MAVLink_system_time_message(time_unix_usec=0, time_boot_ms=100_000)), 5.0)
    _feed(core, _from(mavlink.MAVLink_system_time_message(time_unix_usec=0, time_boot_ms=101_010)), 6.0)
    assert core.odometry_time_usec(7.0) == 102_010_000  # offset 95.01 s: the second sample was less delayed


def test_telemetry_is_never_consumed() -> None:
    core = _core()
    for msg in (_hb(), _wheels(1.0, 0, 0), _attitude(1.0, 0.0)):
        assert not core.handle(Incoming(Link.AUTOPILOT, msg), 1.0).consumed


# ---------------------------------------------------------------- gyro sources

def test_scaled_imu_is_mrad_per_s_clockwise() -> None:
    core = _core(estimator={"gyro_source": "scaled_imu"})
    _feed(core, _wheels(0.0, 0.0, 0.0), 0.0)
    t = 0.0
    for _ in range(20):
        t += 0.05
        _feed(core, _from(mavlink.MAVLink_scaled_imu_message(time_boot_ms=round(t * 1e3), xacc=0, yacc=0, zacc=0,
                                                             xgyro=0, ygyro=0, zgyro=500, xmag=0, ymag=0,
                                                             zmag=0)), t)
    assert core.gyro_source == "scaled_imu"
    assert core.state.omega_rad_s == pytest.approx(-0.5, abs=0.02)  # 500 mrad/s clockwise


def test_auto_prefers_attitude_over_raw_imu() -> None:
    core = _core()
    raw = _from(mavlink.MAVLink_raw_imu_message(time_usec=1000, xacc=0, yacc=0, zacc=0, xgyro=0, ygyro=0, zgyro=0,
                                                xmag=0, ymag=0, zmag=0))
    _feed(core, raw, 0.0)
    assert core.gyro_source == "raw_imu"
    _feed(core, _attitude(0.01, 0.0), 0.01)
    assert core.gyro_source == "attitude" and core.counters["gyro_switches"] == 1


def test_gyro_outlier_is_rejected_and_counted() -> None:
    core = _core()
    t, _ = _drive_twist(core, 0.5, 0.0, 2.0)
    _feed(core, _attitude(t + 0.01, 20.0), t + 0.01)  # 3x what the wheels can turn the rover at
    assert core.counters["gyro_rejected"] == 1
    _feed(core, _attitude(t + 0.02, 0.0), t + 0.02)
    assert core.counters["gyro_rejected"] == 1


# ---------------------------------------------------------------- slip

def test_wheel_slip_counted_and_reported_rate_limited() -> None:
    core = _core()
    t, (left, right) = _drive_twist(core, 0.5, 0.0, 2.0)
    texts = []
    for _ in range(200):  # 10 s: left wheel spins 60 % faster than the ground, the gyro says straight
        t += 0.05
        left += 0.025 * 1.6
        right += 0.025
        _feed(core, _attitude(t, 0.0), t)
        texts += [o.msg.text for o in _feed(core, _wheels(t, left, right), t) if o.msg.get_type() == "STATUSTEXT"]
    assert core.counters["wheel_slip"] >= 190
    assert texts == ["wheel slip"] * 2  # at most one per 5 s: at the start and 5 s later
    # the heading follows the gyro, not the wheels (which would have turned ~10 rad)
    assert abs(core.pose.yaw_rad) < 0.05


# ---------------------------------------------------------------- streams

def _requests(out: list[Outgoing]) -> list[tuple[str, float, float]]:
    res: list[tuple[str, float, float]] = []
    for o in out:
        m = o.msg
        if m.get_type() == "COMMAND_LONG" and m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            assert o.dest is Link.AUTOPILOT and (m.target_system, m.target_component) == (1, 1)
            res.append(("interval", m.param1, m.param2))
        elif m.get_type() == "REQUEST_DATA_STREAM":
            res.append(("stream", m.req_stream_id, m.req_message_rate))
    return res


def test_stream_requests_and_fallback_on_denied() -> None:
    core = _core()
    out = _feed(core, _hb(), 0.0)
    assert _requests(out) == [("interval", 9000, 50_000.0)]  # one at a time: each ACK is unambiguous
    out = _feed(core, _ack(mavlink.MAV_RESULT_DENIED), 0.1)
    assert _requests(out) == [("stream", mavlink.MAV_DATA_STREAM_EXTRA1, 20),
                              ("interval", mavlink.MAVLINK_MSG_ID_ATTITUDE, 50_000.0)]
    reaction = core.handle(Incoming(Link.AUTOPILOT, _ack(mavlink.MAV_RESULT_ACCEPTED)), 0.2)
    assert reaction.consumed and _requests(list(reaction.out)) == []
    assert _requests(core.tick(4.9)) == []  # nothing outstanding, nothing repeated
    assert core.counters["stream_fallbacks"] == 1


def test_position_streams_are_asked_for_only_when_they_do_not_come() -> None:
    # A GCS's map asked for LOCAL_POSITION_NED at 10 Hz: the bridge's own 2 Hz request would slow it down
    # (the last SET_MESSAGE_INTERVAL on a link wins), so it watches first and asks only for what is missing.
    core = _core()
    _feed(core, _hb(), 0.0)
    for t in (0.1, 0.2):
        core.handle(Incoming(Link.AUTOPILOT, _ack(mavlink.MAV_RESULT_ACCEPTED)), t)  # wheels, gyro
    t, sent = 0.2, []
    while t < 6.0:
        t = round(t + 0.1, 6)
        local = mavlink.MAVLink_local_position_ned_message(int(t * 1000), 0, 0, 0, 0, 0, 0)
        local.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
        sent += _requests(_feed(core, local, t))
        sent += _requests(core.tick(t))
    # Only the missing one (asked again while unacknowledged), at 2 Hz.
    assert set(sent) == {("interval", mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 500_000.0)}


def test_stream_request_retried_without_ack_then_falls_back() -> None:
    core = _core()
    assert _requests(_feed(core, _hb(), 0.0)) == [("interval", 9000, 50_000.0)]
    assert _requests(core.tick(0.5)) == []
    assert _requests(core.tick(1.0)) == [("interval", 9000, 50_000.0)]
    assert _requests(core.tick(2.0)) == [("interval", 9000, 50_000.0)]
    assert _requests(core.tick(3.0)) == [("stream", mavlink.MAV_DATA_STREAM_EXTRA1, 20),
                                         ("interval", mavlink.MAVLINK_MSG_ID_ATTITUDE, 50_000.0)]


def test_slow_stream_is_reported_and_requested_again() -> None:
    core = _core()
    _feed(core, _hb(), 0.0)
    _feed(core, _ack(mavlink.MAV_RESULT_DENIED), 0.0)
    _feed(core, _ack(mavlink.MAV_RESULT_ACCEPTED), 0.0)
    out: list[Outgoing] = []
    t = 0.0
    while t < 8.0:  # WHEEL_DISTANCE at 1 Hz (ArduPilot's EXTRA1 default), ATTITUDE at 20 Hz
        t = round(t + 0.05, 3)
        _feed(core, _attitude(t, 0.0), t)
        if abs(t - round(t)) < 1e-9:
            _feed(core, _wheels(t, 0.0, 0.0), t)
        out += core.tick(t)
    texts = [o.msg.text for o in out if o.msg.get_type() == "STATUSTEXT"]
    assert texts == ["WHEEL_DISTANCE 1.0 Hz, need 14"]
    assert ("stream", mavlink.MAV_DATA_STREAM_EXTRA1, 20) in _requests(out)
    assert core.counters["stream_slow"] == 1


# ---------------------------------------------------------------- reboots and resets

def test_reboot_rebases_without_a_jump_and_bumps_reset_counter_once() -> None:
    core = _core()
    _feed(core, _hb(), 0.0)
    t, _ = _drive_twist(core, 0.5, 0.2, 4.0, t0=100.0, start=(20.0, 21.0))
    before = core.pose_at(t + 0.05)
    # reboot: time and distances restart near zero, the gyro's clock too
    out = _feed(core, _wheels(0.5, 0.0, 0.0), t + 0.05)
    assert core.reset_counter == 1 and core.counters["reboots"] == 1
    assert ("interval", 9000, 50_000.0) in _requests(out)  # the new autopilot needs asking again
    after = core.pose_at(t + 0.05)
    assert math.hypot(after.x_m - before.x_m, after.y_m - before.y_m) < 0.03
    # driving on from the new baseline integrates from there, and the counter stays
    _feed(core, _attitude(0.55, -0.2), t + 0.1)
    _feed(core, _wheels(0.55, 0.025 - 0.2 * L / 2 * 0.05, 0.025 + 0.2 * L / 2 * 0.05), t + 0.1)
    assert core.reset_counter == 1 and core.counters["wheel_reboots"] == 1
    moved = core.pose_at(t + 0.1)
    assert math.hypot(moved.x_m - after.x_m, moved.y_m - after.y_m) == pytest.approx(0.025, abs=0.01)


def test_pose_reset_command_sets_the_pose_and_acks() -> None:
    core = _core()
    _feed(core, _hb(), 0.0)
    t, _ = _drive_twist(core, 0.5, 0.0, 1.0)
    cmd = _from(mavlink.MAVLink_command_long_message(target_system=1, target_component=191,
                                                    command=POSE_RESET_COMMAND, confirmation=0, param1=2.0,
                                                    param2=3.0, param3=90.0, param4=0, param5=0, param6=0,
                                                    param7=0), sysid=255, compid=190)
    reaction = core.handle(Incoming(Link.GCS, cmd), t)
    assert reaction.consumed
    ack = reaction.out[0]
    assert ack.dest is Link.GCS and ack.msg.get_type() == "COMMAND_ACK"
    assert (ack.msg.command, ack.msg.result, ack.msg.target_system, ack.msg.target_component) == (
        POSE_RESET_COMMAND, mavlink.MAV_RESULT_ACCEPTED, 255, 190)
    # FRD in, ours inside: y right 3 -> y left -3, yaw 90 deg clockwise -> -pi/2
    assert core.pose.x_m == pytest.approx(2.0) and core.pose.y_m == pytest.approx(-3.0)
    assert core.pose.yaw_rad == pytest.approx(-math.pi / 2)
    assert core.reset_counter == 1
    msg = _odometry(core, t)
    assert msg.reset_counter == 1 and msg.y == pytest.approx(3.0, abs=0.01)


def test_pose_reset_for_another_component_is_not_consumed() -> None:
    core = _core()
    cmd = _from(mavlink.MAVLink_command_long_message(target_system=1, target_component=1,
                                                    command=POSE_RESET_COMMAND, confirmation=0, param1=0,
                                                    param2=0, param3=0, param4=0, param5=0, param6=0, param7=0),
                sysid=255, compid=190)
    assert not core.handle(Incoming(Link.GCS, cmd), 0.0).consumed
    assert core.reset_counter == 0


def test_reset_pose_from_the_cli() -> None:
    core = _core()
    core.reset_pose(Pose2D(1.0, 2.0, 0.5), 0.0)
    assert core.pose == Pose2D(1.0, 2.0, 0.5) and core.reset_counter == 1 and core.counters["pose_resets"] == 1


# ---------------------------------------------------------------- synthetic drives

def _run(geometry: TrueGeometry, calibrate: bool, **kw: Any) -> tuple[float, float, EstimateCore, Any]:
    """Max heading error (rad) of the EKF and of raw wheel odometry over a deterministic drive."""
    core = _core(estimator={"calibrate": calibrate})
    max_ekf = max_raw = 0.0
    truth = None
    now = 0.0
    for now, msg, truth in drive(_route(), geometry, **kw):
        if msg is not None:
            core.handle(Incoming(Link.AUTOPILOT, msg), now)
        elif core.state.time_s is not None:
            max_ekf = max(max_ekf, abs(math.remainder(core.pose_at(now).yaw_rad - truth.yaw_rad, 2 * math.pi)))
            max_raw = max(max_raw, abs(math.remainder(core.raw_pose.yaw_rad - truth.yaw_rad, 2 * math.pi)))
    return max_ekf, max_raw, core, truth


def _route() -> list[tuple[float, float, float]]:
    seg: list[tuple[float, float, float]] = [(2.0, 0.0, 0.0)]
    for _ in range(3):
        seg += [(10.0, 0.8, 0.0), (3.0, 0.5, 0.6), (4.0, 0.0, -1.0), (1.0, 0.0, 0.0)]
    return seg


MISCALIBRATED = TrueGeometry(track_width_m=L * 1.03, left_radius_m=0.05, right_radius_m=0.05 * 1.02)


def test_ekf_heading_error_at_least_3x_smaller_than_raw_wheel_odometry() -> None:
    ekf, raw, _core_after, truth = _run(MISCALIBRATED, calibrate=False, gyro_bias_rad_s=0.002, seed=3)
    assert truth.dist_m > 25.0
    assert raw > 3.0 * ekf
    assert ekf < math.radians(5.0)


def test_calibration_moves_the_track_width_toward_the_truth() -> None:
    _, _, core, _ = _run(MISCALIBRATED, calibrate=True, seed=4)
    # The wheels' mean scale is not observable without an absolute reference: the track the filter can see
    # is the true one in units of the nominal radius, 1.03 / 1.01 of the profile's (radii 1.00 and 1.02).
    seen = L * 1.03 / 1.01
    est = core.state.track_width_m
    assert abs(est - seen) < 0.3 * abs(L - seen)  # 70 % of that error removed
    ratio = core.state.right_radius_m / core.state.left_radius_m
    assert ratio == pytest.approx(1.02, abs=0.006)


def test_silent_link_holds_the_pose_and_cumulative_distances_catch_up() -> None:
    core = _core()
    t, (left, right) = _drive_twist(core, 0.5, 0.0, 2.0)
    x_last = core.pose.x_m
    # 1.5 s of silence: ODOMETRY moves on for at most 0.2 s at 0.5 m/s, then holds
    held = core.pose_at(t + 1.5)
    assert held.x_m == pytest.approx(x_last + 0.1, abs=0.005)
    sigma_before = core.state.sigma_xy_m
    # the link comes back without a reboot: the wheels went on at 0.5 m/s, 0.775 m in 1.55 s
    t2 = t + 1.55
    _feed(core, _attitude(t2, 0.0), t2)
    _feed(core, _wheels(t2, left + 0.775, right + 0.775), t2)
    assert core.pose.x_m == pytest.approx(x_last + 0.775, abs=0.01)
    assert core.reset_counter == 0
    assert core.state.sigma_xy_m > sigma_before  # nothing measured the silence


def test_arrival_jitter_does_not_change_the_estimate() -> None:
    # The filter runs on the autopilot's stamps: the same messages arriving with different network
    # and scheduling delays (here up to 30 ms, per message) must give the same filter state. Per-stream
    # arrival-time mapping once shifted the gyro against the wheels and cost degrees per turn.
    rng = random.Random(7)
    samples = list(drive(_route(), TrueGeometry(), seed=5))
    messages = [(now, msg) for now, msg, _ in samples if msg is not None]
    steady, jittered = _core(), _core()
    for now, msg in messages:
        steady.handle(Incoming(Link.AUTOPILOT, msg), now)
    late = 0.0
    for now, msg in messages:
        late = max(late, now + rng.uniform(0.0, 0.03))  # delayed, never reordered
        jittered.handle(Incoming(Link.AUTOPILOT, msg), late)
    a, b = steady.pose, jittered.pose
    assert samples[-1][2].dist_m > 20.0  # it went somewhere, turning both ways
    assert b.x_m == pytest.approx(a.x_m, abs=1e-9) and b.y_m == pytest.approx(a.y_m, abs=1e-9)
    assert b.yaw_rad == pytest.approx(a.yaw_rad, abs=1e-12)


def test_only_the_gyro_sources_in_use_are_decoded_and_a_silent_one_opens_the_others() -> None:
    """BridgeCore.reads (what the shell decodes from the autopilot) follows the gyro source: a lower-priority
    IMU stream is forwarded undecoded while ATTITUDE is used, and read again once ATTITUDE falls silent."""
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.estimate.gyro import GYRO_SILENT_S

    imu = {mavlink.MAVLINK_MSG_ID_RAW_IMU, mavlink.MAVLINK_MSG_ID_SCALED_IMU}
    core = BridgeCore(profile_from_dict({}))
    ap_reads = core.reads(Link.AUTOPILOT)
    assert ap_reads is not None and imu <= ap_reads  # no source yet: every one is read
    assert core.reads(Link.GCS) is None  # a ground station's frames are all judged by the gate
    core.handle(Incoming(Link.AUTOPILOT, _hb()), 0.0)
    core.handle(Incoming(Link.AUTOPILOT, _attitude(0.02, 0.0)), 0.02)
    ap_reads = core.reads(Link.AUTOPILOT)
    assert ap_reads is not None and not imu & ap_reads and mavlink.MAVLINK_MSG_ID_ATTITUDE in ap_reads
    raw = _from(mavlink.MAVLink_raw_imu_message(time_usec=30_000, xacc=0, yacc=0, zacc=0, xgyro=0, ygyro=0, zgyro=0,
                                                xmag=0, ymag=0, zmag=0))
    core.handle(Incoming(Link.AUTOPILOT, raw), 0.03)
    assert core.estimate.gyro_source == "attitude"
    later = 0.02 + GYRO_SILENT_S + 0.1
    core.tick(later)
    ap_reads = core.reads(Link.AUTOPILOT)
    assert ap_reads is not None and imu <= ap_reads
    raw = _from(mavlink.MAVLink_raw_imu_message(time_usec=round(later * 1e6), xacc=0, yacc=0, zacc=0, xgyro=0, ygyro=0,
                                                zgyro=0, xmag=0, ymag=0, zmag=0))
    core.handle(Incoming(Link.AUTOPILOT, raw), later)
    assert core.estimate.gyro_source == "raw_imu" and core.estimate.counters["gyro_switches"] == 1


def test_a_fixed_gyro_source_is_the_only_imu_decoded() -> None:
    from rover_bridge.app.composition import BridgeCore

    core = BridgeCore(profile_from_dict({"estimator": {"gyro_source": "raw_imu"}}))
    ap_reads = core.reads(Link.AUTOPILOT)
    assert ap_reads is not None
    assert mavlink.MAVLINK_MSG_ID_RAW_IMU in ap_reads and mavlink.MAVLINK_MSG_ID_SCALED_IMU not in ap_reads
    assert mavlink.MAVLINK_MSG_ID_ATTITUDE in ap_reads  # the command core's heading
