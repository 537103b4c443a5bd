"""rover-bridge: a MAVLink 2 companion bridge for differential-drive rovers.

The public math (kinematics, limits, odometry, frames) and the profile (params, errors) live at the
top level; command/ and estimate/ are the two flows' pure cores, mavlink/ the protocol edge, app/ the
composition and the process around it. Dependencies point one way: math <- mavlink <- flows <- app.
"""

__version__ = "0.1.0"
