"""Driver: a ground station's velocity requests and MANUAL_CONTROL (pure).

- A valid request is followed at once: the output goes out in the same `handle` call, and it shows the
  request (rover_bridge.command.output_stage: how far the limiter moves).
- No valid request for command.setpoint_timeout_s: the request brakes through the limiter at its
  deceleration limits; once at zero it is dropped (idle).
- Earth-frame (heading) requests need a fresh ATTITUDE from the autopilot (younger than
  safety.attitude_timeout_s): without one they are rejected on arrival, and a stale yaw during motion brakes
  like a timeout.
- Requests are refused, consumed and counted while the autopilot's heartbeat is missing or lost, while it is
  disarmed (safety.require_armed), while `rover-bridge calibrate` drives, in a stop mode or a mode the table
  ([modes] gcs) does not list them for (said once per source: a planner still streaming must not undo the
  GCS's Hold, nor take the wheels from the autopilot's own navigation), and during a wiring fault. A velocity
  request or MANUAL_CONTROL takes over from a position target for good.
- Requests are consumed only when addressed to the vehicle; while its id is unknown they are forwarded
  untouched. Only requests arriving on the GCS side are considered.
"""

from __future__ import annotations

from collections.abc import Callable

from rover_bridge.command.drivers import CommandState, Wheels
from rover_bridge.command.modes import ModeTable, mode_name
from rover_bridge.command.setpoints import BodyVelocity, HeadingVelocity, Rejected, Request, decode_request
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.gate import SecurityPolicy
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Outgoing, Reaction
from rover_bridge.params import Profile

NO_ATTITUDE = "no_attitude"
UNAUTHORISED = "unauthorised"
MAX_SAID = 1024  # (report, source) pairs remembered for "say once"
_UNFOLLOWED = (CommandState.WAITING, CommandState.LINK_LOST)


