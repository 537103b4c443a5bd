"""BridgeCore hands a gyro sample to the estimate flow with the next message or tick (composition.handle).

What must hold: the estimate is exactly the one of a core that hands every sample over at once (same
ODOMETRY, same state, same counters), whatever the sequence; the source in use and what is decoded
never lag; a held sample waits at most GYRO_HOLD_MAX_S when nothing else comes; shutdown hands it over.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_deadlines import _event

from rover_bridge.app.composition import GYRO_HOLD_MAX_S, BridgeCore
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Outgoing
from rover_bridge.params import Profile

ODOMETRY = mavlink.MAVLINK_MSG_ID_ODOMETRY
# Mostly gyro and wheels (the held path), with everything else that may come between them.
EVENTS = st.lists(st.tuples(st.sampled_from(("gyro", "gyro", "wheels", "wheels", "ap_heartbeat", "system_time",
                                             "request", "gcs_heartbeat", "interval_ack")),
                            st.floats(0.0, 0.06), st.integers(0, 40)), min_size=1, max_size=120)


def _odometry(out: list[Outgoing] | tuple[Outgoing, ...]) -> list[bytes]:
    return [bytes(o.msg.pack(mavlink.MAVLink(None))) for o in out if o.msg.get_msgId() == ODOMETRY]


def _run(events: list[tuple[str, float, int]], hold: bool) -> tuple[BridgeCore, list[tuple[float, bytes]]]:
    core = BridgeCore(Profile())
    core.hold_gyro = hold
    t, odometry = 0.0, []
    for kind, gap_s, value in events:
        end = t + gap_s
        while (deadline := core.next_deadline_s(t)) <= end:
            t = max(t, deadline)
            odometry += [(t, b) for b in _odometry(core.tick(t))]
        t = end
        reaction = core.handle(_event(kind, t, value), t)
        odometry += [(t, b) for b in _odometry(reaction.out)]
    odometry += [(t, b) for b in _odometry(core.shutdown(t))]
    return core, odometry


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(EVENTS)
def test_the_held_path_computes_exactly_what_handing_over_at_once_does(events: list[tuple[str, float, int]]) -> None:
    held, odo_held = _run(events, hold=True)
    eager, odo_eager = _run(events, hold=False)
    # The held core ticks at more times (a held sample's deadline); every ODOMETRY is the same, at the same time.
    assert odo_held == odo_eager
    assert np.array_equal(held.estimate.ekf.x, eager.estimate.ekf.x)
    assert np.array_equal(held.estimate.ekf.P, eager.estimate.ekf.P)
    assert held.estimate.counters == eager.estimate.counters
    assert held.estimate.raw_pose == eager.estimate.raw_pose


def _attitude_then_nothing(core: BridgeCore) -> float:
    t = 0.0
    for k in range(5):  # a source in use first (the first sample is never held: it chooses the source)
        t = 0.02 * k
        core.handle(_event("gyro", t, 3), t)
        core.handle(_event("wheels", t + 0.001, k), t + 0.001)
    t += 0.02
    while core.next_deadline_s(t) <= t:  # nothing else due: only the held sample sets the next deadline
        core.tick(t)
    core.handle(_event("gyro", t, 7), t)
    return t


def test_a_held_sample_is_fused_by_the_next_deadline_when_nothing_else_comes() -> None:
    core = BridgeCore(Profile())
    t = _attitude_then_nothing(core)
    samples = core.estimate.counters["gyro_samples"]
    deadline = core.next_deadline_s(t)
    assert t < deadline <= t + GYRO_HOLD_MAX_S + 1e-9
    core.tick(deadline)
    assert core.estimate.counters["gyro_samples"] == samples + 1


def test_shutdown_hands_a_held_sample_over() -> None:
    core = BridgeCore(Profile())
    t = _attitude_then_nothing(core)
    samples = core.estimate.counters["gyro_samples"]
    core.shutdown(t)
    assert core.estimate.counters["gyro_samples"] == samples + 1


def test_only_the_source_in_use_is_held_and_the_first_sample_is_not() -> None:
    core = BridgeCore(Profile())
    core.handle(_event("gyro", 0.0, 3), 0.0)
    assert core.estimate.gyro_source == "attitude" and core.estimate.counters["gyro_samples"] == 1
    raw = mavlink.MAVLink_raw_imu_message(20_000, 0, 0, -1000, 0, 0, 10, 0, 0, 0)
    raw_inc = Incoming(_event("gyro", 0.0, 0).link, mavlink.MAVLink(None, 1, 1).decode(
        bytearray(raw.pack(mavlink.MAVLink(None, 1, 1)))))
    core.handle(raw_inc, 0.02)  # another source: handed over at once (it may switch the source)
    assert core.estimate.counters["gyro_samples"] == 1  # not fused: ATTITUDE is preferred, but it was seen
    core.handle(_event("gyro", 0.04, 3), 0.04)
    assert core.estimate.counters["gyro_samples"] == 1  # held
    core.handle(_event("wheels", 0.041, 1), 0.041)
    assert core.estimate.counters["gyro_samples"] == 2
