"""The application: the composition of both flows (BridgeCore), the runner (the one loop), the CLI and its
commands, the demo and replay. The only place with sockets, clocks, signals and files.
May import anything in rover_bridge, except that only the CLI (cli, commands/) may import rover_bridge.fleet:
the fleet report consumes replay and calibration from here, and its command is the CLI's thin shell over it.
"""
