"""`bench_bridge.py latency`: GCS request datagram in -> RC_CHANNELS_OVERRIDE datagram out, next to a pymavlink
UDP echo; value latency (the first override that shows the request); telemetry forwarding latency.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import select
import socket
import struct
import subprocess
import tempfile
import time
from collections.abc import Callable
from typing import Any

from bridge.harness import (
    AP_COMP,
    AP_SYS,
    DEFAULT_PROFILE,
    GCS_COMP,
    GCS_SYS,
    LOCAL,
    MSG_OVERRIDE,
    REPO,
    Packer,
    body_velocity_request,
    drain,
    free_udp_port,
    msg_id,
    pct,
    print_table,
    recv_stamped,
    self_cmd,
    udp_socket,
)
from bridge.process import Heartbeats, bridges, stop_all
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.params import load_profile

# ------------------------------------------------------------------------------------- 1. latency

def wait_for(sock: socket.socket, want: Callable[[bytes], bool], timeout_s: float) -> float | None:
    """Kernel receive time of the first datagram on `sock` that `want`s, or None on timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        while (got := recv_stamped(sock)) is not None:
            if want(got[0]):
                return got[1]
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        select.select([sock], [], [], left)


def bench_latency(args: argparse.Namespace) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        under_test = bridges(args, str(DEFAULT_PROFILE), tmp)
        echo_port = free_udp_port()
        # The echo runs under the same BENCH_PREFIX as the bridges, so the comparison stays fair.
        echo = subprocess.Popen([*os.environ.get("BENCH_PREFIX", "").split(), *self_cmd("_echo", str(echo_port))],
                                stdout=subprocess.PIPE, cwd=REPO)
        socks = [(udp_socket(True), udp_socket()) for _ in under_test]
        echo_sock = udp_socket(True)
        stats: list[dict[str, Any]] = []
        is_override: Callable[[bytes], bool] = lambda f: msg_id(f) == MSG_OVERRIDE  # noqa: E731
        any_frame: Callable[[bytes], bool] = lambda f: True  # noqa: E731
        # (name, send socket, destination, receive socket, which frames count as the answer)
        paths = [(f"{br.name}: request -> override", gcs, br.gcs_addr, ap, is_override)
                 for br, (ap, gcs) in zip(under_test, socks, strict=True)]
        paths.append(("pymavlink echo: round trip", echo_sock, (LOCAL, echo_port), echo_sock, any_frame))
        samples: list[list[float]] = [[] for _ in paths]
        lost = [0] * len(paths)
        try:
            assert echo.stdout is not None
            echo.stdout.readline()
            for br, (ap, gcs) in zip(under_test, socks, strict=True):
                br.wait_up(ap, gcs)
            beats = [Heartbeats(ap, br, gcs) for br, (ap, gcs) in zip(under_test, socks, strict=True)]
            packer = Packer(GCS_SYS, GCS_COMP)
            next_slot = time.monotonic()
            for i in range(args.requests + 50):  # the first 50 warm up (caches, branch state)
                now = time.monotonic()
                for hb in beats:
                    hb.poll(now)
                for _ap, gcs in socks:
                    drain(gcs)
                frame = packer.pack(body_velocity_request(i, 0.3 + 0.1 * (i % 3), 0.0))
                k = i % len(paths)  # rotate who goes first: no systematic bias from the order
                for which in [*range(k, len(paths)), *range(k)]:
                    _name, tx, dest, rx, want = paths[which]
                    t0 = time.time()
                    tx.sendto(frame, dest)
                    t1 = wait_for(rx, want, 0.5)
                    if i < 50:
                        continue
                    if t1 is None:
                        lost[which] += 1
                    else:
                        samples[which].append((t1 - t0) * 1e6)
                next_slot += args.interval_ms / 1000.0
                pause = next_slot - time.monotonic()
                if pause > 0:
                    time.sleep(pause)
                for ap, _gcs in socks:
                    drain(ap)
        finally:
            echo.kill()
            echo.wait()
            stats = stop_all(under_test, [sock for pair in socks for sock in pair])
            echo_sock.close()
    rows = [[name, len(xs), n_lost, pct(xs, 50), pct(xs, 99), max(xs)]
            for (name, *_rest), xs, n_lost in zip(paths, samples, lost, strict=True)]
    print_table(f"1. latency, {args.requests} requests, one every {args.interval_ms} ms, microseconds "
                "(kernel receive stamps)", ["path", "n", "lost", "p50_us", "p99_us", "max_us"], rows)
    echo_p99 = pct(samples[-1], 99)
    for (name, *_rest), xs in zip(paths[:-1], samples[:-1], strict=True):
        p99 = pct(xs, 99)
        ratio = p99 / echo_p99
        print(f"{name.split(':')[0]}: p99 / echo p99 = {ratio:.2f}  (target: p99 <= 1000 us "
              f"[{'met' if p99 <= 1000 else 'MISSED'}], <= 3x echo [{'met' if ratio <= 3 else 'MISSED'}])")
    for br, st in zip(under_test, stats, strict=True):
        print(f"{br.name} counters: accepted {st.get('command', {}).get('requests.accepted')}, "
              f"outputs {st.get('command', {}).get('outputs.sent')}")
    value_latency(args)
    forward_latency(args)


