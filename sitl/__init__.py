"""sitl: a loopback autopilot emulator that behaves like ArduPilot Rover on a diff-drive robot.

It never imports ``rover_bridge``: it is the independent ground truth the bridge is judged
against. Conventions (NED world, yaw clockwise from north, yaw rate clockwise positive) are
documented in ``sitl.physics``; MAVLink behaviour and its ArduPilot sources in
``sitl.autopilot``.

In-process use::

    from sitl import Emulator, VehicleConfig
    emu = Emulator(vehicle=VehicleConfig(start_armed=True), seed=0)
    emu.open("udpin:127.0.0.1:14551")
    emu.step(0.01)          # lockstep: read, advance physics, send what is due
    emu.truth.x_m
    emu.close()

Rover's own navigation (missions in AUTO, RTL, SMART_RTL, fence and failsafe actions) is in
``sitl.rover`` and the modules it names; ``sitl.gcs.InProcessGcs`` is a scripted ground station for an
in-process emulator (missions, modes, commands).
"""

from sitl.autopilot import MODE_GUIDED, MODE_HOLD, MODE_MANUAL, Autopilot, ReceivedMessage
from sitl.config import ConfigError, VehicleConfig, load_vehicle
from sitl.emulator import Emulator
from sitl.endpoint import ConnectionStringError, PortInUseError
from sitl.faults import FaultConfig, LinkFaults
from sitl.gcs import InProcessGcs
from sitl.physics import PhysicsState, TruthState
from sitl.scenario import Scenario, load_scenario

__all__ = [
    "MODE_GUIDED",
    "MODE_HOLD",
    "MODE_MANUAL",
    "Autopilot",
    "ConfigError",
    "ConnectionStringError",
    "Emulator",
    "FaultConfig",
    "InProcessGcs",
    "LinkFaults",
    "PhysicsState",
    "PortInUseError",
    "ReceivedMessage",
    "Scenario",
    "TruthState",
    "VehicleConfig",
    "load_scenario",
    "load_vehicle",
]
