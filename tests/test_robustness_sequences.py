"""Sequences of autopilot (and ground-station) messages with arbitrary field values, in order.

A fuzz that decodes each frame alone cannot find a fault that needs a history: a boot-time ATTITUDE
followed by a WHEEL_DISTANCE stamped in UNIX microseconds made the EKF step through 54 years in 0.1 s
steps (the bridge hung, deaf to SIGTERM), and a maximal uint64 stamp made ODOMETRY's stamp overflow
its field (the bridge crashed). Here every numeric field of every message a core reads takes values
from 0, the type's extremes, NaN, infinities, UNIX-epoch and boot-time stamps, and random ones, over
a sequence, and every `handle` and `tick` must:
- return (never raise), with every message it returns packable on the wire;
- do bounded work: the EKF's prediction sub-steps per call are counted, not timed.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rover_bridge.app.composition import BridgeCore
from rover_bridge.estimate.ekf import MAX_PREDICT_GAP_S, MAX_PREDICT_STEP_S
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import profile_from_dict

INT_LIMITS = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535), "int16_t": (-32768, 32767),
              "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1), "uint64_t": (0, 2**64 - 1),
              "int64_t": (-2**63, 2**63 - 1)}
UNIX_US = 1_733_000_000_000_000  # a UNIX-epoch time_usec (2024)
FLOATS = st.one_of(st.sampled_from([0.0, math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e-38, 1.0, -1.0]),
                   st.floats(-1e3, 1e3, width=32))
# Per call, prediction may run to its gap limit a few times (a wheel step, its baseline, a gyro sample).
WORK_BOUND = 4 * math.ceil(MAX_PREDICT_GAP_S / MAX_PREDICT_STEP_S) + 4


def ints(kind: str, name: str) -> st.SearchStrategy[int]:
    lo, hi = INT_LIMITS[kind]
    special = [lo, hi, 0, 1]
    if name in ("time_usec", "time_unix_usec"):
        special += [UNIX_US, 1_000_000, 10_000_000_000, 2**63]
    if name == "time_boot_ms":
        special += [1000, 4_000_000_000]
    return st.one_of(st.sampled_from([v for v in special if lo <= v <= hi]), st.integers(lo, hi))


def message(cls: Any) -> st.SearchStrategy[Any]:
    fields: dict[str, st.SearchStrategy[Any]] = {}
    for name, kind, length in zip(cls.fieldnames, cls.fieldtypes, cls.array_lengths, strict=True):
        if kind == "char":
            fields[name] = st.just(b"")
            continue
        one = FLOATS if kind in ("float", "double") else ints(kind, name)
        fields[name] = st.lists(one, min_size=length, max_size=length) if length else one
    return st.fixed_dictionaries(fields).map(lambda kw: cls(**kw))


AUTOPILOT = [mavlink.MAVLink_heartbeat_message, mavlink.MAVLink_attitude_message, mavlink.MAVLink_scaled_imu_message,
             mavlink.MAVLink_raw_imu_message, mavlink.MAVLink_wheel_distance_message,
             mavlink.MAVLink_system_time_message, mavlink.MAVLink_command_ack_message,
             mavlink.MAVLink_local_position_ned_message, mavlink.MAVLink_timesync_message,
             mavlink.MAVLink_command_long_message]
GCS = [mavlink.MAVLink_set_position_target_local_ned_message, mavlink.MAVLink_manual_control_message,
       mavlink.MAVLink_command_long_message, mavlink.MAVLink_set_mode_message]

EVENT = st.one_of(
    st.tuples(st.just(Link.AUTOPILOT), st.one_of(*[message(c) for c in AUTOPILOT])),
    st.tuples(st.just(Link.GCS), st.one_of(*[message(c) for c in GCS])),
    st.tuples(st.just(None), st.just(None)),  # a tick
)
GAPS = st.sampled_from([0.0005, 0.01, 0.05, 0.3, 2.0, 100.0])


def _wire(msg: Any, sysid: int, compid: int) -> Any | None:
    """As the shell hands it over: packed with these source ids and decoded (None if it cannot be sent)."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    try:
        return mavlink.MAVLink(None).decode(bytearray(msg.pack(mav)))
    except Exception:
        return None


def _healthy_start(core: BridgeCore) -> float:
    """A vehicle that is there and armed, streams running: the state in which faults matter most."""
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           mavlink.MAV_MODE_FLAG_SAFETY_ARMED | 1, 15, 4, 3)
    t = 0.0
    for i in range(40):
        t = 0.05 * i
        for msg in (hb, mavlink.MAVLink_attitude_message(round(t * 1000), 0, 0, 0, 0, 0, 0),
                    mavlink.MAVLink_wheel_distance_message(round(t * 1e6), 2, [0.01 * i] * 2 + [0.0] * 14)):
            core.handle(Incoming(Link.AUTOPILOT, _wire(msg, 1, 1)), t)
        core.tick(t)
    return t


