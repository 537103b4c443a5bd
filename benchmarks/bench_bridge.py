"""End-to-end benchmarks of the shipped bridge process (`python -m rover_bridge run`) over UDP loopback.

Subcommands (each prints a table and finishes in under 2 minutes; `all` runs them in turn):

  hotpath      CPU per message of Runner.step in-process, beside raw parse_buffer and BridgeCore.handle alone
  replay       BridgeCore alone on the cpu table's nominal traffic, in-process: ms of CPU per second of traffic
               and us per message kind (warm code, no sockets: the cores' own work, steadier than `cpu`)
  latency      GCS request datagram in -> RC_CHANNELS_OVERRIDE datagram out, next to a pymavlink UDP echo;
               value latency (the first override that shows the request); telemetry forwarding latency
  throughput   autopilot telemetry flood routed to a GCS: highest zero-loss rate, next to raw parse_buffer
  cpu          CPU % of one core at nominal load (50 Hz wheels / IMU / control, 30 Hz ODOMETRY), next to a
               plain pymavlink router; --parts: also the bridge with its cores stubbed (where the CPU goes);
               --without PART: also the bridge with that part of its filter costing nothing (as replay's);
               --sectors 8 [--sector-hz 10 --mode 15]: also the bridge and a router fed proximity sectors
               (replay takes the same options)
  wakeup       CPU of a Python process that only wakes from select() (what a pass costs before any work)
  regularity   override period jitter at command.rate_hz = 50, quiet and under a 5000 msg/s GCS flood
  contention   the cpu table's nominal load while numpy keeps both cores busy, at normal priority and with the
               systemd unit's scheduling: override periods, deadlines seen from outside beside the bridge's own
               count, request -> override, watchdog ping gaps (2 x 63 s; not in `all`)
  memory       RSS over one million messages (in-process Runner + BridgeCore; --subprocess: the real process)
  startup      process start -> first HEARTBEAT sent; import-time breakdown

Run: python benchmarks/bench_bridge.py all [--base DIR]   (or one subcommand; --help for options)
  --base DIR          also measure the bridge of another source tree side by side, e.g. the previous
                      commit: mkdir /tmp/base && git archive HEAD~1 | tar -x -C /tmp/base
  BENCH_PREFIX=...    run the bridges (and the echo) under e.g. "chrt -f 10" or "nice -n -10"
  BENCH_CPROFILE=P    run this tree's bridge under cProfile (CPU time), stats to P
Not a test: numbers depend on the machine and its load; nothing here asserts on them. Comparisons
(bridge vs echo, bridge vs raw parse, quiet vs flood, this tree vs --base) are measured side by
side in the same run.

The harness fakes the autopilot and the GCS with plain UDP sockets and frames packed once by
pymavlink, so its own cost stays small next to the bridge's. Receive times are the kernel's
(SO_TIMESTAMPNS): on loopback that is when the sender's sendto() queued the datagram, so the
harness's own wake-up delay is not charged to the bridge (nor to the echo).

This file only dispatches: each subcommand is a module of benchmarks/bridge/ (its name), the harness they
share is bridge/harness.py, the bridge under test and the helper processes (the hidden subcommands `_echo`,
`_router`, `_flood`, `_burn`, `_replay`) bridge/process.py.
"""

from __future__ import annotations

import argparse
import json

from bridge.contention import bench_contention, burn_main
from bridge.cpu import bench_cpu
from bridge.free_parts import WITHOUT
from bridge.harness import ROVER_GUIDED, ROVER_STEERING
from bridge.hotpath import bench_hotpath
from bridge.latency import bench_latency
from bridge.memory import bench_memory
from bridge.process import echo_main, flood_main, router_main
from bridge.regularity import bench_regularity
from bridge.replay import bench_replay, replay_main
from bridge.startup import bench_startup
from bridge.throughput import bench_throughput
from bridge.wakeup import bench_wakeup