def collect_overrides(sock: socket.socket, parser: Any, out: list[tuple[float, int]]) -> None:
    """Every RC_CHANNELS_OVERRIDE queued on `sock`: (kernel stamp, left PWM)."""
    while (got := recv_stamped(sock)) is not None:
        for m in parser.parse_buffer(got[0]) or []:
            if m.get_msgId() == MSG_OVERRIDE:
                out.append((got[1], int(m.chan1_raw)))


def straight_pwm(v_m_s: float) -> float:
    """The default profile's PWM for driving straight at v (its linear map, no speed curve)."""
    prof = load_profile(DEFAULT_PROFILE)
    trim, span = prof.output.pwm_trim, prof.output.pwm_max - prof.output.pwm_trim
    return trim + span * v_m_s / prof.robot.left_radius_m / prof.robot.max_wheel_rad_s


def value_latency(args: argparse.Namespace) -> None:
    """A GCS alternating 0.2 and 0.3 m/s every 35-65 ms (random spacing, fixed seed); every override
    captured with its kernel stamp. Per request: the first override after it (any value), and the first
    one that moved toward it (left PWM above / below the last override before the request); never
    reflected = no such override before the next request."""
    rng = random.Random(7)
    spacing = [rng.uniform(0.035, 0.065) for _ in range(args.value_requests)]
    with tempfile.TemporaryDirectory() as tmp:
        under_test = bridges(args, str(DEFAULT_PROFILE), tmp)
        rows = []
        for br in under_test:
            ap, gcs = udp_socket(True), udp_socket()
            parser = mavlink.MAVLink(None)
            overrides: list[tuple[float, int]] = []  # (kernel stamp, left PWM)
            requests: list[tuple[float, float]] = []  # (send time, v)
            try:
                br.wait_up(ap, gcs)
                hb = Heartbeats(ap, br, gcs)
                packer = Packer(GCS_SYS, GCS_COMP)

                start = time.monotonic() + 1.0  # the first second warms up
                t_next = start
                for i, gap in enumerate(spacing):
                    while (now := time.monotonic()) < t_next:
                        hb.poll(now)
                        collect_overrides(ap, parser, overrides)
                        select.select([ap], [], [], min(0.005, t_next - now))
                    v = 0.2 if i % 2 == 0 else 0.3
                    t_sent = time.time()
                    gcs.sendto(packer.pack(body_velocity_request(i, v, 0.0)), br.gcs_addr)
                    requests.append((t_sent, v))
                    t_next += gap
                end = time.monotonic() + 0.2
                while time.monotonic() < end:
                    collect_overrides(ap, parser, overrides)
                    time.sleep(0.005)
            finally:
                br.stop()
                ap.close()
                gcs.close()
            first, moved = [], []
            never = 0
            for k, (t_req, v) in enumerate(requests[1:], start=1):
                t_end = requests[k + 1][0] if k + 1 < len(requests) else math.inf
                before = [pwm for t, pwm in overrides if t < t_req]
                after = [(t, pwm) for t, pwm in overrides if t_req <= t < t_end]
                if not before or not after:
                    never += 1
                    continue
                first.append((after[0][0] - t_req) * 1e3)
                # Toward the request from where the wheels were (not from the previous request: the rover
                # may not have reached it); already there counts as shown at once.
                goal = straight_pwm(v)
                if abs(goal - before[-1]) < 1.0:
                    moved.append(first[-1])
                    continue
                up = goal > before[-1]
                hit = next((t for t, pwm in after if (pwm > before[-1]) == up and pwm != before[-1]), None)
                if hit is None:
                    never += 1
                else:
                    moved.append((hit - t_req) * 1e3)
            rows.append([br.name, len(requests) - 1, pct(first, 50), pct(first, 99), pct(moved, 50), pct(moved, 99),
                         never])
    print_table(f"1b. value latency: {args.value_requests} requests alternating 0.2 / 0.3 m/s every 35-65 ms; "
                "ms from the request to the first override, and to the first that moved toward it",
                ["bridge", "n", "first_p50_ms", "first_p99_ms", "moved_p50_ms", "moved_p99_ms", "never_reflected"],
                rows)


