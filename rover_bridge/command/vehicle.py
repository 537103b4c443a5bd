"""What the autopilot says of itself (pure): alive, armed, its mode, its heading; and the modes a GCS asked for.

- Alive: its HEARTBEAT (from the vehicle's autopilot component) is younger than safety.heartbeat_timeout_s.
- Armed: MAV_MODE_FLAG_SAFETY_ARMED in that heartbeat.
- Mode: the heartbeat's custom_mode; after a GCS's DO_SET_MODE that the autopilot ACKed as accepted, the mode
  it asked for, until the next heartbeat (ArduPilot sends one at once after a mode change) says it. Heartbeats
  and ACKs count only from the autopilot's own system and component (rover_bridge.mavlink.identity).
- A stop mode a GCS asked for (SET_MODE or DO_SET_MODE) counts at once: the heartbeat that reports it may be
  a second away, and a Hold button must stop now. The heartbeat takes over after HOLD_ANTICIPATION_S unless
  the autopilot refused the mode, or as soon as it reports the stop mode itself.
- Heading: ATTITUDE.yaw (clockwise from north) from the vehicle's autopilot, fresh for
  safety.attitude_timeout_s; a non-finite yaw is counted and ignored.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.params import Profile

# A ground station's request for a stop mode stops the rover at once; the autopilot's heartbeat (1 Hz,
# possibly one already in flight) takes over after this long unless the autopilot refused the mode.
HOLD_ANTICIPATION_S = 1.5
_ACK_OK = (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)


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


class VehicleState:
    """The autopilot's heartbeat, mode and heading as the command flow needs them (module doc)."""

    def __init__(self, profile: Profile, identity: Identity, stop_modes: frozenset[int],
                 count: Callable[[str], None]) -> None:
        self.identity = identity
        self.heartbeat_timeout_s = profile.safety.heartbeat_timeout_s
        self.attitude_timeout_s = profile.safety.attitude_timeout_s
        self.stop_modes = stop_modes
        self._count = count
        self.last_heartbeat_s: float | None = None
        self.armed = False
        self.custom_mode: int | None = None  # the heartbeat's
        self.anticipated_mode: int | None = None  # an accepted DO_SET_MODE's, until the next heartbeat
        self.driving_mode: int | None = None  # see anticipate(); kept, not computed: read on every output
        self.mode_requested: int | None = None  # the last mode a GCS's DO_SET_MODE asked for
        self.hold_requested_s: float | None = None  # a GCS asked for a stop mode; not yet reported
        self.yaw_cw_rad: float | None = None
        self.yaw_s: float | None = None

    @property
    def mode(self) -> int | None:
        """The mode as best known now: an accepted change the heartbeat has not reported yet, else the heartbeat's."""
        return self.anticipated_mode if self.anticipated_mode is not None else self.custom_mode

    def anticipate(self, mode: int | None) -> None:
        """The mode an accepted DO_SET_MODE asked for (None: the heartbeat's from now on). driving_mode, the mode
        that picks the driver, follows it, except that a change to a stop mode is left to the stop's own
        anticipation (`stopping`), which lapses if the heartbeat does not confirm it."""
        self.anticipated_mode = mode
        self.driving_mode = mode if mode is not None and mode not in self.stop_modes else self.custom_mode

    def link_lost(self, now_s: float) -> bool:
        # Same expression as the deadlines: `now - last >= timeout` can round below the timeout at exactly
        # that deadline, and the shell would wake again and again for a tick that does nothing.
        last = self.last_heartbeat_s
        return last is not None and now_s >= last + self.heartbeat_timeout_s

    def on_heartbeat(self, msg: MAVLinkMessage, now_s: float) -> None:
        self.last_heartbeat_s = now_s
        self.armed = bool(int(msg.base_mode) & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        self.custom_mode = int(msg.custom_mode)
        self.anticipate(None)  # the heartbeat says the mode from now on
        if self.custom_mode in self.stop_modes:
            self.hold_requested_s = None  # reported: from now on the heartbeat says when it ends

    def stopping(self, now_s: float) -> bool:
        """In a stop mode, or a GCS asked for one (anticipated until the heartbeat governs again)."""
        requested = self.hold_requested_s
        if requested is not None and now_s >= requested + HOLD_ANTICIPATION_S:
            self.hold_requested_s = requested = None
        return self.custom_mode in self.stop_modes or requested is not None

    def on_mode_request(self, msg: MAVLinkMessage, now_s: float) -> bool:
        """A GCS asks for a mode (forwarded as is by the caller): True if it is a stop mode, acted on at once."""
        mode = requested_custom_mode(msg, self.identity.vehicle_system_id)
        if mode is not None and msg.get_type() != "SET_MODE":
            self.mode_requested = mode  # its ACK tells whether the autopilot took it
        if mode is None or mode not in self.stop_modes:
            return False
        self.hold_requested_s = now_s
        self._count("hold.requested")
        return True

    def on_mode_ack(self, result: int) -> None:
        """The autopilot's COMMAND_ACK to a DO_SET_MODE (not the bridge's own)."""
        if self.hold_requested_s is not None and result not in _ACK_OK:
            self.hold_requested_s = None  # the autopilot refused the stop mode: its heartbeat governs
        if result == mavlink.MAV_RESULT_ACCEPTED and self.mode_requested is not None:
            self.anticipate(self.mode_requested)  # a GCS's mode change, before its heartbeat
            self.mode_requested = None

    def on_attitude(self, msg: MAVLinkMessage, now_s: float) -> None:
        if not self.identity.from_autopilot(msg):
            return
        yaw = float(msg.yaw)
        if not math.isfinite(yaw):
            self._count("attitude.non_finite")
            return
        self.yaw_cw_rad, self.yaw_s = yaw, now_s

    def fresh_yaw(self, now_s: float) -> float | None:
        if self.yaw_s is None or now_s - self.yaw_s >= self.attitude_timeout_s:
            return None
        return self.yaw_cw_rad
