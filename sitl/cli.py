"""``rover-sitl`` / ``python -m sitl``: run the emulator on a wall clock.

By default it listens where ArduPilot's SITL does, TCP 5760 on 127.0.0.1 (one client at a time, a new one
replacing the old), which is where ``rover-bridge run`` connects by default: the two meet with no options.

Exit codes: 0 after SIGINT/SIGTERM or ``--duration``; 2 for a bad option, a bad file, a bad
connection string or a busy port (with a one-line message on stderr).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from sitl.config import ConfigError, VehicleConfig, load_vehicle
from sitl.emulator import Emulator
from sitl.endpoint import ConnectionStringError
from sitl.modes import MODE_NAMES
from sitl.scenario import Scenario, load_scenario


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rover-sitl",
        description="Loopback autopilot emulator: an ArduPilot-Rover-like MAVLink 2 flight controller "
        "on a simulated differential-drive robot.",
    )
    p.add_argument(
        "--connect",
        "--endpoint",
        dest="connect",
        default="tcpin:127.0.0.1:5760",
        help="pymavlink-style connection string: udpin:/udp:/udpout:/tcpin:/tcp:HOST:PORT "
        "(default %(default)s, ArduPilot SITL's port, where `rover-bridge run` connects by default)",
    )
    p.add_argument("--sysid", type=int, default=1, help="MAVLink system id (default 1)")
    p.add_argument("--seed", type=int, default=0, help="random seed for noise and faults (default 0)")
    p.add_argument("--speedup", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--step", type=float, default=0.01, help="simulation step in seconds (default 0.01)")
    p.add_argument("--scenario", metavar="FILE", help="scenario TOML (timeline of events)")
    p.add_argument("--vehicle", metavar="FILE", help="vehicle profile TOML")
    p.add_argument("--start-armed", action="store_true", help="boot armed (like ARMING_REQUIRE=0)")
    p.add_argument(
        "--passthrough-when-disarmed",
        action="store_true",
        help="RC passthrough outputs drive the wheels even when disarmed (real ArduPilot)",
    )
    p.add_argument("--duration", type=float, metavar="SECONDS", help="stop after this much simulated time")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse exits 2 on a bad option, 0 on --help
        return int(exc.code) if isinstance(exc.code, int) else 2
    if not 1 <= args.sysid <= 255:
        print("rover-sitl: --sysid must be 1..255", file=sys.stderr)
        return 2
    if args.speedup <= 0 or args.step <= 0:
        print("rover-sitl: --speedup and --step must be positive", file=sys.stderr)
        return 2
    try:
        vehicle = load_vehicle(args.vehicle) if args.vehicle else VehicleConfig()
        overrides: dict[str, object] = {}
        if args.start_armed:
            overrides["start_armed"] = True
        if args.passthrough_when_disarmed:
            overrides["passthrough_when_disarmed"] = True
        if overrides:
            vehicle = VehicleConfig.from_mapping({**_as_mapping(vehicle), **overrides})
        scenario = load_scenario(args.scenario) if args.scenario else Scenario()
        emu = Emulator(vehicle=vehicle, scenario=scenario, seed=args.seed, system_id=args.sysid)  # checks params
    except ConfigError as exc:
        print(f"rover-sitl: {exc}", file=sys.stderr)
        return 2
    try:
        emu.open(args.connect)
    except ConnectionStringError as exc:
        print(f"rover-sitl: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"rover-sitl: {exc.strerror or exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    host, port = emu.local_address
    print(
        f"rover-sitl: {args.connect} bound to {host}:{port}, sysid {args.sysid}, seed {args.seed}, "
        f"{'armed' if emu.armed else 'disarmed'}, {MODE_NAMES.get(emu.mode, emu.mode)}",
        file=sys.stderr,
        flush=True,
    )
    try:
        emu.run_realtime(speedup=args.speedup, duration_s=args.duration, stop=stop, step_s=args.step)
    finally:
        emu.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    truth = emu.truth  # where the rover ended, for whoever drove it by hand
    print(
        f"rover-sitl: stopped after {emu.sim_time_s:.1f} s: at x {truth.x_m:.2f} m north, y {truth.y_m:.2f} m east, "
        f"yaw {math.degrees(truth.yaw_rad):.0f} deg",
        file=sys.stderr,
        flush=True,
    )
    return 0


def _as_mapping(vehicle: VehicleConfig) -> dict[str, object]:
    return {f.name: getattr(vehicle, f.name) for f in dataclasses.fields(vehicle)}


if __name__ == "__main__":
    sys.exit(main())
