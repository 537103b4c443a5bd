"""Simple avoidance in the command flow (pure): the bridge's own drivers stop AVOID_MARGIN short of obstacles
and FENCE_MARGIN inside fences.

The gate sits between the safety gates and the output stage (rover_bridge.command.arbiter): the twist a GCS
velocity request, MANUAL_CONTROL or a position target wants has its speed toward an obstacle or fence capped by
`avoidance.limit_velocity` before the limiter. The autopilot's own navigation is not touched (ArduPilot avoids
in it itself), nor is MANUAL unless [avoidance] in_manual (ArduPilot does not avoid in MANUAL).

- Picture: every DISTANCE_SENSOR and OBSTACLE_DISTANCE from the vehicle's system (any component, either link)
  feeds one `ObstaclePicture`, with ATTITUDE's yaw for earth-frame scans. No picture is built and nothing
  changed until the first such message: a rover without range sensors or fences drives exactly as before.
- Fences: rover_bridge.command.fence_watch (FENCE_* as read here, home, the downloaded fence, the rover's place).
- Parameters: AVOID_ENABLE (bit 1: proximity, bit 0: fences), AVOID_MARGIN, AVOID_BACKUP_SPD and FENCE_* are read
  from the autopilot (PARAM_REQUEST_READ at its first heartbeat, and after it comes back) by the ParamReader the
  GCS failsafe uses (rover_bridge.command.param_reader). Until the autopilot has said them ArduPilot's defaults
  apply (AVOID_ENABLE 3, AVOID_MARGIN 2): avoiding with the defaults is the safe side of not knowing. A lone
  unasked PARAM_VALUE is used only once the autopilot confirms it (a forged AVOID_ENABLE 0 must not switch
  avoidance off).
- The rule: the stopping speed at half the profile's max_linear_decel_m_s2, as Rover uses half ATC_DECEL_MAX
  (brakes earlier and gentler: room for a rover that brakes worse than its profile), after the reaction delay
  plus one output period. A reading `age_s` old is taken `|v| * age_s` nearer (the rover has moved since).
  AVOID_BACKUP_SPD is read and reported by the limiter, not applied: the bridge only lowers a request.
- Blind: a sensor seen and then silent caps the speed at crawl_speed_m_s in every direction, said once; so does a
  fence that is on while the rover cannot be placed on it.
- What it does is said by STATUSTEXT on each change (rate-limited) and counted (`avoid.*`, in --stats-json).
"""

from __future__ import annotations

from collections.abc import Callable

from rover_bridge.command.avoidance import AvoidReason, AvoidSettings, FenceQuery, Limited, limit_velocity
from rover_bridge.command.fence_watch import AVOID_FENCE, FENCE_PARAMS, FenceConfig, FenceWatch
from rover_bridge.command.navigation import PoseSource
from rover_bridge.command.obstacles import ObstaclePicture
from rover_bridge.command.param_reader import ParamReader
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.kinematics import Twist2D
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Link, Outgoing
from rover_bridge.params import Profile

SENSOR_MESSAGES = frozenset({"DISTANCE_SENSOR", "OBSTACLE_DISTANCE"})
AVOID_PARAMS = ("AVOID_ENABLE", "AVOID_MARGIN", "AVOID_BACKUP_SPD")
ARDUPILOT_DEFAULTS = {"AVOID_ENABLE": 3.0, "AVOID_MARGIN": 2.0, "AVOID_BACKUP_SPD": 0.75}
AVOID_PROXIMITY = 2  # AVOID_ENABLE bit 1 (bit 0: the fence, rover_bridge.command.fence_watch)
ROVER_MANUAL = int(mavlink.ROVER_MODE_MANUAL)
# What is said when a request starts being limited, once per episode (a group), not per flip between its reasons.
_GROUP = {AvoidReason.OBSTACLE_SLOW: "obstacle", AvoidReason.OBSTACLE_STOP: "obstacle",
          AvoidReason.FENCE_SLOW: "fence", AvoidReason.FENCE_STOP: "fence",
          AvoidReason.FENCE_BREACHED: "breached", AvoidReason.FENCE_UNKNOWN: "unplaced"}


