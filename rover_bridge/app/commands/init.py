"""rover-bridge init PATH: write a commented profile to start a rover of one's own from.

It asks nothing: every value is the declared default (rover_bridge/params.py, the one place the parameters
are declared), so the file loads as it is. The comments say which values must be measured on the rover and
how to check them (`check-params`, `ik`, `calibrate`) before it drives by itself.
"""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

from rover_bridge import __version__
from rover_bridge.app.paths import output_problem
from rover_bridge.errors import ConfigError
from rover_bridge.params import ParamInfo, iter_params, toml_value

NAME = "init"
HELP = "write a commented robot profile to start from (the values to measure on the rover are marked)"

# The keys the file holds, and what to do about each: MEASURE on the rover, CHECK against it, or CHOOSE.
# Everything else keeps its declared default (check-params shows them all).
TODO: dict[str, str] = {
    "robot.wheel_radius_m": "MEASURE: half the loaded wheel's diameter (or: roll 10 turns, distance / (20 pi))",
    "robot.track_width_m": "MEASURE: centre of the left tyre's contact to centre of the right's "
                           "(`calibrate` measures the effective one)",
    "robot.max_wheel_rpm": "MEASURE: wheel speed at full PWM, wheels off the ground (motor rpm / gear ratio); "
                           "`calibrate` measures it",
    "limits.max_linear_m_s": "CHOOSE: the fastest the bridge will drive; keep it under the wheels' top speed",
    "limits.max_angular_rad_s": "CHOOSE: the fastest the bridge will turn",
    "limits.max_linear_accel_m_s2": "CHOOSE: lower it if the rover wheelies or slips when it starts",
    "limits.max_linear_decel_m_s2": "CHOOSE: how hard a stop brakes (timeouts, link loss, exit)",
    "output.left_channel": "MEASURE: the RC channel whose passthrough output drives the left motor "
                           "(SERVOn_FUNCTION = 50 + channel, e.g. 51 = RCIN1 -> 1)",
    "output.right_channel": "MEASURE: as left_channel, for the right motor (53 = RCIN3 -> 3)",
    "output.pwm_min": "CHECK: your ESC's full-reverse pulse",
    "output.pwm_trim": "CHECK: your ESC's stop pulse",
    "output.pwm_max": "CHECK: your ESC's full-forward pulse",
    "output.left_reversed": "CHECK with `ik` (wheels off the ground): true if pwm_max turns the left wheel back",
    "output.right_reversed": "CHECK with `ik`, as left_reversed",
    "encoders.left_index": "MEASURE: which WHEEL_DISTANCE.distance[] is the left wheel (WENC = 0, WENC2 = 1, as "
                           "wired); a spin in place tells (`calibrate` checks it)",
    "encoders.right_index": "MEASURE: as left_index, for the right wheel",
    "encoders.left_reversed": "CHECK: true if the left distance falls while the wheel drives forward",
    "encoders.right_reversed": "CHECK: as left_reversed",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", metavar="PATH", help="where to write the profile, e.g. my-rover.toml")
    parser.add_argument("--force", action="store_true", help="overwrite PATH if it exists")


def _comment(text: str) -> list[str]:
    return textwrap.wrap(text, width=110, initial_indent="# ", subsequent_indent="#   ")


def _key_lines(info: ParamInfo, todo: str) -> list[str]:
    """What to do, what the key means (unit, valid range: from its declaration), then the key."""
    unit = f" [{info.spec.unit}]" if info.spec.unit else ""
    valid = f" Valid: {info.range_text}." if info.range_text else ""
    return [*_comment(todo), *_comment(f"{info.spec.help}{unit}{valid}"), f"{info.name} = {toml_value(info.default)}"]


def profile_template(path: str) -> str:
    """The commented profile ``init`` writes (``path`` only appears in the commands it suggests)."""
    lines = [
        f"# rover-bridge robot profile, written by `rover-bridge init` ({__version__}). It loads as it is:",
        "# every value below is the default (the packaged example rover's, `rover-bridge check-params default`).",
        "#",
        "# Before the rover drives by itself, set the values marked MEASURE to your rover's, and look at the",
        "# ones marked CHECK and CHOOSE. Then, in this order:",
        f"#   rover-bridge check-params {path}",
        "#       every problem at once, or the profile fully resolved (the defaults of every other parameter)",
        f"#   rover-bridge ik --params {path} --v 0 --omega 1",
        "#       which wheel must turn forward in a counter-clockwise spin: check channels and *_reversed against",
        "#       it with the wheels off the ground",
        f"#   rover-bridge calibrate --params {path} --autopilot URL",
        "#       on the ground, armed, 2 m of room: measures each wheel's PWM -> speed map, the track and the",
        "#       radius ratio, names any wiring fault, and writes a patch of keys to copy in here",
        "# Any other parameter (`rover-bridge check-params --table` lists them with units and ranges) can be",
        "# added under its [section].",
    ]
    section = ""
    for info in iter_params():
        todo = TODO.get(info.path)
        if todo is None:
            continue
        if info.section != section:
            lines += ["", f"[{info.section}]"]
            section = info.section
        lines += _key_lines(info, todo)
    return "\n".join(lines) + "\n"


def main(args: argparse.Namespace) -> int:
    path = Path(args.path)
    if problem := output_problem(path, make_folders=True):
        raise ConfigError([problem])
    if path.exists() and not args.force:
        raise ConfigError([f"{path} exists: choose another PATH, or --force to overwrite it"])
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(profile_template(args.path), encoding="utf-8")
    except OSError as exc:
        raise ConfigError([f"{path}: cannot write the profile: {exc.strerror or exc}"]) from exc
    print(f"wrote {path}: set the values marked MEASURE to your rover's, then check them:")
    print(f"  rover-bridge check-params {args.path}")
    print(f"  rover-bridge ik --params {args.path} --v 0 --omega 1")
    print(f"  rover-bridge calibrate --params {args.path} --autopilot URL")
    return 0
