"""Who the bridge is on the MAVLink network, and which vehicle it serves (pure state)."""

from __future__ import annotations

from dataclasses import dataclass, field

from rover_bridge.mavlink.dialect import mavlink
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
    _seen: set[int] = field(default_factory=set)

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

    def is_autopilot_heartbeat(self, msg: mavlink.MAVLink_heartbeat_message) -> bool:
        """True for a heartbeat from the vehicle's autopilot (learning the system id on the first one)."""
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in _NOT_A_VEHICLE:
            return False
        src_system = msg.get_srcSystem()
        if self.configured_system_id:
            return bool(src_system == self.configured_system_id)
        if self.learned_system_id is None:
            self.learned_system_id = src_system
            self.autopilot_component_id = msg.get_srcComponent()
        return bool(src_system == self.learned_system_id)
