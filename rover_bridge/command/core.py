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
- A valid request is followed at once: the output goes out in the same `handle` call, and it shows
  the request. The limiter keeps its own time: the answer to a request steps it to the later of now
  and one period past where it stood (so a request that arrives 1 ms after an output still moves the
  wheels by what the limits allow over a period, not by 1 ms worth: 0.05 m/s at the default 1 m/s^2
  and 20 Hz, where 1 ms worth rounds to the same PWM and the request would show only a period later);
  every other output steps it to now, or not at all while it is ahead. So the command follows the
  limiter's trajectory exactly, evaluated at most one period ahead of time after a request: the
  acceleration limits hold on that trajectory, and a burst of requests cannot run it further ahead.
  A step is never longer than one period (after a stalled loop the limiter must not allow a jump worth
  the whole stall). The shell reads every link before a due periodic output is sent (Runner.step),
  so input that arrived by then is answered first.
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
- Position targets ("go here": SET_POSITION_TARGET_* with x/y used, MISSION_ITEM(_INT) current = 2,
  DO_REPOSITION; rover_bridge.command.targets, .navigation, .navigator) are taken only in one of
  navigation.guided_modes (a GCS's accepted DO_SET_MODE counts until the next heartbeat; DO_REPOSITION's
  CHANGE_MODE asks the autopilot for GUIDED and starts on its ACK), armed, with a ground station's
  HEARTBEAT fresh, and within navigation.max_distance_m; refusals are answered (MISSION_ACK, COMMAND_ACK,
  STATUSTEXT) and consumed. A running target is a request with no setpoint timeout; _watch_goal ends it
  (braking through the limiter) when the mode leaves GUIDED, the ground station falls silent for
  navigation.gcs_timeout_s, or the estimate's pose is reset or lost; link loss, disarm and HOLD end it as
  they end any request; a velocity request or MANUAL_CONTROL takes over for good; arrival brakes to a
  stop. Targets, like requests, are consumed only when addressed to the vehicle.
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

