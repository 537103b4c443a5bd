"""A position target's lifetime around the controller (pure): taking it, following it, telling the GCS.

The command core owns the rules of when a target may run (rover_bridge.command.core); this class holds
what a running target needs besides: the pose source, the controller, the ground stations' heartbeats
(a rover driving itself stops when nobody is watching), the cruise speed DO_CHANGE_SPEED set, the
feedback an autopilot gives while it navigates (NAV_CONTROLLER_OUTPUT, POSITION_TARGET_*,
MISSION_ITEM_REACHED, all from the autopilot's ids, as the GCS expects them) and the answers
(MISSION_ACK, COMMAND_ACK) in ArduPilot's wording.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

from rover_bridge.command.approach import StopProfile
from rover_bridge.command.navigation import GotoController, NavStatus, NavTarget, PoseSource, Unresolved, resolve
from rover_bridge.command.targets import ALTITUDE_IGNORED, SpeedChange, Target
from rover_bridge.frames import NedPose
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Link, Outgoing
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.command.navigator")

POSITION_ONLY_MASK = 0x0FF8  # POSITION_TARGET_*: only x/y/z (lat/lon/alt) valid
MAX_SAID = 256
FRAME_TEXT = {
    "autopilot": "RB: LOCAL_NED targets: autopilot's local frame",
    "start": "RB: LOCAL_NED targets: bridge start pose, north-up",
}


@dataclass(frozen=True, slots=True)
class GotoRequest:
    """The command core's request while it follows a position target."""

    target: NavTarget
    source: tuple[int, int]  # who sent it (sysid, compid)
    reset_counter: int  # the estimate's, when it was taken: a reset voids the target


