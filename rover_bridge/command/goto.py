"""Driver: position targets ("go here": SET_POSITION_TARGET_* with x/y used, MISSION_ITEM(_INT) current = 2,
DO_REPOSITION), followed on the estimate's pose by rover_bridge.command.navigator (pure).

- Taken only in a mode where the mode table gives the wheels to position targets (ArduPilot Rover: GUIDED; a
  GCS's accepted DO_SET_MODE counts until the next heartbeat; DO_REPOSITION's CHANGE_MODE asks the autopilot
  for GUIDED and starts on its ACK), armed, with a ground station's HEARTBEAT fresh, and within
  navigation.max_distance_m; refusals are answered (MISSION_ACK, COMMAND_ACK, STATUSTEXT) and consumed.
  Targets, like requests, are consumed only when addressed to the vehicle.
- A running target is a request with no setpoint timeout; `watch` ends it (braking through the limiter) when
  the mode no longer gives it the wheels, the ground station falls silent for navigation.gcs_timeout_s, or
  the estimate's pose is reset or lost; link loss, disarm and HOLD end it as they end any request; a velocity
  request or MANUAL_CONTROL takes over for good; arrival brakes to a stop.
- DO_CHANGE_SPEED is answered only in such a mode (in AUTO, RTL ... it is the autopilot's own).
- While a target runs, the autopilot's own navigation feedback (AUTOPILOT_NAV_ECHOES) is not forwarded: the
  autopilot, whose wheels the bridge drives, is not navigating, so its version would contradict the bridge's.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from rover_bridge.command.drivers import CommandState, Wheels
from rover_bridge.command.gcs_requests import UNAUTHORISED, GcsRequests
from rover_bridge.command.modes import ModeTable
from rover_bridge.command.navigation import PoseSource, Unresolved
from rover_bridge.command.navigator import GotoRequest, Navigator
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
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.command")

POSITION_TARGETS = frozenset({"SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT"})
MISSION_ITEMS = frozenset({"MISSION_ITEM_INT", "MISSION_ITEM"})
GOTO_COMMANDS = frozenset({mavlink.MAV_CMD_DO_REPOSITION, mavlink.MAV_CMD_DO_CHANGE_SPEED})
GUIDED_CURRENT = 2  # MISSION_ITEM(_INT).current: a guided "go here", not a mission upload
AUTOPILOT_NAV_ECHOES = frozenset({"NAV_CONTROLLER_OUTPUT", "POSITION_TARGET_GLOBAL_INT",
                                  "POSITION_TARGET_LOCAL_NED", "MISSION_ITEM_REACHED"})
MODE_CHANGE_TIMEOUT_S = 1.0  # DO_REPOSITION's "change to GUIDED": the autopilot's ACK is awaited this long
MALFORMED = "malformed"
_NO_LINK = (CommandState.WAITING, CommandState.LINK_LOST)


class _ModeChange:
    """A DO_REPOSITION that asked for GUIDED first: what to start once the autopilot accepts the mode."""

    def __init__(self, msg: MAVLinkMessage, goal: GotoRequest, notes: frozenset[str], deadline_s: float) -> None:
        self.msg, self.goal, self.notes, self.deadline_s = msg, goal, notes, deadline_s


def is_goto(msg: MAVLinkMessage, kind: str) -> bool:
    """A position target, a guided MISSION_ITEM, DO_REPOSITION or DO_CHANGE_SPEED (any addressee)."""
    if kind in POSITION_TARGETS:
        return uses_position(msg)
    if kind in MISSION_ITEMS:
        return int(msg.current) == GUIDED_CURRENT and int(msg.mission_type) == mavlink.MAV_MISSION_TYPE_MISSION
    if kind in ("COMMAND_LONG", "COMMAND_INT"):
        return int(msg.command) in GOTO_COMMANDS
    return False


class PositionTargets:
    """The position-target driver: taking, refusing, answering, following and ending targets (module doc)."""

    name: str = "targets"
    braking_text: tuple[int, str] | None = None
    speed_loop: bool = True

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter, pose_source: PoseSource | None,
                 vehicle: VehicleState, wheels: Wheels, gcs: GcsRequests, modes: ModeTable,
                 count: Callable[[str], None]) -> None:
        self.profile = profile
        self.identity = identity
        self.vehicle = vehicle
        self.wheels = wheels
        self.gcs = gcs
        self.guided_modes = modes.targets
        self._count = count
        self.nav = Navigator(profile, identity, reporter, pose_source)
        self.reporter = reporter
        self.goal: GotoRequest | None = None
        self.mode_change: _ModeChange | None = None

    # ----------------------------------------------------------------- the driver

    @property
    def request(self) -> GotoRequest | None:
        return self.goal

    def braking(self, now_s: float) -> bool:
        return False  # no setpoint timeout: `watch` ends it

    def deadline_s(self) -> float | None:
        """No setpoint timeout; its own deadlines: the feedback's, and the GCS's silence."""
        report, silence = self.nav.next_report_s, self.nav.gcs_deadline_s()
        if report is None or silence is None:
            return silence if report is None else report
        return min(report, silence)

    def target(self, now_s: float) -> tuple[Twist2D | None, list[Outgoing]]:
        goal = self.goal
        assert goal is not None
        step = self.nav.step(goal, now_s)
        if step is None:  # `watch` ends it on the next evaluation; brake meanwhile
            return Twist2D(), []
        twist, status = step
        if status.phase != "done":
            return twist, []
        self._count("goto.reached")
        out = self.nav.arrived(goal, status, now_s)
        self.wheels.brake_to_stop(now_s)
        return Twist2D(), out

    def drop(self) -> None:
        self.goal = None

    def hold(self, request: GotoRequest, now_s: float) -> None:
        self.goal = request

    def taken_over(self, by: str, now_s: float) -> list[Outgoing]:
        self._count(f"goto.cancelled.{by.split(' ')[0].lower()}")
        self.goal = None
        return self.nav.cancelled(by, now_s)

    def in_guided(self) -> bool:
        return self.vehicle.mode in self.guided_modes

    def watch(self, now_s: float) -> list[Outgoing]:
        """End a running target that may not go on (module doc): said, and braked to a stop where the
        state machine does not stop it itself (link lost, HOLD and disarmed with require_armed do)."""
        goal = self.goal
        if goal is None:
            return []
        v = self.vehicle
        brake = True
        if v.last_heartbeat_s is None or v.link_lost(now_s):
            reason, brake = "autopilot link lost", False
        elif not v.armed:
            reason, brake = "disarmed", not self.profile.safety.require_armed
        elif v.custom_mode in v.stop_modes or v.hold_requested_s is not None:
            reason, brake = "HOLD", False
        elif not self.in_guided():
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
            self.wheels.brake_to_stop(now_s)
        return out

    # ----------------------------------------------------------------- from a ground station

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        """Take, refuse or answer a position target (module doc; docs/gcs.md, "Going to a point")."""
        msg = inc.msg
        if not self.gcs.for_vehicle(msg):
            return NOTHING
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if not self.gcs.authorised(inc):
            return self._refused(msg, Refused(UNAUTHORISED), source, now_s)
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
            if not self.in_guided():
                return NOTHING  # not ours to answer: the autopilot's own navigation (AUTO, RTL...) takes it
            self.nav.set_speed(decoded)
            self._count("goto.speed")
            if self.goal is not None:
                self.goal = self.nav.with_speed(self.goal)
            return Reaction(consumed=True, out=(self.nav.command_ack(msg, mavlink.MAV_RESULT_ACCEPTED),))
        if isinstance(decoded, Refused):
            return self._refused(msg, decoded, source, now_s)
        out = self.wheels.advance(now_s, force_output=False)  # bring link / armed / mode state up to date
        change_mode = kind == "COMMAND_INT" and changes_mode(msg)
        reason = self._state_refusal(now_s, change_mode)
        if reason is not None:
            refused = self._refused(msg, Refused(reason), source, now_s, text=reason)
            return Reaction(consumed=True, out=(*out, *refused.out))
        resolved = self.nav.resolve(decoded, now_s)
        if isinstance(resolved, Unresolved):
            result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED if resolved.temporary else mavlink.MAV_RESULT_DENIED
            refused = self._refused(msg, Refused("unresolved", mavlink.MAV_MISSION_ERROR, result), source,
                                    now_s, text=resolved.text)
            return Reaction(consumed=True, out=(*out, *refused.out))
        goal = self.nav.goal(resolved, source)
        if not self.in_guided():  # change_mode: ask the autopilot for GUIDED, start on its ACK
            out += self._ask_for_guided(msg, goal, decoded.notes, now_s)
            return Reaction(consumed=True, out=tuple(out))
        out += self._start(goal, decoded.notes, now_s)
        if kind in MISSION_ITEMS:
            out.insert(0, self.nav.mission_ack(msg, mavlink.MAV_MISSION_ACCEPTED))
        elif kind == "COMMAND_INT":
            out.insert(0, self.nav.command_ack(msg, mavlink.MAV_RESULT_ACCEPTED))
        return Reaction(consumed=True, out=tuple(out))

    def _state_refusal(self, now_s: float, change_mode: bool = False) -> str | None:
        """Why no target may start now (None: it may)."""
        state = self.wheels.state
        if state in _NO_LINK:
            return "no autopilot heartbeat"
        if not self.vehicle.armed:
            return "disarmed"
        if state is CommandState.HOLD:
            return "autopilot in HOLD"
        if state is CommandState.FAULT:
            return "wiring fault"
        if state is CommandState.DIRECT:
            return "calibrating"
        if not ((change_mode and self.guided_modes) or self.in_guided()):
            return "autopilot not in GUIDED"
        if not self.nav.gcs_watching(now_s):
            return "no GCS heartbeat"
        return None

    def _refused(self, msg: MAVLinkMessage, refused: Refused, source: tuple[int, int], now_s: float,
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

    def _start(self, goal: GotoRequest, notes: frozenset[str], now_s: float) -> list[Outgoing]:
        if self.goal is not None:
            self._count("goto.replaced")
        self._count("goto.accepted")
        out = self.nav.begin(goal, notes, now_s)
        return out + self.wheels.take(self, goal, now_s, "target")

    def _ask_for_guided(self, msg: MAVLinkMessage, goal: GotoRequest, notes: frozenset[str],
                        now_s: float) -> list[Outgoing]:
        """DO_REPOSITION with CHANGE_MODE outside GUIDED: ask the autopilot for it (as ArduPilot switches
        itself); the target starts, and the GCS gets its ACK, when the autopilot accepts."""
        vehicle = self.identity.vehicle_system_id
        assert vehicle is not None
        self.mode_change = _ModeChange(msg, goal, notes, now_s + MODE_CHANGE_TIMEOUT_S)
        self._count("goto.mode_change")
        ask = mavlink.MAVLink_command_long_message(
            target_system=vehicle, target_component=self.identity.autopilot_component_id,
            command=mavlink.MAV_CMD_DO_SET_MODE, confirmation=0,
            param1=float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), param2=float(min(self.guided_modes)),
            param3=0.0, param4=0.0, param5=0.0, param6=0.0, param7=0.0)
        return [Outgoing(Link.AUTOPILOT, ask, self.identity.own_system_id, self.identity.component_id)]

    def mode_change_ack(self, msg: MAVLinkMessage, now_s: float) -> Reaction | None:
        """The autopilot's answer to our own DO_SET_MODE (None: the ACK is not ours)."""
        change = self.mode_change
        target = (int(getattr(msg, "target_system", 0)), int(getattr(msg, "target_component", 0)))
        if change is None or target not in ((0, 0), (self.identity.own_system_id, self.identity.component_id)):
            return None
        self.mode_change = None
        result = int(msg.result)
        source = change.goal.source
        if result != mavlink.MAV_RESULT_ACCEPTED:
            return self._refused(change.msg, Refused("mode", command_result=mavlink.MAV_RESULT_FAILED), source,
                                 now_s, text=f"GUIDED refused by the autopilot ({result})")
        self.vehicle.anticipate(min(self.guided_modes))
        reason = self._state_refusal(now_s)
        if reason is not None:
            return self._refused(change.msg, Refused(reason), source, now_s, text=reason)
        out = [self.nav.command_ack(change.msg, mavlink.MAV_RESULT_ACCEPTED)]
        out += self._start(change.goal, change.notes, now_s)
        return Reaction(consumed=True, out=tuple(out))

    def mode_change_tick(self, now_s: float) -> list[Outgoing]:
        change = self.mode_change
        if change is None or now_s < change.deadline_s:
            return []
        self.mode_change = None
        refused = self._refused(change.msg, Refused("mode", command_result=mavlink.MAV_RESULT_FAILED),
                                change.goal.source, now_s, text="no answer to the change to GUIDED")
        return list(refused.out)

    def echo_to_hide(self, msg: MAVLinkMessage) -> bool:
        """The autopilot's own navigation feedback, while the bridge's stands for it (AUTOPILOT_NAV_ECHOES)."""
        return self.goal is not None and self.identity.from_autopilot(msg)
