"""rover-bridge replay LOG.tlog (or an ArduPilot DataFlash LOG.bin): run the estimator offline over a recorded log."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rover_bridge.app.commands import add_params_argument
from rover_bridge.app.paths import input_problem, output_problem
from rover_bridge.errors import ConfigError

NAME = "replay"
HELP = ("run the estimator over a recorded .tlog or DataFlash .bin; write pose, velocity, covariance and the "
        "calibration as CSV and print a summary")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="a .tlog recorded by `rover-bridge run --tlog` (or a ground station), or an "
                                    "ArduPilot DataFlash .bin with wheel encoders (WENC)")
    add_params_argument(parser)
    parser.add_argument("--csv", default=None, metavar="PATH", help="output CSV (default: LOG with .csv)")
    parser.add_argument("--plot", default=None, metavar="PATH",
                        help="also draw the replayed path here (needs matplotlib); 'none' (the default): no picture")


def main(args: argparse.Namespace) -> int:
    from rover_bridge.app.replay import replay, write_csv
    from rover_bridge.params import load_profile

    profile = load_profile(args.params)
    csv_path = Path(args.csv) if args.csv else Path(args.log).with_suffix(".csv")
    plot = args.plot if args.plot and args.plot.lower() != "none" else None
    outputs = [("--csv" if args.csv else "CSV", csv_path), *([("--plot", Path(plot))] if plot else [])]
    problems = [p for p in [log_problem(args.log), *(output_problem(path, label) for label, path in outputs)] if p]
    problems += [f"{label} {path}: that is the log itself: give another path" for label, path in outputs
                 if path.resolve() == Path(args.log).resolve()]
    if problems:
        raise ConfigError(problems)
    result = replay(args.log, profile)
    write_csv(result.rows, csv_path)
    print(result.summary())
    if result.log.trailing_bytes:
        print(f"rover-bridge replay: {args.log} ends mid-frame: it was cut short", file=sys.stderr)
    print(f"csv: {csv_path} ({len(result.rows)} rows)")
    if plot:
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            print("plot skipped: matplotlib is not installed (pip install matplotlib)")
            return 0
        fig, ax = plt.subplots(figsize=(6, 6))
        # FRD: x forward (up on the page), y right.
        ax.plot([r.y_m for r in result.rows], [r.x_m for r in result.rows], "C0-", label="replayed EKF")
        if result.live:
            ax.plot([r.y_m for r in result.live], [r.x_m for r in result.live], "k:", label="live ODOMETRY")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("right [m]")
        ax.set_ylabel("forward [m]")
        if result.rows or result.live:
            ax.legend()
        else:  # an empty panel says why
            ax.text(0.5, 0.5, NO_PATH, transform=ax.transAxes, ha="center", va="center", color="0.35")
        fig.savefig(plot, dpi=90)
        print(f"picture: {plot}")
    return 0 if result.rows else 1


NO_PATH = "no path: the log holds no wheel samples the estimate\ncould use (WHEEL_DISTANCE) and no ODOMETRY"


def log_problem(path: str) -> str | None:
    """What stops `path` from being replayed at all: not there, a folder (`fleet` reads folders), unreadable,
    empty, or plainly no log of its kind."""
    from rover_bridge.app.log_frames import format_problem

    if Path(path).is_dir():
        return f"{path}: a folder, not a log (replay reads one log; `rover-bridge fleet {path}` reads every log in it)"
    problem = input_problem(path, what="log")
    if problem is None and Path(path).is_file() and (wrong := format_problem(Path(path))):
        problem = f"{path}: {wrong}"
    return problem