from rover_bridge.command.navigation import PoseSource, Unresolved
from rover_bridge.command.navigator import GotoRequest, Navigator
from rover_bridge.command.outputs import OutputMap, WheelPwm
from rover_bridge.command.setpoints import (
    REQUEST_TYPES,
    BodyVelocity,
    HeadingVelocity,
    Rejected,
    Request,
    decode_request,
)
from rover_bridge.command.targets import (
    Refused,
    SpeedChange,
    Target,
    changes_mode,
    decode_command,
    decode_mission_item,
    decode_position_target,
    uses_position,
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
POSITION_TARGETS = frozenset({"SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT"})
MISSION_ITEMS = frozenset({"MISSION_ITEM_INT", "MISSION_ITEM"})
GOTO_COMMANDS = frozenset({mavlink.MAV_CMD_DO_REPOSITION, mavlink.MAV_CMD_DO_CHANGE_SPEED})
GUIDED_CURRENT = 2  # MISSION_ITEM(_INT).current: a guided "go here", not a mission upload
# What the autopilot says about its own navigation: while the bridge follows a target, the autopilot (whose
# wheels the bridge drives) is not navigating, so its version would contradict the bridge's to the GCS.
AUTOPILOT_NAV_ECHOES = frozenset({"NAV_CONTROLLER_OUTPUT", "POSITION_TARGET_GLOBAL_INT",
                                  "POSITION_TARGET_LOCAL_NED", "MISSION_ITEM_REACHED"})
MODE_CHANGE_TIMEOUT_S = 1.0  # DO_REPOSITION's "change to GUIDED": the autopilot's ACK is awaited this long
MALFORMED = "malformed"


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


class _ModeChange:
    """A DO_REPOSITION that asked for GUIDED first: what to start once the autopilot accepts the mode."""

    def __init__(self, msg: MAVLinkMessage, goal: GotoRequest, notes: frozenset[str], deadline_s: float) -> None:
        self.msg, self.goal, self.notes, self.deadline_s = msg, goal, notes, deadline_s


class CommandCore:
    """Messages and the current time in, override messages out (see the module doc for the rules)."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter,
                 pose_source: PoseSource | None = None) -> None:
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        self.drive = DiffDrive.from_params(profile.robot)
        self.outputs = OutputMap.from_profile(profile)
        self.limiter = TwistLimiter(TwistLimits.from_params(profile.limits))
        self.period_s = 1.0 / profile.command.rate_hz
        self._setpoint_timeout_s = profile.command.setpoint_timeout_s
        self._heartbeat_timeout_s = profile.safety.heartbeat_timeout_s
        self.state = CommandState.WAITING
        self.counters: dict[str, int] = {}
        self.last_wheel_pwm: WheelPwm | None = None
        self.request: Request | GotoRequest | None = None  # headings already made absolute
        self._request_s: float | None = None
        self._last_heartbeat_s: float | None = None
        self._armed = False
        self._yaw_cw_rad: float | None = None
        self._yaw_s: float | None = None
        self._last_output_s: float | None = None
        self._limiter_s: float | None = None  # the time the limiter's state stands for (module doc)
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
        # Position targets (rover_bridge.command.navigator); the mode a DO_SET_MODE the autopilot accepted
        # asked for, until its next heartbeat (ArduPilot sends one at once after a mode change) says it.
        self.nav = Navigator(profile, identity, reporter, pose_source)
        self._guided_modes = frozenset(profile.navigation.guided_modes)
        self._mode_requested: int | None = None  # the last mode a GCS's DO_SET_MODE asked for
        self._anticipated_mode: int | None = None
        self._mode_change: _ModeChange | None = None
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
    AUTOPILOT_READS = frozenset({"HEARTBEAT", "ATTITUDE", "COMMAND_ACK", "TIMESYNC"}) | AUTOPILOT_NAV_ECHOES

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
            elif kind in AUTOPILOT_NAV_ECHOES:
                return Reaction(consumed=True) if self._echo_to_hide(msg) else NOTHING
            return NOTHING
        if kind == "HEARTBEAT":
            self.nav.on_gcs_heartbeat(msg, now_s)
            return NOTHING
        try:
            goto = self._is_goto(msg, kind)
        except (AttributeError, TypeError, ValueError, OverflowError):
            goto = False  # a malformed frame: the paths below judge it as they always did
        if goto:
            return self._on_goto(inc, now_s)
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
        out = self._mode_change_tick(now_s)
        due = self._next_output_s is None or now_s >= self._next_output_s
        out += self._advance(now_s, force_output=due)
        goal = self.request
        if isinstance(goal, GotoRequest) and self.state is CommandState.ACTIVE:
            out += self.nav.report(goal, now_s)
        return out

    def next_deadline_s(self, now_s: float) -> float:
        if self.state is CommandState.STOPPING:
            return min(self._stop_sent_s + STOP_RESEND_S,
                       self._stop_began_s + self.profile.safety.stop_confirm_timeout_s)
        if self.state is CommandState.STOPPED or self.identity.vehicle_system_id is None:
            return now_s + self.period_s  # nothing can be sent yet; look again a period later
        # Runs on every turn of the loop: plain comparisons, no lists.
        first = now_s if self._next_output_s is None else self._next_output_s
        goal = self.request
        if isinstance(goal, GotoRequest):
            # A target needs no stream (no setpoint timeout); its own deadlines: feedback, GCS silence.
            for deadline in (self.nav.next_report_s, self.nav.gcs_deadline_s()):
                if deadline is not None and deadline < first:
                    first = deadline
        elif self.state is CommandState.ACTIVE and self._request_s is not None:
            first = min(first, self._request_s + self._setpoint_timeout_s)
        if self._mode_change is not None:
            first = min(first, self._mode_change.deadline_s)
        if self._last_heartbeat_s is not None and self.state is not CommandState.LINK_LOST:
            first = min(first, self._last_heartbeat_s + self._heartbeat_timeout_s)
        return first

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
        self._anticipated_mode = None  # the heartbeat says the mode from now on
        if self._custom_mode not in self._guided_modes:
            self.nav.cruise_m_s = None  # DO_CHANGE_SPEED lasts while in GUIDED (ArduPilot: reset on entry)
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
        if mode is not None and msg.get_type() != "SET_MODE":
            self._mode_requested = mode  # its ACK tells whether the autopilot took it
        if mode is None or mode not in self._stop_modes:
            return NOTHING
        self._hold_requested_s = now_s
        self._count("hold.requested")
        return Reaction(consumed=False, out=tuple(self._advance(now_s, force_output=False)))

    def _on_command_ack(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        if int(msg.command) == mavlink.MAV_CMD_DO_SET_MODE:
            if self._mode_change is not None and self._ack_is_ours(msg):
                return self._on_mode_change_ack(int(msg.result), now_s)
            if self._hold_requested_s is not None and int(msg.result) not in _ACK_OK:
                self._hold_requested_s = None  # the autopilot refused the stop mode: its heartbeat governs
            if int(msg.result) == mavlink.MAV_RESULT_ACCEPTED and self._mode_requested is not None:
                self._anticipated_mode = self._mode_requested  # a GCS's mode change, before its heartbeat
                self._mode_requested = None
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

    def _for_vehicle(self, msg: MAVLinkMessage) -> bool:
        """Addressed to the vehicle, which is known: ours to act on (else forwarded untouched, counted)."""
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            self._count("forwarded.vehicle_unknown")
            return False
        if not self._addressed(msg, vehicle):
            self._count("forwarded.not_for_vehicle")
            return False
        return True

    def _on_request(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        if not self._for_vehicle(msg):
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
        if isinstance(self.request, GotoRequest):
            # A velocity request (or MANUAL_CONTROL) takes over; the target does not resume afterwards.
            self._count("goto.cancelled.velocity")
            out += self.nav.cancelled(f"velocity from {source[0]}:{source[1]}", now_s)
        self.request, self._request_s, self._refused = request, now_s, False
        out += self._advance(now_s, force_output=True, answer=True)
        return Reaction(consumed=True, out=tuple(out))

    def _reject(self, reason: str, source: tuple[int, int], now_s: float) -> Reaction:
        self._count(f"rejected.{reason}")
        text = f"RB: rejected {reason} from {source[0]}:{source[1]}"
        out = self._say_once(f"rejected.{reason}", text, source, now_s)
        return Reaction(consumed=True, out=tuple(out))

    # ----------------------------------------------------------------- state and outputs

    def _advance(self, now_s: float, force_output: bool, answer: bool = False) -> list[Outgoing]:
        """Update the state for `now_s`; send outputs if forced, due to a state change, or braking done.
        `answer`: the output answers a new request (the module doc: how far the limiter moves)."""
        before = self.state
        out = self._watch_goal(now_s)
        out += self._set_state(self._evaluate(now_s), now_s)
        if self.identity.vehicle_system_id is not None and (force_output or self.state is not before):
            out += self._output(now_s, answer)
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
        if isinstance(self.request, GotoRequest):
            return CommandState.ACTIVE  # no setpoint timeout: _watch_goal ends it (the module doc)
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

    def _output(self, now_s: float, answer: bool = False) -> list[Outgoing]:
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            return []
        said: list[Outgoing] = []
        goal = self.request
        target: Twist2D | None
        if self.state is CommandState.ACTIVE and isinstance(goal, GotoRequest):
            target, said = self._goto_twist(goal, now_s)
        else:
            target = self._target(now_s) if self.state is CommandState.ACTIVE else None
        last = self._last_output_s
        period = self.period_s
        dt_s = period if last is None else min(period, now_s - last)  # since the last output (the speed loop)
        # The limiter's own time (module doc): an answer steps it to the later of now and one period past
        # where it stood; any other output to now (nothing, while it is ahead).
        at = self._limiter_s
        if at is None:
            at = now_s - period
        until = max(now_s, min(at, now_s) + period) if answer else now_s
        if self.state in _RAMPING:
            step_s = min(period, until - at)
            if step_s > 0.0:
                self.limiter.step(target if target is not None else Twist2D(), step_s)
                self._limiter_s = until
        else:
            self.limiter.reset(Twist2D())
            self._limiter_s = now_s
        raw = self.drive.to_wheel_speeds(self.limiter.current)
        wheels = raw.desaturate(self.profile.robot.max_wheel_rad_s)
        moving = self.state in _DRIVING or (self.state is CommandState.HOLD and self.limiter.current != Twist2D())
        out: list[Outgoing] = said
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

    # ----------------------------------------------------------------- position targets

    def _is_goto(self, msg: MAVLinkMessage, kind: str) -> bool:
        """A position target, a guided MISSION_ITEM, DO_REPOSITION or DO_CHANGE_SPEED (any addressee)."""
        if kind in POSITION_TARGETS:
            return uses_position(msg)
        if kind in MISSION_ITEMS:
            return int(msg.current) == GUIDED_CURRENT and int(msg.mission_type) == mavlink.MAV_MISSION_TYPE_MISSION
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            return int(msg.command) in GOTO_COMMANDS
        return False

    def _in_guided(self) -> bool:
        mode = self._anticipated_mode if self._anticipated_mode is not None else self._custom_mode
        return mode in self._guided_modes

    def _on_goto(self, inc: Incoming, now_s: float) -> Reaction:
        """Take, refuse or answer a position target (module doc; the README's "Going to a point")."""
        msg = inc.msg
        if not self._for_vehicle(msg):
            return NOTHING
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if not self._authorised(inc):
            return self._goto_refused(msg, Refused(UNAUTHORISED), source, now_s)
        decoded: Target | SpeedChange | Refused | None
        try:
            if kind in POSITION_TARGETS:
                decoded = decode_position_target(msg)
            elif kind in MISSION_ITEMS:
                decoded = decode_mission_item(msg)
            else:
                decoded = decode_command(msg)
        except (AttributeError, TypeError, ValueError, OverflowError):
            decoded = Refused(MALFORMED, mavlink.MAV_MISSION_ERROR, mavlink.MAV_RESULT_DENIED)
        if decoded is None:
            return NOTHING
        if isinstance(decoded, SpeedChange):
            if not self._in_guided():
                return NOTHING  # not ours to answer: the autopilot's own navigation (AUTO, RTL...) takes it
            self.nav.set_speed(decoded)
            self._count("goto.speed")
            if isinstance(self.request, GotoRequest):
                self.request = self.nav.with_speed(self.request)
            return Reaction(consumed=True, out=(self.nav.command_ack(msg, mavlink.MAV_RESULT_ACCEPTED),))
        if isinstance(decoded, Refused):
            return self._goto_refused(msg, decoded, source, now_s)
        out = self._advance(now_s, force_output=False)  # bring link / armed / mode state up to date
        change_mode = kind == "COMMAND_INT" and changes_mode(msg)
        reason = self._goto_state_refusal(now_s, change_mode)
        if reason is not None:
            refused = self._goto_refused(msg, Refused(reason), source, now_s, text=reason)
            return Reaction(consumed=True, out=(*out, *refused.out))
        resolved = self.nav.resolve(decoded, now_s)
        if isinstance(resolved, Unresolved):
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED if resolved.temporary else mavlink.MAV_RESULT_DENIED
            refused = self._goto_refused(msg, Refused("unresolved", mavlink.MAV_MISSION_ERROR, result), source,
                                         now_s, text=resolved.text)
            return Reaction(consumed=True, out=(*out, *refused.out))
        goal = self.nav.goal(resolved, source)
        if not self._in_guided():  # change_mode: ask the autopilot for GUIDED, start on its ACK
            out += self._ask_for_guided(msg, goal, decoded.notes, now_s)
            return Reaction(consumed=True, out=tuple(out))
        out += self._start_goal(goal, decoded.notes, now_s)
        if kind in MISSION_ITEMS:
            out.insert(0, self.nav.mission_ack(msg, mavlink.MAV_MISSION_ACCEPTED))
        elif kind == "COMMAND_INT":
            out.insert(0, self.nav.command_ack(msg, mavlink.MAV_RESULT_ACCEPTED))
        return Reaction(consumed=True, out=tuple(out))

    def _goto_state_refusal(self, now_s: float, change_mode: bool = False) -> str | None:
        """Why no target may start now (None: it may)."""
        if self.state in (CommandState.WAITING, CommandState.LINK_LOST):
            return "no autopilot heartbeat"
        if not self._armed:
            return "disarmed"
        if self.state is CommandState.HOLD:
            return "autopilot in HOLD"
        if self.state is CommandState.FAULT:
            return "wiring fault"
        if self.state is CommandState.DIRECT:
            return "calibrating"
        if not (change_mode or self._in_guided()):
            return "autopilot not in GUIDED"
        if not self.nav.gcs_watching(now_s):
            return "no GCS heartbeat"
        return None

    def _goto_refused(self, msg: MAVLinkMessage, refused: Refused, source: tuple[int, int], now_s: float,
                      text: str | None = None) -> Reaction:
        """Refused: the answer its message gets (MISSION_ACK, COMMAND_ACK, none) and a STATUSTEXT."""
        reason = refused.reason if text is None else text
        key = refused.reason if text is None else text.split(",")[0]
        self._count(f"goto.refused.{key.replace(' ', '_')}")
        kind = msg.get_type()
        out: list[Outgoing] = []
        if kind in MISSION_ITEMS:
            out.append(self.nav.mission_ack(msg, refused.mission_result))
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            out.append(self.nav.command_ack(msg, refused.command_result))
        log.warning("target from %d:%d refused: %s", *source, reason)
        out += self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, f"RB: target refused: {reason}", now_s,
                                        key=f"goto.refused.{key}")
        return Reaction(consumed=True, out=tuple(out))

    def _start_goal(self, goal: GotoRequest, notes: frozenset[str], now_s: float) -> list[Outgoing]:
        if isinstance(self.request, GotoRequest):
            self._count("goto.replaced")
        self._count("goto.accepted")
        out = self.nav.begin(goal, notes, now_s)
        self.request, self._request_s, self._refused = goal, now_s, False
        return out + self._advance(now_s, force_output=True, answer=True)

    def _ask_for_guided(self, msg: MAVLinkMessage, goal: GotoRequest, notes: frozenset[str],
                        now_s: float) -> list[Outgoing]:
        """DO_REPOSITION with CHANGE_MODE outside GUIDED: ask the autopilot for it (as ArduPilot switches
        itself); the target starts, and the GCS gets its ACK, when the autopilot accepts."""
        vehicle = self.identity.vehicle_system_id
        assert vehicle is not None
        self._mode_change = _ModeChange(msg, goal, notes, now_s + MODE_CHANGE_TIMEOUT_S)
        self._count("goto.mode_change")
        ask = mavlink.MAVLink_command_long_message(
            target_system=vehicle, target_component=self.identity.autopilot_component_id,
            command=mavlink.MAV_CMD_DO_SET_MODE, confirmation=0,
            param1=float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), param2=float(min(self._guided_modes)),
            param3=0.0, param4=0.0, param5=0.0, param6=0.0, param7=0.0)
        return [Outgoing(Link.AUTOPILOT, ask, self.identity.own_system_id, self.identity.component_id)]

    def _ack_is_ours(self, msg: MAVLinkMessage) -> bool:
        target = (int(getattr(msg, "target_system", 0)), int(getattr(msg, "target_component", 0)))
        return target in ((0, 0), (self.identity.own_system_id, self.identity.component_id))

    def _on_mode_change_ack(self, result: int, now_s: float) -> Reaction:
        change = self._mode_change
        assert change is not None
        self._mode_change = None
        source = change.goal.source
        if result != mavlink.MAV_RESULT_ACCEPTED:
            refused = self._goto_refused(change.msg, Refused("mode", command_result=mavlink.MAV_RESULT_FAILED),
                                         source, now_s, text=f"GUIDED refused by the autopilot ({result})")
            return Reaction(consumed=True, out=refused.out)
        self._anticipated_mode = min(self._guided_modes)
        reason = self._goto_state_refusal(now_s)
        if reason is not None:
            return self._goto_refused(change.msg, Refused(reason), source, now_s, text=reason)
        out = [self.nav.command_ack(change.msg, mavlink.MAV_RESULT_ACCEPTED)]
        out += self._start_goal(change.goal, change.notes, now_s)
        return Reaction(consumed=True, out=tuple(out))

    def _mode_change_tick(self, now_s: float) -> list[Outgoing]:
        change = self._mode_change
        if change is None or now_s < change.deadline_s:
            return []
        self._mode_change = None
        refused = self._goto_refused(change.msg, Refused("mode", command_result=mavlink.MAV_RESULT_FAILED),
                                     change.goal.source, now_s, text="no answer to the change to GUIDED")
        return list(refused.out)

    def _watch_goal(self, now_s: float) -> list[Outgoing]:
        """End a running target that may not go on (module doc): said, and braked to a stop where the
        state machine does not stop it itself (link lost, HOLD and disarmed with require_armed do)."""
        goal = self.request
        if not isinstance(goal, GotoRequest):
            return []
        hb = self._last_heartbeat_s
        brake = True
        if hb is None or now_s >= hb + self.profile.safety.heartbeat_timeout_s:
            reason, brake = "autopilot link lost", False
        elif not self._armed:
            reason, brake = "disarmed", not self.profile.safety.require_armed
        elif self._custom_mode in self._stop_modes or self._hold_requested_s is not None:
            reason, brake = "HOLD", False
        elif not self._in_guided():
            reason = "mode left GUIDED"
        elif not self.nav.gcs_watching(now_s):
            reason = f"no GCS heartbeat for {self.profile.navigation.gcs_timeout_s:g} s"
        elif goal.reset_counter != self.nav.reset_counter:
            reason = "position estimate reset"
        elif not self.nav.pose_fresh(now_s):
            reason = "position estimate lost"
        else:
            return []
        self._count(f"goto.cancelled.{reason.split(' ')[0].lower()}")
        out = self.nav.cancelled(reason, now_s)
        if brake:
            self._brake_to_stop(now_s)
        return out

    def _brake_to_stop(self, now_s: float) -> None:
        """The target is over: a zero request already timed out, so BRAKING ramps to zero, then IDLE."""
        self.request = BodyVelocity(0.0, 0.0)
        self._request_s = now_s - self.profile.command.setpoint_timeout_s

    def _goto_twist(self, goal: GotoRequest, now_s: float) -> tuple[Twist2D, list[Outgoing]]:
        step = self.nav.step(goal, now_s)
        if step is None:  # _watch_goal ends it on the next evaluation; brake meanwhile
            return Twist2D(), []
        twist, status = step
        if status.phase != "done":
            return twist, []
        self._count("goto.reached")
        out = self.nav.arrived(goal, status, now_s)
        self._brake_to_stop(now_s)
        return Twist2D(), out

    def _echo_to_hide(self, msg: MAVLinkMessage) -> bool:
        """The autopilot's own navigation feedback, while the bridge's stands for it (AUTOPILOT_NAV_ECHOES)."""
        return (isinstance(self.request, GotoRequest) and msg.get_srcSystem() == self.identity.vehicle_system_id
                and msg.get_srcComponent() == self.identity.autopilot_component_id)

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
