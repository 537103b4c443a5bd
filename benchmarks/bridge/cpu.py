"""`bench_bridge.py cpu`: CPU % of one core at nominal load, next to a plain pymavlink router; --parts, --without;
--sectors N: also this tree's bridge and a router fed N proximity sectors on top (what avoidance costs, issue 43).
"""

from __future__ import annotations

import argparse
import math
import select
import tempfile
import time
from typing import Any

from bridge.harness import drain, print_table, replay_frames, udp_socket, write_profile
from bridge.process import STUBS, Bridge, PlainRouter, bridges, stop_all


def bench_cpu(args: argparse.Namespace) -> None:
    sectors = args.sectors if args.sector_hz > 0 else 0
    with tempfile.TemporaryDirectory() as tmp:
        profile = write_profile({"command.rate_hz": "50.0"}, tmp)
        parts = [Bridge(profile, tmp, name, stub=stub) for stub, name in STUBS.items()] if args.parts else []
        parts += [Bridge(profile, tmp, f"bridge, {part} free", without=part) for part in args.without or ()]
        # --sectors: this tree's bridge and a router that get the proximity sectors on top of the same traffic;
        # each bridge is reckoned against the router fed what it was fed (x a router on the same traffic).
        fed: list[Bridge] = []
        if sectors:
            extra = f" + {sectors} sectors @ {args.sector_hz:g} Hz"
            fed = [Bridge(profile, tmp, "bridge" + extra), PlainRouter(tmp, "pymavlink router" + extra)]
        under_test = [*bridges(args, profile, tmp), *parts, *fed, PlainRouter(tmp)]
        sees = [br in fed for br in under_test]  # gets the sectors
        socks = [(udp_socket(), udp_socket()) for _ in under_test]
        samples: list[list[tuple[float, float, float]]] = [[] for _ in under_test]
        stats: list[dict[str, Any]] = []
        all_socks = [s for pair in socks for s in pair]
        try:
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                br.wait_up(ap, gcs)
            total = args.warmup_s + args.seconds
            traffic = paired_traffic(total, sectors, args.sector_hz, args.mode)  # built before the clock starts
            start = time.monotonic()
            measure_at = start + args.warmup_s
            measuring = False
            # Who gets an instant's frames first turns with every instant: the first process sent to wakes
            # first and sees its burst whole more often (measured: about 15 % fewer passes, 0.05-0.15x of the
            # router less CPU for the same tree listed first), so a fixed order favours it.
            pairs = list(zip(under_test, socks, sees, strict=True))
            turn, last_offset = 0, None
            for offset, to_gcs_port, plain, sectored in traffic:
                if offset != last_offset:
                    turn, last_offset = (turn + 1) % len(pairs), offset
                target = start + offset
                while (now := time.monotonic()) < target:
                    select.select(all_socks, [], [], target - now)
                    for sock in all_socks:
                        drain(sock)
                if not measuring and now >= measure_at:
                    for br, smp in zip(under_test, samples, strict=True):
                        smp.append((time.monotonic(), *br.cpu_split_s()))
                    measuring = True
                # The same bytes go to every bridge under test (sent one after the other); the sectors' stream
                # (same events, its own sequence numbers) to those that see them.
                for br, (ap, gcs), fed_sectors in pairs[turn:] + pairs[:turn]:
                    frame = sectored if fed_sectors else plain
                    if frame is None:
                        continue
                    if to_gcs_port:
                        gcs.sendto(frame, br.gcs_addr)
                    else:
                        ap.sendto(frame, br.ap_addr)
            for br, smp in zip(under_test, samples, strict=True):
                smp.append((time.monotonic(), *br.cpu_split_s()))
        finally:
            stats = stop_all(under_test, all_socks)
    cpu: list[tuple[float, float, float]] = []  # wall, user, sys over the measured window
    for smp in samples:
        (t0, u0, s0), (t1, u1, s1) = smp[0], smp[-1]
        cpu.append((t1 - t0, u1 - u0, s1 - s0))
    pcts = [(user + sys_) / wall * 100.0 for wall, user, sys_ in cpu]
    router_pct = {sees[i]: pcts[i] for i, br in enumerate(under_test) if isinstance(br, PlainRouter)}
    rows = []
    ratios: dict[str, float] = {}
    for br, (wall, user, sys_), st, cpu_pct, fed_sectors in zip(under_test, cpu, stats, pcts, sees, strict=True):
        reference = router_pct[fed_sectors]
        ratio = cpu_pct / reference if reference > 0 else math.inf
        ratios[br.name] = ratio
        is_router = isinstance(br, PlainRouter)
        est, cmd = st.get("estimate", {}), st.get("command", {})
        rows.append([br.name, f"{wall:.1f}", f"{user:.2f}", f"{sys_:.2f}", f"{cpu_pct:.2f}", f"{ratio:.2f}",
                     "-" if is_router else ("met" if ratio <= 1.5 else "MISSED"),
                     est.get("odometry_sent"), cmd.get("outputs.sent"), cmd.get("requests.accepted"),
                     st.get("runner", {}).get("forwarded"), st.get("runner", {}).get("ticks"),
                     st.get("runner", {}).get("passes", "-"), cmd.get("avoid.sensor_seen", "-")])
    print_table("3. CPU at nominal load: WHEEL_DISTANCE, ATTITUDE, RAW_IMU 50 Hz; requests 50 Hz, command.rate_hz 50; "
                "ODOMETRY 30 Hz; other telemetry ~40 Hz; GCS 6 Hz. Target: <= 1.5x the plain pymavlink router "
                "in the same run (x_router)",
                ["bridge", "wall_s", "user_s", "sys_s", "cpu_%_core", "x_router", "target", "odometry", "outputs",
                 "accepted", "forwarded", "ticks", "passes", "sensor_seen"],
                rows)
    if sectors:
        with_s, without = fed[0].name, "bridge"
        names = [br.name for br in under_test]
        plain_pct = router_pct[False]
        extra_pct = pcts[under_test.index(fed[0])] - pcts[names.index(without)]
        print(f"\nsectors' cost: {ratios[with_s] - ratios[without]:+.3f}x (each against the router fed the same; "
              f"target <= +0.1x); {extra_pct / plain_pct:+.3f}x of the router without them (the extra routing "
              f"included); that router fed them: {router_pct[True] / plain_pct - 1.0:+.3f}x")
    if getattr(args, "base", None):
        print(f"\nthis tree against base: {ratios['bridge'] - ratios['base']:+.3f}x")


def paired_traffic(seconds: float, sectors: int, sector_hz: float,
                   custom_mode: int) -> list[tuple[float, bool, bytes | None, bytes | None]]:
    """(offset, to the GCS port, frame without sectors, frame with them) of the nominal traffic, and with
    `sectors` the same traffic with the sectors on top packed as one sequence (the plain frame None at a
    sector's event); without sectors both frames are the same."""
    plain = replay_frames(seconds, custom_mode=custom_mode)
    if not sectors:
        return [(offset, to_gcs, frame, frame) for offset, _what, to_gcs, frame in plain]
    out: list[tuple[float, bool, bytes | None, bytes | None]] = []
    nominal = iter(plain)
    for offset, what, to_gcs, frame in replay_frames(seconds, sectors, sector_hz, custom_mode):
        if what.startswith("SECTOR"):
            out.append((offset, to_gcs, None, frame))
            continue
        p_offset, p_what, _to_gcs, p_frame = next(nominal)
        assert (p_offset, p_what) == (offset, what)  # the same events in the same order
        out.append((offset, to_gcs, p_frame, frame))
    return out
