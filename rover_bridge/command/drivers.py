"""What the command core and its drivers share: the states, what a driver is, what a driver may ask of the core.

A driver (ArduPilot Rover's Mode classes are the model: one small class per way of driving) holds at most
one request: it says what it wants the wheels to do now (a twist) and whether it still can (a request that
timed out, or that cannot be followed, brakes through the limiter). Which driver may hold the wheels in
which autopilot mode is the mode table's (rover_bridge.command.modes); the safety gates come first
(rover_bridge.command.core).
"""

from __future__ import annotations

import enum
from typing import Any, Protocol

from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Outgoing


class CommandState(enum.Enum):
    WAITING = "waiting"  # no autopilot heartbeat yet
    IDLE = "idle"  # no request: neutral
    ACTIVE = "active"  # following a fresh request
    BRAKING = "braking"  # request timed out (or heading unknown): ramping to zero
    LINK_LOST = "link_lost"  # autopilot heartbeat lost: neutral until it returns and a fresh request comes
    DISARMED = "disarmed"  # require_armed and the autopilot is disarmed: neutral
    REFUSED = "refused"  # the autopilot refused DO_SET_SERVO: neutral until a fresh request
    HOLD = "hold"  # the autopilot is in a stop mode (HOLD): brake to zero, then neutral, until a fresh request
    FAULT = "fault"  # a wiring fault (a wheel turning the wrong way or not at all): neutral
    DIRECT = "direct"  # `rover-bridge calibrate` sets each wheel's PWM itself (no request, no loop)
    STOPPING = "stopping"  # shutdown() sent neutral and release: waiting for the autopilot's proof
    STOPPED = "stopped"  # the stop is over (confirmed or timed out): nothing more is sent


STATE_TEXT = {
    CommandState.IDLE: (mavlink.MAV_SEVERITY_INFO, "RB: idle, wheels neutral"),
    CommandState.ACTIVE: (mavlink.MAV_SEVERITY_INFO, "RB: active, driving"),
    CommandState.BRAKING: (mavlink.MAV_SEVERITY_WARNING, "RB: no request, braking to a stop"),
    CommandState.LINK_LOST: (mavlink.MAV_SEVERITY_CRITICAL, "RB: autopilot heartbeat lost, neutral"),
    CommandState.DISARMED: (mavlink.MAV_SEVERITY_NOTICE, "RB: autopilot disarmed, neutral"),
    CommandState.REFUSED: (mavlink.MAV_SEVERITY_ERROR, "RB: DO_SET_SERVO refused, neutral"),
    CommandState.HOLD: (mavlink.MAV_SEVERITY_NOTICE, "RB: autopilot in HOLD, braking, then neutral"),
    CommandState.FAULT: (mavlink.MAV_SEVERITY_CRITICAL, "RB: wiring fault: neutral until disarmed"),
    CommandState.DIRECT: (mavlink.MAV_SEVERITY_WARNING, "RB: calibrating: driving wheels directly"),
    CommandState.STOPPING: (mavlink.MAV_SEVERITY_NOTICE, "RB: stopping, neutral sent, confirming"),
    CommandState.STOPPED: (mavlink.MAV_SEVERITY_NOTICE, "RB: stopped, autopilot confirmed release"),
}


class Driver(Protocol):
    """One way of driving. `request` is what it follows (None: it does not hold the wheels)."""

    name: str  # its name in the mode table ([modes]): "gcs", "targets", "autopilot"
    braking_text: tuple[int, str] | None  # what BRAKING says when its request brakes (None: the usual)

    @property
    def request(self) -> Any: ...

    def braking(self, now_s: float) -> bool:
        """Its request timed out or cannot be followed now: the wheels brake through the limiter."""

    def deadline_s(self) -> float | None:
        """When its request times out (None: it does not time out)."""

    def target(self, now_s: float) -> tuple[Twist2D | None, list[Outgoing]]:
        """The twist it wants now (None: brake) and what it has to say about it."""

    def drop(self) -> None:
        """Forget the request (a safety path took the wheels away)."""

    def hold(self, request: Any, now_s: float) -> None:
        """Hold `request` from now on (the core's `take`)."""

    def taken_over(self, by: str, now_s: float) -> list[Outgoing]:
        """Another driver takes the wheels (`by` says who, for a report): forget the request."""


class Wheels(Protocol):
    """What a driver may ask of the command core."""

    @property
    def state(self) -> CommandState: ...

    @property
    def active(self) -> Driver | None: ...

    def advance(self, now_s: float, force_output: bool, answer: bool = False) -> list[Outgoing]:
        """Bring the state up to date for `now_s`; the output too if forced (`answer`: to a fresh request)."""

    def take(self, driver: Driver, request: Any, now_s: float, by: str) -> list[Outgoing]:
        """`driver` holds the wheels with `request` from now on, answered at once (`by`: who, for reports)."""

    def brake_to_stop(self, now_s: float) -> None:
        """The active request is over: brake through the limiter to a stop, then idle."""
