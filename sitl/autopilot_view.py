"""The autopilot as its message handlers see it (sitl/incoming.py, sitl/commands.py, sitl/messages.py).

sitl.autopilot.Autopilot calls those handlers with itself; they name its type through this Protocol, not
through sitl.autopilot, so that no handler module and the autopilot import each other. mypy checks that
Autopilot is an AutopilotView wherever it passes itself.
"""

from __future__ import annotations

from typing import Protocol

from sitl.config import VehicleConfig
from sitl.extnav import ExtNavConsumer
from sitl.fence_store import FenceStore
from sitl.mav import MAVLinkMessage, mavlink
from sitl.mission import Mission
from sitl.mission_protocol import MissionProtocol
from sitl.obstacles import Shape
from sitl.params import Param
from sitl.physics import PhysicsState
from sitl.rc import RcServos
from sitl.rover import Rover
from sitl.streams import Streams


class AutopilotView(Protocol):
    """What the handlers read, call and set on the autopilot (each member is Autopilot's, same meaning)."""

    vehicle: VehicleConfig
    mav: mavlink.MAVLink
    system_id: int
    component_id: int
    params: dict[str, Param]
    outbox: list[MAVLinkMessage]
    rc: RcServos
    streams: Streams
    mission: Mission
    fence: FenceStore
    obstacles: tuple[Shape, ...]
    armed: bool
    boot_us: int
    extnav: ExtNavConsumer
    rover: Rover
    protocol: MissionProtocol

    @property
    def mode(self) -> int: ...

    @property
    def rebooting(self) -> bool: ...

    @property
    def now_us(self) -> int: ...

    @property
    def extnav_position_source(self) -> bool: ...

    def time_boot_ms(self, now_us: int) -> int: ...

    def param(self, name: str) -> float: ...

    def set_param(self, name: str, value: float) -> bool: ...

    def param_value_msg(self, name: str) -> MAVLinkMessage: ...

    def count(self, name: str, n: int = 1) -> None: ...

    def send_text(self, severity: int, text: str) -> None: ...

    def lat_lon_of(self, north_m: float, east_m: float) -> tuple[float, float]: ...

    def mission_current_msg(self, seq: int) -> MAVLinkMessage: ...

    def has_position(self) -> bool: ...

    def heading_rad(self, s: PhysicsState) -> float: ...

    def rc_inputs(self, now_us: int) -> dict[int, int]: ...

    def _set_override(self, ch: int, pwm: int, now_us: int) -> None: ...

    def servo_outputs(self) -> dict[int, int]: ...

    def wheel_distances_m(self, physics: PhysicsState) -> tuple[float, float]: ...

    def take_odometry(self, msg: MAVLinkMessage, now_us: int) -> None: ...

    def start_reboot(self, now_us: int) -> None: ...
