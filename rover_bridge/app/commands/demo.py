"""rover-bridge demo: see the bridge drive an emulated rover, on a laptop, in under a minute."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

NAME = "demo"
HELP = ("start the sitl emulator and the bridge as separate processes on UDP loopback, drive a route "
        "from a scripted ground station, and report errors against ground truth")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from rover_bridge.app.demo import SCENARIOS

    parser.add_argument("--scenario", default="clean", choices=sorted(SCENARIOS),
                        help="conditions: clean, miscalibrated (2 %% radius / 3 %% track error), slip, gyro-bias")
    parser.add_argument("--plot", default="demo.png", metavar="PATH",
                        help="write the map and error plot here (default %(default)s); 'none' to skip")
    parser.add_argument("--quick", action="store_true", help="a shorter route (about 20 s), for tests")
    parser.add_argument("--seed", type=int, default=1, help="emulator noise seed (default %(default)s)")


def main(args: argparse.Namespace) -> int:
    from rover_bridge.app.demo import run_demo

    plot_path = None if args.plot.lower() == "none" else Path(args.plot)
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
