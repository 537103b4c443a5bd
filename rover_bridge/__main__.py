"""`python -m rover_bridge` is the same as the `rover-bridge` console script."""

from rover_bridge.app.cli import console_main

console_main()
