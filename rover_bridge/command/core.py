"""The command flow's pure core: messages and the current time in, wheel overrides out. It only wires:

```
 vehicle state: heartbeat, armed, mode, attitude              rover_bridge.command.vehicle
        |
 drivers: GCS requests | position targets | the autopilot's    .gcs_requests, .goto, .demand
          navigation                                          (.drivers: what a driver is)
        |   which may hold the wheels in which mode           .modes ([modes])
 safety gates: link, disarm, faults, calibrate, stop modes    .safety
        |   who holds the wheels now                          .arbiter
 simple avoidance: the bridge's drivers stop short of         .proximity (.obstacles, .avoidance)
        |   obstacles (DISTANCE_SENSOR, OBSTACLE_DISTANCE)
 output stage: limiter -> kinematics -> desaturation ->       .output_stage
               wheel speed loop -> PWM -> messages
 the stop at exit, confirmed                                  .stopping
```

Each part's module says its rules; docs/safety.md and docs/gcs.md repeat them for users. Here: before the
vehicle's id is known nothing is sent at all (an override cannot be addressed); every exit path the shell can
reach calls `shutdown` (neutral, release, then the autopilot's proof); a dead bridge is covered by the
autopilot's override timeout (RC_OVERRIDE_TIME).
"""

from __future__ import annotations

import logging

from rover_bridge.command.arbiter import Arbiter
from rover_bridge.command.demand import AutopilotNavigation
from rover_bridge.command.drivers import CommandState
from rover_bridge.command.fence_watch import MISSION_MESSAGES
from rover_bridge.command.gcs_requests import GcsRequests
from rover_bridge.command.goto import AUTOPILOT_NAV_ECHOES, PositionTargets, is_goto
from rover_bridge.command.modes import AUTOPILOT, ModeTable
from rover_bridge.command.navigation import PoseSource
from rover_bridge.command.output_stage import OutputStage
from rover_bridge.command.outputs import OutputMap, WheelPwm
from rover_bridge.command.proximity import SENSOR_MESSAGES, ProximityAvoidance
from rover_bridge.command.safety import SafetyGates
from rover_bridge.command.setpoints import REQUEST_TYPES
from rover_bridge.command.stopping import EMERGENCY_PROBE_TS1, StopConfirmation
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.command.wheel_control import WheelSpeedLoop
from rover_bridge.kinematics import MeasuredWheels, Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.params import Profile

__all__ = ["EMERGENCY_PROBE_TS1", "CommandCore", "CommandState"]

log = logging.getLogger("rover_bridge.command")

STOP_UNCONFIRMED = (mavlink.MAV_SEVERITY_CRITICAL, "RB: stop NOT confirmed by the autopilot")
STOP_NOTHING = (mavlink.MAV_SEVERITY_NOTICE, "RB: stopped (no vehicle known: nothing sent)")
MODE_REQUESTS = frozenset({"SET_MODE", "COMMAND_LONG", "COMMAND_INT"})
GCS_SEEN = frozenset({"HEARTBEAT", "MANUAL_CONTROL"})  # what ArduPilot counts as its GCS alive (gcs_failsafe)
_OVER = (CommandState.STOPPING, CommandState.STOPPED)


