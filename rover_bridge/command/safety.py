"""The safety gates (pure): which safety path holds the wheels now, before any driver may.

In order (the first that applies wins):
- no autopilot heartbeat yet: WAITING (nothing can be addressed);
- its heartbeat silent for safety.heartbeat_timeout_s: LINK_LOST, neutral at once, the request dropped;
- safety.require_armed and the autopilot disarmed: DISARMED, neutral, the request dropped (ArduPilot's RC
  passthrough drives the motors even when disarmed, so a disarm would otherwise not stop the wheels);
- a wiring fault (control.fault_*): FAULT, neutral, requests refused until the autopilot is disarmed (the
  operator's "fixed, try again"); which wheel and what to check are said by STATUSTEXT;
- `rover-bridge calibrate` driving each wheel itself: DIRECT (not in a stop mode);
- a stop mode (rover_bridge.command.vehicle), or a mode the table lists for no driver
  (rover_bridge.command.modes): HOLD, the request dropped while the limiter brakes to zero.
And DO_SET_SERVO refused by the autopilot (servo mode): the request is dropped and the wheels idle at trim
(REFUSED) until a fresh request tries again.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from rover_bridge.command.drivers import CommandState
from rover_bridge.command.modes import ModeTable, mode_name
from rover_bridge.command.outputs import WheelPwm
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.command.wheel_control import WiringFault
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.command")

_ACK_OK = (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)


class SafetyGates:
    """The gates in the module doc's order, and what opens and closes them."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter, vehicle: VehicleState,
                 modes: ModeTable, count: Callable[[str], None]) -> None:
        self.require_armed = profile.safety.require_armed
        self.servo_mode = profile.output.mode == "servo"
        self.identity = identity
        self.reporter = reporter
        self.vehicle = vehicle
        self.modes = modes
        self._count = count
        self.wiring_fault: WiringFault | None = None
        self.direct: WheelPwm | None = None  # calibrate: each wheel's PWM, set directly
        self.refused = False  # the autopilot refused DO_SET_SERVO; cleared by a fresh request
        self.hold_text: tuple[int, str] | None = None  # HOLD for a mode no driver is listed for: its words

    def gate(self, now_s: float) -> CommandState | None:
        """The state a safety path imposes now (None: the drivers may hold the wheels)."""
        v = self.vehicle
        last = v.last_heartbeat_s
        if last is None:
            return CommandState.WAITING
        if now_s >= last + v.heartbeat_timeout_s:  # VehicleState.link_lost, inline: this runs on every output
            return CommandState.LINK_LOST
        if self.require_armed and not v.armed:
            return CommandState.DISARMED
        if self.wiring_fault is not None:
            return CommandState.FAULT
        if self.direct is not None and v.custom_mode not in v.stop_modes:
            return CommandState.DIRECT
        if v.stopping(now_s):
            self.hold_text = None
            return CommandState.HOLD
        if v.driving_mode not in self.modes.known:
            text = f"RB: {mode_name(v.driving_mode)}: no driver, braking, then neutral"
            self.hold_text = (mavlink.MAV_SEVERITY_WARNING, text)
            return CommandState.HOLD
        return None

    def on_heartbeat(self) -> None:
        if not self.vehicle.armed and self.wiring_fault is not None:
            # Disarming is how an operator says "fixed, try again" (a stuck wheel freed, a wire changed).
            self.wiring_fault = None
            self._count("fault.cleared")

    def fault(self, fault: WiringFault, now_s: float) -> list[Outgoing]:
        """A wiring fault: counted, logged, said (two lines: what happened, what to check)."""
        self._count(f"fault.{fault.wheel}.{fault.kind}")
        self.wiring_fault = fault
        log.critical("wiring fault: %s wheel %s (commanded against measured wheel speeds); %s", fault.wheel,
                     fault.kind, fault.texts[1][len("RB: "):])
        out: list[Outgoing] = []
        for text in fault.texts:
            out += self.reporter.statustext(mavlink.MAV_SEVERITY_CRITICAL, text, now_s, key=text)
        return out

    def servo_ack(self, msg: MAVLinkMessage, now_s: float) -> tuple[bool, list[Outgoing]] | None:
        """The autopilot's answer to our DO_SET_SERVO (None: not one): (refused?, what to say)."""
        if not self.servo_mode or int(msg.command) != mavlink.MAV_CMD_DO_SET_SERVO:
            return None
        # MAVLink 1 acks carry no target (0): take them as ours, we are the one sending DO_SET_SERVO.
        if (int(getattr(msg, "target_system", 0)) not in (0, self.identity.override_source_system)
                or int(getattr(msg, "target_component", 0)) not in (0, self.identity.component_id)):
            return None
        result = int(msg.result)
        if result in _ACK_OK:
            self._count("servo.accepted")
            return False, []
        self._count("servo.refused")
        self.refused = True
        return True, self.reporter.statustext(mavlink.MAV_SEVERITY_ERROR, f"RB: DO_SET_SERVO result {result}",
                                              now_s, key="servo.refused")
