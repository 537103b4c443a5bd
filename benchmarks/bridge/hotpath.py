"""`bench_bridge.py hotpath`: CPU per message of Runner.step in-process, beside raw parse_buffer and
BridgeCore.handle alone; with --base, another tree's shell too.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from bridge.harness import (
    BIG_RCVBUF,
    DEFAULT_PROFILE,
    GCS_COMP,
    GCS_SYS,
    LOCAL,
    Packer,
    drain,
    flood_frames,
    free_udp_port,
    heartbeat_gcs,
    print_table,
    udp_socket,
)
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import load_profile

# ------------------------------------------------------------------------------------- hot path (in-process)

def _load_tree_modules(root: Path) -> tuple[Any, Any]:
    """links and runner modules of another source tree (the rest of the package is this tree's)."""
    import importlib.util
    mods = []
    for name, places in (("links", ("mavlink/links", "links")), ("runner", ("app/loop", "runner"))):
        # This tree's layout (packages by flow) or an older flat one.
        path = next(p for p in (root / "rover_bridge" / f"{place}.py" for place in places) if p.exists())
        spec = importlib.util.spec_from_file_location(f"_base_{name}", path)
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod  # dataclasses look their module up there
        spec.loader.exec_module(mod)
        mods.append(mod)
    links_mod, runner_mod = mods
    for shared in ("Endpoint", "RawFrame"):  # the other tree's runner must see its own links' types
        if hasattr(runner_mod, shared) and hasattr(links_mod, shared):
            setattr(runner_mod, shared, getattr(links_mod, shared))
    return links_mod, runner_mod


def bench_hotpath(args: argparse.Namespace) -> None:
    """CPU per message of one Runner.step over datagrams already queued on its UDP socket (no
    scheduling, no wake-ups: the code path alone), beside pymavlink's parse_buffer and BridgeCore.handle
    alone on the same frames; with --base, the shell (links.py + runner.py) of another tree too."""
    from rover_bridge.app import loop as this_runner
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.mavlink import links as this_links
    from rover_bridge.mavlink.wire import Incoming, Link

    profile = load_profile(str(DEFAULT_PROFILE))
    shells: dict[str, tuple[Any, Any]] = {"bridge": (this_links, this_runner)}
    if args.base:
        shells["base"] = _load_tree_modules(Path(args.base).resolve())
    rigs: dict[str, tuple[Any, socket.socket, socket.socket, tuple[str, int]]] = {}
    for name, (links_mod, runner_mod) in shells.items():
        ap_port, gcs_port = free_udp_port(), free_udp_port()
        ap_ep = links_mod.Endpoint(f"udpin:{LOCAL}:{ap_port}", Link.AUTOPILOT)
        gcs_ep = links_mod.Endpoint(f"udpin:{LOCAL}:{gcs_port}", Link.GCS)
        for ep in (ap_ep, gcs_ep):  # the whole batch must fit, whatever either tree asks for
            ep.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BIG_RCVBUF)
        runner = runner_mod.Runner(BridgeCore(profile), ap_ep, [gcs_ep])
        ap, gcs = udp_socket(), udp_socket()
        gcs.sendto(Packer(GCS_SYS, GCS_COMP).pack(heartbeat_gcs()), (LOCAL, gcs_port))  # the GCS is a peer
        rigs[name] = (runner, ap, gcs, (LOCAL, ap_port))
    batch = args.batch
    frames_all = flood_frames(batch * args.repeats, 3000.0)
    results: dict[str, list[float]] = {"parse": [], "core": [], **{name: [] for name in rigs}}
    core_only = BridgeCore(profile)
    clock = {name: 100.0 for name in rigs}
    for rep in range(args.repeats):
        frames = frames_all[rep * batch:(rep + 1) * batch]
        mav = mavlink.MAVLink(None)
        mav.robust_parsing = True
        c0 = time.process_time()
        msgs = [m for f in frames for m in (mav.parse_buffer(f) or [])]
        results["parse"].append((time.process_time() - c0) / batch * 1e6)
        c0 = time.process_time()
        for i, m in enumerate(msgs):
            core_only.handle(Incoming(Link.AUTOPILOT, m), 100.0 + rep * 0.5 + i / 3000.0)
        results["core"].append((time.process_time() - c0) / batch * 1e6)
        names = list(rigs) if rep % 2 == 0 else list(rigs)[::-1]
        for name in names:
            runner, ap, gcs, dest = rigs[name]
            for f in frames:
                ap.sendto(f, dest)
            clock[name] += 0.5
            c0 = time.process_time()
            runner.step(clock[name])
            results[name].append((time.process_time() - c0) / batch * 1e6)
            drain(gcs)
            drain(ap)
    for runner, ap, gcs, _dest in rigs.values():
        runner.close()
        ap.close()
        gcs.close()
    parse_us = statistics.median(results["parse"])
    rows = [["pymavlink parse_buffer (raw parse)", statistics.median(results["parse"]), min(results["parse"]), "100%"],
            ["BridgeCore.handle alone (decoded messages)", statistics.median(results["core"]),
             min(results["core"]), "-"]]
    for name in rigs:
        med = statistics.median(results[name])
        rows.append([f"{name}: Runner.step (read, handle, forward)", med, min(results[name]), f"{parse_us / med:.0%}"])
        shell = med - statistics.median(results["core"])
        rows.append([f"{name}: the same minus BridgeCore.handle (parse + shell)", shell, "-",
                     f"{parse_us / shell:.0%}"])
    print_table(f"hot path: CPU microseconds per message, {args.repeats} batches of {batch} queued datagrams of the "
                f"throughput mix, in-process", ["what", "median_us", "min_us", "rate_vs_raw_parse"], rows)
