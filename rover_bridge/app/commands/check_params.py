"""rover-bridge check-params FILE: print the resolved profile, or every problem and exit 2."""

from __future__ import annotations

import argparse

from rover_bridge.errors import ConfigError
from rover_bridge.params import load_profile, markdown_table, profile_to_toml, profile_warnings

NAME = "check-params"
HELP = "validate a robot profile (TOML) and print it fully resolved"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", nargs="?", metavar="PROFILE",
                        help="profile to check: a TOML file or a packaged profile's name (e.g. default)")
    parser.add_argument("--table", action="store_true",
                        help="print the parameter reference as a Markdown table (the README's) and exit")


def main(args: argparse.Namespace) -> int:
    if args.table:
        print(markdown_table(), end="")
        return 0
    if not args.file:
        raise ConfigError(["check-params: give a profile FILE (or --table)"])
    profile = load_profile(args.file)  # ConfigError -> cli prints every problem, exit 2
    print(f"# {args.file}: OK, fully resolved (defaults filled in)")
    for warning in profile_warnings(profile):
        print(f"# warning: {warning}")
    print(profile_to_toml(profile), end="")
    return 0
