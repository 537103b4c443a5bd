"""The emulator's own MAVLink import point (it must never import ``rover_bridge``).

pymavlink chooses MAVLink 1 or 2 from the MAVLINK20 environment variable at import time, so
it is set here before pymavlink is imported. The ardupilotmega dialect holds everything the
emulator speaks: common.xml (WHEEL_DISTANCE 9000, ODOMETRY 331) plus SIMSTATE (164).
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

mavutil.set_dialect("ardupilotmega")

MAVLinkMessage = mavlink.MAVLink_message

__all__ = ["MAVLinkMessage", "mavlink", "mavutil"]
