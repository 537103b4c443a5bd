"""ODOMETRY leaves in passes the shell makes anyway (rover_bridge.estimate.publish.EARLY_FRACTION).

On a companion computer a wake-up of its own costs more CPU than the message (benchmarks/bench_bridge.py
cpu). What must hold, with the real shell, core and sitl emulator over loopback UDP, the loop woken as
`Runner.run` wakes it (a frame arrived, or its next deadline): ODOMETRY keeps its rate, an early one is
at least half a period after the one before, and to the autopilot never closer than its EKF takes
external navigation (20 ms); with the autopilot's telemetry at 50 Hz few need a wake-up of their own.
"""

from __future__ import annotations

import dataclasses
import itertools
import select

import pytest
from lockstep import Lockstep

from rover_bridge.params import Profile
from sitl import VehicleConfig

STEP_S = 0.001


def _profile(targets: str) -> Profile:
    p = Profile()
    return dataclasses.replace(p, estimator=dataclasses.replace(p.estimator, stream_rate_hz=50.0),
                               odometry=dataclasses.replace(p.odometry, targets=targets))


def _drive_woken_as_run_does(ls: Lockstep, seconds: float) -> tuple[list[float], int]:
    """Step the emulator every ms, the bridge only when a link is readable or its deadline came.
    Returns when ODOMETRY left, and how many of those passes nothing but the deadline woke."""
    runner, publisher = ls.runner, ls.core.estimate.publisher
    fds = [fd for fd in (ep.fileno() for ep in runner.endpoints) if fd is not None]
    sent_at: list[float] = []
    own_wakes = 0
    t = ls.t_s
    for i in range(round(seconds / STEP_S)):
        t = round(t + STEP_S, 9)
        ls.t_s = t
        ls.emu.step(STEP_S)
        if i % 1000 == 0:
            ls.gcs_heartbeat()
        readable = bool(select.select(fds, [], [], 0.0)[0])
        if not readable and t < runner.next_deadline_s:
            continue  # Runner.run would still be asleep
        before = publisher.sent
        runner.step(t)
        if publisher.sent > before:
            sent_at.append(t)
            own_wakes += not readable
        while (msg := ls.gcs.recv_msg()) is not None:
            ls.view.add(t, msg)
    return sent_at, own_wakes


@pytest.mark.parametrize(("targets", "max_own_fraction"), [("gcs", 0.1), ("autopilot", 0.4)])
def test_odometry_rides_on_telemetry_passes_and_keeps_its_rate(targets: str, max_own_fraction: float) -> None:
    # Telemetry at 50 Hz by SET_MESSAGE_INTERVAL needs SCHED_LOOP_RATE 100: at Rover's default 50, ArduPilot
    # (and the emulator) refuse intervals under 1.25 loop periods (25 ms).
    vehicle = VehicleConfig(external_nav=targets == "autopilot", params=(("SCHED_LOOP_RATE", 100.0),))
    ls = Lockstep(_profile(targets), vehicle, seed=3, dt_s=0.01)
    try:
        ls.run_for(4.0)  # the autopilot found, streams at 50 Hz, wheels flowing, the frame decided
        extnav = ls.emu.autopilot.extnav.counters
        frames_before = extnav["frames"]
        sent_at, own_wakes = _drive_woken_as_run_does(ls, 5.0)
        period = ls.core.estimate.publisher.period_s
        intervals = [b - a for a, b in itertools.pairwise(sent_at)]
        assert abs(len(sent_at) - 5.0 / period) <= 2  # 30 Hz, as configured
        assert min(intervals) >= 0.5 * period - STEP_S and max(intervals) <= 2.0 * period
        # Without the early window each ODOMETRY but the few that coincide with telemetry wakes the loop.
        assert own_wakes <= max_own_fraction * len(sent_at), (own_wakes, len(sent_at))
        if targets == "gcs":
            assert len(ls.view.of("ODOMETRY")) >= len(sent_at) - 1  # they reached the ground station
        else:
            assert min(intervals) >= 0.021 - 1e-9
            assert extnav["dropped_rate"] == 0 and extnav["frames"] - frames_before >= len(sent_at) - 1
    finally:
        ls.close()
