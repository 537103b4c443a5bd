"""Who the bridge is on the MAVLink network, and which vehicle it serves (pure state)."""

from __future__ import annotations

from dataclasses import dataclass

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.params import Profile

# Autopilot types we take a vehicle heartbeat from; GCSs and companions also send HEARTBEAT.
_NOT_A_VEHICLE = {mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL,
                  mavlink.MAV_TYPE_ADSB, mavlink.MAV_TYPE_CAMERA}


@dataclass
class Identity:
    """Shared by the command and estimate cores: the vehicle's ids and the bridge's own."""

    configured_system_id: int = 0  # 0: learn from the autopilot's heartbeat
    component_id: int = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
    override_source_system: int = 255
    learned_system_id: int | None = None
    autopilot_component_id: int = 1
    _autopilot_learnt: bool = False
    _autopilot_confirmed: bool = False  # its heartbeat came more than once: no single (forged) frame
    _learnt_from: object = None  # the heartbeat it was learnt from (both cores ask about each one)

    @classmethod
    def from_profile(cls, profile: Profile) -> Identity:
        return cls(configured_system_id=profile.mavlink.vehicle_system_id,
                   component_id=profile.mavlink.component_id,
                   override_source_system=profile.output.override_source_system)

    @property
    def vehicle_system_id(self) -> int | None:
        """The vehicle's system id, or None while it is still unknown."""
        return self.configured_system_id or self.learned_system_id

    @property
    def own_system_id(self) -> int:
        """System id of the bridge's own messages: the vehicle's (it is part of the vehicle)."""
        return self.vehicle_system_id or 1

    def from_autopilot(self, msg: MAVLinkMessage) -> bool:
        """Sent by the vehicle's autopilot (its system and component as learnt): not a companion, a peripheral or
        another vehicle."""
        return bool(msg.get_srcSystem() == self.vehicle_system_id
                    and msg.get_srcComponent() == self.autopilot_component_id)

    def addressed_to_bridge(self, msg: MAVLinkMessage) -> bool:
        """Addressed to the bridge itself (an answer to its own request): not a ground station's business."""
        return bool(getattr(msg, "target_system", None) == self.own_system_id
                    and getattr(msg, "target_component", None) == self.component_id)

    def is_autopilot_heartbeat(self, msg: mavlink.MAVLink_heartbeat_message, relearn: bool = False) -> bool:
        """True for a heartbeat from the vehicle's autopilot: the system and component of the first vehicle
        heartbeat (of the configured system, if one is), learnt then. `relearn` (the caller's: the autopilot's
        heartbeat is lost) lets another vehicle heartbeat take the place of one heard only once, so that a first
        heartbeat that was a corrupted or forged frame does not shut the real autopilot out for good; one heard
        twice keeps it. Any other component of the system (a companion, a peripheral, a forged frame) is not the
        autopilot: its mode and arming say nothing."""
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in _NOT_A_VEHICLE:
            return False
        src_system, src_component = msg.get_srcSystem(), msg.get_srcComponent()
        if self.configured_system_id and src_system != self.configured_system_id:
            return False
        learnt = self._autopilot_learnt or self.learned_system_id is not None
        if not learnt or (relearn and not self._autopilot_confirmed):
            if not self.configured_system_id:
                self.learned_system_id = src_system
            self.autopilot_component_id = src_component
            self._autopilot_learnt, self._learnt_from = True, msg
            return True
        ours = bool(src_system == self.vehicle_system_id and src_component == self.autopilot_component_id)
        if ours and msg is not self._learnt_from:
            self._autopilot_confirmed, self._learnt_from = True, None
        return ours