class Navigator:
    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter,
                 source: PoseSource | None) -> None:
        self.params = profile.navigation
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        self.source = source
        self.controller = GotoController(profile.navigation, profile.limits, StopProfile.of(profile))
        self.cruise_m_s: float | None = None  # DO_CHANGE_SPEED's, until the mode leaves GUIDED
        self.last_gcs_heartbeat_s: float | None = None
        self.report_period_s = 1.0 / self.params.report_hz
        self.next_report_s: float | None = None
        self.last_status: NavStatus | None = None
        self._said: set[tuple[str, int, int]] = set()

    # ----------------------------------------------------------------- ground stations
    def on_gcs_heartbeat(self, msg: MAVLinkMessage, now_s: float) -> None:
        """A ground station's HEARTBEAT (a GCS type, or any other system than the vehicle's)."""
        if int(msg.type) == mavlink.MAV_TYPE_GCS or msg.get_srcSystem() != self.identity.vehicle_system_id:
            self.last_gcs_heartbeat_s = now_s

    def gcs_deadline_s(self) -> float | None:
        last = self.last_gcs_heartbeat_s
        return None if last is None else last + self.params.gcs_timeout_s

    def gcs_watching(self, now_s: float) -> bool:
        deadline = self.gcs_deadline_s()
        return deadline is not None and now_s < deadline

    # ----------------------------------------------------------------- taking a target
    def set_speed(self, change: SpeedChange) -> None:
        if change.reset:
            self.cruise_m_s = None
        elif change.speed_m_s is not None:
            self.cruise_m_s = change.speed_m_s

    def with_speed(self, goal: GotoRequest) -> GotoRequest:
        """The running goal at the cruise speed DO_CHANGE_SPEED just set."""
        speed = min(self.cruise_m_s or self.params.speed_m_s, self.profile.limits.max_linear_m_s)
        return replace(goal, target=replace(goal.target, speed_m_s=speed))

    def resolve(self, target: Target, now_s: float) -> NavTarget | Unresolved:
        if self.source is None:
            return Unresolved("no position estimate")
        return resolve(target, self.source, now_s, self.params, self.profile.limits.max_linear_m_s,
                       self.cruise_m_s, self.profile.safety.attitude_timeout_s)

    def goal(self, target: NavTarget, source: tuple[int, int]) -> GotoRequest:
        return GotoRequest(target, source, self.reset_counter)

    @property
    def reset_counter(self) -> int:
        return 0 if self.source is None else self.source.reset_counter

    def begin(self, goal: GotoRequest, notes: frozenset[str], now_s: float) -> list[Outgoing]:
        """A new target runs: reset the controller, say where it goes (and the frame note, once)."""
        self.controller.reset()
        self.next_report_s = now_s
        t = goal.target
        out: list[Outgoing] = []
        if t.frame_note:
            out += self.say_once(f"frame.{t.frame_note}", FRAME_TEXT[t.frame_note], (0, 0), now_s)
        if ALTITUDE_IGNORED in notes:
            out += self.say_once("note.altitude", f"RB: target altitude ignored ({goal.source[0]}:{goal.source[1]})",
                                 goal.source, now_s)
        status = self._status(goal, now_s)
        if status is not None:
            text = (f"RB: going {status.distance_m:.1f} m, bearing {math.degrees(status.bearing_cw_rad) % 360:.0f}, "
                    f"{t.speed_m_s:.2f} m/s")
            log.info("%s (from %d:%d)", text, *goal.source)
            out += self.reporter.statustext(mavlink.MAV_SEVERITY_INFO, text, now_s, key="goto.begin")
        return out

    # ----------------------------------------------------------------- following it
    def pose_fresh(self, now_s: float) -> bool:
        return self.source is not None and self.source.nav_pose(now_s) is not None

    def step(self, goal: GotoRequest, now_s: float) -> tuple[Twist2D, NavStatus] | None:
        """The twist toward the target now (None without a pose); phase "done" when it is reached."""
        pose = None if self.source is None else self.source.nav_pose(now_s)
        if pose is None:
            return None
        twist, status = self.controller.twist(pose, goal.target)
        self.last_status = status
        return twist, status

    def _status(self, goal: GotoRequest, now_s: float) -> NavStatus | None:
        pose = None if self.source is None else self.source.nav_pose(now_s)
        return None if pose is None else self.controller.status(pose, goal.target)

    def arrived(self, goal: GotoRequest, status: NavStatus, now_s: float) -> list[Outgoing]:
        """MISSION_ITEM_REACHED (seq 0, as Rover sends for a guided target) and a STATUSTEXT."""
        # Said inside the radius once the braking curve asks for nearly nothing more (the last command the
        # limiter takes to zero in one output), not on entering it: the rest is closed along the heading.
        text = f"RB: target reached (within {self.params.arrival_radius_m:g} m)"
        log.info("%s (target from %d:%d)", text, *goal.source)
        self.next_report_s = None
        out = [self._as_autopilot(mavlink.MAVLink_mission_item_reached_message(seq=0))]
        return out + self.reporter.statustext(mavlink.MAV_SEVERITY_INFO, text, now_s, key="goto.reached")

    def cancelled(self, reason: str, now_s: float) -> list[Outgoing]:
        self.next_report_s = None
        log.warning("target cancelled: %s", reason)
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, f"RB: target cancelled: {reason}", now_s,
                                        key=f"goto.cancel.{reason}")

    def report(self, goal: GotoRequest, now_s: float) -> list[Outgoing]:
        """NAV_CONTROLLER_OUTPUT and POSITION_TARGET_* when due (navigation.report_hz)."""
        due = self.next_report_s
        if due is None or now_s < due:
            return []
        self.next_report_s = due + self.report_period_s if now_s - due < self.report_period_s \
            else now_s + self.report_period_s
        status = self._status(goal, now_s)
        if status is None:
            return []
        t = goal.target
        bearing_deg = round(math.degrees(status.bearing_cw_rad))
        nav = mavlink.MAVLink_nav_controller_output_message(
            nav_roll=0.0, nav_pitch=0.0, nav_bearing=bearing_deg, target_bearing=bearing_deg,
            wp_dist=min(65535, int(status.distance_m)), alt_error=0.0, aspd_error=0.0,
            xtrack_error=status.crosstrack_m)
        boot_ms = 0 if self.source is None else max(0, int(self.source.autopilot_time_s(now_s) * 1000.0))
        boot_ms &= 0xFFFFFFFF
        target_msg: MAVLinkMessage
        if t.global_target is not None:
            target_msg = mavlink.MAVLink_position_target_global_int_message(
                time_boot_ms=boot_ms, coordinate_frame=mavlink.MAV_FRAME_GLOBAL_INT, type_mask=POSITION_ONLY_MASK,
                lat_int=round(t.global_target.lat_deg * 1e7), lon_int=round(t.global_target.lon_deg * 1e7),
                alt=0.0, vx=0.0, vy=0.0, vz=0.0, afx=0.0, afy=0.0, afz=0.0, yaw=0.0, yaw_rate=0.0)
        else:
            ned: NedPose = t.anchor.to_ned(t.x_m, t.y_m, 0.0)
            target_msg = mavlink.MAVLink_position_target_local_ned_message(
                time_boot_ms=boot_ms, coordinate_frame=mavlink.MAV_FRAME_LOCAL_NED, type_mask=POSITION_ONLY_MASK,
                x=ned.north_m, y=ned.east_m, z=0.0, vx=0.0, vy=0.0, vz=0.0, afx=0.0, afy=0.0, afz=0.0, yaw=0.0,
                yaw_rate=0.0)
        return [self._as_autopilot(nav), self._as_autopilot(target_msg)]

    # ----------------------------------------------------------------- answers
    def mission_ack(self, msg: MAVLinkMessage, result: int) -> Outgoing:
        """MISSION_ACK as ArduPilot answers a guided MISSION_ITEM: to the sender, mission_type MISSION."""
        return self._as_autopilot(mavlink.MAVLink_mission_ack_message(
            target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent(), type=result,
            mission_type=mavlink.MAV_MISSION_TYPE_MISSION))

    def command_ack(self, msg: MAVLinkMessage, result: int) -> Outgoing:
        return self._as_autopilot(mavlink.MAVLink_command_ack_message(
            command=int(msg.command), result=result, progress=0, result_param2=0,
            target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent()))

    def _as_autopilot(self, msg: MAVLinkMessage) -> Outgoing:
        # The GCS matches answers and navigation feedback to the autopilot's ids (MAVSDK waits for the ACK
        # from the component it sent the command to); the autopilot never sees these targets, so never
        # answers them itself.
        return Outgoing(Link.GCS, msg, self.identity.own_system_id, self.identity.autopilot_component_id)

    def say_once(self, key: str, text: str, source: tuple[int, int], now_s: float) -> list[Outgoing]:
        if (key, *source) in self._said or len(self._said) >= MAX_SAID:
            return []
        self._said.add((key, *source))
        return self.reporter.statustext(mavlink.MAV_SEVERITY_NOTICE, text, now_s, key=key)
