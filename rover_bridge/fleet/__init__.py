"""The fleet report over many rovers' logs (`rover-bridge fleet`): which logs (jobs), one log's analysis
(analysis, drift), per rover (rovers), where it runs (cluster, on Dask), the report folder written (folder).
A consumer of the application: each log is replayed through rover_bridge.app.replay.
May import anything in rover_bridge except the CLI (rover_bridge.app.cli, rover_bridge.app.commands), whose
`fleet` command is the thin shell around this package; nothing below the CLI imports it.
"""
