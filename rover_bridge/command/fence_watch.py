"""The autopilot's fences as the bridge's drivers must keep them, and where the rover is on them (pure).

ArduPilot's simple avoidance stops the rover FENCE_MARGIN inside its fences when FENCE_ENABLE is set and
AVOID_ENABLE has bit 0 (AC_Avoid::adjust_velocity_fence). What the bridge needs for the same:

- FENCE_ENABLE, FENCE_TYPE (2: the circle, 4: the stored polygons and circles), FENCE_RADIUS and FENCE_MARGIN, read
  from the autopilot by the avoidance's ParamReader (rover_bridge.command.proximity), given here as `FenceConfig`;
  a COMMAND_ACK accepting MAV_CMD_DO_FENCE_ENABLE reads them again.
- Home (the circle's centre, the polygons' origin): HOME_POSITION, asked for with MAV_CMD_REQUEST_MESSAGE every
  HOME_RETRY_S while it is unknown and a fence is on, and taken whenever the autopilot sends it (a new home).
- The stored fence (FENCE_TYPE bit 2): downloaded with the mission protocol (rover_bridge.command.fence_download)
  when the fence goes on, when the autopilot comes back, and when the autopilot accepts a ground station's fence
  upload or clear (its MISSION_ACK of type FENCE passes through the bridge), and every STORED_REFRESH_S while it is
  used (an upload on another link passes no MISSION_ACK through the bridge).
- Where the rover is: the bridge's own estimate, anchored to the autopilot's GLOBAL_POSITION_INT: the fix's
  north/east from home, plus how far the estimate has moved since the fix's stamp (rotated to north by ATTITUDE's
  heading, as the go-to does). With no fresh fix (navigation.gps_timeout_s), no estimate, no heading or no home,
  the position is unknown: `query` says None and the caller crawls (rover_bridge.command.proximity).
"""

from __future__ import annotations

from dataclasses import dataclass

from rover_bridge.command.avoidance import FenceQuery
from rover_bridge.command.fence_download import TYPE_FENCE, FenceDownload
from rover_bridge.command.fences import CircleFence, Fences, PolygonFence, stored_fences
from rover_bridge.command.navigation import PoseSource, heading_anchor
from rover_bridge.frames import ne_from_lat_lon
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity

FENCE_PARAMS = ("FENCE_ENABLE", "FENCE_TYPE", "FENCE_RADIUS", "FENCE_MARGIN")
FENCE_TYPE_CIRCLE = 2
FENCE_TYPE_POLYGON = 4
AVOID_FENCE = 1  # AVOID_ENABLE bit 0
HOME_RETRY_S = 2.0
# The stored fence is downloaded again this often while it is used: a ground station on another link (a radio
# straight to the autopilot) or the old FENCE_POINT protocol changes it without a MISSION_ACK passing the bridge.
STORED_REFRESH_S = 10.0
MISSION_MESSAGES = frozenset({"MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK"})


@dataclass(frozen=True, slots=True)
class FenceConfig:
    """What the autopilot's parameters say of its fences (FENCE_ENABLE with AVOID_ENABLE bit 0: `enabled`)."""

    enabled: bool
    type_bits: int
    radius_m: float
    margin_m: float

    @property
    def circle(self) -> bool:
        return self.enabled and bool(self.type_bits & FENCE_TYPE_CIRCLE) and self.radius_m > 0.0

    @property
    def stored(self) -> bool:
        return self.enabled and bool(self.type_bits & FENCE_TYPE_POLYGON)


