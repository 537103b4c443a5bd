"""Deferred fusion (rover_bridge.estimate.core): the filter's work waits for a reader, and changes nothing.

What must hold: a core that defers computes exactly what one that fuses at once does (every ODOMETRY, at
the same time, the same bytes; the same state, counters, raw odometry and STATUSTEXTs), whatever the
sequence: gaps, reboots, LOCAL_POSITION_NED, requests between. The command flow's measured wheel speeds do
not wait; a queued measurement waits at most FUSE_MAX_DELAY_S when nothing reads the filter; anything
that reads it (an accessor, a pose reset) sees every measurement handed over so far.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_deadlines import AP, _event, _wire

from rover_bridge.app.composition import BridgeCore
from rover_bridge.estimate.core import FUSE_MAX_DELAY_S
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile

ODOMETRY = mavlink.MAVLINK_MSG_ID_ODOMETRY
STATUSTEXT = mavlink.MAVLINK_MSG_ID_STATUSTEXT
KINDS = ("gyro", "gyro", "gyro", "wheels", "wheels", "wheels", "request", "system_time", "ap_heartbeat",
         "local_position", "reboot")
# Mostly the sensors' 20 ms; now and then a silence long enough to restart the motion (SILENCE_S).
GAPS = st.one_of(st.floats(0.0, 0.03), st.floats(0.0, 0.03), st.floats(0.0, 0.03), st.floats(0.4, 0.8))
EVENTS = st.lists(st.tuples(st.sampled_from(KINDS), GAPS, st.integers(0, 60)), min_size=1, max_size=150)


def _incoming(kind: str, t_s: float, epoch_s: float, value: int) -> Incoming:
    """An event at time t_s on an autopilot whose boot clock started at epoch_s."""
    stamp_s = t_s - epoch_s
    if kind == "local_position":
        msg = mavlink.MAVLink_local_position_ned_message(round(stamp_s * 1e3), 0.01 * value, 0.0, 0, 0, 0, 0)
        return Incoming(Link.AUTOPILOT, _wire(AP, msg))
    return _event(kind, stamp_s if kind in ("gyro", "wheels", "system_time") else t_s, value)


def _run(events: list[tuple[str, float, int]], defer: bool) -> tuple[BridgeCore, list[tuple[float, bytes]],
                                                                      list[str]]:
    core = BridgeCore(Profile())
    core.estimate.defer_fusion = defer
    core.hold_gyro = defer  # the eager core hands every sample over at once, too
    t, epoch = 10.0, 0.0
    odometry: list[tuple[float, bytes]] = []
    texts: list[str] = []

    def collect(out: list[Outgoing] | tuple[Outgoing, ...]) -> None:
        for o in out:
            if o.msg.get_msgId() == ODOMETRY:
                odometry.append((t, bytes(o.msg.pack(mavlink.MAVLink(None)))))
            elif o.msg.get_msgId() == STATUSTEXT:
                texts.append(o.msg.text)

    for kind, gap_s, value in events:
        end = t + gap_s
        while (deadline := core.next_deadline_s(t)) <= end:
            t = max(t, deadline)
            collect(core.tick(t))  # the deferring core ticks at more times (FUSE_MAX_DELAY_S, held samples)
        t = end
        if kind == "reboot":
            epoch = t - 0.001 * value  # the boot clock starts again
            continue
        collect(core.handle(_incoming(kind, t, epoch, value), t).out)
        if core.next_early_s(t) <= t:  # ODOMETRY leaving early in a message's pass, as the shell sends it
            collect(core.early_tick(t))
    collect(core.shutdown(t))
    return core, odometry, texts


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(EVENTS)
def test_deferring_computes_exactly_what_fusing_at_once_does(events: list[tuple[str, float, int]]) -> None:
    deferred, odo_deferred, texts_deferred = _run(events, defer=True)
    eager, odo_eager, texts_eager = _run(events, defer=False)
    assert odo_deferred == odo_eager
    assert np.array_equal(deferred.estimate.ekf.x, eager.estimate.ekf.x)
    assert np.array_equal(deferred.estimate.ekf.P, eager.estimate.ekf.P)
    assert deferred.estimate.counters == eager.estimate.counters
    assert deferred.estimate.raw_pose == eager.estimate.raw_pose
    assert deferred.estimate.state == eager.estimate.state
    assert sorted(texts_deferred) == sorted(texts_eager)  # the gate's and slip's may come later, none lost


def _driving(core: BridgeCore, cycles: int) -> float:
    t = 0.0
    for k in range(cycles):
        t = 0.02 * k
        core.handle(_event("gyro", t, 3), t)
        core.handle(_event("wheels", t + 0.001, k), t + 0.001)  # 0.5 m/s
    return t + 0.001


def test_the_speed_loop_gets_the_wheels_at_once_while_the_filter_waits() -> None:
    core = BridgeCore(Profile())
    t = _driving(core, 3)
    assert core.estimate.fusion_pending > 0  # nothing read the filter yet
    core.handle(_event("wheels", t + 0.02, 3), t + 0.02)
    sample = core.estimate.take_wheel_sample()
    assert sample is None  # already handed to the command flow in handle: measured at once
    measured = core.command.loop.measured if core.command.loop is not None else None
    assert measured is not None and measured.left_rad_s > 0.0
    assert core.estimate.fusion_pending > 0


def test_a_queued_measurement_waits_at_most_the_bound_when_nothing_reads_the_filter() -> None:
    profile = Profile()
    core = BridgeCore(dataclasses.replace(profile, odometry=dataclasses.replace(profile.odometry, targets="none")))
    t = _driving(core, 2)
    pending_since = t - 0.02 - 0.001  # the first queued (the gyro sample of the first cycle)
    while (deadline := core.next_deadline_s(t)) <= t:
        core.tick(t)
    assert core.estimate.fusion_pending > 0
    assert deadline <= pending_since + FUSE_MAX_DELAY_S + 1e-9
    core.tick(pending_since + FUSE_MAX_DELAY_S)
    assert core.estimate.fusion_pending == 0


def test_every_reader_sees_every_measurement_handed_over() -> None:
    deferred, eager = BridgeCore(Profile()), BridgeCore(Profile())
    eager.estimate.defer_fusion = False
    eager.hold_gyro = False
    for core in (deferred, eager):
        _driving(core, 6)
    assert deferred.estimate.fusion_pending > 0
    assert deferred.estimate.pose == eager.estimate.pose  # the accessor fused the queue first
    assert deferred.estimate.fusion_pending == 0
    assert deferred.estimate.pose_at(0.2) == eager.estimate.pose_at(0.2)
