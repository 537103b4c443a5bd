"""`bench_bridge.py memory`: RSS over one million messages (in-process Runner + BridgeCore; --subprocess: the
real process).
"""

from __future__ import annotations

import argparse
import select
import tempfile
import time
from pathlib import Path

from bridge.harness import (
    DEFAULT_PROFILE,
    GCS_COMP,
    GCS_SYS,
    LOCAL,
    Packer,
    Telemetry,
    body_velocity_request,
    drain,
    forwarded_frames,
    free_udp_port,
    heartbeat_gcs,
    print_table,
    udp_socket,
)
from bridge.process import Bridge
from rover_bridge.params import load_profile

# ------------------------------------------------------------------------------------- 5. memory

CHEAP_MIX = ("SYS_STATUS", "GPS_RAW_INT", "VFR_HUD", "SERVO_OUTPUT_RAW", "GLOBAL_POSITION_INT", "HEARTBEAT")


def self_rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def bench_memory(args: argparse.Namespace) -> None:
    if args.subprocess:
        bench_memory_subprocess(args)
    else:
        bench_memory_inprocess(args)


def bench_memory_inprocess(args: argparse.Namespace) -> None:
    """The shipped shell and core in this process (Runner over real UDP endpoints, the same
    read / handle / forward path as the process, minus select()): batches of datagrams are queued
    on the bridge's sockets, then one Runner.step takes them. Fast enough for a million messages
    in under two minutes; the harness allocates everything it sends before the first RSS reading."""
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.app.loop import Runner
    from rover_bridge.mavlink.links import Endpoint
    from rover_bridge.mavlink.wire import Link

    total = args.warmup + args.messages
    batch = 500
    ap_port, gcs_port = free_udp_port(), free_udp_port()
    ap_ep = Endpoint(f"udpin:{LOCAL}:{ap_port}", Link.AUTOPILOT)
    gcs_ep = Endpoint(f"udpin:{LOCAL}:{gcs_port}", Link.GCS)
    runner = Runner(BridgeCore(load_profile(str(DEFAULT_PROFILE))), ap_ep, [gcs_ep])
    ap, gcs = udp_socket(), udp_socket()
    tel = Telemetry()
    gcs_packer = Packer(GCS_SYS, GCS_COMP)
    gcs.sendto(gcs_packer.pack(heartbeat_gcs()), (LOCAL, gcs_port))
    # Forwarded-only telemetry is prepacked and cycled (the core ignores its stamps); the estimator's
    # inputs are packed as they go, stamped on the simulated clock handed to the runner (3 kHz), so
    # the estimator runs its normal path (stamps never jump back: no "reboots").
    cycle = [tel.frame(CHEAP_MIX[i % len(CHEAP_MIX)], 100.0 + i / 3000.0) for i in range(1200)]
    ekf_kinds = ("WHEEL_DISTANCE", "ATTITUDE", "SYSTEM_TIME")
    requests = [gcs_packer.pack(body_velocity_request(k, 0.1 * k, 0.05 * k)) for k in range(10)]
    rss: list[tuple[int, float, int]] = []
    checkpoints = sorted({args.warmup, *(args.warmup + k * args.messages // 4 for k in range(1, 5))})
    sent = 0
    t_s = 100.0
    start = time.monotonic()
    try:
        while sent < total:
            for i in range(batch):
                n = sent + i
                if n % 50 == 0:
                    gcs.sendto(requests[(n // 50) % 10], (LOCAL, gcs_port))
                elif n % 12 == 1:  # 1/12 of the stream: wheels, attitude, time in turn
                    ap.sendto(tel.frame(ekf_kinds[(n // 12) % 3], t_s + i / 3000.0), (LOCAL, ap_port))
                else:
                    ap.sendto(cycle[n % len(cycle)], (LOCAL, ap_port))
            sent += batch
            t_s += batch / 3000.0
            runner.step(t_s)
            drain(gcs)
            drain(ap)
            if checkpoints and sent >= checkpoints[0]:
                checkpoints.pop(0)
                rss.append((sent, time.monotonic() - start, self_rss_kb()))
    finally:
        runner.close()
        ap.close()
        gcs.close()
    rx = ap_ep.rx_frames + gcs_ep.rx_frames
    base_kb = rss[0][2]
    rows = [[n, f"{t:.1f}", kb / 1024.0, (kb - base_kb) / 1024.0] for n, t, kb in rss]
    print_table(f"5. memory: VmRSS of the Runner + BridgeCore (in-process, real UDP endpoints), 90% forwarded-only "
                f"telemetry, 8% WHEEL_DISTANCE/ATTITUDE/SYSTEM_TIME, 2% requests; first row after {args.warmup:,} "
                "warm-up messages",
                ["messages_sent", "elapsed_s", "rss_mb", "growth_mb"], rows)
    growth = (rss[-1][2] - base_kb) / 1024.0
    measured = rss[-1][0] - rss[0][0]
    print(f"growth over {measured:,} messages after warm-up: {growth:.2f} MB (target < 5 MB "
          f"[{'met' if growth < 5 else 'MISSED'}]); runner received {rx:,} frames "
          f"(rx_bad {ap_ep.rx_bad + gcs_ep.rx_bad}), forwarded {runner.forwarded:,}, consumed {runner.consumed:,}")


def bench_memory_subprocess(args: argparse.Namespace) -> None:
    """Closed loop: at most `window` forwarded frames in flight, so the bridge runs flat out and
    nothing is dropped; the mix is 90% forwarded telemetry (prepacked), 8% WHEEL_DISTANCE / ATTITUDE
    stamped with the real elapsed time (the estimator runs its normal path), 2% velocity requests."""
    total = args.warmup + args.messages
    with tempfile.TemporaryDirectory() as tmp:
        bridge = Bridge(str(DEFAULT_PROFILE), tmp)
        ap, gcs = udp_socket(), udp_socket()
        tel = Telemetry()
        gcs_packer = Packer(GCS_SYS, GCS_COMP)
        cheap = [tel.frame(CHEAP_MIX[i % len(CHEAP_MIX)], 100.0 + i * 0.01) for i in range(1200)]
        requests = [gcs_packer.pack(body_velocity_request(k, 0.1 * k, 0.05 * k)) for k in range(10)]
        rss: list[tuple[int, float, int]] = []
        buf = bytearray(2048)
        sent = fwd_sent = received = lost = 0
        checkpoints = sorted({args.warmup, *(args.warmup + k * args.messages // 4 for k in range(1, 5))})
        try:
            bridge.wait_up(ap, gcs)
            start = time.monotonic()
            last_progress = start
            while sent < total and time.monotonic() - start < args.max_s:
                while sent < total and fwd_sent - received - lost < args.window:
                    if sent % 50 == 0:
                        gcs.sendto(requests[(sent // 50) % 10], bridge.gcs_addr)  # consumed, not forwarded
                    else:
                        if sent % 12 == 1:
                            kind = "WHEEL_DISTANCE" if sent % 24 == 1 else "ATTITUDE"
                            frame = tel.frame(kind, 100.0 + time.monotonic() - start)
                        else:
                            frame = cheap[sent % len(cheap)]
                        ap.sendto(frame, bridge.ap_addr)
                        fwd_sent += 1
                    sent += 1
                    if checkpoints and sent >= checkpoints[0]:
                        checkpoints.pop(0)
                        time.sleep(0.2)  # let it catch up before reading its RSS
                        rss.append((sent, time.monotonic() - start, bridge.rss_kb()))
                select.select([gcs], [], [], 0.05)
                got = 0
                while True:
                    try:
                        k = gcs.recv_into(buf)
                    except BlockingIOError:
                        break
                    got += forwarded_frames(buf, k)
                received += got
                drain(ap)
                now = time.monotonic()
                if got:
                    last_progress = now
                elif now - last_progress > 1.0:  # nothing back for a second: what is in flight is lost
                    lost += fwd_sent - received - lost
                    last_progress = now
            if not rss or rss[-1][0] != sent:
                time.sleep(0.2)
                rss.append((sent, time.monotonic() - start, bridge.rss_kb()))
        finally:
            stats = bridge.stop()
            ap.close()
            gcs.close()
    links = stats.get("links", {})
    rx = sum(v.get("rx", 0) for v in links.values())
    base_kb = rss[0][2]
    rows = [[n, f"{t:.1f}", kb / 1024.0, (kb - base_kb) / 1024.0] for n, t, kb in rss]
    print_table(f"5. memory: bridge VmRSS, closed loop (<= {args.window} in flight), 90% forwarded telemetry, 8% "
                f"WHEEL_DISTANCE/ATTITUDE, 2% requests; first row after {args.warmup:,} warm-up messages",
                ["messages_sent", "elapsed_s", "rss_mb", "growth_mb"], rows)
    growth = (rss[-1][2] - base_kb) / 1024.0
    measured = rss[-1][0] - rss[0][0]
    print(f"growth over {measured:,} messages after warm-up: {growth:.2f} MB (target < 5 MB over 1,000,000 "
          f"[{'met' if growth < 5 and measured >= 1_000_000 else 'MISSED' if growth >= 5 else 'not reached'}]); "
          f"bridge received {rx:,} frames, rx_bad {sum(v.get('rx_bad', 0) for v in links.values())}, "
          f"lost in flight {lost:,}")
