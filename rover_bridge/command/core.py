"""The command flow's pure core: velocity requests in, wheel overrides out, safely.

request -> TwistLimiter -> DiffDrive inverse kinematics -> desaturation at max_wheel_rpm ->
per-wheel PWM -> RC_CHANNELS_OVERRIDE (or DO_SET_SERVO) to the autopilot.

Decisions (the README repeats them for users):

- Outputs go out every 1/rate_hz in every state once the vehicle's system id is known; only
  ACTIVE and BRAKING may send anything but neutral (trim on both wheels). Holding neutral while
  idle keeps the rover still for as long as the bridge is alive; releasing instead would hand the
  passthrough motor outputs to whatever the RC receiver says (possibly nothing, or an off-centre
  stick). A dead bridge is covered by the autopilot's override timeout (RC_OVERRIDE_TIME), and
  every exit path the shell can reach calls `shutdown`: neutral, then release.
- Before the vehicle's id is known nothing is sent at all (an override cannot be addressed).
- A valid request is followed at once: the output goes out in the same `handle` call, through
  the limiter with dt = time since the last output, capped at one period (after a stalled loop the
  limiter must not allow a jump worth the whole stall).
- No valid request for command.setpoint_timeout_s: BRAKING, the limiter ramps to zero at its
  deceleration limits; once at zero the request is dropped and the state is IDLE (neutral).
- Autopilot heartbeat silent for safety.heartbeat_timeout_s: LINK_LOST, immediately neutral
  (no ramp: we no longer know what the autopilot does, and 3 s have already passed). The request
  is dropped, so only a request received after the heartbeat returns drives again.
- safety.require_armed: while the autopilot's heartbeat lacks MAV_MODE_FLAG_SAFETY_ARMED, hold
  neutral (ArduPilot's RC passthrough drives the motors even when disarmed, so a disarm would
  otherwise not stop the wheels). The request is dropped as on link loss.
- Earth-frame (heading) requests need a fresh ATTITUDE from the autopilot (younger than
  safety.attitude_timeout_s): without one they are rejected on arrival, and a stale yaw during
  motion brakes like a timeout.
- DO_SET_SERVO refused by the autopilot (servo mode): REFUSED, request dropped, trim on both
  outputs; a fresh request tries again.
- The autopilot in one of safety.stop_modes (ArduPilot Rover's HOLD, what a GCS's Hold, Pause or
  Stop button selects: RC passthrough ignores the mode, so the wheels would keep the bridge's PWM):
  HOLD, the request is dropped and the limiter brakes to zero, then neutral; requests are refused
  while it lasts, and only a fresh one after the mode has changed drives again.
- A wiring fault (control.fault_*: a wheel commanded hard that turns the wrong way, not at all, or
  runs away, or the two swapped): FAULT, neutral, the request dropped and requests refused until
  the autopilot is disarmed (the operator's "fixed, try again"); which wheel and what to check are
  said by STATUSTEXT.
- Closed loop (control.mode): the wheel targets go through the per-wheel speed loop
  (rover_bridge.command.wheel_control) on the speeds the estimate flow measured; while the estimator
  reports slip (control.slip_compensation) no wheel is driven faster than when the slip began.
- shutdown (every exit path of the shell): neutral, release, then a TIMESYNC probe; STOPPING until
  the autopilot answers the probe (proof that it parsed the stop) or stop_confirm_timeout_s passes,
  resending every STOP_RESEND_S; then STOPPED, and nothing more is sent.
- Requests are consumed only when addressed to the vehicle; while its id is unknown they are
  forwarded untouched. Only requests arriving on the GCS side are considered.
"""

from __future__ import annotations

import enum
import logging
import math

from rover_bridge.command.outputs import OutputMap, WheelPwm
from rover_bridge.command.setpoints import (
    REQUEST_TYPES,
    BodyVelocity,
    HeadingVelocity,
    Rejected,
    Request,
    decode_request,
)
from rover_bridge.command.wheel_control import WheelSpeedLoop, WiringFault, WiringMonitor
from rover_bridge.kinematics import DiffDrive, MeasuredWheels, Twist2D, WheelSpeeds
from rover_bridge.limits import TwistLimiter, TwistLimits
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.gate import SecurityPolicy
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.command")

