"""The one place that chooses the MAVLink wire protocol and dialect.

pymavlink picks MAVLink 1 or 2 from the MAVLINK20 environment variable at import time, so it
is set here, before anything imports pymavlink. Every module of the package imports MAVLink
through this module. The ardupilotmega dialect includes common.xml (WHEEL_DISTANCE 9000,
ODOMETRY 331) plus the ArduPilot messages the emulator speaks (SIMSTATE).
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

mavutil.set_dialect("ardupilotmega")

MAVLinkMessage = mavlink.MAVLink_message

__all__ = ["MAVLinkMessage", "mavlink", "mavutil"]
