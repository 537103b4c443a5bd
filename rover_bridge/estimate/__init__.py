"""The estimate flow (pure): wheel distances + gyro -> EKF -> ODOMETRY, with stream requests and clock mapping.
wheel_input checks encoder readings, ekf is the filter, core (EstimateCore) wires the small collaborators.
May import: the top-level math, params, errors and the pure parts of mavlink. Never command, app or links.
"""
