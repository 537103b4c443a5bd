"""rover-bridge demo: see the bridge drive an emulated rover, on a laptop, in under a minute."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

NAME = "demo"
HELP = ("start the sitl emulator and the bridge as separate processes on UDP loopback, drive a route "
        "from a scripted ground station, and report errors against ground truth")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from rover_bridge.app.demo import SCENARIO_HELP, SCENARIOS

    parser.add_argument("--scenario", default="clean", choices=list(SCENARIOS),
                        help="; ".join(f"{name}: {SCENARIO_HELP[name]}" for name in SCENARIOS)
                        + " (default %(default)s)")
    parser.add_argument("--plot", default=None, metavar="PATH",
                        help="write the map and error plots here (default demo.png for the clean route, "
                             "demo-SCENARIO.png for another); 'none' for no picture")
    parser.add_argument("--quick", action="store_true", help="a shorter route (about 20 s), for tests")
    parser.add_argument("--seed", type=int, default=1, help="emulator noise seed (default %(default)s)")


def main(args: argparse.Namespace) -> int:
    from rover_bridge.app.demo import picture_name, run_demo
    from rover_bridge.app.paths import output_problem
    from rover_bridge.errors import ConfigError

    plot = picture_name(args.scenario) if args.plot is None else args.plot
    plot_path = None if plot.lower() == "none" else Path(plot)
    if plot_path is not None and (problem := output_problem(plot_path, "--plot")):
        raise ConfigError([problem])  # now, not after the drive
    try:
        summary = run_demo(args.scenario, 0.45 if args.quick else 1.0, args.seed, plot_path)
    except KeyboardInterrupt:
        # run_demo's cleanup has already stopped the bridge (overrides released) and the emulator.
        print("\ndemo interrupted: bridge and emulator stopped")
        return 130
    except RuntimeError as exc:
        print(f"\ndemo failed: {exc}")
        return 1
    ok = math.isfinite(summary.ekf_final_m) and summary.distance_m > 1.0
    if not ok:
        print("demo: the rover did not drive the route; see the messages above")
    return 0 if ok else 1