def sectors_options(p: argparse.ArgumentParser, router: str | None) -> None:
    """--sectors, --sector-hz, --mode (cpu, replay): what avoidance costs with a proximity sensor (issue 43)."""
    p.add_argument("--sectors", type=int, default=0, choices=range(9), metavar="N",
                   help=f"also run this tree's bridge{' and ' + router if router else ''} fed N proximity sectors "
                        "(DISTANCE_SENSOR, orientation 0..N-1: a wall 5 m ahead, the rest clear) on top of the "
                        "same traffic (default 0: none)")
    p.add_argument("--sector-hz", type=float, default=10.0, help="each sector's rate (default %(default)s)")
    p.add_argument("--mode", type=int, default=ROVER_STEERING,
                   help=f"the autopilot's HEARTBEAT custom_mode (default %(default)s STEERING; {ROVER_GUIDED} GUIDED)")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("latency")
    p.add_argument("--requests", type=int, default=5000)
    p.add_argument("--value-requests", type=int, default=600, help="requests of the value-latency run")
    p.add_argument("--interval-ms", type=float, default=2.0, help="time between requests (default %(default)s)")
    p.add_argument("--forward-frames", type=int, default=500, help="frames of the telemetry-forwarding run")
    p = sub.add_parser("throughput")
    p.add_argument("--start-hz", type=float, default=4000.0)
    p.add_argument("--step-s", type=float, default=1.5)
    p.add_argument("--max-steps", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p = sub.add_parser("cpu")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--warmup-s", type=float, default=3.0)
    p.add_argument("--parts", action="store_true",
                   help="also run this tree's bridge with parts of its cores stubbed (routing; routing + "
                        "outputs; one flow only; the command flow with an estimator that costs nothing): "
                        "where its CPU goes")
    p.add_argument("--without", action="append", choices=WITHOUT,
                   help="also run this tree's bridge with that part of the filter costing nothing (repeatable; "
                        "as replay --without, in the running process)")
    sectors_options(p, "a router")
    p = sub.add_parser("regularity")
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--flood-hz", type=float, default=5000.0)
    p = sub.add_parser("contention")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--warmup-s", type=float, default=3.0)
    p.add_argument("--rate-hz", type=float, default=50.0, help="command.rate_hz (the cpu table's: %(default)s)")
    p.add_argument("--harness-priority", type=int, default=20,
                   help="SCHED_FIFO priority of the harness while it measures (above the unit's)")
    p.add_argument("--unit-first", action="store_true", help="run the unit's scheduling first")
    p.add_argument("--autogroup-nice", type=int, default=None, metavar="N",
                   help="run this session's scheduler autogroup at nice N (-20: as if only the numpy load "
                        "competed on a machine other sessions share; needs root)")
    p = sub.add_parser("memory")
    p.add_argument("--messages", type=int, default=1_000_000)
    p.add_argument("--warmup", type=int, default=20_000)
    p.add_argument("--window", type=int, default=256, help="forwarded frames in flight at most")
    p.add_argument("--max-s", type=float, default=110.0, help="stop sending after this long (default %(default)s)")
    p.add_argument("--subprocess", action="store_true",
                   help="measure the real process, closed loop (slower: fewer messages in the time limit)")
    p = sub.add_parser("startup")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--top", type=int, default=10)
    p = sub.add_parser("wakeup")
    p.add_argument("--rate-hz", type=float, default=110.0, help="wake-ups a second (the bridge's passes at nominal "
                   "load: about 110)")
    p.add_argument("--seconds", type=float, default=10.0)
    p = sub.add_parser("hotpath")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--batch", type=int, default=1500)
    p = sub.add_parser("replay")
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--without", action="append", choices=WITHOUT,
                   help="also replay this tree with that part of the filter costing nothing (repeatable): the most "
                        "that trimming it could save")
    sectors_options(p, None)
    all_p = sub.add_parser("all")
    for sp in (sub.choices["latency"], sub.choices["throughput"], sub.choices["cpu"], sub.choices["regularity"],
               sub.choices["hotpath"], sub.choices["replay"], all_p):
        sp.add_argument("--base", metavar="DIR", help="also measure the bridge of another source tree, side by side")
    p = sub.add_parser("_echo")
    p.add_argument("port", type=int)
    p = sub.add_parser("_router")
    p.add_argument("ap_port", type=int)
    p.add_argument("gcs_port", type=int)
    p.add_argument("stats_path")
    p = sub.add_parser("_flood")
    p.add_argument("port", type=int)
    p.add_argument("rate", type=float)
    p.add_argument("seconds", type=float)
    p = sub.add_parser("_burn")
    p.add_argument("seconds", type=float)
    p.add_argument("threads", type=int)
    p = sub.add_parser("_replay")
    p.add_argument("seconds", type=float)
    p.add_argument("repeats", type=int)
    p.add_argument("--without", choices=WITHOUT)
    sectors_options(p, None)
    args = parser.parse_args(argv)
    if args.cmd == "_echo":
        echo_main(args.port)
    elif args.cmd == "_router":
        router_main(args.ap_port, args.gcs_port, args.stats_path)
    elif args.cmd == "_flood":
        flood_main(args.port, args.rate, args.seconds)
    elif args.cmd == "_burn":
        burn_main(args.seconds, args.threads)
    elif args.cmd == "_replay":
        print(json.dumps(replay_main(args.seconds, args.repeats, args.without, args.sectors, args.sector_hz,
                                     args.mode)))
    elif args.cmd == "all":
        with_base = ("hotpath", "replay", "latency", "throughput", "cpu", "regularity")
        for name in ("hotpath", "replay", "latency", "throughput", "cpu", "wakeup", "regularity", "memory", "startup"):
            main([name, "--base", args.base] if args.base and name in with_base else [name])
    else:
        {"latency": bench_latency, "throughput": bench_throughput, "cpu": bench_cpu, "regularity": bench_regularity,
         "memory": bench_memory, "startup": bench_startup, "hotpath": bench_hotpath, "replay": bench_replay,
         "wakeup": bench_wakeup, "contention": bench_contention}[args.cmd](args)


if __name__ == "__main__":
    main()
