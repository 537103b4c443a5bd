"""Subcommands of the `rover-bridge` CLI, one module each (see rover_bridge.app.cli)."""

from __future__ import annotations

import argparse

DEFAULT_PROFILE = "default"


def add_params_argument(parser: argparse.ArgumentParser, *, required: bool = False) -> None:
    """``--params``: a profile file, or the name of a packaged profile (found from any directory)."""
    from rover_bridge.params import packaged_profiles

    names = ", ".join(packaged_profiles())
    default = "" if required else f"; default {DEFAULT_PROFILE!r}, the packaged example rover"
    parser.add_argument("--params", required=required, default=None if required else DEFAULT_PROFILE,
                        metavar="PROFILE",
                        help=f"robot profile: a TOML file (`rover-bridge init PATH` writes one to start from) or a "
                             f"packaged profile's name ({names}){default}")
