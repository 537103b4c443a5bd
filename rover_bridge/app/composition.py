"""The whole pure core: messages and the current time in, messages out. No sockets, no clock.

`BridgeCore` composes the command flow (rover_bridge.command.core.CommandCore) and the estimate flow
(rover_bridge.estimate.core.EstimateCore), which share one Identity and one Reporter, and sends
the bridge's own HEARTBEAT. The shell (rover_bridge.app.loop) feeds every decoded message to
`handle`, calls `tick` at `next_deadline_s()`, and calls `shutdown` on every exit path.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from rover_bridge.command.core import CommandCore
from rover_bridge.estimate.core import EstimateCore
from rover_bridge.kinematics import MeasuredWheels
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.gate import BRIDGE_COMMANDS, CommandGate
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.params import Profile

HEARTBEAT_PERIOD_S = 1.0


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
        # Both flows see every message (unrolled: this runs for every frame the bridge reads).
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
        if not (rc.out or re_.out):
            return re_ if re_.consumed else rc
        return Reaction(consumed=rc.consumed or re_.consumed, out=rc.out + re_.out)

    def tick(self, now_s: float) -> list[Outgoing]:
        out: list[Outgoing] = []
        if self._next_heartbeat_s is None or now_s >= self._next_heartbeat_s:
            # Keep the 1 Hz grid; after a stall, restart it rather than bursting the missed beats.
            last = self._next_heartbeat_s
            self._next_heartbeat_s = (now_s if last is None or now_s - last > HEARTBEAT_PERIOD_S else last) \
                + HEARTBEAT_PERIOD_S
            out.extend(self._heartbeats())
        for sub in self._subcores:
            out.extend(sub.tick(now_s))
        return out

    def next_deadline_s(self, now_s: float) -> float:
        hb = now_s if self._next_heartbeat_s is None else self._next_heartbeat_s
        return min(hb, self.command.next_deadline_s(now_s), self.estimate.next_deadline_s(now_s))

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Every subcore's safe-stop messages (neutral, release, the probe that confirms them), in order.
        The shell then keeps handling and ticking until `stop_settled` (see CommandCore.shutdown)."""
        out: list[Outgoing] = []
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
