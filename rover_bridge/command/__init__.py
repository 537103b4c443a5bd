"""The command flow (pure): drivers (GCS requests, position targets, the autopilot's own navigation) -> limits ->
inverse kinematics -> wheel speed loop -> wheel outputs, with every safe stop. core (CommandCore) only wires the
parts: vehicle, modes, drivers, safety, arbiter, output_stage, stopping (each module says its rules).
May import: the top-level math, params, errors and the pure parts of mavlink. Never estimate, app or links.
"""