class GcsRequests:
    """The velocity-request driver, and the checks every command from a ground station passes first."""

    name: str = "gcs"
    braking_text: tuple[int, str] | None = None

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter, vehicle: VehicleState,
                 modes: ModeTable, wheels: Wheels, count: Callable[[str], None]) -> None:
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        self.vehicle = vehicle
        self.modes = modes
        self.wheels = wheels
        self._count = count
        self.security = SecurityPolicy(profile.security)
        self.timeout_s = profile.command.setpoint_timeout_s
        self.request: Request | None = None  # headings already made absolute
        self.since_s: float | None = None
        self.said: set[tuple[str, int, int]] = set()

    # ----------------------------------------------------------------- the driver

    def braking(self, now_s: float) -> bool:
        since = self.since_s
        return since is None or now_s >= since + self.timeout_s or self._twist(now_s) is None

    def deadline_s(self) -> float | None:
        return None if self.since_s is None else self.since_s + self.timeout_s

    def target(self, now_s: float) -> tuple[Twist2D | None, list[Outgoing]]:
        return self._twist(now_s), []

    def _twist(self, now_s: float) -> Twist2D | None:
        """The twist the request asks for now; None if it cannot be followed (no fresh yaw)."""
        request = self.request
        if isinstance(request, BodyVelocity):
            return request.twist()
        if isinstance(request, HeadingVelocity):
            yaw = self.vehicle.fresh_yaw(now_s)
            if yaw is None:
                return None
            kp_1_s, max_rad_s = self.profile.command.heading_kp_1_s, self.profile.limits.max_angular_rad_s
            return request.twist(yaw, kp_1_s, max_rad_s)
        return None

    def drop(self) -> None:
        self.request, self.since_s = None, None

    def brake(self, now_s: float) -> None:
        """A zero request that has already timed out: the limiter brakes to zero, then the wheels idle."""
        self.request, self.since_s = BodyVelocity(0.0, 0.0), now_s - self.timeout_s

    # ----------------------------------------------------------------- from a ground station

    def for_vehicle(self, msg: MAVLinkMessage) -> bool:
        """Addressed to the vehicle, which is known: ours to act on (else forwarded untouched, counted)."""
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            self._count("forwarded.vehicle_unknown")
            return False
        if msg.get_type() == "MANUAL_CONTROL":  # no component field
            addressed = int(msg.target) == vehicle
        else:
            addressed = (int(msg.target_system) == vehicle
                         and int(msg.target_component) in self.profile.command.accept_target_components)
        if not addressed:
            self._count("forwarded.not_for_vehicle")
        return addressed

    def authorised(self, inc: Incoming) -> bool:
        """[security] (signature, allow-list): may this source command the rover?

        BridgeCore's CommandGate refuses such frames before they get here (and counts them by reason); this
        second check keeps a CommandCore used on its own just as strict.
        """
        return self.security.reason(inc, self.identity) is None

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        if not self.for_vehicle(msg):
            return NOTHING
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if not self.authorised(inc):
            return self.reject(UNAUTHORISED, source, now_s)
        decoded = decode_request(msg, self.profile.command)
        if isinstance(decoded, Rejected):
            return self.reject(decoded.reason, source, now_s)
        out = self.wheels.advance(now_s, force_output=False)  # bring link / armed / timeout state up to date
        state = self.wheels.state
        if state in _UNFOLLOWED:
            self._count("dropped.link_lost")
            return Reaction(consumed=True, out=tuple(out))
        if state is CommandState.DISARMED:
            self._count("dropped.disarmed")
            return Reaction(consumed=True, out=tuple(out))
        if state is CommandState.DIRECT:
            self._count("dropped.direct")
            return Reaction(consumed=True, out=tuple(out))
        mode = self.vehicle.driving_mode
        if state is CommandState.HOLD or mode not in self.modes.gcs:
            # The GCS pressed Hold: a request still streaming from a planner must not undo it. Nor may one undo
            # a mode the autopilot drives in (AUTO, RTL ...): the mode decides who drives.
            why = "hold" if state is CommandState.HOLD else "mode"
            where = "HOLD" if self.modes.listed(mode) and why == "hold" else mode_name(mode)
            self._count(f"dropped.{why}")
            out += self.say_once(f"dropped.{why}", f"RB: in {where}, request from {source[0]}:{source[1]} ignored",
                                 source, now_s)
            return Reaction(consumed=True, out=tuple(out))
        request: Request = decoded
        if isinstance(decoded, HeadingVelocity):
            yaw = self.vehicle.fresh_yaw(now_s)
            if yaw is None:
                reaction = self.reject(NO_ATTITUDE, source, now_s)
                return Reaction(consumed=True, out=(*out, *reaction.out))
            request = decoded.absolute(yaw)
        for note in decoded.notes:
            self._count(f"note.{note}")
            out += self.say_once(f"note.{note}", f"RB: {note} ({source[0]}:{source[1]})", source, now_s)
        if state is CommandState.FAULT:
            self._count("dropped.fault")
            return Reaction(consumed=True, out=tuple(out))
        self._count("requests.accepted")
        # A velocity request (or MANUAL_CONTROL) takes over from a position target for good.
        out += self.wheels.take(self, request, now_s, f"velocity from {source[0]}:{source[1]}")
        return Reaction(consumed=True, out=tuple(out))

    def hold(self, request: Request, now_s: float) -> None:
        self.request, self.since_s = request, now_s

    def taken_over(self, by: str, now_s: float) -> list[Outgoing]:
        self.drop()
        return []

    def reject(self, reason: str, source: tuple[int, int], now_s: float) -> Reaction:
        self._count(f"rejected.{reason}")
        text = f"RB: rejected {reason} from {source[0]}:{source[1]}"
        out = self.say_once(f"rejected.{reason}", text, source, now_s)
        return Reaction(consumed=True, out=tuple(out))

    def say_once(self, key: str, text: str, source: tuple[int, int], now_s: float) -> list[Outgoing]:
        """Report `text` once per (key, source); later occurrences are only counted."""
        # Bounded: spoofed source ids (65k of them) must not grow the set without limit; past the cap
        # only the counters record them.
        if (key, *source) in self.said or len(self.said) >= MAX_SAID:
            return []
        self.said.add((key, *source))
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, text, now_s, key=key)
