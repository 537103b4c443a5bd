"""`rover-bridge` command line: one subcommand per module in rover_bridge.app.commands.

Each command module exposes `NAME`, `HELP`, `add_arguments(parser)` and `main(args) -> int`.
Exit codes: 0 ok, 1 runtime failure (a link that does not open, a file that cannot be written however checked),
2 bad configuration or usage (a path given that cannot be read or written: rover_bridge.app.paths).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from types import ModuleType

from rover_bridge import __version__
from rover_bridge.app.logs import install_log_rate_limit
from rover_bridge.errors import ConfigError, LinkError

# Each subcommand lives in its own module (rover_bridge/app/commands/NAME.py).
COMMAND_MODULES = ("run", "demo", "init", "calibrate", "replay", "fleet", "check_params", "ik")


def _load(module_name: str) -> ModuleType:
    return importlib.import_module(f"rover_bridge.app.commands.{module_name}")


def build_parser() -> argparse.ArgumentParser:
    # allow_abbrev=False: otherwise a subcommand option such as `ik --v` is taken as an
    # ambiguous abbreviation of --version/--verbose by this top-level parser.
    parser = argparse.ArgumentParser(prog="rover-bridge", allow_abbrev=False,
                                     description="MAVLink 2 companion bridge for differential-drive rovers: "
                                                 "velocity requests in, safe per-wheel overrides out; wheel "
                                                 "encoders + gyro fused into ODOMETRY. Try `rover-bridge demo`.")
    parser.add_argument("--version", action="version", version=f"rover-bridge {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name in COMMAND_MODULES:
        mod = _load(module_name)
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_main=mod.main)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    install_log_rate_limit()  # a flood of bad input must not become a flood of log lines
    try:
        code: int = args._main(args)
    except ConfigError as exc:
        if len(exc.problems) == 1:
            print(f"rover-bridge: {exc.problems[0]}", file=sys.stderr)
        else:
            print("rover-bridge: configuration errors:", file=sys.stderr)
            for problem in exc.problems:
                print(f"  - {problem}", file=sys.stderr)
        return 2
    except LinkError as exc:  # not the configuration's fault: exit 1, so systemd tries again
        print(f"rover-bridge: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        # A file that failed after its check (rover_bridge.app.paths): a full disk, a folder removed meanwhile.
        # Still one line, naming the file (or the command: a write that fails at close names none).
        where = f": {exc.filename}" if exc.filename else f" {args.command}"
        print(f"rover-bridge{where}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    return code


def console_main() -> None:
    """Process entry point (`rover-bridge`, `python -m rover_bridge`): main(), then a fast exit.

    By the time main() returns, the safe stop has been sent and every file written is closed; the
    interpreter's own teardown of numpy/scipy would still take 100-300 ms, which would put a
    SIGTERM'd bridge past its 200 ms exit budget (a supervisor waiting on it sees a slow stop).
    """
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(code)
