"""rover-bridge check-params FILE: print the resolved profile, or every problem and exit 2."""

from __future__ import annotations

import argparse

from rover_bridge.params import load_profile, profile_to_toml

NAME = "check-params"
HELP = "validate a robot profile (TOML) and print it fully resolved"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="profile to check, e.g. params/default.toml")


def main(args: argparse.Namespace) -> int:
    profile = load_profile(args.file)  # ConfigError -> cli prints every problem, exit 2
    print(f"# {args.file}: OK, fully resolved (defaults filled in)")
    print(profile_to_toml(profile), end="")
    return 0
