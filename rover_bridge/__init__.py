"""rover-bridge: a MAVLink 2 companion bridge for differential-drive rovers.

The public math (kinematics, limits, odometry, frames) and the profile (params, errors) live at the
top level; command/ and estimate/ are the two flows' pure cores, mavlink/ the protocol edge, app/ the
composition and the process around it, fleet/ the report over many logs (replayed through app's replay).
Dependencies point one way: math <- mavlink <- flows <- app <- fleet <- the CLI (app/cli.py, app/commands/).
"""

__version__ = "0.1.0"
