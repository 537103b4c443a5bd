"""The command flow (pure): requests -> limits -> inverse kinematics -> wheel outputs, with every safe stop.
setpoints decodes requests, outputs maps wheel speeds to PWM messages, core (CommandCore) decides.
May import: the top-level math, params, errors and the pure parts of mavlink. Never estimate, app or links.
"""
