"""`bench_bridge.py replay`: BridgeCore alone on the cpu table's nominal traffic, in-process, each run in a
child process (`_replay`): ms of CPU per second of traffic and us per message kind.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from bridge.free_parts import make_free
from bridge.harness import REPO, ROVER_STEERING, msg_id, print_table, replay_frames, self_cmd, write_profile
from bridge.process import bridge_env
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import load_profile


def replay_main(seconds: float, repeats: int, without: str | None = None, sectors: int = 0, sector_hz: float = 10.0,
                mode: int = ROVER_STEERING) -> dict[str, Any]:
    """The replay of one tree (the rover_bridge this process imports): what bench_replay prints.

    Passes as the running bridge makes them at this load: the autopilot's frames are read in the pass of
    the next ground-station frame (its link rests between reads, mavlink.autopilot_batch_ms), each handled
    at its own arrival time; then what is due (tick) and what may leave early (ODOMETRY), as Runner.step
    does; a deadline before the next frame is a pass of its own.

    After each pass pymavlink decodes that pass's frames again, timed on its own: the reference. The
    machine's speed can swing 1.5x within a minute here; the cores' time over the reference's (x_ref)
    cancels that, as the cpu table's router does."""
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.mavlink import fastcodec
    from rover_bridge.mavlink.wire import Incoming, Link

    if without is not None:
        make_free(without)
    parser = mavlink.MAVLink(None)
    passes: list[tuple[float, list[tuple[float, str, Any, Any, int]], list[bytes]]] = []
    batch: list[tuple[float, str, Any, Any, int]] = []
    raw: list[bytes] = []
    for off, kind, gcs, f in replay_frames(seconds, sectors, sector_hz, mode):
        kind = "DISTANCE_SENSOR" if kind.startswith("SECTOR") else kind
        msg = fastcodec.decode(f) or parser.decode(bytearray(f))
        batch.append((1000.0 + off, kind, Link.GCS if gcs else Link.AUTOPILOT, msg, msg_id(f)))
        raw.append(bytes(f))
        if gcs:
            passes.append((1000.0 + off, batch, raw))
            batch, raw = [], []
    totals: list[float] = []
    refs: list[float] = []
    per_kind: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        profile = load_profile(write_profile({"command.rate_hz": "50.0"}, tmp))
    logging.disable(logging.WARNING)  # the cores' STATUSTEXT log lines (no encoders yet, ...)
    warm_s = 1000.0 + seconds / 4
    clock = time.process_time
    for _ in range(repeats):
        core = BridgeCore(profile)
        kind_s: dict[str, float] = {}
        counts: dict[str, int] = {}

        def add(what: str, dt: float, now: float, kind_s: dict[str, float] = kind_s,
                counts: dict[str, int] = counts) -> None:
            if now >= warm_s:
                kind_s[what] = kind_s.get(what, 0.0) + dt
                counts[what] = counts.get(what, 0) + 1

        def due(now: float, core: Any = core) -> None:
            c0 = clock()
            if now >= core.next_deadline_s(now):
                core.tick(now)
                add("tick", clock() - c0, now)
                c0 = clock()
            if now >= core.next_early_s(now):
                core.early_tick(now)
                add("early tick", clock() - c0, now)

        t = 1000.0
        ref_s = 0.0
        for pass_s, frames, datagrams in passes:
            while (deadline := core.next_deadline_s(t)) < pass_s:  # the loop woke for it
                t = max(t, deadline)
                due(t)
            for now, kind, link, msg, mid in frames:
                c0 = clock()
                reads = core.reads(link)
                if reads is None or mid in reads:  # as the shell: undecoded frames never reach the core
                    core.handle(Incoming(link, msg), now)
                add(kind, clock() - c0, now)
            t = pass_s
            due(t)
            c0 = clock()
            for datagram in datagrams:
                parser.decode(bytearray(datagram))
            if t >= warm_s:
                ref_s += clock() - c0
        totals.append(sum(kind_s.values()) / (seconds * 0.75) * 1e3)
        refs.append(sum(kind_s.values()) / ref_s)
        for k, v in kind_s.items():
            per_kind.setdefault(k, []).append(v / counts[k] * 1e6)
    logging.disable(logging.NOTSET)
    return {"ms_per_s": statistics.median(totals), "runs": totals, "x_ref": statistics.median(refs),
            "us": {k: statistics.median(v) for k, v in per_kind.items()}}


def bench_replay(args: argparse.Namespace) -> None:
    # Each run in a fresh process, the trees taking turns (measured: the same tree read about 10 % cheaper in
    # this process than in a child, so both are children).
    roots = {"bridge": REPO, **({"base": Path(args.base).resolve()} if args.base else {})}
    extra: dict[str, list[str]] = {name: ["--mode", str(args.mode)] for name in roots}
    for part in args.without or ():
        roots[f"bridge, {part} free"] = REPO
        extra[f"bridge, {part} free"] = ["--without", part, "--mode", str(args.mode)]
    if args.sectors and args.sector_hz > 0:  # this tree fed the proximity sectors on top (as cpu --sectors)
        name = f"bridge + {args.sectors} sectors @ {args.sector_hz:g} Hz"
        roots[name] = REPO
        extra[name] = ["--sectors", str(args.sectors), "--sector-hz", str(args.sector_hz), "--mode", str(args.mode)]
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in roots}
    for rep in range(args.repeats):
        for name in list(roots) if rep % 2 == 0 else list(roots)[::-1]:
            done = subprocess.run(self_cmd("_replay", str(args.seconds), "1", *extra[name]), capture_output=True,
                                  text=True, cwd=REPO, env=bridge_env(roots[name]), check=True)
            runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
    kinds = sorted({k for rs in runs.values() for r in rs for k in r["us"]})
    rows = []
    for name, rs in runs.items():
        totals, ratios = [r["ms_per_s"] for r in rs], [r["x_ref"] for r in rs]
        rows.append([name, f"{statistics.median(ratios):.3f}", " / ".join(f"{x:.3f}" for x in ratios),
                     f"{statistics.median(totals):.2f}",
                     *[f"{statistics.median(r['us'].get(k, 0.0) for r in rs):.1f}" for k in kinds]])
    print_table(f"replay: BridgeCore alone on {args.seconds:.0f} s of the cpu table's nominal traffic, in-process "
                f"(the last three quarters measured; median of {args.repeats} processes per tree); x_ref: the cores' "
                "CPU over pymavlink's decode of the same frames, timed between the passes; ms of CPU per second of "
                "traffic; us per message kind, per tick (command output, heartbeat, deadlines) and per early tick "
                "(ODOMETRY)", ["tree", "x_ref", "runs", "ms_per_s", *kinds], rows)
