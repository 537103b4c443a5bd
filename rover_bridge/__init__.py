"""rover-bridge: a MAVLink 2 companion bridge for differential-drive rovers.

Pure core (kinematics, limits, odometry, estimator, setpoints, outputs, bridge) with no
sockets, no clocks and no threads; a thin shell (links, runner, cli) does the I/O.
"""

__version__ = "0.1.0"
