"""`bench_bridge.py contention`: the cpu table's nominal load while numpy keeps both cores busy, at normal
priority and with the systemd unit's scheduling (and the `_burn` helper process that keeps them busy).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import select
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from bridge.harness import (
    MSG_OVERRIDE,
    REPO,
    SO_TIMESTAMPNS,
    drain,
    keep_stamped,
    pct,
    print_table,
    replay_frames,
    self_cmd,
    udp_socket,
    write_profile,
)
from bridge.process import Bridge
from rover_bridge.mavlink.dialect import mavlink

# ------------------------------------------------------------------------------------- 4b. contention

UNIT = REPO / "deploy" / "rover-bridge.service"
CHRT_POLICY = {"fifo": "-f", "rr": "-r", "batch": "-b", "idle": "-i", "other": "-o"}


def unit_settings() -> dict[str, str]:
    """The [Service] keys of the shipped systemd unit (comments and continuations skipped)."""
    return dict(line.split("=", 1) for line in UNIT.read_text().splitlines()
                if "=" in line and not line.startswith(("#", " ")))


def unit_prefix(settings: dict[str, str]) -> list[str]:
    """The command prefix that runs a process as the unit's scheduling does (CPUSchedulingPolicy=,
    CPUSchedulingPriority=, Nice=)."""
    prefix: list[str] = []
    if "Nice" in settings:
        prefix += ["nice", "-n", settings["Nice"]]
    policy = settings.get("CPUSchedulingPolicy")
    if policy:
        prefix += ["chrt", CHRT_POLICY[policy], settings.get("CPUSchedulingPriority", "0")]
    return prefix


def burn_main(seconds: float, threads: int) -> None:
    """Keep `threads` cores busy for `seconds` with numpy (matrix products release the GIL); prints the
    products done. Started with one BLAS thread each (OPENBLAS_NUM_THREADS=1 and the like)."""
    import threading

    import numpy as np

    a = np.random.default_rng(0).random((192, 192))
    done = [0] * threads
    end = time.monotonic() + seconds

    def work(k: int) -> None:
        while time.monotonic() < end:
            a @ a
            done[k] += 1

    workers = [threading.Thread(target=work, args=(k,)) for k in range(threads)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    print(sum(done), flush=True)


def cpu_idle_fraction(before: list[int], after: list[int]) -> float:
    """The machine's idle share between two /proc/stat 'cpu' lines (idle + iowait over all)."""
    delta = [b - a for a, b in zip(before, after, strict=True)]
    return (delta[3] + delta[4]) / max(1, sum(delta))


def proc_stat_cpu() -> list[int]:
    return [int(x) for x in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]