NO_ATTITUDE = "no_attitude"
MAX_SAID = 1024  # (report, source) pairs remembered for "say once"
UNAUTHORISED = "unauthorised"


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
STOP_UNCONFIRMED = (mavlink.MAV_SEVERITY_CRITICAL, "RB: stop NOT confirmed by the autopilot")
STOP_NOTHING = (mavlink.MAV_SEVERITY_NOTICE, "RB: stopped (no vehicle known: nothing sent)")

_DRIVING = (CommandState.ACTIVE, CommandState.BRAKING)
_RAMPING = (CommandState.ACTIVE, CommandState.BRAKING, CommandState.HOLD)  # the limiter runs, no reset
_OVER = (CommandState.STOPPING, CommandState.STOPPED)
# Stop confirmation: a TIMESYNC request (tc1 = 0) goes after neutral and release; ArduPilot answers it
# while parsing (GCS_Common.cpp handle_timesync, ts1 echoed), so the answer proves that both were
# handled. ts1 carries this tag plus the attempt number, so the answer is recognisably ours.
STOP_PROBE_TAG = 0x5242_5354 << 32  # "RBST"
STOP_RESEND_S = 0.1
EMERGENCY_PROBE_TS1 = STOP_PROBE_TAG + 0xFFFF_FFFF  # the stop guard's probe (never a normal attempt number)
# A ground station's request for a stop mode stops the rover at once; the autopilot's heartbeat (1 Hz,
# possibly one already in flight) takes over after this long unless the autopilot refused the mode.
HOLD_ANTICIPATION_S = 1.5
MODE_REQUESTS = frozenset({"SET_MODE", "COMMAND_LONG", "COMMAND_INT"})


def requested_custom_mode(msg: MAVLinkMessage, vehicle: int | None) -> int | None:
    """The custom_mode a SET_MODE or DO_SET_MODE command asks of `vehicle`, or None if it asks nothing."""
    try:
        if msg.get_type() == "SET_MODE":
            if vehicle is None or int(msg.target_system) not in (0, vehicle):
                return None
            base, custom = int(msg.base_mode), int(msg.custom_mode)
        else:
            if int(msg.command) != mavlink.MAV_CMD_DO_SET_MODE:
                return None
            if vehicle is None or int(msg.target_system) not in (0, vehicle):
                return None
            base, custom = int(msg.param1), int(msg.param2)
    except (TypeError, ValueError, OverflowError, AttributeError):
        return None  # NaN params, a malformed frame: not a mode request we can read
    return custom if base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED else None
_ACK_OK = (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)