def _check_outputs(out: Any) -> None:
    for item in out:
        item.msg.pack(mavlink.MAVLink(None, srcSystem=item.src_system, srcComponent=item.src_component))


@pytest.mark.parametrize("targets", ["gcs", "both"])
@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(events=st.lists(st.tuples(EVENT, GAPS), min_size=1, max_size=60))
def test_any_sequence_is_bounded_work_and_never_raises(targets: str, events: list[Any]) -> None:
    core = BridgeCore(profile_from_dict({"odometry": {"targets": targets}}))
    now = _healthy_start(core)
    ekf = core.estimate.ekf
    for (link, msg), gap in events:
        now += gap
        before = ekf.predict_steps
        if link is None:
            _check_outputs(core.tick(now))
        else:
            ids = (1, 1) if link is Link.AUTOPILOT else (255, 190)
            wired = _wire(msg, *ids)
            if wired is None:
                continue
            _check_outputs(core.handle(Incoming(link, wired), now).out)
        _check_outputs(core.tick(now))
        assert ekf.predict_steps - before <= WORK_BOUND


def _feed(core: BridgeCore, msg: Any, now: float) -> list[Any]:
    out = list(core.handle(Incoming(Link.AUTOPILOT, _wire(msg, 1, 1)), now).out)
    return out + core.tick(now)


def test_one_wheel_reading_stamped_far_back_does_not_move_the_clock_or_the_pose_for_good() -> None:
    core = BridgeCore(profile_from_dict({}))
    boot_s = -200.0  # the autopilot has been up 200 s
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           mavlink.MAV_MODE_FLAG_SAFETY_ARMED | 1, 15, 4, 3)

    def real(now: float, left: float) -> None:
        _feed(core, hb, now)
        _feed(core, mavlink.MAVLink_attitude_message(round((now - boot_s) * 1000), 0, 0, 0, 0, 0, 0), now)
        _feed(core, mavlink.MAVLink_wheel_distance_message(round((now - boot_s) * 1e6), 2,
                                                           [left, left] + [0.0] * 14), now)

    now, left = 0.0, 0.0
    for _i in range(40):  # 0.4 m/s
        now += 0.05
        left += 0.02
        real(now, left)
    # One frame: 100 s back, the distances 30 m off. A reboot, as far as the bridge can tell.
    _feed(core, mavlink.MAVLink_wheel_distance_message(round((now - boot_s - 100.0) * 1e6), 2,
                                                       [30.0, 30.0] + [0.0] * 14), now + 0.01)
    for _i in range(20):  # the autopilot's next words
        now += 0.05
        left += 0.02
        real(now, left)
    assert core.estimate.counters["clock_restored"] == 1
    assert core.estimate.odometry_time_usec(now) == pytest.approx((now - boot_s) * 1e6, abs=2e3)  # its clock
    x = core.estimate.pose_at(now).x_m
    assert x == pytest.approx(left - 0.02, abs=0.06)  # every interval at 0.4 m/s but the one not stepped


def test_a_maximal_wheel_stamp_publishes_a_clamped_odometry_stamp() -> None:
    core = BridgeCore(profile_from_dict({}))
    now = _healthy_start(core)
    for _i in range(5):
        now += 0.05
        out = _feed(core, mavlink.MAVLink_wheel_distance_message(2**64 - 1, 2, [0.5] * 2 + [0.0] * 14), now)
        _check_outputs(out)
    odometry = [o.msg for o in core.tick(now + 0.05) if o.msg.get_type() == "ODOMETRY"]
    assert odometry and 0 <= odometry[0].time_usec < 2**64


def test_a_wheel_stream_switching_to_unix_time_is_re_based_said_once_and_the_estimate_goes_on() -> None:
    core = BridgeCore(profile_from_dict({}))
    now = _healthy_start(core)  # boot-time stamps up to 1.95 s
    ekf = core.estimate.ekf
    texts: list[str] = []
    left = 0.4
    for _i in range(60):
        now += 0.05
        left += 0.02  # 0.4 m/s
        before = ekf.predict_steps
        out = _feed(core, mavlink.MAVLink_attitude_message(round(now * 1000), 0, 0, 0, 0, 0, 0), now)
        out += _feed(core, mavlink.MAVLink_wheel_distance_message(UNIX_US + round(now * 1e6), 2,
                                                                  [left, left] + [0.0] * 14), now)
        assert ekf.predict_steps - before <= WORK_BOUND
        texts += [o.msg.text for o in out if o.msg.get_type() == "STATUSTEXT"]
    assert sum("WHEEL_DISTANCE clock jumped" in t for t in texts) == 1
    state = core.estimate.state
    assert state.v_m_s == pytest.approx(0.4, abs=0.05)  # wheel steps still fused, on the boot clock
    assert core.estimate.counters["clock_jumps"] == 1 and core.estimate.counters["reboots"] == 0
