"""The subcommands of benchmarks/bench_bridge.py, one module each, and what they share (harness, process)."""