class FenceWatch:
    """The fence's configuration, home, the stored fence and the rover's place on them (module doc)."""

    def __init__(self, identity: Identity, source: PoseSource | None, gps_timeout_s: float,
                 heading_timeout_s: float) -> None:
        self.identity = identity
        self.source = source
        self.gps_timeout_s = gps_timeout_s
        self.heading_timeout_s = heading_timeout_s
        self.download = FenceDownload()
        self.config: FenceConfig | None = None
        self.home: tuple[float, float] | None = None  # lat, lon deg
        self.fences: Fences | None = None  # what limits the drivers now; None: no fence to keep
        self._home_next_s: float | None = None

    @property
    def wanted(self) -> bool:
        config = self.config
        return config is not None and (config.circle or config.stored)

    @property
    def known(self) -> bool:
        """Home is known, and the stored fence downloaded if it is used: the fences can be placed."""
        config = self.config
        return self.home is not None and not (config is not None and config.stored and self.download.items is None)

    def configure(self, config: FenceConfig | None, now_s: float) -> None:
        """The parameters as read now (None: not known yet, so no fence: ArduPilot's FENCE_ENABLE default is 0)."""
        if config == self.config:
            return
        self.config = config
        if config is not None and config.stored and self.download.items is None and not self.download.running:
            self.download.start(now_s)
        if self.wanted and self.home is None and self._home_next_s is None:
            self._home_next_s = now_s
        self._build()

    def refresh(self, now_s: float) -> None:
        """The fence may have changed (an upload accepted, the autopilot back): download it again if it is used."""
        if self.config is not None and self.config.stored:
            self.download.start(now_s)
        if self.wanted:
            self._home_next_s = now_s  # a rebooted autopilot may have a new home

    def on_home(self, msg: MAVLinkMessage) -> None:
        self.home = (msg.latitude * 1e-7, msg.longitude * 1e-7)
        self._home_next_s = None
        self._build()

    def addressed_to_us(self, msg: MAVLinkMessage) -> bool:
        """A mission message of type FENCE for the bridge (its own download): the caller consumes it."""
        return int(getattr(msg, "mission_type", 0)) == TYPE_FENCE and self.identity.addressed_to_bridge(msg)

    def on_mission(self, msg: MAVLinkMessage, now_s: float) -> list[MAVLinkMessage]:
        """MISSION_COUNT / MISSION_ITEM_INT / MISSION_ACK from the autopilot: ours go to the download; another
        client's accepted fence upload or clear means the fence changed."""
        if self.addressed_to_us(msg):
            version = self.download.version
            out = self.download.on_message(msg, now_s, self._autopilot())
            if self.download.version != version:
                self._build()
            return out
        if (msg.get_type() == "MISSION_ACK" and int(getattr(msg, "mission_type", 0)) == TYPE_FENCE
                and int(msg.type) == mavlink.MAV_MISSION_ACCEPTED):
            self.refresh(now_s)
        return []

    def tick(self, now_s: float) -> list[MAVLinkMessage]:
        if self.identity.vehicle_system_id is None:
            return []
        out: list[MAVLinkMessage] = []
        done_s = self.download.done_s
        if (self.config is not None and self.config.stored and not self.download.running and done_s is not None
                and now_s - done_s >= STORED_REFRESH_S):
            self.download.start(now_s)
        if self.download.due(now_s):
            out += self.download.requests(now_s, self._autopilot())
        if self._home_next_s is not None and now_s >= self._home_next_s and self.wanted and self.home is None:
            self._home_next_s = now_s + HOME_RETRY_S
            target = self._autopilot()
            out.append(mavlink.MAVLink_command_long_message(
                target[0], target[1], mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                float(mavlink.MAVLINK_MSG_ID_HOME_POSITION), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        return out

    def query(self, now_s: float) -> FenceQuery | None:
        """The fences and the rover on them now; None while the position is unknown (module doc)."""
        fences, home, source = self.fences, self.home, self.source
        if fences is None or home is None or source is None or not self.known:
            return None
        gps = source.gps
        if gps is None or now_s - gps[0] > self.gps_timeout_s:
            return None
        pose = source.nav_pose(now_s)
        anchor = heading_anchor(source, now_s, self.heading_timeout_s)
        if pose is None or anchor is None:
            return None
        _, stamp, lat, lon = gps
        fix_n, fix_e = ne_from_lat_lon(home[0], home[1], lat, lon)
        at = source.nav_pose_at(stamp)
        then = anchor.to_ned(at.x_m, at.y_m, at.yaw_rad)
        now = anchor.to_ned(pose.x_m, pose.y_m, pose.yaw_rad)
        return FenceQuery(fences, fix_n + now.north_m - then.north_m, fix_e + now.east_m - then.east_m,
                          now.yaw_cw_rad)

    def unplaced(self, now_s: float) -> str:
        """Why `query` says None now, in a few words for the STATUSTEXT."""
        source = self.source
        if self.home is None:
            return "no home yet"
        if not self.known:
            return "fence not downloaded yet"
        if source is None or source.nav_pose(now_s) is None:
            return "no position estimate"
        gps = source.gps
        if gps is None or now_s - gps[0] > self.gps_timeout_s:
            return "no GPS fix"
        return "no heading"

    def _autopilot(self) -> tuple[int, int]:
        vehicle = self.identity.vehicle_system_id
        return (0 if vehicle is None else vehicle), self.identity.autopilot_component_id

    def _build(self) -> None:
        config = self.config
        if config is None or not (config.circle or config.stored):
            self.fences = None
            return
        circle = CircleFence(config.radius_m) if config.circle else None
        items = self.download.items
        polygons: tuple[PolygonFence, ...] = ()
        circles: tuple[CircleFence, ...] = ()
        if config.stored and items and self.home is not None:
            points = [(i.command, i.param1, i.lat_e7 * 1e-7, i.lon_e7 * 1e-7) for i in items]
            polygons, circles = stored_fences(points, *self.home)
        self.fences = Fences(config.margin_m, circle, polygons, circles)
