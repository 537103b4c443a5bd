"""Unit tests of the estimate flow's collaborators, each on its own (time is an argument everywhere)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.estimate.clock import (
    CLOCK_DRIFT,
    JUMP,
    LATENCY_WINDOW_S,
    REBOOT,
    RESTORED,
    AutopilotClock,
    Stamp,
)
from rover_bridge.estimate.diagnostics import (
    SLIP_MIN_INTERVALS,
    SLIP_REPORT_INTERVAL_S,
    CalibrationReports,
    SlipMonitor,
)
from rover_bridge.estimate.gyro import GYRO_SILENT_S, GyroSelector
from rover_bridge.estimate.models import IW, IX, IY, IYAW, N_STATES
from rover_bridge.estimate.publish import OdometryPublisher, quality, reference_covariances, sigma_xy
from rover_bridge.estimate.resets import POSE_RESET_COMMAND, ResetCounter, requested_pose
from rover_bridge.estimate.streams import (
    STREAM_ACK_ATTEMPTS,
    STREAM_ACK_TIMEOUT_S,
    Stream,
    StreamRequests,
)
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Link
from rover_bridge.odometry import Pose2D
from rover_bridge.params import EstimatorParams, OdometryParams

ATT = mavlink.MAVLINK_MSG_ID_ATTITUDE
SCALED = mavlink.MAVLINK_MSG_ID_SCALED_IMU
RAW = mavlink.MAVLINK_MSG_ID_RAW_IMU


# ------------------------------------------------------------------------------------ clock

def test_clock_maps_now_through_the_smallest_latency() -> None:
    clock = AutopilotClock()
    assert clock.autopilot_time_s(5.0) == 5.0  # nothing learnt: now itself
    clock.observe(1.00, 101.03)
    clock.observe(1.05, 101.06)  # 10 ms latency: the smallest so far
    assert clock.offset_s == pytest.approx(100.01)
    assert clock.autopilot_time_s(101.10) == pytest.approx(1.09)
    assert clock.time_usec(101.10) == 1_090_000


def test_clock_offset_creeps_up_at_most_at_the_drift_rate() -> None:
    clock = AutopilotClock()
    clock.observe(0.0, 100.0)  # offset 100
    clock.observe(9.0, 110.0)  # latency 101 s: the clock runs slow; the offset may rise 0.05 s/s
    assert clock.offset_s == pytest.approx(100.0 + CLOCK_DRIFT * 10.0)


def test_clock_follows_an_autopilot_clock_that_fell_behind_within_two_windows() -> None:
    # A starved SITL re-bases its clock: every stamp from then on arrives 0.75 s later than before. Creeping
    # at CLOCK_DRIFT the offset would take 15 s; a whole window's smallest latency above it moves it at once.
    clock = AutopilotClock()
    now = 100.0
    for _ in range(100):  # 2 s of 50 Hz stamps, 5 to 15 ms late
        now += 0.02
        clock.observe(now - 100.0 - 0.005 - 0.01 * (round(now * 50) % 2), now)
    assert clock.offset_s == pytest.approx(100.005)
    followed_at = None
    for k in range(150):
        now += 0.02
        clock.observe(now - 100.0 - 0.755 - 0.01 * (k % 2), now)
        if followed_at is None and clock.offset_s > 100.7:
            followed_at = k * 0.02
    assert followed_at is not None and followed_at <= 2.0 * LATENCY_WINDOW_S + 0.05
    assert clock.offset_s == pytest.approx(100.755, abs=2e-3)
    # jitter within STEP_S never moves it up at once: only the creep
    quiet = AutopilotClock()
    for k in range(300):
        quiet.observe(k * 0.02, 100.0 + k * 0.02 + (0.0 if k % 10 == 0 else 0.09))
    assert quiet.offset_s < 100.0 + CLOCK_DRIFT * 0.3  # at most the creep since the last 0-latency stamp


def test_clock_restarted_by_stamps_jumping_back() -> None:
    clock = AutopilotClock()
    clock.observe(50.0, 150.0, "wheels")
    assert clock.observe(49.8, 150.1, "wheels").event is None  # reordering, within the window
    assert clock.observe(0.2, 151.0, "wheels") == Stamp(0.2, REBOOT)  # a reboot
    assert clock.offset_s == pytest.approx(150.8)
    assert clock.observe(0.25, 151.05, "gyro").event is None  # the other streams restarted with it


def test_clock_a_reboot_that_one_stamp_faked_lasts_until_the_next_stamp() -> None:
    clock = AutopilotClock()
    for i in range(50):  # boot clock at 200 s, 10 ms late
        for stream in ("wheels", "gyro"):
            clock.observe(200.0 + 0.02 * i, 300.01 + 0.02 * i, stream)
    assert clock.offset_s == pytest.approx(100.01)
    assert clock.observe(100.0, 301.0, "wheels").event == REBOOT  # one stamp 100 s back (corrupted, forged)
    assert clock.observe(200.995, 301.005, "gyro") == Stamp(pytest.approx(200.995), RESTORED)  # goes on: undone
    assert clock.offset_s == pytest.approx(100.01)
    assert clock.observe(201.0, 301.01, "wheels").event is None  # every stream is back where it was
    assert clock.autopilot_time_s(301.1) == pytest.approx(201.09)
    # A real reboot: the stamps go on from it; the clock from before it stays unused ...
    assert clock.observe(0.5, 302.0, "wheels").event == REBOOT
    assert clock.observe(0.52, 302.02, "gyro").event is None and clock.offset_s == pytest.approx(301.5)
    # ... unless one stamp goes on from there: then the next real one restarts it again.
    assert clock.observe(202.0, 302.03, "gyro").event == RESTORED
    assert clock.observe(0.55, 302.05, "gyro").event == REBOOT and clock.offset_s == pytest.approx(301.5)
    assert clock.observe(0.57, 302.07, "wheels").event is None


def test_clock_re_bases_one_stream_on_another_epoch_and_back() -> None:
    clock = AutopilotClock()
    for i in range(10):
        clock.observe(10.0 + 0.05 * i, 110.0 + 0.05 * i, "gyro")
    unix = 1.7e9
    first = clock.observe(unix + 10.5, 110.5, "wheels")  # this stream now counts UNIX time
    assert first.event == JUMP and first.t_s == pytest.approx(10.5) and first.jump_s == pytest.approx(unix)
    assert clock.observe(unix + 10.55, 110.55, "wheels") == Stamp(pytest.approx(10.55))  # re-based, quietly
    assert clock.observe(10.55, 110.55, "gyro").event is None  # the others are untouched
    assert clock.offset_s == pytest.approx(100.0)
    back = clock.observe(10.6, 110.6, "wheels")  # and back to boot time
    assert back.event == JUMP and back.t_s == pytest.approx(10.6)
    assert clock.observe(10.65, 110.65, "wheels").event is None


def test_clock_stamps_out_of_any_range_are_events_not_errors() -> None:
    clock = AutopilotClock()
    clock.observe(1.0, 101.0)
    assert clock.observe(math.nan, 101.1).event == JUMP
    assert clock.observe((2**64 - 1) * 1e-6, 101.2).event == JUMP
    assert clock.time_usec(101.3) == pytest.approx(1.3e6, abs=5e3)  # (float precision of a 1.8e13 s stamp)
    huge = AutopilotClock()
    huge.observe(0.0, 1e15)
    assert huge.time_usec(2e15) == 2**64 - 1 and AutopilotClock().time_usec(-5.0) == 0  # clamped to uint64


# ------------------------------------------------------------------------------------ streams

def _streams() -> StreamRequests:
    identity = Identity(learned_system_id=1)
    return StreamRequests([Stream("WHEEL_DISTANCE", 9000, mavlink.MAV_DATA_STREAM_EXTRA1),
                           Stream("ATTITUDE", ATT, mavlink.MAV_DATA_STREAM_EXTRA1)], 20.0, identity,
                          Reporter(identity))


def _ack(result: int) -> mavlink.MAVLink_command_ack_message:
    return mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, result, 0, 0, 1, 191)


def test_streams_ask_one_at_a_time_and_fall_back_on_denied() -> None:
    s = _streams()
    first = s.on_heartbeat(0.0)
    assert [o.msg.param1 for o in first] == [9000.0]  # one outstanding request
    assert s.next_deadline_s(0.0) == STREAM_ACK_TIMEOUT_S
    reaction = s.handle_ack(_ack(mavlink.MAV_RESULT_DENIED), 0.1)
    kinds = [o.msg.get_type() for o in reaction.out]
    assert reaction.consumed and kinds == ["REQUEST_DATA_STREAM", "COMMAND_LONG"]  # fallback, then the next
    assert reaction.out[1].msg.param1 == float(ATT)
    assert s.counters["stream_fallbacks"] == 1 and s.counters["stream_requests"] == 2


def test_streams_retry_then_fall_back_without_an_ack() -> None:
    s = _streams()
    s.on_heartbeat(0.0)
    t = 0.0
    for _ in range(STREAM_ACK_ATTEMPTS - 1):
        t += STREAM_ACK_TIMEOUT_S
        assert [o.msg.get_type() for o in s.pump(t)] == ["COMMAND_LONG"]
    t += STREAM_ACK_TIMEOUT_S
    assert [o.msg.get_type() for o in s.pump(t)] == ["REQUEST_DATA_STREAM", "COMMAND_LONG"]


def test_streams_someone_elses_ack_is_not_ours() -> None:
    s = _streams()
    s.on_heartbeat(0.0)
    other = mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 0, 255, 190)
    assert not s.handle_ack(other, 0.1).consumed


def test_streams_a_heartbeat_gap_restarts_the_requests_and_slow_streams_are_asked_again() -> None:
    s = _streams()
    s.on_heartbeat(0.0)
    s.handle_ack(_ack(mavlink.MAV_RESULT_ACCEPTED), 0.1)
    s.handle_ack(_ack(mavlink.MAV_RESULT_ACCEPTED), 0.2)
    assert s.on_heartbeat(1.0) == []  # no gap
    for i in range(20):  # 20 arrivals over the 5 s window after the 2 s grace: 4 Hz, far below 14 Hz
        s.arrival("WHEEL_DISTANCE", 2.2 + i * 0.25)
        s.arrival("ATTITUDE", 2.2 + i * 0.25)
    out = s.check_rates(7.2)
    assert [o.msg.get_type() for o in out].count("REQUEST_DATA_STREAM") == 2
    assert s.counters["stream_slow"] == 2
    assert [o.msg.get_type() for o in s.on_heartbeat(20.0)] == ["COMMAND_LONG"]  # after a gap: again
    assert s.counters["stream_restarts"] == 2


# ------------------------------------------------------------------------------------ gyro

def test_gyro_auto_prefers_attitude_and_decodes_only_what_it_would_switch_to() -> None:
    g = GyroSelector(EstimatorParams(gyro_source="auto"))
    assert g.reads == {ATT, SCALED, RAW}
    assert g.accept_source("raw_imu", 0.0)  # nothing else yet
    assert g.reads == {ATT, SCALED, RAW}
    assert g.accept_source("attitude", 0.1)  # higher priority: switch
    assert g.source == "attitude" and g.switches == 1 and g.reads == {ATT}
    assert not g.accept_source("raw_imu", 0.2)
    g.update_reads(0.1 + GYRO_SILENT_S + 0.01)  # attitude fell silent: read everything again
    assert g.reads == {ATT, SCALED, RAW}
    assert g.accept_source("raw_imu", 0.1 + GYRO_SILENT_S + 0.02)


def test_gyro_fixed_source_and_stale_stamps() -> None:
    g = GyroSelector(EstimatorParams(gyro_source="scaled_imu"))
    assert g.reads == {SCALED}
    assert not g.accept_source("attitude", 0.0)
    g.fused("scaled_imu", 10.0)
    assert g.is_stale("scaled_imu", 10.0) and g.is_stale("scaled_imu", 9.6)
    assert not g.is_stale("scaled_imu", 10.01) and not g.is_stale("scaled_imu", 1.0)  # newer; a reboot


# ------------------------------------------------------------------------------------ publish

def _state() -> tuple[np.ndarray, np.ndarray]:
    x = np.zeros(N_STATES)
    x[IX], x[IY], x[IYAW], x[IW] = 1.0, 2.0, 0.5, 0.3
    P = np.diag([0.01, 0.04, 0.001, 0.1, 0.2, 1e-4, 1e-3, 1e-3])  # noqa: N806
    return x, P


def test_publisher_keeps_its_grid_and_restarts_it_after_a_stall() -> None:
    pub = OdometryPublisher(OdometryParams(rate_hz=10.0))
    assert pub.due(0.0) and not pub.due(0.05) and pub.due(0.1001)
    assert pub.next_s == pytest.approx(0.2)  # on the grid, not 0.2001
    assert pub.due(5.0) and pub.next_s == pytest.approx(5.1)  # a stall: a new grid, no burst
    assert not OdometryPublisher(OdometryParams(targets="none")).due(0.0)
    assert OdometryPublisher(OdometryParams(targets="both")).links == (Link.GCS, Link.AUTOPILOT)


def test_publisher_sends_early_only_within_the_window_and_keeps_its_grid() -> None:
    pub = OdometryPublisher(OdometryParams(rate_hz=10.0))  # window: 50 ms before each grid point
    assert pub.due(0.0, early=True) and pub.next_s == pytest.approx(0.1)
    assert pub.early_deadline_s(0.0) == pytest.approx(0.05) and pub.deadline_s(0.0) == pytest.approx(0.1)
    assert not pub.due(0.049, early=True) and not pub.due(0.06)  # before the window; not due without early
    assert pub.due(0.06, early=True) and pub.next_s == pytest.approx(0.2)  # early: the grid point, not 0.16
    assert pub.due(0.23) and pub.next_s == pytest.approx(0.3)  # late (no pass in the window)
    assert pub.early_deadline_s(0.23) == pytest.approx(0.28)  # the next early one half a period after it
    assert OdometryPublisher(OdometryParams(targets="none")).early_deadline_s(0.0) is None


def test_early_odometry_is_never_closer_than_the_autopilot_takes_it() -> None:
    # ArduPilot's EKF3 drops external navigation less than 20 ms after the previous sample.
    pub = OdometryPublisher(OdometryParams(rate_hz=30.0, targets="both"))
    assert pub.due(1.0) and pub.early_deadline_s(1.0) == pytest.approx(1.021)  # not 1.0167
    assert not pub.due(1.0205, early=True) and pub.due(1.0215, early=True)
    fast = OdometryPublisher(OdometryParams(rate_hz=50.0, targets="autopilot"))
    assert fast.due(1.0) and fast.early_deadline_s(1.0) == pytest.approx(1.02)  # its grid point: never early
    gcs = OdometryPublisher(OdometryParams(rate_hz=30.0))  # ground stations only: the whole window
    assert gcs.due(1.0) and gcs.early_deadline_s(1.0) == pytest.approx(1.0 + 0.5 / 30.0)


@settings(max_examples=300, deadline=None)
@given(rate_hz=st.sampled_from((10.0, 30.0, 40.0, 50.0)), targets=st.sampled_from(("gcs", "autopilot")),
       gaps=st.lists(st.tuples(st.floats(1e-4, 1.0), st.booleans()), min_size=2, max_size=300))
def test_early_odometry_keeps_the_average_rate_and_its_spacing(rate_hz: float, targets: str,
                                                               gaps: list[tuple[float, bool]]) -> None:
    # Passes at random times, at most half a period apart (a busy link), some made anyway (early allowed),
    # some at deadlines: ODOMETRY never leaves before its window, never twice for one grid point, an
    # early one to the autopilot never within 21 ms of the one before, any at least half a period
    # apart, and the rate holds (no drift, no burst).
    pub = OdometryPublisher(OdometryParams(rate_hz=rate_hz, targets=targets))
    period = pub.period_s
    t, sent = 1.0, []
    for gap, early in gaps:
        t += gap * 0.5 * period
        grid = pub.next_s
        if pub.due(t, early):
            assert grid is None or t >= grid - pub.early_s - 1e-12
            assert grid is None or pub.next_s == pytest.approx(grid + period)
            if sent and early and t < grid and targets == "autopilot":
                assert t - sent[-1] >= 0.021 - 1e-9
            sent.append(t)
    assert all(b - a >= 0.5 * period - 1e-9 for a, b in itertools.pairwise(sent))
    assert all(b - a <= 2.0 * period + 1e-9 for a, b in itertools.pairwise(sent))
    assert abs(len(sent) - (t - 1.0) / period) <= 2


def test_publisher_packs_frd_signs_and_the_unobserved_variance() -> None:
    x, P = _state()  # noqa: N806
    msg = OdometryPublisher(OdometryParams(unobserved_variance=7.0)).message(x, P, 123, 4, 55)
    assert (msg.time_usec, msg.reset_counter, msg.quality) == (123, 4, 55)
    assert msg.y == -2.0 and msg.yawspeed == pytest.approx(-0.3)
    assert msg.pose_covariance[0] == pytest.approx(0.01) and msg.pose_covariance[6] == pytest.approx(0.04)
    assert msg.pose_covariance[11] == 7.0  # z, unobserved
    assert msg.frame_id == mavlink.MAV_FRAME_LOCAL_FRD and msg.child_frame_id == mavlink.MAV_FRAME_BODY_FRD


def test_quality_falls_with_uncertainty_and_is_zero_without_wheels() -> None:
    _, P = _state()  # noqa: N806
    assert sigma_xy(P) == pytest.approx(0.2)
    good = quality(P / 100.0, True)
    assert 1 <= quality(P, True) < good <= 100
    assert quality(P, False) == 0


# ------------------------------------------------------------------------------------ resets

def _reset_cmd(x: float, y: float, yaw_deg: float) -> mavlink.MAVLink_command_long_message:
    return mavlink.MAVLink_command_long_message(1, 191, POSE_RESET_COMMAND, 0, x, y, yaw_deg, 0, 0, 0, 0)


def test_requested_pose_converts_frd_keeps_nan_coordinates_and_denies_garbage() -> None:
    current = Pose2D(5.0, 6.0, 0.1)
    pose = requested_pose(_reset_cmd(1.0, 2.0, 90.0), current)
    assert pose == Pose2D(1.0, -2.0, pytest.approx(-math.pi / 2))
    assert requested_pose(_reset_cmd(math.nan, 2.0, math.nan), current) == Pose2D(5.0, -2.0, 0.1)
    assert requested_pose(_reset_cmd(1e7, 0.0, 0.0), current) is None
    assert requested_pose(_reset_cmd(0.0, 0.0, 720.0), current) is None
    assert requested_pose(_reset_cmd(math.inf, 0.0, 0.0), current) is None


def test_reset_counter_rises_on_resets_and_reboots_and_wraps() -> None:
    identity = Identity(learned_system_id=1)
    r = ResetCounter(Reporter(identity))
    out = r.reboot("time back 5 s", 0.0)
    assert r.value == 1 and "reboot" in out[0].msg.text
    r.value = 255
    r.pose_reset(Pose2D(), 10.0)
    assert r.value == 0 and r.counters == {"reboots": 1, "pose_resets": 1, "pose_resets_denied": 0}


# ------------------------------------------------------------------------------------ reports

def test_slip_needs_consecutive_intervals_and_reports_rate_limited() -> None:
    m = SlipMonitor(Reporter(Identity(learned_system_id=1)))
    texts = []
    for i in range(SLIP_MIN_INTERVALS - 1):
        texts += m.interval(True, i * 0.05)
    assert m.count == 0 and texts == [] and not m.slipping
    assert m.interval(True, 1.0) and m.count == 1 and m.slipping
    assert m.interval(True, 1.05) == [] and m.count == 2  # counted, not reported again so soon
    assert m.interval(False, 1.1) == [] and not m.slipping
    m.interval(True, 1.0 + SLIP_REPORT_INTERVAL_S)
    assert m.interval(True, 1.05 + SLIP_REPORT_INTERVAL_S)


def test_calibration_reports_only_when_enabled_and_every_interval() -> None:
    reporter = Reporter(Identity(learned_system_id=1))
    assert CalibrationReports(reporter, False).tick(100.0, True, 0.3, 0.05, 0.05) == []
    c = CalibrationReports(reporter, True)
    assert c.tick(0.0, False, 0.3, 0.05, 0.05) == [] and c.next_s is None  # no wheels yet
    assert c.tick(1.0, True, 0.3, 0.05, 0.05) == [] and c.next_s == 31.0
    out = c.tick(31.0, True, 0.3057, 0.0499, 0.0509)
    assert out and out[0].msg.text == "cal track 0.3057 r 0.0499/0.0509"


@pytest.mark.parametrize("value", [1e39, -1e300, math.inf, math.nan, 2.0**70])
def test_publisher_clamps_every_field_to_its_wire_type(value: float) -> None:
    x, P = _state()  # noqa: N806
    x[:] = value
    P[:, :] = value
    msg = OdometryPublisher(OdometryParams()).message(x, P, 2**64 + 5 if value > 0 else -3, 300, 1000)
    packed = msg.pack(mavlink.MAVLink(None, 1, 191))  # would raise struct.error / OverflowError unclamped
    decoded = mavlink.MAVLink(None).decode(bytearray(packed))
    assert 0 <= decoded.time_usec <= 2**64 - 1 and decoded.reset_counter <= 255 and decoded.quality <= 255


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.floats(-math.pi, math.pi))
def test_odometry_covariances_are_the_general_constructions(seed: int, anchored: bool, rotation: float) -> None:
    # The closed form written out per entry (it runs at 30 Hz) against 6x6 S C S, rotation, upper triangle.
    from rover_bridge.frames import LocalAnchor

    rng = np.random.default_rng(seed)
    x = rng.normal(size=N_STATES)
    a = rng.normal(size=(N_STATES, N_STATES))
    P = a @ a.T  # noqa: N806
    anchor = LocalAnchor(1.5, -2.0, rotation) if anchored else None
    pub = OdometryPublisher(OdometryParams())
    msg = pub.message(x, P, 1, 0, 50, anchor)
    pose, vel = reference_covariances(x, P, pub.unobserved_variance, anchor)
    got = list(msg.pose_covariance) + list(msg.velocity_covariance)
    assert got == pytest.approx(pose + vel, rel=1e-12, abs=1e-12)
    if anchor is None:  # bit for bit, the signs of the zeros included
        assert [math.copysign(1.0, v) for v in got] == [math.copysign(1.0, v) for v in pose + vel]


def test_no_class_in_rover_bridge_is_over_300_lines() -> None:
    # The estimate core only wires; each behaviour is a small class (issue 30: none in estimate/ over 300 lines).
    import ast

    root = Path(__file__).resolve().parents[1] / "rover_bridge"
    sizes = {}
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                sizes[f"{path.relative_to(root)}:{node.name}"] = (node.end_lineno or node.lineno) - node.lineno + 1
    assert "estimate/core.py:EstimateCore" in sizes and "estimate/ekf.py:WheelGyroEKF" in sizes
    assert {name: n for name, n in sizes.items() if n > 300} == {}