@contextlib.contextmanager
def realtime_harness(priority: int) -> Iterator[bool]:
    """The harness (autopilot and ground station) at a real-time priority above the bridge's while it
    measures: it stands for hardware outside this computer, its traffic and stamps stay on time. False
    (and nothing changed) where the process may not."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, AttributeError, OSError):
        yield False
        return
    try:
        yield True
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def outside_deadlines(stamps: list[float], period_s: float) -> tuple[Any, list[tuple[float, float]]]:
    """The overrides as the autopilot saw them (kernel stamps), accounted by the bridge's own definition
    (rover_bridge.app.deadlines: only written times count, so arrival times find the same ones late):
    the accounting, and (stamp, time past its grid point) of each on-grid override."""
    from rover_bridge.app.deadlines import OVERRIDES, OutputTiming, Schedule
    from rover_bridge.params import Profile

    t = Profile().timing
    out = OutputTiming(Schedule(OVERRIDES, period_s), t.budget_fraction, t.deadline_fraction)
    on_grid = []
    for at in stamps:
        past = out.record(at, at)
        if past is not None:
            on_grid.append((at, past))
    return out, on_grid


def contention_run(name: str, prefix: list[str], profile: str, tmp: str, args: argparse.Namespace,
                   watchdog_usec: int) -> list[Any]:
    """One bridge at the cpu table's nominal load for warm-up + seconds, both cores kept busy by numpy."""
    notify_path = os.path.join(tmp, f"notify-{name}.sock")
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(notify_path)
    notify.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    notify.setblocking(False)
    br = Bridge(profile, tmp, f"bridge-{name}", prefix=prefix,
                env_extra={"NOTIFY_SOCKET": notify_path, "WATCHDOG_USEC": str(watchdog_usec)})
    ap, gcs = udp_socket(True), udp_socket()
    ap_frames: list[tuple[bytes, float]] = []
    pings: list[float] = []
    requests: list[float] = []
    total = args.warmup_s + args.seconds
    burner = None
    try:
        br.wait_up(ap, gcs, ap_frames=ap_frames)
        blas_one = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
        burner = subprocess.Popen(self_cmd("_burn", str(total + 1.0), "2"), stdout=subprocess.PIPE, cwd=REPO,
                                  env={**os.environ, **blas_one})
        traffic = replay_frames(total)
        # The socket queues only net.unix.max_dgram_qlen (10) pings, and nothing read it while the bridge came
        # up: the bridge's later pings were refused meanwhile. Gaps count from here.
        _notify_messages(notify)
        with realtime_harness(args.harness_priority) as rt:
            idle0 = proc_stat_cpu()
            start, traffic_start = time.monotonic(), time.time()
            for offset, what, to_gcs, frame in traffic:
                target = start + offset
                while (now := time.monotonic()) < target:
                    select.select([ap, gcs, notify], [], [], target - now)
                    keep_stamped(ap, ap_frames)
                    drain(gcs)
                    pings += [stamp for data, stamp in _notify_messages(notify) if data == b"WATCHDOG=1"]
                if what == "REQUEST":
                    requests.append(time.time())
                (gcs if to_gcs else ap).sendto(frame, br.gcs_addr if to_gcs else br.ap_addr)
            idle = cpu_idle_fraction(idle0, proc_stat_cpu())
        settle = time.monotonic() + 0.2
        while (now := time.monotonic()) < settle:
            select.select([ap, notify], [], [], settle - now)
            keep_stamped(ap, ap_frames)
            pings += [stamp for data, stamp in _notify_messages(notify) if data == b"WATCHDOG=1"]
    finally:
        stats = br.stop()
        keep_stamped(ap, ap_frames)
        burned = burner.communicate(timeout=30)[0].decode().strip() if burner is not None else "-"
        for sock in (ap, gcs, notify):
            sock.close()
    parser = mavlink.MAVLink(None)
    overrides: list[tuple[float, int]] = []  # (kernel stamp, left channel)
    for data, stamp in ap_frames:
        for m in parser.parse_buffer(data) or []:
            if m.get_msgId() == MSG_OVERRIDE:
                overrides.append((stamp, int(m.chan1_raw)))
    # The stop on SIGTERM (neutral, then release: not periodic outputs, the bridge does not count them).
    first_release = next((i for i, (_, ch) in enumerate(overrides) if ch == 0), len(overrides))
    stamps = [t for t, _ in overrides[:max(0, first_release - 1)]]
    period = 1.0 / args.rate_hz
    outside, on_grid = outside_deadlines(stamps, period)  # the whole run: what the bridge's counters cover
    inside = stats.get("timing", {}).get("overrides", {})
    measured_from = traffic_start + args.warmup_s  # the target's window: after the warm-up
    window = [t for t in stamps if t >= measured_from]
    window_past = [(t, past) for t, past in on_grid if t >= measured_from]
    window_late = [t for t, past in window_past if past > outside.deadline_s]
    periods_ms = [(b - a) * 1e3 for a, b in itertools.pairwise(window)]
    latency_ms: list[float] = []
    k = 0
    for t_req in requests:
        while k < len(stamps) and stamps[k] < t_req:
            k += 1
        if k < len(stamps) and t_req >= measured_from:
            latency_ms.append((stamps[k] - t_req) * 1e3)
    gaps_ms = [(b - a) * 1e3 for a, b in itertools.pairwise(pings)]
    late_pct = 100.0 * len(window_late) / max(1, len(window))
    if window_late:
        print(f"{name}: late overrides at " + ", ".join(f"{t - traffic_start:.2f}" for t in window_late[:20])
              + f" s into the run{' ...' if len(window_late) > 20 else ''}")
    worst_ms = max((past for _, past in window_past), default=0.0) * 1e3
    return [name, " ".join(prefix) or "-", "yes" if rt else "no", f"{100 * (1 - idle):.0f}", burned, len(window),
            f"{pct(periods_ms, 99):.2f}", f"{max(periods_ms):.1f}", len(window_late), f"{late_pct:.3f}",
            f"{worst_ms:.1f}", outside.late, inside.get("late", "-"), inside.get("over_budget", "-"),
            f"{pct(latency_ms, 50):.2f}", f"{pct(latency_ms, 99):.2f}", f"{max(latency_ms):.1f}", len(pings),
            f"{max(gaps_ms):.0f}" if gaps_ms else "-", br.proc.returncode]


