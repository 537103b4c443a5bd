"""The whole pure core: messages and the current time in, messages out. No sockets, no clock.

`BridgeCore` composes the command flow (rover_bridge.command.core.CommandCore) and the estimate flow
(rover_bridge.estimate.core.EstimateCore), which share one Identity and one Reporter, and sends
the bridge's own HEARTBEAT. The shell (rover_bridge.app.loop) feeds every decoded message to
`handle`, calls `tick` at `next_deadline_s()` (and `early_tick` in a pass it makes anyway once
`next_early_s()` has come), and calls `shutdown` on every exit path.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

from rover_bridge.command.core import CommandCore
from rover_bridge.estimate.core import EstimateCore
from rover_bridge.estimate.streams import Stream
from rover_bridge.kinematics import MeasuredWheels
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.gate import BRIDGE_COMMANDS, CommandGate
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.params import Profile

HEARTBEAT_PERIOD_S = 1.0
_SERVO_OUTPUT_RAW = mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW
_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
_DISTANCE_SENSOR = mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR
_DEMAND_IDS = frozenset(getattr(mavlink, f"MAVLINK_MSG_ID_{name}") for name in CommandCore.DEMAND_READS)
# A gyro sample waits at most this long for the next message or tick before the estimate flow gets it.
GYRO_HOLD_MAX_S = 0.025


class SubCore(Protocol):
    def handle(self, inc: Incoming, now_s: float) -> Reaction: ...
    def tick(self, now_s: float) -> list[Outgoing]: ...
    def next_deadline_s(self, now_s: float) -> float: ...
    def shutdown(self, now_s: float) -> list[Outgoing]: ...


class BridgeCore:
    def __init__(self, profile: Profile) -> None:
        self.profile = profile
        self.identity = Identity.from_profile(profile)
        self.reporter = Reporter(self.identity)
        self.estimate = EstimateCore(profile, self.identity, self.reporter)
        # Position targets are followed on the estimate flow's pose (rover_bridge.command.navigation).
        self.command = CommandCore(profile, self.identity, self.reporter, pose_source=self.estimate)
        # The autopilot's demand (rover_bridge.command.demand) at the rate its driver needs, asked for by the
        # estimate flow's stream requests (one requester, so every SET_MESSAGE_INTERVAL ACK is unambiguous; the
        # same fallback, REQUEST_DATA_STREAM, and the same re-asking after a reboot) from the first heartbeat
        # that reports a mode the autopilot drives in: until then nobody needs it at 40 Hz, on this link or
        # forwarded to the ground stations.
        self._demand: Stream | None = None
        if profile.modes.autopilot:
            self._demand = Stream("SERVO_OUTPUT_RAW", _SERVO_OUTPUT_RAW, mavlink.MAV_DATA_STREAM_RC_CHANNELS,
                                  rate_hz=profile.demand.rate_hz, wanted=False)
            self.estimate.streams.add(self._demand)
        # The autopilot's range sensors (simple avoidance, rover_bridge.command.proximity) at [avoidance]
        # sensor_rate_hz once it has sent one: its EXTRA3 stream is often 1 Hz, slower than the sensor timeout.
        self._ranges: Stream | None = None
        if profile.avoidance.enabled and profile.avoidance.sensor_rate_hz > 0.0:
            self._ranges = Stream("DISTANCE_SENSOR", _DISTANCE_SENSOR, mavlink.MAV_DATA_STREAM_EXTRA3,
                                  rate_hz=profile.avoidance.sensor_rate_hz, check_rate=False, wanted=False)
            self.estimate.streams.add(self._ranges)
        # [security] in front of both cores: a refused frame reaches neither, nor the autopilot.
        self.gate = CommandGate(profile, self.identity, self.reporter)
        self._subcores: tuple[SubCore, ...] = (self.command, self.estimate)
        # Who else wants the measured wheel speeds (`rover-bridge calibrate`).
        self.wheel_observers: list[Callable[[MeasuredWheels, float], None]] = []
        self._next_heartbeat_s: float | None = None
        names = CommandCore.AUTOPILOT_READS | EstimateCore.AUTOPILOT_READS | BRIDGE_COMMANDS
        ids = frozenset(getattr(mavlink, f"MAVLINK_MSG_ID_{name}") for name in names)
        # Gyro messages only as the estimator wants them now (they change rarely: cached per set).
        self._ap_always = ids - EstimateCore.ALL_GYRO_IDS | {mavlink.MAVLINK_MSG_ID_ATTITUDE}  # the command core's
        self._ap_gyro = self.estimate.gyro_reads
        self._autopilot_reads = self._ap_always | self._ap_gyro
        # Gyro samples the estimate flow has not been handed yet (see handle), with their arrival times;
        # hold_gyro False hands each over at once (what the tests compare the held path with).
        self.hold_gyro = True
        self._gyro_held: list[tuple[Incoming, float]] = []
        # The filter's work waits for a reader (ODOMETRY, mostly): EstimateCore's deferred fusion.
        self.estimate.defer_fusion = True

    def reads(self, link: Link) -> frozenset[int] | None:
        """Message ids the core reads from `link` now (None: all). The shell decodes only these and
        forwards the rest as raw bytes; handle() ignores the rest too, so both paths behave alike.
        Everything from a ground station is read: the security gate judges every frame."""
        return self._autopilot_ids() if link is Link.AUTOPILOT else None

    def _autopilot_ids(self) -> frozenset[int]:
        gyro = self.estimate.gyro_reads
        if gyro is not self._ap_gyro:
            self._ap_gyro = gyro
            self._autopilot_reads = self._ap_always | gyro
        return self._autopilot_reads

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        msg_id = inc.msg.get_msgId()
        from_autopilot = inc.link is Link.AUTOPILOT
        if from_autopilot and msg_id not in self._autopilot_ids():
            return NOTHING
        if self.gate.policy.active:
            refused = self.gate.check(inc, now_s)
            if refused is not None:
                return refused
        # Both flows see every message (unrolled: this runs for every frame the bridge reads). A gyro
        # sample reaches the estimate flow with the next message of any kind or the next tick, in
        # arrival order and with its own arrival time, so the estimate is computed exactly as if it had
        # been handed over at once; it costs less: the sample arrives first in the autopilot's burst
        # (ATTITUDE before WHEEL_DISTANCE), alone in its pass, and is fused in the wheel reading's pass,
        # where the estimate flow's code is already warm. Nothing reads the estimate in between: the
        # held samples are handed over before any other message reaches either flow. Only samples of the
        # source in use wait: any other may switch the source, and what is decoded with it (reads).
        if from_autopilot and msg_id == self.estimate.gyro_source_id and self.hold_gyro:
            self._gyro_held.append((inc, now_s))
            return self.command.handle(inc, now_s)
        held = self._hand_over_gyro() if self._gyro_held else []
        rc = self.command.handle(inc, now_s)
        re_ = self.estimate.handle(inc, now_s)
        if from_autopilot and msg_id == mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE:
            # The estimate flow measured the wheels; the command flow's speed loop and slip compensation use it.
            sample = self.estimate.take_wheel_sample()
            if sample is not None:
                self.command.on_wheels(sample, now_s)
                for observe in self.wheel_observers:
                    observe(sample, now_s)
            self.command.set_slipping(self.estimate.slip.slipping)
        elif from_autopilot and msg_id == _SERVO_OUTPUT_RAW:
            self.estimate.streams.arrival("SERVO_OUTPUT_RAW", now_s)
        elif (msg_id == _HEARTBEAT and self._demand is not None and not self._demand.wanted and from_autopilot
              and self.command.demand_wanted):
            re_ = Reaction(re_.consumed, (*re_.out, *self.estimate.streams.want(self._demand.name, now_s)))
            self._ap_always = self._ap_always | _DEMAND_IDS  # decoded from now on
            self._autopilot_reads = self._ap_always | self._ap_gyro
        elif (msg_id == _DISTANCE_SENSOR and from_autopilot and self._ranges is not None and not self._ranges.wanted
              and self.identity.from_autopilot(inc.msg) and self.command.avoid.picture is not None):
            re_ = Reaction(re_.consumed, (*re_.out, *self.estimate.streams.want(self._ranges.name, now_s)))
        if not (rc.out or re_.out or held):
            return re_ if re_.consumed else rc
        return Reaction(consumed=rc.consumed or re_.consumed, out=(*held, *rc.out, *re_.out))

    def _hand_over_gyro(self) -> list[Outgoing]:
        """The held gyro samples to the estimate flow, oldest first; what it answered."""
        held, self._gyro_held = self._gyro_held, []
        out: list[Outgoing] = []
        for inc, arrived_s in held:
            out.extend(self.estimate.handle(inc, arrived_s).out)
        return out

    def tick(self, now_s: float) -> list[Outgoing]:
        out = self._hand_over_gyro()
        if self._next_heartbeat_s is None or now_s >= self._next_heartbeat_s:
            # Keep the 1 Hz grid; after a stall, restart it rather than bursting the missed beats.
            last = self._next_heartbeat_s
            self._next_heartbeat_s = (now_s if last is None or now_s - last > HEARTBEAT_PERIOD_S else last) \
                + HEARTBEAT_PERIOD_S
            out.extend(self._heartbeats())
        for sub in self._subcores:
            out.extend(sub.tick(now_s))
        self.command.set_slipping(self.estimate.slip.slipping)  # the verdict of what was fused in the tick
        return out

    def next_deadline_s(self, now_s: float) -> float:
        hb = now_s if self._next_heartbeat_s is None else self._next_heartbeat_s
        if self._gyro_held:
            hb = min(hb, self._gyro_held[0][1] + GYRO_HOLD_MAX_S)
        return min(hb, self.command.next_deadline_s(now_s), self.estimate.next_deadline_s(now_s))

    def next_early_s(self, now_s: float) -> float:
        """From when early_tick has something to send: an output that may leave before its deadline in a
        pass the shell makes anyway (a message arrived). Only ODOMETRY does (OdometryPublisher.due)."""
        early = self.estimate.next_early_s(now_s)
        return math.inf if early is None else early

    def early_tick(self, now_s: float) -> list[Outgoing]:
        """The outputs that may leave early (see next_early_s), the held gyro samples fused first, as in tick."""
        out = self._hand_over_gyro()
        out.extend(self.estimate.odometry_due(now_s))
        self.command.set_slipping(self.estimate.slip.slipping)
        return out

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Every subcore's safe-stop messages (neutral, release, the probe that confirms them), in order.
        The shell then keeps handling and ticking until `stop_settled` (see CommandCore.shutdown)."""
        out = self._hand_over_gyro()
        for sub in self._subcores:
            out.extend(sub.shutdown(now_s))
        return out

    @property
    def stop_settled(self) -> bool:
        """shutdown() has run and the autopilot confirmed it, or the wait for that is over."""
        return self.command.stop_settled

    @property
    def stop_confirmed(self) -> bool | None:
        """True: the autopilot proved it handled the stop; False: it did not answer; None: nothing to stop."""
        return self.command.stop_confirmed

    def _heartbeats(self) -> list[Outgoing]:
        msg = mavlink.MAVLink_heartbeat_message(
            type=mavlink.MAV_TYPE_ONBOARD_CONTROLLER, autopilot=mavlink.MAV_AUTOPILOT_INVALID,
            base_mode=0, custom_mode=0, system_status=mavlink.MAV_STATE_ACTIVE, mavlink_version=3)
        sysid, compid = self.identity.own_system_id, self.identity.component_id
        out = [Outgoing(Link.AUTOPILOT, msg, sysid, compid)]
        # To the ground stations only while the autopilot is there: the bridge's heartbeat carries the
        # vehicle's system id, and GCS libraries (MAVSDK: any heartbeat of the system in the last 3 s)
        # would otherwise show a vehicle whose autopilot is gone as connected.
        if self.command.autopilot_alive:
            out.insert(0, Outgoing(Link.GCS, msg, sysid, compid))
        return out
