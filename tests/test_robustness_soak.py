"""Soak: one simulated hour of driving, pure core against the emulator, no sockets.

One simulated hour through UDP sockets in lockstep takes minutes of CI time, so this soak is
pure-core: the sitl emulator's own messages (Emulator(record_sent=True), re-decoded from their
bytes) go into BridgeCore.handle, and the BridgeCore's outgoing messages go into Emulator.handle_message
(packed with their source ids and decoded again), all on one simulated clock stepped at the
control period. The GCS drives a repeating pattern (arcs, reversing, stops that time out and brake,
and a few rejected requests). Accelerated so the hour fits in CI: the control loop runs at 8 Hz (the
rate checked for drift), sensors and ODOMETRY at 2 Hz, the emulator's physics in 125 ms steps;
every code path of the hour still runs in every minute.

Checked: memory allocated during the last ten simulated minutes and still alive at the end
(tracemalloc; tracing the whole hour would triple its cost) stays small, and Python's count of
allocated memory blocks does not grow from minute 10 to the end;
no internal list or dict grows with time (Reporter.sent, rate-limiter keys, report-once sets,
estimator buffers and stream tables, emulator queues); every simulated minute carries exactly the
same number of wheel outputs (8 Hz: 480 per minute, no drift); the estimate stays finite.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import random
import sys
import tracemalloc
from typing import Any

from rover_bridge.app.composition import BridgeCore
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile
from sitl import Emulator, VehicleConfig

# The control period (command.rate_hz = 8 here), one emulator step each. 1/8 s is exact in binary,
# so simulated times land exactly on the bridge's deadlines (0.1 s would not: t + 0.1 can come out
# a hair above the next step's time and skip a whole period, a stepping artefact).
DT_S = 0.125
OUTPUTS_PER_MINUTE = 480
MINUTES = 60
BODY_VEL = 0b0000_0101_1100_0111


def sizes(core: BridgeCore, emu: Emulator) -> dict[str, int]:
    """Lengths of every internal collection that could grow with time."""
    est: Any = core.estimate
    return {
        "reporter.sent": len(core.reporter.sent),
        "limiter.tokens": len(core.reporter.limiter._tokens),
        "limiter.last": len(core.reporter.limiter._last_s),
        "limiter.suppressed": len(core.reporter.limiter.suppressed),
        "command.said": len(core.command._said),
        "command.counters": len(core.command.counters),
        "gate.reported": len(core.gate._reported),
        "gate.counters": len(core.gate.counters),
        "estimate.counters": len(est.counters),
        "estimate.gyro_window": len(est.fusion.gyro_window),
        "estimate.gyro_sources": est.gyro.tracked_sources,
        "estimate.streams": len(est.streams.streams),
        "emu.link_in": len(emu._link_in),
        "emu.link_out": len(emu._link_out),
        "emu.outbox": len(emu.autopilot.outbox),
        "emu.collector": len(emu._collector.packets),
        "emu.statustexts": len(emu.statustexts_sent),
    }


class Soak:
    def __init__(self) -> None:
        p = Profile()
        p = dataclasses.replace(p, command=dataclasses.replace(p.command, rate_hz=1.0 / DT_S),
                                estimator=dataclasses.replace(p.estimator, stream_rate_hz=2.0),
                                odometry=dataclasses.replace(p.odometry, rate_hz=2.0))
        self.core = BridgeCore(p)
        self.emu = Emulator(VehicleConfig(start_armed=True, physics_dt_s=DT_S), seed=17, record_sent=True)
        self.gcs = mavlink.MAVLink(None, 255, 190)
        self.parser = mavlink.MAVLink(None)
        self.t_s = 0.0
        self.overrides = 0
        self.to_gcs = 0

    def _decode(self, msg: MAVLinkMessage) -> MAVLinkMessage:
        decoded: MAVLinkMessage = self.parser.decode(bytearray(msg.get_msgbuf()))
        return decoded

    def route(self, out: Any) -> None:
        for item in out:
            assert isinstance(item, Outgoing)
            if item.dest is Link.AUTOPILOT:
                if item.msg.get_type() == "RC_CHANNELS_OVERRIDE":
                    self.overrides += 1
                self.emu.handle_message(item.msg, src_system=item.src_system, src_component=item.src_component)
            else:
                self.to_gcs += 1

    def gcs_send(self, msg: MAVLinkMessage) -> None:
        frame = self._decode_packed(msg.pack(self.gcs))
        self.route(self.core.handle(Incoming(Link.GCS, frame), self.t_s).out)

    def _decode_packed(self, data: bytes) -> MAVLinkMessage:
        decoded: MAVLinkMessage = self.parser.decode(bytearray(data))
        return decoded

    def step(self, i: int) -> None:
        self.t_s = round((i + 1) * DT_S, 9)
        self.emu.step(DT_S)
        log = self.emu.sent_log
        assert log is not None
        for _, msg in log:
            self.route(self.core.handle(Incoming(Link.AUTOPILOT, self._decode(msg)), self.t_s).out)
        log.clear()
        self.script(i)
        if self.t_s >= self.core.next_deadline_s(self.t_s):
            self.route(self.core.tick(self.t_s))

    def script(self, i: int) -> None:
        """The GCS: 1 Hz heartbeat; a 60 s cycle of arcs, a reverse, a stop; now and then a bad request."""
        if i % 8 == 0:
            self.gcs_send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                            0, 0, 0, 3))
        phase_s = self.t_s % 60.0
        # Requests at 8 Hz while driving (one per step).
        if phase_s < 25.0:
            self.gcs_send(self._request(0.5, 0.3))
        elif phase_s < 35.0:
            self.gcs_send(self._request(-0.3, -0.2))
        elif phase_s < 45.0:
            self.gcs_send(self._request(0.4, -0.4))
        # 45-60 s: silence: the requests time out, the rover brakes and idles
        if i % 401 == 0:
            self.gcs_send(self._request(float("nan"), 0.0))  # rejected, reported once, counted

    def _request(self, vx: float, yaw_rate_cw: float) -> MAVLinkMessage:
        return mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, 8, BODY_VEL, 0, 0, 0, vx, 0, 0, 0, 0,
                                                                     0, 0, yaw_rate_cw)


def test_one_simulated_hour_no_growth_no_drift() -> None:
    soak = Soak()
    steps_per_minute = round(60.0 / DT_S)
    per_minute: list[int] = []
    sizes_at: dict[int, dict[str, int]] = {}
    blocks_at: dict[int, int] = {}
    baseline = 0
    for minute in range(MINUTES):
        if minute == MINUTES - 10:
            gc.collect()
            tracemalloc.start(1)
            baseline = tracemalloc.get_traced_memory()[0]
        before = soak.overrides
        for i in range(minute * steps_per_minute, (minute + 1) * steps_per_minute):
            soak.step(i)
        per_minute.append(soak.overrides - before)
        if minute in (3, 10, 30, MINUTES - 1):
            gc.collect()
            sizes_at[minute] = sizes(soak.core, soak.emu)
            blocks_at[minute] = sys.getallocatedblocks()
    gc.collect()
    grown = tracemalloc.get_traced_memory()[0] - baseline
    tracemalloc.stop()

    # Control rate: exactly 8 Hz every simulated minute (the first is short by the start-up).
    assert set(per_minute[1:]) == {OUTPUTS_PER_MINUTE}, per_minute
    # No queue or table grows after the warm-up (Reporter.sent is a ring of the last 100 reports).
    bounded = {"reporter.sent"}
    late, early = sizes_at[MINUTES - 1], sizes_at[10]
    assert {k: v for k, v in late.items() if k not in bounded} == {k: v for k, v in early.items() if k not in bounded}
    assert late["reporter.sent"] == 100  # full (reports keep coming every cycle), and no fuller
    # Memory: what the last ten minutes (4800 outputs, ~15k messages) allocated and left alive is
    # small (a leak of 16 bytes per message would show), and the block count stays flat all hour.
    assert grown < 128 * 1024, grown
    assert blocks_at[MINUTES - 1] - blocks_at[10] < 2000, blocks_at
    # It really drove all hour, and the estimate stayed finite.
    assert soak.core.command.counters["requests.accepted"] > 20_000
    assert soak.core.command.counters.get("state.braking", 0) >= MINUTES - 1
    pose = soak.core.estimate.pose
    assert all(math.isfinite(v) for v in (pose.x_m, pose.y_m, pose.yaw_rad))
    assert soak.core.command.counters.get("rejected.non_finite", 0) >= 3


def test_control_rate_does_not_drift_when_the_loop_wakes_late() -> None:
    """The real loop wakes a little after each deadline (select(), scheduling): 0-3 ms, seeded.

    Scheduling each output one period after the late one would stretch every period by the lateness
    (19.4 Hz instead of 20 here); the output grid must hold: 1200 outputs every minute.
    """
    core = BridgeCore(Profile())
    ap, parser = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None)
    heartbeat = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                  mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, mavlink.MAV_STATE_ACTIVE, 3)
    rng = random.Random(7)
    t_s, next_hb_s, minute_end_s, n = 0.0, 0.0, 60.0, 0
    counts: list[int] = []
    while len(counts) < 5:
        out: list[Outgoing] = []
        if t_s >= next_hb_s:
            msg = parser.decode(bytearray(heartbeat.pack(ap)))
            out += core.handle(Incoming(Link.AUTOPILOT, msg), t_s).out
            next_hb_s += 1.0
        out += core.tick(t_s)
        n += sum(1 for o in out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE")
        if t_s >= minute_end_s:
            counts.append(n)
            n, minute_end_s = 0, minute_end_s + 60.0
        t_s = min(core.next_deadline_s(t_s), next_hb_s) + rng.uniform(0.0, 0.003)
    assert all(abs(c - 1200) <= 1 for c in counts), counts