def _notify_messages(sock: socket.socket) -> list[tuple[bytes, float]]:
    out: list[tuple[bytes, float]] = []
    keep_stamped(sock, out)
    return out


@contextlib.contextmanager
def autogroup_nice(nice: int | None) -> Iterator[str]:
    """With `nice`, this session's scheduler autogroup (the bench, the bridge and the numpy load share it)
    at that nice while it runs: on a machine shared with other sessions, whose autogroups otherwise split
    the CPU with this one, -20 approximates a machine where only the numpy load competes. Says what held."""
    path = Path("/proc/self/autogroup")
    if nice is None or not path.exists():
        yield path.read_text().strip() if path.exists() else "no autogroup"
        return
    before = path.read_text().split()[-1]
    try:
        path.write_text(str(nice))
    except OSError as exc:
        yield f"autogroup nice not set ({exc.strerror})"
        return
    try:
        yield path.read_text().strip()
    finally:
        path.write_text(before)


def bench_contention(args: argparse.Namespace) -> None:
    settings = unit_settings()
    watchdog_usec = round(float(settings.get("WatchdogSec", "1")) * 1e6)
    modes = [("normal", []), ("unit", unit_prefix(settings))]
    rows = []
    with tempfile.TemporaryDirectory() as tmp, autogroup_nice(args.autogroup_nice) as group:
        profile = write_profile({"command.rate_hz": f"{args.rate_hz}"}, tmp)
        for name, prefix in modes if not args.unit_first else modes[::-1]:
            rows.append(contention_run(name, prefix, profile, tmp, args, watchdog_usec))
    load = os.getloadavg()
    print_table(f"4b. held under load: the cpu table's nominal traffic ({args.rate_hz:.0f} Hz overrides) for "
                f"{args.warmup_s:.0f} + {args.seconds:.0f} s per run while numpy keeps both cores busy (2 threads, "
                f"normal priority); WatchdogSec={watchdog_usec / 1e6:g}. Overrides as the autopilot received them "
                f"(kernel stamps) over the last {args.seconds:.0f} s: period, late (past 95 % of the period after the "
                "grid point, rover_bridge.app.deadlines), request -> the first override after it; over the whole "
                "run (start-up included): late seen from outside beside the bridge's own count (--stats-json); "
                f"machine load average {load[0]:.1f} / {load[1]:.1f} at the end; scheduler group {group}",
                ["sched", "prefix", "harness_rt", "busy_%", "products", "overrides", "period_p99_ms",
                 "period_max_ms", "late", "late_%", "worst_past_ms", "run_late_seen", "run_late_counted",
                 "over_budget", "req_p50_ms", "req_p99_ms", "req_max_ms", "pings", "ping_gap_max_ms", "exit"], rows)
    for row in rows:
        name, late_pct, seen, counted, gap = row[0], float(row[9]), row[11], row[12], row[18]
        agree = "agree" if str(seen) == str(counted) else "DISAGREE"
        target = (f"late {late_pct:.3f} % (target <= 0.1 % [{'met' if late_pct <= 0.1 else 'MISSED'}])"
                  if name == "unit" else f"late {late_pct:.3f} % (reported beside the unit's)")
        gap_ok = gap != "-" and float(gap) <= watchdog_usec / 2e3
        print(f"{name}: {target}; whole run, bridge and bench {agree} ({counted} / {seen}); longest watchdog gap "
              f"{gap} ms (target <= {watchdog_usec / 2e3:.0f} ms [{'met' if gap_ok else 'MISSED'}])")
        if row[19] != 0:  # SIGTERM'd bridges exit 0; 1 is the stop guard's (the loop stood for loop_watchdog_s)
            print(f"{name}: the bridge exited {row[19]} before the end (its log says why): no counters of its own")