class ProximityAvoidance:
    """The picture, the fences, the AVOID_* and FENCE_* parameters and the cap on the drivers' twist (module doc)."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter, vehicle: VehicleState,
                 count: Callable[[str], None], source: PoseSource | None = None) -> None:
        p = profile.avoidance
        self.params = p
        self.identity = identity
        self.reporter = reporter
        self.vehicle = vehicle
        self._count = count
        self.decel_m_s2 = 0.5 * profile.limits.max_linear_decel_m_s2  # Rover: 0.5 * ATC_DECEL_MAX
        self.delay_s = p.reaction_delay_s + 1.0 / profile.command.rate_hz
        self.picture: ObstaclePicture | None = None  # None until a sensor is seen: no cost, no change
        self.reader = ParamReader(AVOID_PARAMS + FENCE_PARAMS)
        self.fence = FenceWatch(identity, source, profile.navigation.gps_timeout_s, profile.safety.attitude_timeout_s)
        self.reason = AvoidReason.PASS  # the last output's
        self.blind = False  # a silent sensor was said
        self._settings: AvoidSettings | None = None  # as the parameters say now; None: to be worked out again

    # ----------------------------------------------------------------- inputs

    def on_sensor(self, msg: MAVLinkMessage, now_s: float) -> None:
        """A DISTANCE_SENSOR or OBSTACLE_DISTANCE (any link): the vehicle's system only."""
        if not self.params.enabled or msg.get_srcSystem() != self.identity.vehicle_system_id:
            return
        if self.picture is None:
            self.picture = ObstaclePicture(self.params.sector_timeout_s, self.params.sensor_timeout_s)
            self._count("avoid.sensor_seen")
        self.picture.handle(msg, now_s, self.vehicle.fresh_yaw(now_s))

    def autopilot_back(self, now_s: float) -> None:
        """The autopilot's first heartbeat or one after a gap (a reboot): read AVOID_* and FENCE_* again, and its
        fence and home if they are used."""
        if self.params.enabled:
            self.reader.restart(now_s)
            self._settings = None
            self.fence.refresh(now_s)

    def fence_switched(self, now_s: float) -> None:
        """The autopilot accepted MAV_CMD_DO_FENCE_ENABLE: read FENCE_* again (values kept meanwhile)."""
        if self.params.enabled:
            self.reader.refresh(now_s)

    def on_param_value(self, msg: MAVLinkMessage, now_s: float) -> None:
        # Every PARAM_VALUE passes here (a GCS's full download: hundreds): only ours change anything.
        if self.params.enabled and self.identity.from_autopilot(msg) and self.reader.on_param_value(msg, now_s):
            self._settings = None
            self.fence.configure(self.fence_config(), now_s)

    def on_home(self, msg: MAVLinkMessage) -> None:
        if self.params.enabled and self.identity.from_autopilot(msg):
            self.fence.on_home(msg)

    def on_mission(self, msg: MAVLinkMessage, now_s: float) -> tuple[bool, list[Outgoing]]:
        """A mission message from the autopilot: (consumed: it answers the bridge's own download, the messages)."""
        if not self.params.enabled or not self.identity.from_autopilot(msg):
            return False, []
        ours = self.fence.addressed_to_us(msg)
        return ours, self._to_autopilot(self.fence.on_mission(msg, now_s))

    def tick(self, now_s: float) -> list[Outgoing]:
        vehicle = self.identity.vehicle_system_id
        if vehicle is None:
            return []
        msgs: list[MAVLinkMessage] = []
        if self.reader.due(now_s):
            msgs += self.reader.requests(now_s, vehicle, self.identity.autopilot_component_id)
            self._settings = None
            self.fence.configure(self.fence_config(), now_s)  # values dropped unconfirmed
        msgs += self.fence.tick(now_s)
        return self._to_autopilot(msgs) if msgs else []

    def _to_autopilot(self, msgs: list[MAVLinkMessage]) -> list[Outgoing]:
        return [Outgoing(Link.AUTOPILOT, m, self.identity.own_system_id, self.identity.component_id) for m in msgs]

    # ----------------------------------------------------------------- the cap

    def value(self, name: str) -> float:
        """An AVOID_* parameter as used now: the autopilot's word, else ArduPilot's default."""
        said = self.reader.confirmed(name)
        return ARDUPILOT_DEFAULTS[name] if said is None else said

    def fence_config(self) -> FenceConfig | None:
        """FENCE_* and AVOID_ENABLE bit 0 as the autopilot has said them; None until it has (no fence). While one
        is unconfirmed (a lone PARAM_VALUE that changed it, or a read after the autopilot came back) the last word
        stands: a single forged FENCE_ENABLE 0 must not switch the fence off."""
        said = [self.reader.confirmed(name) for name in FENCE_PARAMS]
        if any(v is None for v in said):
            return self.fence.config
        enable, kind, radius, margin = (float(v or 0.0) for v in said)
        enabled = int(enable) == 1 and bool(int(self.value("AVOID_ENABLE")) & AVOID_FENCE)
        return FenceConfig(enabled, int(kind), radius, max(margin, 0.0))

    def settings(self) -> AvoidSettings:
        return AvoidSettings(margin_m=max(self.value("AVOID_MARGIN"), 0.0), decel_m_s2=self.decel_m_s2,
                             delay_s=self.delay_s, crawl_speed_m_s=self.params.crawl_speed_m_s,
                             backup_speed_m_s=self.value("AVOID_BACKUP_SPD"),
                             proximity=bool(int(self.value("AVOID_ENABLE")) & AVOID_PROXIMITY))

    def limit(self, target: Twist2D, now_s: float, mode: int | None,
              moving_m_s: float) -> tuple[Twist2D, list[Outgoing]]:
        """The driver's twist with its speed toward obstacles and fence edges capped (`moving_m_s`: the limiter's
        speed now)."""
        picture, fences = self.picture, self.fence.fences
        if picture is None and fences is None:
            return target, []
        if mode == ROVER_MANUAL and not self.params.in_manual:
            return target, self._said(Limited(target.v_m_s, target.omega_rad_s), now_s)
        settings = self._settings
        if settings is None:
            settings = self._settings = self.settings()
        out: list[Outgoing] = []
        view = None
        if picture is not None and settings.proximity:
            view = picture.near(now_s, abs(moving_m_s))
            out += self._blind(view.blind, now_s)
        fence: FenceQuery | None = None
        if fences is not None:
            fence = self.fence.query(now_s)
        limited = limit_velocity(target.v_m_s, target.omega_rad_s, settings, view, fence, with_backup=False,
                                 fence_unplaced=fences is not None and fence is None)
        out += self._said(limited, now_s)
        if limited.v_m_s == target.v_m_s:
            return target, out
        return Twist2D(limited.v_m_s, target.omega_rad_s), out

    # ----------------------------------------------------------------- saying it

    def _said(self, limited: Limited, now_s: float) -> list[Outgoing]:
        reason = limited.reason
        if reason is self.reason:
            return []
        group, before = _GROUP.get(reason), _GROUP.get(self.reason)
        self.reason = reason
        self._count(f"avoid.{reason.value}")
        if group is None or group == before:
            return []
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, self._text(reason, now_s), now_s,
                                        key=f"avoid.{group}")

    def _text(self, reason: AvoidReason, now_s: float) -> str:
        if reason is AvoidReason.FENCE_BREACHED:
            return "RB: outside the fence: only the way back in"
        if reason is AvoidReason.FENCE_UNKNOWN:
            cause = self.fence.unplaced(now_s)
            return f"RB: fence on, {cause}: crawling ({self.params.crawl_speed_m_s:g} m/s)"
        if reason in (AvoidReason.FENCE_SLOW, AvoidReason.FENCE_STOP):
            config = self.fence.config
            margin_m = 0.0 if config is None else config.margin_m
            return f"RB: fence ahead: slowing to stop {margin_m:g} m inside"
        return f"RB: obstacle ahead: slowing to stop {self.value('AVOID_MARGIN'):g} m short"

    def _blind(self, blind: bool, now_s: float) -> list[Outgoing]:
        if blind == self.blind:
            return []
        self.blind = blind
        self._count("avoid.sensor_silent" if blind else "avoid.sensor_back")
        if blind:
            text = f"RB: proximity sensor silent: crawling ({self.params.crawl_speed_m_s:g} m/s)"
            return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, text, now_s, key="avoid.blind")
        return self.reporter.statustext(mavlink.MAV_SEVERITY_INFO, "RB: proximity sensor back", now_s,
                                        key="avoid.blind")