def collect_forwarded(sock: socket.socket, got: dict[int, float]) -> None:
    """The VFR_HUD frames of forward_latency queued on `sock`: their number (airspeed) -> kernel stamp."""
    while (item := recv_stamped(sock)) is not None:
        data, stamp = item
        i = 0
        while i + 10 <= len(data) and data[i] == 0xFD:  # every frame of the datagram
            if data[i + 7] == mavlink.MAVLINK_MSG_ID_VFR_HUD and data[i + 5] == AP_SYS:
                got.setdefault(round(struct.unpack_from("<f", data[i:i + 14].ljust(14, b"\0"), 10)[0]), stamp)
            i += 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)


def forward_latency(args: argparse.Namespace) -> None:
    """Telemetry alone (VFR_HUD, forwarded raw) every 15-25 ms (random spacing, fixed seed) and nothing
    else: no request wakes the bridge, so a frame waits for the batch (mavlink.autopilot_batch_ms) at
    most. Per frame: its send time to the kernel stamp of the datagram that brought it to the GCS."""
    rng = random.Random(11)
    spacing = [rng.uniform(0.015, 0.025) for _ in range(args.forward_frames)]
    mav = mavlink.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
    frames = []
    for i in range(len(spacing)):
        frames.append(bytes(mavlink.MAVLink_vfr_hud_message(float(i + 1), 0.0, 0, 0, 0.0, 0.0).pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    with tempfile.TemporaryDirectory() as tmp:
        under_test = bridges(args, str(DEFAULT_PROFILE), tmp)
        rows = []
        for br in under_test:
            ap, gcs = udp_socket(), udp_socket(True)
            sent: dict[int, float] = {}
            got: dict[int, float] = {}
            try:
                br.wait_up(ap, gcs)
                hb = Heartbeats(ap, br, gcs)
                t_next = time.monotonic() + 1.0
                for i, gap in enumerate(spacing):
                    while (now := time.monotonic()) < t_next:
                        hb.poll(now)
                        collect_forwarded(gcs, got)
                        drain(ap)
                        select.select([gcs], [], [], min(0.005, t_next - now))
                    sent[i + 1] = time.time()
                    ap.sendto(frames[i], br.ap_addr)
                    t_next += gap
                end = time.monotonic() + 0.3
                while time.monotonic() < end:
                    collect_forwarded(gcs, got)
                    time.sleep(0.005)
            finally:
                br.stop()
                ap.close()
                gcs.close()
            lat = [(got[k] - t) * 1e3 for k, t in sent.items() if k in got]
            rows.append([br.name, len(sent), len(sent) - len(lat), pct(lat, 50), pct(lat, 99), max(lat)])
    print_table(f"1c. telemetry forwarding: {args.forward_frames} autopilot frames every 15-25 ms and nothing "
                "else; ms from the send to the GCS's kernel stamp", ["bridge", "n", "lost", "p50_ms", "p99_ms",
                                                                   "max_ms"], rows)
