"""Who holds the wheels now (pure): the safety gates first, then the driver holding a request; and the output.

- Outputs go out every 1/rate_hz in every state once the vehicle's system id is known; only ACTIVE and
  BRAKING (and HOLD while it brakes) may send anything but neutral (trim on both wheels). Holding neutral
  while idle keeps the rover still for as long as the bridge is alive; releasing instead would hand the
  passthrough motor outputs to whatever the RC receiver says (possibly nothing, or an off-centre stick).
- At most one driver holds a request (rover_bridge.command.drivers); a driver taking the wheels takes them
  from the one before (which is told, and forgets its request) with the limiter's motion kept, so a handover
  never steps the wheels by more than the limits allow.
- A request that times out or cannot be followed brakes through the limiter at its deceleration limits
  (BRAKING); once at zero it is dropped (IDLE). A running position target has no timeout; when it ends it
  brakes the same way (a zero request that has already timed out).
- A safety gate (rover_bridge.command.safety) drops the request: LINK_LOST and DISARMED also drop the
  limiter's motion (neutral at once), HOLD keeps it and brakes to zero, then neutral; FAULT is neutral at once;
  GCS_SILENT is neutral and release once, then nothing at all (ArduPilot must see no override).
- A driver the mode table no longer lists for the autopilot's mode (rover_bridge.command.modes) brakes as if
  its request had timed out, until the driver the new mode lists takes the wheels.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from rover_bridge.command.drivers import STATE_TEXT, CommandState, Driver
from rover_bridge.command.gcs_requests import GcsRequests
from rover_bridge.command.modes import AUTOPILOT, ModeTable
from rover_bridge.command.output_stage import OutputStage
from rover_bridge.command.proximity import ProximityAvoidance
from rover_bridge.command.safety import SafetyGates
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.command.wheel_control import WiringFault
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing

log = logging.getLogger("rover_bridge.command")

_DRIVING = (CommandState.ACTIVE, CommandState.BRAKING)
_RAMPING = (CommandState.ACTIVE, CommandState.BRAKING, CommandState.HOLD)  # the limiter runs, no reset
_DROPPING = (CommandState.LINK_LOST, CommandState.DISARMED, CommandState.GCS_SILENT)  # drop request and motion
_ZERO = Twist2D()


class Arbiter:
    """The state machine between the drivers, the safety gates and the output stage (module doc)."""

    def __init__(self, identity: Identity, reporter: Reporter, vehicle: VehicleState, modes: ModeTable,
                 gates: SafetyGates, stage: OutputStage, count: Callable[[str], None]) -> None:
        self.identity = identity
        self.reporter = reporter
        self.vehicle = vehicle
        self.modes = modes
        self.gates = gates
        self.stage = stage
        self._count = count
        self.state = CommandState.WAITING
        self.active: Driver | None = None  # the driver holding the wheels (its request is the request)
        self.gcs: GcsRequests | None = None  # set by the core: the driver a finished target brakes through
        self.avoid: ProximityAvoidance | None = None  # set by the core: caps the bridge's own drivers' twist
        self.watchers: list[Callable[[float], list[Outgoing]]] = []  # run before each evaluation

    # ----------------------------------------------------------------- what drivers ask (drivers.Wheels)

    def take(self, driver: Driver, request: object, now_s: float, by: str) -> list[Outgoing]:
        out: list[Outgoing] = []
        previous = self.active
        if previous is not None and previous is not driver:
            out += previous.taken_over(by, now_s)
        driver.hold(request, now_s)
        self.active, self.gates.refused = driver, False
        return out + self.advance(now_s, force_output=True, answer=True)

    def brake_to_stop(self, now_s: float) -> None:
        """The active request is over: a zero request already timed out, so BRAKING ramps to zero, then IDLE."""
        gcs = self.gcs
        assert gcs is not None
        if self.active is not None and self.active is not gcs:
            self.active.drop()
        gcs.brake(now_s)
        self.active = gcs

    def advance(self, now_s: float, force_output: bool, answer: bool = False) -> list[Outgoing]:
        """Update the state for `now_s`; send outputs if forced, due to a state change, or braking done.
        `answer`: the output answers a new request (rover_bridge.command.output_stage: how far the limiter moves)."""
        before = self.state
        out: list[Outgoing] = []
        for watch in self.watchers:
            out += watch(now_s)
        mode = self.vehicle.driving_mode
        if mode != self.modes.said_mode:
            out += self.modes.announce(mode, now_s)
        state = self.evaluate(now_s)
        if state is not before:
            out += self.set_state(state, now_s, self._text(state))
        if self.identity.vehicle_system_id is not None and (force_output or self.state is not before):
            out += self._output(now_s, answer)
        return out

    # ----------------------------------------------------------------- the state

    def evaluate(self, now_s: float) -> CommandState:
        """The safety gates first (rover_bridge.command.safety), then the active driver."""
        gate = self.gates.gate(now_s)
        if gate is not None:
            if gate in _DROPPING:
                self.drop_request()
            elif gate is CommandState.HOLD:
                # Brake through the limiter (the limiter keeps its motion), then neutral; the request is gone,
                # so only a fresh one after the mode has changed drives again.
                self.release()
            return gate
        active = self.active
        if active is None or active.request is None:
            return CommandState.REFUSED if self.gates.refused else CommandState.IDLE
        if active.braking(now_s):
            return CommandState.BRAKING
        if self.vehicle.driving_mode not in self.modes.of[active.name]:
            self.brake_to_stop(now_s)  # the mode no longer gives it the wheels (a target's watch says why)
            return CommandState.BRAKING
        return CommandState.ACTIVE

    def _text(self, state: CommandState) -> tuple[int, str] | None:
        """What a new state says when not its usual (a stop for a mode with no driver, a stale demand)."""
        if state is CommandState.HOLD:
            return self.gates.hold_text
        if state is CommandState.BRAKING and self.active is not None:
            return self.active.braking_text
        return None

    def set_state(self, new: CommandState, now_s: float, text: tuple[int, str] | None = None) -> list[Outgoing]:
        if new is self.state:
            return []
        old, self.state = self.state, new
        self._count(f"state.{new.value}")
        log.info("command state %s -> %s", old.value, new.value)
        severity, said = text if text is not None else STATE_TEXT[new]
        out = self.reporter.statustext(severity, said, now_s, key=f"state.{new.value}")
        if new is CommandState.GCS_SILENT and self.identity.vehicle_system_id is not None:
            out = self.stage.release(now_s) + out
        return out

    def release(self) -> None:
        """The request is gone (the limiter keeps its motion)."""
        if self.active is not None:
            self.active.drop()
            self.active = None

    def drop_request(self) -> None:
        self.release()
        self.stage.limiter.reset(_ZERO)

    # ----------------------------------------------------------------- the output

    def _output(self, now_s: float, answer: bool = False) -> list[Outgoing]:
        state = self.state
        said: list[Outgoing] = []
        target: Twist2D | None = None
        stage = self.stage
        if state is CommandState.ACTIVE and self.active is not None:
            target, said = self.active.target(now_s)
            avoid = self.avoid
            # Simple avoidance after the safety gates, before the limiter; the autopilot's navigation avoids itself.
            if target is not None and avoid is not None and self.active.name != AUTOPILOT:
                target, more = avoid.limit(target, now_s, self.vehicle.driving_mode, stage.limiter.current.v_m_s)
                said = said + more
        stage.step_limiter(target, now_s, answer, ramping=state in _RAMPING)
        if state is CommandState.GCS_SILENT:
            self.stage.skip(now_s)  # set_state sent neutral and release; nothing more
            return []
        direct = self.gates.direct
        if state is CommandState.DIRECT and direct is not None:
            return stage.direct_output(direct, now_s)
        moving = state in _DRIVING or (state is CommandState.HOLD and stage.limiter.current != _ZERO)
        speed_loop = self.active is None or self.active.speed_loop
        msgs, reports, fault = stage.drive_output(now_s, moving, speed_loop)
        out = msgs + said + reports
        if fault is not None:
            out += self._fault(fault, now_s)
        if self.state is CommandState.BRAKING and stage.limiter.current == _ZERO:
            # Stopped: the neutral just built is the last braking output; from now on IDLE.
            self.drop_request()
            state = self.evaluate(now_s)
            out += self.set_state(state, now_s, self._text(state))
        return out

    def _fault(self, fault: WiringFault, now_s: float) -> list[Outgoing]:
        out = self.gates.fault(fault, now_s)
        self.release()
        self.stage.reset_after_fault()
        return out + self.set_state(CommandState.FAULT, now_s)