class CommandCore:
    """Messages and the current time in, override messages out (see the module doc for the rules)."""

    # What handle() reads from the autopilot link (BridgeCore decodes nothing else from it); the demand only
    # once the autopilot has driven in one of its modes (demand_wanted): until then nobody needs it decoded.
    AUTOPILOT_READS = frozenset({"HEARTBEAT", "ATTITUDE", "COMMAND_ACK", "TIMESYNC", "PARAM_VALUE",
                                 "STATUSTEXT", "HOME_POSITION"}) | AUTOPILOT_NAV_ECHOES | SENSOR_MESSAGES
    AUTOPILOT_READS |= MISSION_MESSAGES
    DEMAND_READS = frozenset({"SERVO_OUTPUT_RAW"})

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter,
                 pose_source: PoseSource | None = None) -> None:
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        self.counters: dict[str, int] = {}
        count = self._count
        self.modes = modes = ModeTable(profile.modes, reporter)
        self.vehicle = vehicle = VehicleState(profile, identity, modes.stop, count)
        self.gates = SafetyGates(profile, identity, reporter, vehicle, modes, count)
        self.stage = OutputStage(profile, identity, reporter, count)
        self.stopper = StopConfirmation(self.stage.outputs, identity, profile.safety.stop_confirm_timeout_s, count)
        self.wheels = wheels = Arbiter(identity, reporter, vehicle, modes, self.gates, self.stage, count)
        self.gcs = wheels.gcs = GcsRequests(profile, identity, reporter, vehicle, modes, wheels, count)
        self.targets = PositionTargets(profile, identity, reporter, pose_source, vehicle, wheels, self.gcs, modes,
                                       count)
        self.autopilot = AutopilotNavigation(profile, identity, reporter, vehicle, modes, self.stage, wheels, count)
        wheels.watchers.append(self.targets.watch)
        self.avoid = wheels.avoid = ProximityAvoidance(profile, identity, reporter, vehicle, count, pose_source)

    # ----------------------------------------------------------------- read-only views

    @property
    def state(self) -> CommandState:
        return self.wheels.state

    @property
    def request(self) -> object:  # what the wheels follow: a velocity request, a position target, or None
        active = self.wheels.active
        return None if active is None else active.request

    @property
    def commanded(self) -> Twist2D:  # the twist of the last output (after the limiter)
        return self.stage.limiter.current

    @property
    def autopilot_alive(self) -> bool:  # its heartbeat is fresh (seen, not timed out)
        return self.state not in (CommandState.WAITING, CommandState.LINK_LOST)

    @property
    def stop_settled(self) -> bool:  # shutdown() has run and its confirmation is over (answered or timed out)
        return self.state is CommandState.STOPPED

    @property
    def demand_wanted(self) -> bool:  # the autopilot is in a mode it drives in: its demand is needed
        return self.modes.allows(AUTOPILOT, self.vehicle.driving_mode)

    @property
    def stop_confirmed(self) -> bool | None:
        return self.stopper.confirmed

    @property
    def last_wheel_pwm(self) -> WheelPwm | None:
        return self.stopper.neutral if self.stopper.attempts else self.stage.last_wheel_pwm

    @property
    def outputs(self) -> OutputMap:
        return self.stage.outputs

    @property
    def loop(self) -> WheelSpeedLoop | None:
        return self.stage.loop

    @property
    def _said(self) -> set[tuple[str, int, int]]:
        return self.gcs.said

    # ----------------------------------------------------------------- SubCore protocol

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        state = self.wheels.state
        if state in _OVER:
            if state is CommandState.STOPPING and self.stopper.answered(inc, now_s):
                return Reaction(consumed=True, out=tuple(self.wheels.set_state(CommandState.STOPPED, now_s)))
            return NOTHING
        msg = inc.msg
        kind = msg.get_type()
        if inc.link is Link.AUTOPILOT:
            if kind == "HEARTBEAT":
                return self._on_heartbeat(msg, now_s)
            if kind == "ATTITUDE":
                self.vehicle.on_attitude(msg, now_s)
            elif kind == "COMMAND_ACK":
                return self._on_command_ack(msg, now_s)
            elif kind == "SERVO_OUTPUT_RAW":
                return self.autopilot.handle(msg, now_s)
            elif kind in SENSOR_MESSAGES:
                self.avoid.on_sensor(msg, now_s)
            elif kind == "PARAM_VALUE":
                self.avoid.on_param_value(msg, now_s)
                return Reaction(consumed=False, out=tuple(self.gates.gcs_failsafe.on_param_value(msg, now_s)))
            elif kind == "STATUSTEXT":
                return self._resumed(now_s) if self.gates.gcs_failsafe.on_statustext(msg) else NOTHING
            elif kind in MISSION_MESSAGES:  # the fence's download (ours: consumed) or another client's upload
                consumed, out = self.avoid.on_mission(msg, now_s)
                return Reaction(consumed=consumed, out=tuple(out)) if consumed or out else NOTHING
            elif kind == "HOME_POSITION":
                self.avoid.on_home(msg)
            elif kind in AUTOPILOT_NAV_ECHOES:
                if kind == "NAV_CONTROLLER_OUTPUT":
                    self.autopilot.on_nav(msg, now_s)
                return Reaction(consumed=True) if self.targets.echo_to_hide(msg) else NOTHING
            return NOTHING
        if kind in SENSOR_MESSAGES:  # e.g. a depth camera on the companion computer (the vehicle's system)
            if msg.get_srcComponent() != self.identity.autopilot_component_id:  # the autopilot's come its own way
                self.avoid.on_sensor(msg, now_s)
            return NOTHING
        if kind in GCS_SEEN:
            resumed = self.gates.gcs_failsafe.on_gcs(msg, now_s)
            if kind == "HEARTBEAT":
                self.targets.nav.on_gcs_heartbeat(msg, now_s)
                return self._resumed(now_s) if resumed else NOTHING
        try:
            goto = is_goto(msg, kind)
        except (AttributeError, TypeError, ValueError, OverflowError):
            goto = False  # a malformed frame: the paths below judge it as they always did
        if goto:
            return self.targets.handle(inc, now_s)
        if kind in REQUEST_TYPES:
            return self.gcs.handle(inc, now_s)
        if kind in MODE_REQUESTS:
            if not self.vehicle.on_mode_request(msg, now_s):
                return NOTHING
            return Reaction(consumed=False, out=tuple(self.wheels.advance(now_s, force_output=False)))
        return NOTHING

    def tick(self, now_s: float) -> list[Outgoing]:
        state = self.wheels.state
        if state is CommandState.STOPPED:
            return []
        if state is CommandState.STOPPING:
            if self.stopper.timed_out(now_s):
                return self.wheels.set_state(CommandState.STOPPED, now_s, STOP_UNCONFIRMED)
            return self.stopper.messages(now_s) if self.stopper.resend_due(now_s) else []
        out = self.targets.mode_change_tick(now_s) + self.gates.gcs_failsafe.tick(now_s) + self.avoid.tick(now_s)
        nxt = self.stage.next_output_s
        out += self.wheels.advance(now_s, force_output=nxt is None or now_s >= nxt)
        if self.wheels.active is self.targets and self.state is CommandState.ACTIVE:
            goal = self.targets.goal
            assert goal is not None
            out += self.targets.nav.report(goal, now_s)
        return out

    def next_deadline_s(self, now_s: float) -> float:
        state = self.wheels.state
        if state is CommandState.STOPPING:
            return self.stopper.deadline_s()
        if state is CommandState.STOPPED or self.identity.vehicle_system_id is None:
            return now_s + self.stage.period_s  # nothing can be sent yet; look again a period later
        # Runs on every turn of the loop: plain comparisons, no lists.
        nxt = self.stage.next_output_s
        first = now_s if nxt is None else nxt
        active = self.wheels.active
        if state is CommandState.ACTIVE and active is not None:
            deadline = active.deadline_s()  # a request's timeout; a target's feedback and GCS silence
            if deadline is not None and deadline < first:
                first = deadline
        change = self.targets.mode_change
        if change is not None:
            first = min(first, change.deadline_s)
        last_hb = self.vehicle.last_heartbeat_s
        if last_hb is not None and state is not CommandState.LINK_LOST:
            first = min(first, last_hb + self.vehicle.heartbeat_timeout_s)
        return first

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Neutral, then release (servo mode: trim on both outputs), then a TIMESYNC probe; STOPPING until the
        autopilot answers it or safety.stop_confirm_timeout_s passes (rover_bridge.command.stopping)."""
        if self.state in _OVER:
            return []
        self.wheels.drop_request()
        if self.identity.vehicle_system_id is None:
            return self.wheels.set_state(CommandState.STOPPED, now_s, STOP_NOTHING)  # no vehicle: nothing to stop
        out = self.stopper.begin(now_s)
        out += self.wheels.set_state(CommandState.STOPPING, now_s)
        return out

    def emergency_stop(self) -> list[Outgoing]:
        """The stop as another thread sends it when the loop is stuck (rover_bridge.app.guard): neutral,
        release, and a probe with EMERGENCY_PROBE_TS1; the core's state is not touched. Empty while the
        vehicle is unknown."""
        return [] if self.identity.vehicle_system_id is None else self.stopper.emergency()

    # ----------------------------------------------------------------- calibrate, measured wheels, slip

    def set_direct(self, pwm: WheelPwm | None, now_s: float) -> list[Outgoing]:
        """Drive each wheel at this PWM (None: back to requests): `rover-bridge calibrate`'s steps. Every
        safety path still applies first (link lost, disarmed, a stop mode, a fault, the stop at exit); a
        request arriving meanwhile is refused."""
        if self.state in _OVER:
            return []
        self.gates.direct = pwm
        self.wheels.drop_request()
        return self.wheels.advance(now_s, force_output=True)

    def on_wheels(self, sample: MeasuredWheels, now_s: float) -> None:
        """Measured wheel speeds (the estimate flow's checked WHEEL_DISTANCE increments, via the composition)."""
        self.stage.on_wheels(sample, now_s)

    def set_slipping(self, slipping: bool) -> None:
        """The estimator's verdict on wheel slip (via the composition), for slip compensation."""
        self.stage.slipping = slipping

    # ----------------------------------------------------------------- from the autopilot

    def _on_heartbeat(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        vehicle = self.vehicle
        # While the autopilot's heartbeat is lost another vehicle heartbeat may take its place (Identity).
        if not self.identity.is_autopilot_heartbeat(msg, relearn=vehicle.link_lost(now_s)):
            return NOTHING
        if vehicle.last_heartbeat_s is None or vehicle.link_lost(now_s):
            self.gates.gcs_failsafe.autopilot_back(now_s)  # first seen, or back (rebooted?): read its FS_GCS_*
            self.avoid.autopilot_back(now_s)  # and AVOID_* / FENCE_*, the fence and home
        vehicle.on_heartbeat(msg, now_s)
        self.gates.gcs_failsafe.silence.on_mode(vehicle.custom_mode)
        if not self.targets.in_guided():
            self.targets.nav.cruise_m_s = None  # DO_CHANGE_SPEED lasts while in GUIDED (ArduPilot: reset on entry)
        self.gates.on_heartbeat()
        return Reaction(consumed=False, out=tuple(self.wheels.advance(now_s, force_output=False)))

    def _resumed(self, now_s: float) -> Reaction:
        """A GCS silence ended (the GCS spoke, or the autopilot acted): the drivers may have the wheels again."""
        return Reaction(consumed=False, out=tuple(self.wheels.advance(now_s, force_output=False)))

    def _on_command_ack(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        if not self.identity.from_autopilot(msg):
            return NOTHING  # another component's answer (or a forged one) says nothing of the autopilot's mode
        command = int(msg.command)
        if command == mavlink.MAV_CMD_DO_FENCE_ENABLE and int(msg.result) == mavlink.MAV_RESULT_ACCEPTED:
            self.avoid.fence_switched(now_s)
            return NOTHING
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE and self.identity.addressed_to_bridge(msg):
            return Reaction(consumed=True)  # the answer to the fence's request for home: not the GCS's business
        if int(msg.command) == mavlink.MAV_CMD_DO_SET_MODE:
            ours = self.targets.mode_change_ack(msg, now_s)
            if ours is not None:
                return ours
            self.vehicle.on_mode_ack(int(msg.result))
            return NOTHING
        servo = self.gates.servo_ack(msg, now_s)
        if servo is None:
            return NOTHING
        refused, out = servo
        if refused:
            self.wheels.drop_request()
            out += self.wheels.advance(now_s, force_output=False)
        return Reaction(consumed=True, out=tuple(out))

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1
