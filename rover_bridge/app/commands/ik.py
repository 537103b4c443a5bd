"""rover-bridge ik --params FILE [--v M_S] [--omega RAD_S]: the wheel speeds a twist request becomes.

The table a person checks when a new robot first moves: for each (v, omega) request, the
wheel speeds that will be commanded (after desaturation to max_wheel_rpm), whether they
had to be scaled down, and the twist the robot then actually gets. The [limits] section is
not applied here (it shapes how fast requests change, not the geometry).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from rover_bridge.app.commands import add_params_argument
from rover_bridge.errors import ConfigError
from rover_bridge.kinematics import DiffDrive, Twist2D, WheelSpeeds, rad_s_to_rpm
from rover_bridge.params import Profile, load_profile

NAME = "ik"
HELP = "print the wheel speeds (rad/s, RPM) for a grid of (v, omega) requests, or one, for a profile"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_params_argument(parser, required=True)
    parser.add_argument("--v", type=float, default=None, metavar="M_S",
                        help="one forward speed request [m/s]")
    parser.add_argument("--omega", type=float, default=None, metavar="RAD_S",
                        help="one yaw rate request [rad/s], counter-clockwise positive")


@dataclass(frozen=True, slots=True)
class IkRow:
    requested: Twist2D
    wheels: WheelSpeeds  # what is commanded, after desaturation
    scale: float  # common factor desaturation applied (1.0 = untouched)
    achieved: Twist2D


def solve(dd: DiffDrive, max_wheel_rad_s: float, request: Twist2D) -> IkRow:
    raw = dd.to_wheel_speeds(request)
    wheels = raw.desaturate(max_wheel_rad_s)
    largest = max(abs(raw.left_rad_s), abs(raw.right_rad_s))
    scale = 1.0 if wheels is raw or largest == 0.0 else max_wheel_rad_s / largest
    return IkRow(requested=request, wheels=wheels, scale=scale, achieved=dd.to_twist(wheels))


def grid(profile: Profile) -> list[Twist2D]:
    """Requests at 0, +-half and +-full of the [limits] maxima, both axes."""
    v_max = profile.limits.max_linear_m_s
    w_max = profile.limits.max_angular_rad_s
    fractions = (1.0, 0.5, 0.0, -0.5, -1.0)
    return [Twist2D(v_m_s=fv * v_max, omega_rad_s=fw * w_max) for fv in fractions for fw in fractions]


def format_table(profile: Profile, rows: list[IkRow]) -> str:
    r = profile.robot
    lines = [
        f"# geometry: left radius {r.left_radius_m:g} m, right radius {r.right_radius_m:g} m, "
        f"track {r.track_width_m:g} m",
        f"# wheel limit: {r.max_wheel_rpm:g} RPM = {r.max_wheel_rad_s:.4f} rad/s "
        f"(left {r.max_wheel_rad_s * r.left_radius_m:.4f} m/s, "
        f"right {r.max_wheel_rad_s * r.right_radius_m:.4f} m/s)",
        "# omega is counter-clockwise positive; wheel speeds are after desaturation (one common scale)",
        f"{'v_m_s':>9} {'omega_rad_s':>11} | {'left_rad_s':>10} {'right_rad_s':>11} {'left_rpm':>9} "
        f"{'right_rpm':>9} | {'clamped':>13} | {'got_v_m_s':>9} {'got_omega':>9}",
    ]
    for row in rows:
        w = row.wheels
        clamped = f"yes (x{row.scale:.3f})" if row.scale < 1.0 else "no"
        lines.append(
            f"{row.requested.v_m_s:9.3f} {row.requested.omega_rad_s:11.3f} | {w.left_rad_s:10.3f} "
            f"{w.right_rad_s:11.3f} {rad_s_to_rpm(w.left_rad_s):9.2f} {rad_s_to_rpm(w.right_rad_s):9.2f} | "
            f"{clamped:>13} | {row.achieved.v_m_s:9.3f} {row.achieved.omega_rad_s:9.3f}")
    return "\n".join(lines) + "\n"


def main(args: argparse.Namespace) -> int:
    profile = load_profile(args.params)  # ConfigError -> cli prints every problem, exit 2
    problems = [f"--{name}: expected a finite number, got {value!r}"
                for name, value in (("v", args.v), ("omega", args.omega))
                if value is not None and not math.isfinite(value)]
    if problems:
        raise ConfigError(problems)
    dd = DiffDrive.from_params(profile.robot)
    if args.v is None and args.omega is None:
        requests = grid(profile)
    else:
        requests = [Twist2D(v_m_s=args.v or 0.0, omega_rad_s=args.omega or 0.0)]
    rows = [solve(dd, profile.robot.max_wheel_rad_s, t) for t in requests]
    print(f"# {args.params}")
    print(format_table(profile, rows), end="")
    return 0