class CommandCore:
    """Messages and the current time in, override messages out (see the module doc for the rules)."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter) -> None:
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        self.drive = DiffDrive.from_params(profile.robot)
        self.outputs = OutputMap.from_profile(profile)
        self.limiter = TwistLimiter(TwistLimits.from_params(profile.limits))
        self.period_s = 1.0 / profile.command.rate_hz
        self.state = CommandState.WAITING
        self.counters: dict[str, int] = {}
        self.last_wheel_pwm: WheelPwm | None = None
        self.request: Request | None = None  # headings already made absolute
        self._request_s: float | None = None
        self._last_heartbeat_s: float | None = None
        self._armed = False
        self._yaw_cw_rad: float | None = None
        self._yaw_s: float | None = None
        self._last_output_s: float | None = None
        self._next_output_s: float | None = None
        self._refused = False
        self._said: set[tuple[str, int, int]] = set()
        self.security = SecurityPolicy(profile.security)
        c = profile.control
        ranges = (self.outputs.speed_range(left=True), self.outputs.speed_range(left=False))
        self.loop = WheelSpeedLoop(c, *ranges) if c.mode == "closed_loop" else None
        self.wiring = WiringMonitor(c, *ranges)
        self._open_measured: tuple[float, WheelSpeeds] | None = None  # open loop: (arrival, speeds)
        self._loop_closed = True  # said once when it changes
        self._slipping = False
        self._slip_hold: WheelSpeeds | None = None
        self._wiring_fault: WiringFault | None = None
        self._direct: WheelPwm | None = None  # calibrate: each wheel's PWM, set directly
        self._custom_mode: int | None = None  # the autopilot's mode (HEARTBEAT custom_mode)
        self._hold_requested_s: float | None = None  # a GCS asked for a stop mode; not yet reported
        self._stop_modes = frozenset(profile.safety.stop_modes)
        # Stop confirmation (see shutdown): when it began, when it was last sent, the probes in flight.
        self._stop_began_s = 0.0
        self._stop_sent_s = 0.0
        self._stop_attempts = 0
        self.stop_confirmed: bool | None = None  # None until answered or timed out (or nothing to stop)

    # ----------------------------------------------------------------- read-only views

    @property
    def commanded(self) -> Twist2D:
        """The twist of the last output (after the limiter)."""
        return self.limiter.current

    @property
    def autopilot_alive(self) -> bool:
        """The autopilot's heartbeat is fresh (seen, not timed out)."""
        return self.state not in (CommandState.WAITING, CommandState.LINK_LOST)

    @property
    def stop_settled(self) -> bool:
        """shutdown() has run and its confirmation is over (answered or timed out)."""
        return self.state is CommandState.STOPPED

    # ----------------------------------------------------------------- SubCore protocol

    # What handle() reads from the autopilot link (BridgeCore decodes nothing else from it).
    AUTOPILOT_READS = frozenset({"HEARTBEAT", "ATTITUDE", "COMMAND_ACK", "TIMESYNC"})

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        if self.state in _OVER:
            return self._while_stopping(inc, now_s)
        msg = inc.msg
        kind = msg.get_type()
        if inc.link is Link.AUTOPILOT:
            if kind == "HEARTBEAT":
                return self._on_heartbeat(msg, now_s)
            if kind == "ATTITUDE":
                self._on_attitude(msg, now_s)
            elif kind == "COMMAND_ACK":
                return self._on_command_ack(msg, now_s)
            return NOTHING
        if kind in REQUEST_TYPES:
            return self._on_request(inc, now_s)
        if kind in MODE_REQUESTS:
            return self._on_mode_request(msg, now_s)
        return NOTHING

    def tick(self, now_s: float) -> list[Outgoing]:
        if self.state is CommandState.STOPPED:
            return []
        if self.state is CommandState.STOPPING:
            return self._stop_tick(now_s)
        due = self._next_output_s is None or now_s >= self._next_output_s
        return self._advance(now_s, force_output=due)

    def next_deadline_s(self, now_s: float) -> float:
        if self.state is CommandState.STOPPING:
            return min(self._stop_sent_s + STOP_RESEND_S,
                       self._stop_began_s + self.profile.safety.stop_confirm_timeout_s)
        if self.state is CommandState.STOPPED or self.identity.vehicle_system_id is None:
            return now_s + self.period_s  # nothing can be sent yet; look again a period later
        deadlines = [now_s if self._next_output_s is None else self._next_output_s]
        if self.state is CommandState.ACTIVE and self._request_s is not None:
            deadlines.append(self._request_s + self.profile.command.setpoint_timeout_s)
        if self._last_heartbeat_s is not None and self.state is not CommandState.LINK_LOST:
            deadlines.append(self._last_heartbeat_s + self.profile.safety.heartbeat_timeout_s)
        return min(deadlines)

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Neutral, then release (servo mode: trim on both outputs), then a TIMESYNC probe; STOPPING.

        Sent is not done: over a stream link (TCP: SITL's SERIAL0, mavlink-router) ArduPilot parses
        its input on its main loop, and bytes a client sends just before it closes are never parsed as
        its own, so a stop that is not confirmed may not have happened (rc_override: 3 s more driving;
        servo: no end). The autopilot answers the probe while parsing, after the stop, so its answer
        proves the stop; until then (at most safety.stop_confirm_timeout_s) the stop is resent every
        STOP_RESEND_S and the shell keeps the link open. Nothing but the stop is sent afterwards.
        """
        if self.state in _OVER:
            return []
        self._drop_request()
        if self.identity.vehicle_system_id is None:
            return self._set_state(CommandState.STOPPED, now_s, STOP_NOTHING)  # no vehicle: nothing to stop
        self._stop_began_s = now_s
        out = self._stop_messages(now_s)
        out += self._set_state(CommandState.STOPPING, now_s)
        return out

    def _stop_messages(self, now_s: float) -> list[Outgoing]:
        vehicle = self.identity.vehicle_system_id
        assert vehicle is not None
        target = (vehicle, self.identity.autopilot_component_id)
        msgs = self.outputs.command(self.outputs.neutral, *target)
        if self.outputs.mode == "rc_override":
            msgs += self.outputs.release(*target)
        self._stop_attempts += 1
        msgs.append(mavlink.MAVLink_timesync_message(tc1=0, ts1=STOP_PROBE_TAG + self._stop_attempts))
        self.last_wheel_pwm = self.outputs.neutral
        self._stop_sent_s = now_s
        self._count("stop.sent")
        return [self._to_autopilot(m) for m in msgs]

    def emergency_stop(self) -> list[Outgoing]:
        """The stop as another thread sends it when the loop is stuck (rover_bridge.app.guard): neutral,
        release, and a probe with EMERGENCY_PROBE_TS1; the core's state is not touched. Empty while the
        vehicle is unknown."""
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            return []
        target = (vehicle, self.identity.autopilot_component_id)
        msgs = self.outputs.command(self.outputs.neutral, *target)
        if self.outputs.mode == "rc_override":
            msgs += self.outputs.release(*target)
        msgs.append(mavlink.MAVLink_timesync_message(tc1=0, ts1=EMERGENCY_PROBE_TS1))
        return [self._to_autopilot(m) for m in msgs]

    def _stop_tick(self, now_s: float) -> list[Outgoing]:
        if now_s >= self._stop_began_s + self.profile.safety.stop_confirm_timeout_s:
            self.stop_confirmed = False
            self._count("stop.unconfirmed")
            log.error("the autopilot did not confirm the stop within %.2f s: it may still drive the wheels "
                      "(rc_override: until RC_OVERRIDE_TIME; servo: until something else moves them)",
                      self.profile.safety.stop_confirm_timeout_s)
            return self._set_state(CommandState.STOPPED, now_s, STOP_UNCONFIRMED)
        if now_s >= self._stop_sent_s + STOP_RESEND_S:
            return self._stop_messages(now_s)
        return []

    def _while_stopping(self, inc: Incoming, now_s: float) -> Reaction:
        """While STOPPING only the probe's answer matters: a TIMESYNC reply (tc1 != 0) echoing our ts1."""
        msg = inc.msg
        if (self.state is not CommandState.STOPPING or inc.link is not Link.AUTOPILOT
                or msg.get_type() != "TIMESYNC"):
            return NOTHING
        try:
            ours = int(msg.tc1) != 0 and 0 < int(msg.ts1) - STOP_PROBE_TAG <= self._stop_attempts
        except (TypeError, ValueError):
            return NOTHING
        if not ours:
            return NOTHING
        self.stop_confirmed = True
        self._count("stop.confirmed")
        log.info("stop confirmed by the autopilot after %.0f ms", 1000.0 * (now_s - self._stop_began_s))
        return Reaction(consumed=True, out=tuple(self._set_state(CommandState.STOPPED, now_s)))

    # ----------------------------------------------------------------- hooks

    def _authorised(self, inc: Incoming) -> bool:
        """[security] (signature, allow-list): may this source command the rover?

        BridgeCore's CommandGate refuses such frames before they get here (and counts them by reason); this
        second check keeps a CommandCore used on its own just as strict.
        """
        return self.security.reason(inc, self.identity) is None

    # ----------------------------------------------------------------- incoming

    def _on_heartbeat(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        if not self.identity.is_autopilot_heartbeat(msg):
            return NOTHING
        self._last_heartbeat_s = now_s
        self._armed = bool(int(msg.base_mode) & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        self._custom_mode = int(msg.custom_mode)
        if not self._armed and self._wiring_fault is not None:
            # Disarming is how an operator says "fixed, try again" (a stuck wheel freed, a wire changed).
            self._wiring_fault = None
            self._count("fault.cleared")
        if self._custom_mode in self._stop_modes:
            self._hold_requested_s = None  # reported: from now on the heartbeat says when it ends
        return Reaction(consumed=False, out=tuple(self._advance(now_s, force_output=False)))

    def _on_attitude(self, msg: MAVLinkMessage, now_s: float) -> None:
        if (msg.get_srcSystem() != self.identity.vehicle_system_id
                or msg.get_srcComponent() != self.identity.autopilot_component_id):
            return
        yaw = float(msg.yaw)
        if not math.isfinite(yaw):
            self._count("attitude.non_finite")
            return
        self._yaw_cw_rad, self._yaw_s = yaw, now_s

    def _on_mode_request(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        """A ground station asks the vehicle for a mode (forwarded as is). A stop mode is acted on at
        once: the heartbeat that reports it may be a second away, and a Hold button must stop now."""
        mode = requested_custom_mode(msg, self.identity.vehicle_system_id)
        if mode is None or mode not in self._stop_modes:
            return NOTHING
        self._hold_requested_s = now_s
        self._count("hold.requested")
        return Reaction(consumed=False, out=tuple(self._advance(now_s, force_output=False)))

    def _on_command_ack(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        if int(msg.command) == mavlink.MAV_CMD_DO_SET_MODE:
            if self._hold_requested_s is not None and int(msg.result) not in _ACK_OK:
                self._hold_requested_s = None  # the autopilot refused the stop mode: its heartbeat governs
            return NOTHING
        if self.outputs.mode != "servo" or int(msg.command) != mavlink.MAV_CMD_DO_SET_SERVO:
            return NOTHING
        # MAVLink 1 acks carry no target (0): take them as ours, we are the one sending DO_SET_SERVO.
        if (int(getattr(msg, "target_system", 0)) not in (0, self.identity.override_source_system)
                or int(getattr(msg, "target_component", 0)) not in (0, self.identity.component_id)):
            return NOTHING
        result = int(msg.result)
        if result in _ACK_OK:
            self._count("servo.accepted")
            return Reaction(consumed=True)
        self._count("servo.refused")
        self._refused = True
        self._drop_request()
        out = self.reporter.statustext(mavlink.MAV_SEVERITY_ERROR, f"RB: DO_SET_SERVO result {result}", now_s,
                                       key="servo.refused")
        out += self._advance(now_s, force_output=False)
        return Reaction(consumed=True, out=tuple(out))

    def _addressed(self, msg: MAVLinkMessage, vehicle: int) -> bool:
        if msg.get_type() == "MANUAL_CONTROL":  # no component field
            return int(msg.target) == vehicle
        return (int(msg.target_system) == vehicle
                and int(msg.target_component) in self.profile.command.accept_target_components)

    def _on_request(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            self._count("forwarded.vehicle_unknown")
            return NOTHING
        if not self._addressed(msg, vehicle):
            self._count("forwarded.not_for_vehicle")
            return NOTHING
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if not self._authorised(inc):
            return self._reject(UNAUTHORISED, source, now_s)
        decoded = decode_request(msg, self.profile.command)
        if isinstance(decoded, Rejected):
            return self._reject(decoded.reason, source, now_s)
        out = self._advance(now_s, force_output=False)  # bring link / armed / timeout state up to date
        if self.state in (CommandState.WAITING, CommandState.LINK_LOST):
            self._count("dropped.link_lost")
            return Reaction(consumed=True, out=tuple(out))
        if self.state is CommandState.DISARMED:
            self._count("dropped.disarmed")
            return Reaction(consumed=True, out=tuple(out))
        if self.state is CommandState.DIRECT:
            self._count("dropped.direct")
            return Reaction(consumed=True, out=tuple(out))
        if self.state is CommandState.HOLD:
            # The GCS pressed Hold: a request still streaming from a planner must not undo it.
            self._count("dropped.hold")
            out += self._say_once("dropped.hold", f"RB: in HOLD, request from {source[0]}:{source[1]} ignored",
                                  source, now_s)
            return Reaction(consumed=True, out=tuple(out))
        request: Request = decoded
        if isinstance(decoded, HeadingVelocity):
            yaw = self._fresh_yaw(now_s)
            if yaw is None:
                reaction = self._reject(NO_ATTITUDE, source, now_s)
                return Reaction(consumed=True, out=(*out, *reaction.out))
            request = decoded.absolute(yaw)
        for note in decoded.notes:
            self._count(f"note.{note}")
            out += self._say_once(f"note.{note}", f"RB: {note} ({source[0]}:{source[1]})", source, now_s)
        if self._wiring_fault is not None:
            self._count("dropped.fault")
            return Reaction(consumed=True, out=tuple(out))
        self._count("requests.accepted")
        self.request, self._request_s, self._refused = request, now_s, False
        out += self._advance(now_s, force_output=True)
        return Reaction(consumed=True, out=tuple(out))

    def _reject(self, reason: str, source: tuple[int, int], now_s: float) -> Reaction:
        self._count(f"rejected.{reason}")
        text = f"RB: rejected {reason} from {source[0]}:{source[1]}"
        out = self._say_once(f"rejected.{reason}", text, source, now_s)
        return Reaction(consumed=True, out=tuple(out))

    # ----------------------------------------------------------------- state and outputs

    def _advance(self, now_s: float, force_output: bool) -> list[Outgoing]:
        """Update the state for `now_s`; send outputs if forced, due to a state change, or braking done."""
        before = self.state
        out = self._set_state(self._evaluate(now_s), now_s)
        if self.identity.vehicle_system_id is not None and (force_output or self.state is not before):
            out += self._output(now_s)
        return out

    def _evaluate(self, now_s: float) -> CommandState:
        if self._last_heartbeat_s is None:
            return CommandState.WAITING
        # Same expression as next_deadline_s: `now - last >= timeout` can round below the timeout at
        # exactly that deadline, and the shell would wake again and again for a tick that does nothing.
        if now_s >= self._last_heartbeat_s + self.profile.safety.heartbeat_timeout_s:
            self._drop_request()
            return CommandState.LINK_LOST
        if self.profile.safety.require_armed and not self._armed:
            self._drop_request()
            return CommandState.DISARMED
        if self._wiring_fault is not None:
            return CommandState.FAULT
        if self._direct is not None and self._custom_mode not in self._stop_modes:
            return CommandState.DIRECT
        requested = self._hold_requested_s
        if requested is not None and now_s >= requested + HOLD_ANTICIPATION_S:
            self._hold_requested_s = requested = None
        if self._custom_mode in self._stop_modes or requested is not None:
            # Brake through the limiter (the limiter keeps its motion), then neutral; the request is gone,
            # so only a fresh one after the mode has changed drives again.
            self.request, self._request_s = None, None
            return CommandState.HOLD
        if self.request is None or self._request_s is None:
            return CommandState.REFUSED if self._refused else CommandState.IDLE
        if now_s >= self._request_s + self.profile.command.setpoint_timeout_s or self._target(now_s) is None:
            return CommandState.BRAKING
        return CommandState.ACTIVE

    def _target(self, now_s: float) -> Twist2D | None:
        """The twist the current request asks for now; None if it cannot be followed (no fresh yaw)."""
        request = self.request
        if isinstance(request, BodyVelocity):
            return request.twist()
        if isinstance(request, HeadingVelocity):
            yaw = self._fresh_yaw(now_s)
            if yaw is None:
                return None
            kp_1_s, max_rad_s = self.profile.command.heading_kp_1_s, self.profile.limits.max_angular_rad_s
            return request.twist(yaw, kp_1_s, max_rad_s)
        return None

    def _fresh_yaw(self, now_s: float) -> float | None:
        if self._yaw_s is None or now_s - self._yaw_s >= self.profile.safety.attitude_timeout_s:
            return None
        return self._yaw_cw_rad

    def _output(self, now_s: float) -> list[Outgoing]:
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            return []
        target = self._target(now_s) if self.state is CommandState.ACTIVE else None
        last = self._last_output_s
        dt_s = self.period_s if last is None else min(self.period_s, now_s - last)
        if self.state in _RAMPING:
            if dt_s > 0.0:
                self.limiter.step(target if target is not None else Twist2D(), dt_s)
        else:
            self.limiter.reset(Twist2D())
        raw = self.drive.to_wheel_speeds(self.limiter.current)
        wheels = raw.desaturate(self.profile.robot.max_wheel_rad_s)
        moving = self.state in _DRIVING or (self.state is CommandState.HOLD and self.limiter.current != Twist2D())
        out: list[Outgoing] = []
        if self.state is CommandState.DIRECT and self._direct is not None:
            msgs = self.outputs.command(self._direct, vehicle, self.identity.autopilot_component_id)
            self.last_wheel_pwm = self._direct
            self._last_output_s = now_s
            nxt = self._next_output_s
            on_grid = nxt is not None and 0.0 <= now_s - nxt < self.period_s
            self._next_output_s = nxt + self.period_s if on_grid and nxt is not None else now_s + self.period_s
            self._count("outputs.direct")
            return [self._to_autopilot(m) for m in msgs]
        if moving:
            wheels, said = self._slip_limited(wheels, now_s)
            out += said
            command = wheels
            if self.loop is not None:
                result = self.loop.command(wheels, dt_s, now_s, pre_scaled=wheels is not raw,
                                           freeze=self._slip_hold is not None)
                command = result.command
                out += self._encoders_fresh(result.closed or wheels == WheelSpeeds(), now_s)
            fault = self.wiring.check(wheels, self._measured(now_s), now_s)
            pwm = self.outputs.to_pwm(command)
            if fault is not None:
                out += self._fault(fault, now_s)
                pwm = self.outputs.neutral
        else:
            if self.loop is not None:
                self.loop.reset()
            self.wiring.reset()
            self._slip_hold = None
            pwm = self.outputs.neutral
        msgs = self.outputs.command(pwm, vehicle, self.identity.autopilot_component_id)
        self.last_wheel_pwm = pwm
        self._last_output_s = now_s
        # A periodic output keeps the fixed grid (now + period would add the loop's lateness to every
        # period, a slow drift of the refresh rate); an early output (a fresh request acted on at once)
        # or one more than a period late starts a new grid from now.
        nxt = self._next_output_s
        on_grid = nxt is not None and 0.0 <= now_s - nxt < self.period_s
        self._next_output_s = nxt + self.period_s if on_grid and nxt is not None else now_s + self.period_s
        self._count("outputs.sent")
        out = [self._to_autopilot(m) for m in msgs] + out
        if self.state is CommandState.BRAKING and self.limiter.current == Twist2D():
            # Stopped: the neutral just built is the last braking output; from now on IDLE.
            self._drop_request()
            out += self._set_state(self._evaluate(now_s), now_s)
        return out

    def _drop_request(self) -> None:
        self.request, self._request_s = None, None
        self.limiter.reset(Twist2D())

    # ----------------------------------------------------------------- wheel speed loop, wiring, slip

    def set_direct(self, pwm: WheelPwm | None, now_s: float) -> list[Outgoing]:
        """Drive each wheel at this PWM (None: back to requests): `rover-bridge calibrate`'s steps. Every
        safety path still applies first (link lost, disarmed, a stop mode, a fault, the stop at exit); a
        request arriving meanwhile is refused."""
        if self.state in _OVER:
            return []
        self._direct = pwm
        self._drop_request()
        return self._advance(now_s, force_output=True)

    def on_wheels(self, sample: MeasuredWheels, now_s: float) -> None:
        """Measured wheel speeds (the estimate flow's checked WHEEL_DISTANCE increments, via the composition)."""
        if self.loop is not None:
            self.loop.measure(sample, now_s)
        else:
            self._open_measured = (now_s, sample.speeds)

    def set_slipping(self, slipping: bool) -> None:
        """The estimator's verdict on wheel slip (via the composition), for slip compensation."""
        self._slipping = slipping

    def _measured(self, now_s: float) -> WheelSpeeds | None:
        if self.loop is not None:
            return self.loop.measured if self.loop.fresh(now_s) else None
        seen = self._open_measured
        if seen is None or now_s - seen[0] >= self.profile.control.encoder_timeout_s:
            return None
        return seen[1]

    def _encoders_fresh(self, fresh: bool, now_s: float) -> list[Outgoing]:
        """Say once when the loop falls back to feedforward (stale encoders) and when it closes again."""
        if fresh == self._loop_closed:
            return []
        self._loop_closed = fresh
        self._count("control.closed" if fresh else "control.stale")
        text = ("RB: wheel encoders back: speed loop closed" if fresh
                else "RB: no wheel encoders: feedforward only")
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, text, now_s, key="control.encoders")

    def _slip_limited(self, wheels: WheelSpeeds, now_s: float) -> tuple[WheelSpeeds, list[Outgoing]]:
        """Slip compensation: while the wheels slip, no wheel is driven faster than when slip began."""
        measured = self._measured(now_s)
        # Slip is a wheel spinning the way it is driven, faster than the ground moves; a wheel measured
        # the other way is a wiring fault for the monitor, not slip to hold the speeds for.
        agrees = measured is not None and (measured.left_rad_s * wheels.left_rad_s >= 0.0
                                           and measured.right_rad_s * wheels.right_rad_s >= 0.0)
        if not (self.profile.control.slip_compensation and self._slipping and agrees):
            self._slip_hold = None
            return wheels, []
        out: list[Outgoing] = []
        if self._slip_hold is None:
            self._slip_hold = wheels
            self._count("slip.limited")
            out = self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, "RB: wheel slip: holding wheel speeds",
                                           now_s, key="slip.limited")
        hold = self._slip_hold

        def capped(value: float, held: float) -> float:
            return math.copysign(min(abs(value), abs(held)), value) if value * held > 0.0 else 0.0

        return WheelSpeeds(capped(wheels.left_rad_s, hold.left_rad_s),
                           capped(wheels.right_rad_s, hold.right_rad_s)), out

    def _fault(self, fault: WiringFault, now_s: float) -> list[Outgoing]:
        self._count(f"fault.{fault.wheel}.{fault.kind}")
        self._wiring_fault = fault
        self.request, self._request_s = None, None
        self.limiter.reset(Twist2D())
        if self.loop is not None:
            self.loop.reset()
        self.wiring.reset()
        log.critical("wiring fault: %s wheel %s (commanded against measured wheel speeds); %s", fault.wheel,
                     fault.kind, fault.texts[1][len("RB: "):])
        out: list[Outgoing] = []
        for text in fault.texts:
            out += self.reporter.statustext(mavlink.MAV_SEVERITY_CRITICAL, text, now_s, key=text)
        out += self._set_state(CommandState.FAULT, now_s)
        return out

    def _set_state(self, new: CommandState, now_s: float, text: tuple[int, str] | None = None) -> list[Outgoing]:
        if new is self.state:
            return []
        old, self.state = self.state, new
        self._count(f"state.{new.value}")
        log.info("command state %s -> %s", old.value, new.value)
        severity, said = text if text is not None else STATE_TEXT[new]
        return self.reporter.statustext(severity, said, now_s, key=f"state.{new.value}")

    def _to_autopilot(self, msg: MAVLinkMessage) -> Outgoing:
        # ArduPilot obeys overrides only from its GCS id (MAV_GCS_SYSID): see output.override_source_system.
        return Outgoing(Link.AUTOPILOT, msg, self.identity.override_source_system, self.identity.component_id)

    def _say_once(self, key: str, text: str, source: tuple[int, int], now_s: float) -> list[Outgoing]:
        """Report `text` once per (key, source); later occurrences are only counted."""
        # Bounded: spoofed source ids (65k of them) must not grow the set without limit; past the cap
        # only the counters record them.
        if (key, *source) in self._said or len(self._said) >= MAX_SAID:
            return []
        self._said.add((key, *source))
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, text, now_s, key=key)

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1
