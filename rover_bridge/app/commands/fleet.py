"""rover-bridge fleet LOGS... --params P: every log replayed on Dask, one report per log, per rover, per fleet.

A thin shell over rover_bridge.fleet: analysis (per log), rovers (per rover), folder (the folder written)
and cluster (where it runs). Exit 0 when at least one log was used, 1 when none, 2 on bad usage (also
when Dask is not installed: the message says what to install).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rover_bridge.app.commands import add_params_argument

NAME = "fleet"
HELP = ("replay many logs (.tlog, ArduPilot DataFlash .bin) in parallel on Dask: per log, per rover and per fleet "
        "drift, calibration, slips, stalls and wiring signs; tables, a picture, profile patches")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG", help="log files, folders (searched recursively) or globs")
    add_params_argument(parser)
    parser.add_argument("--out", default="fleet-report", metavar="DIR", help="report folder (default %(default)s)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="an existing Dask scheduler (tcp://host:8786); default: a local cluster")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes of the local cluster (default: one per core)")
    parser.add_argument("--rover-by", choices=("both", "sysid", "folder"), default="both",
                        help="which logs are one rover's: the autopilot's system id, the log's folder, or both "
                             "(default %(default)s)")
    parser.add_argument("--threshold-pct", type=float, default=2.0, metavar="PCT",
                        help="flag a rover whose track or radius ratio is off the profile by more "
                             "(default %(default)s)")
    parser.add_argument("--use-truncated", action="store_true",
                        help="use the whole frames of a log that ends mid-frame (default: skip it)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    from rover_bridge.errors import ConfigError
    from rover_bridge.fleet.cluster import require_dask

    require_dask()
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.app.paths import output_folder_problem
    from rover_bridge.fleet.analysis import LogReport, fleet_profile
    from rover_bridge.fleet.cluster import DaskMap
    from rover_bridge.fleet.folder import patch_name, picture, summary, write_table
    from rover_bridge.fleet.jobs import expand
    from rover_bridge.fleet.rovers import RoverReport, rover_key, rovers
    from rover_bridge.params import load_profile

    problems = []
    if args.workers is not None and args.workers < 1:
        problems.append("--workers must be at least 1")
    if not 0.0 < args.threshold_pct < 100.0:
        problems.append("--threshold-pct must be between 0 and 100")
    if out_problem := output_folder_problem(args.out, "--out"):  # now, not after every log was replayed
        problems.append(out_problem)
    if problems:
        raise ConfigError(problems)
    given = load_profile(args.params)
    profile = fleet_profile(given)
    if not given.estimator.calibrate:
        print("fleet: estimator.calibrate is off in the profile: turned on for the fleet's replays", file=sys.stderr)
    jobs = expand(args.logs)
    with DaskMap(args.scheduler, args.workers, progress=not args.no_progress) as dask_map:
        print(f"fleet: {len(jobs)} logs on {dask_map.worker_count} Dask workers "
              f"({args.scheduler or 'a local cluster'}, ready in {dask_map.started_s:.1f} s)", file=sys.stderr)
        logs = dask_map.run(jobs, profile, args.use_truncated)
    threshold = args.threshold_pct / 100.0
    prior = BridgeCore(profile).estimate.calibration_estimate()
    fleet = rovers(logs, profile, prior, args.rover_by, threshold)
    out = Path(args.out)
    (out / "patches").mkdir(parents=True, exist_ok=True)
    written = [write_table(logs, LogReport.columns(), out / "logs"), write_table(fleet, RoverReport.columns(),
                                                                                out / "rovers")]
    for r in fleet:
        if r.calibration_logs:
            path = out / "patches" / f"{patch_name(r.rover)}.toml"
            path.write_text(r.patch_toml(args.params), encoding="utf-8")
    pic = picture(logs, fleet, lambda r: rover_key(r, args.rover_by), threshold, out / "fleet.png")
    text = summary(logs, fleet, threshold, args.rover_by)
    (out / "summary.txt").write_text(text, encoding="utf-8")
    print(text)
    print("written: " + ", ".join(str(p) for p in [*written, out / "summary.txt", out / "patches"])
          + (f", {pic}" if pic else " (no picture: matplotlib is not installed)"))
    return 0 if any(r.used for r in logs) else 1
