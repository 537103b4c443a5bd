"""Subcommands of the `rover-bridge` CLI, one module each (see rover_bridge.app.cli)."""
