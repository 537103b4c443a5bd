"""`rover-bridge fleet` on an emulated fleet: accuracy of the per-rover calibration, and speed on Dask.

The fleet: 6 rovers of the default profile's geometry (0.30 m track, 0.05 m wheels), each with its own
known miscalibration (true track and right/left radius ratio spread over +-5 % of the profile's), 40 logs
in all, written as ground-station .tlogs from the sitl emulator driven in lockstep by a scripted pilot
(RC overrides of the passthrough channels: straight runs, arcs, spins, stops; seeded, so every run writes
the same bytes). `write_fleet` is also what the tests use.

    python benchmarks/bench_fleet.py [--logs-dir DIR] [--duration-s 90] [--workers 1 2]

prints: the accuracy table (truth against what the fleet found, flags), then the speed table (the same
40 logs on a LocalCluster with 1 and with 2 worker processes, start-up included; `replay` alone, in
process, log after log, for the per-log throughput) and the machine's load average while it ran. Measure on a
quiet machine: with the kernel's autogroup scheduling on (it says so), a loaded machine gives this session one
share of the CPU however many worker processes it starts.
"""

from __future__ import annotations

import argparse
import os
import random
import struct
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sitl import Emulator, Scenario, VehicleConfig
from sitl.mav import mavlink

NOMINAL_TRACK_M = 0.30
NOMINAL_RADIUS_M = 0.05
TRIM_US = 1500
START_UNIX_S = 1_790_000_000.0  # 2026-09-21: the first log of every rover
DAY_S = 86_400.0


@dataclass(frozen=True)
class EmulatedRover:
    name: str
    system_id: int
    track_scale: float  # truth: effective track / the profile's
    radius_ratio: float  # truth: right wheel radius / left
    logs: int
    gyro_bias_rad_s: float = 0.002

    def vehicle(self, **overrides: object) -> VehicleConfig:
        q = self.radius_ratio
        settings: dict[str, object] = dict(
            start_armed=True, wheel_radius_m=NOMINAL_RADIUS_M, track_width_m=NOMINAL_TRACK_M,
            true_track_width_m=NOMINAL_TRACK_M * self.track_scale,
            true_left_radius_m=NOMINAL_RADIUS_M * 2.0 / (1.0 + q),
            true_right_radius_m=NOMINAL_RADIUS_M * 2.0 * q / (1.0 + q),
            gyro_bias_rad_s=self.gyro_bias_rad_s, rate_extra1_hz=20.0, rate_position_hz=2.0, rate_rc_channels_hz=10.0,
            rate_raw_sensors_hz=0.0, physics_dt_s=0.01)
        settings.update(overrides)
        return VehicleConfig(**settings)  # type: ignore[arg-type]


# Truths chosen away from the 2 % flag threshold on both sides, so that a 0.5 % error cannot move a rover
# across it: flagged are the rovers with a value 3 % or more off, never those within 1 %.
FLEET = (
    EmulatedRover("rover-a", 11, 1.000, 1.000, 7),
    EmulatedRover("rover-b", 12, 1.010, 0.990, 7),
    EmulatedRover("rover-c", 13, 1.050, 1.000, 7),
    EmulatedRover("rover-d", 14, 0.950, 1.030, 7),
    EmulatedRover("rover-e", 15, 1.000, 0.950, 6),
    EmulatedRover("rover-f", 16, 1.035, 1.045, 6),
)


def drive_script(seed: int, duration_s: float) -> list[tuple[float, int, int]]:
    """(duration_s, left PWM, right PWM) segments: straight runs, arcs, spins both ways and stops."""
    rng = random.Random(seed)
    out: list[tuple[float, int, int]] = [(2.0, TRIM_US, TRIM_US)]
    total = 2.0
    while total < duration_s - 2.0:
        kind = rng.choice(("straight", "straight", "arc", "spin", "stop"))
        d = rng.uniform(2.0, 5.0)
        base = rng.choice((-1, 1, 1, 1)) * rng.randint(150, 400)
        if kind == "straight":
            left, right = base, base
        elif kind == "arc":
            turn = rng.choice((-1, 1)) * rng.randint(60, 200)
            left, right = base - turn, base + turn
        elif kind == "spin":
            s = rng.choice((-1, 1)) * rng.randint(150, 300)
            left, right = -s, s
        else:
            left = right = 0
            d = rng.uniform(0.5, 1.5)
        out.append((d, TRIM_US + left, TRIM_US + right))
        total += d
    out.append((max(0.5, duration_s - total), TRIM_US, TRIM_US))
    return out


def write_log(path: Path, rover: EmulatedRover, seed: int, start_unix_s: float, duration_s: float,
              scenario: Scenario | None = None, script: list[tuple[float, int, int]] | None = None,
              drop: tuple[str, ...] = (), **vehicle: object) -> None:
    """One ground-station .tlog of `rover` driven by `script` (default drive_script(seed)): the emulator's
    frames but those of the types in `drop`, stamped from start_unix_s on."""
    emu = Emulator(vehicle=rover.vehicle(**vehicle), scenario=scenario, seed=seed, system_id=rover.system_id,
                   record_sent=True)
    pilot = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    dt_s = 0.02
    sent = emu.sent_log
    assert sent is not None
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        for seg_s, left, right in script or drive_script(seed, duration_s):
            for i in range(round(seg_s / dt_s)):
                if i % 10 == 0:  # the pilot's overrides at 5 Hz (they lapse after 3 s)
                    ov = pilot.rc_channels_override_encode(rover.system_id, 1, left, 0, right, 0, 0, 0, 0, 0)
                    emu.handle_message(ov, src_system=255)
                emu.step(dt_s)
                for t_s, msg in sent:
                    if msg.get_type() not in drop:
                        f.write(struct.pack(">Q", round((start_unix_s + t_s) * 1e6)) + msg.get_msgbuf())
                sent.clear()


def write_fleet(folder: Path, duration_s: float = 90.0, rovers: tuple[EmulatedRover, ...] = FLEET,
                logs_per_rover: int | None = None) -> list[Path]:
    """The fleet's logs under folder/<rover>/<date>.tlog, every rover's logs a day apart; existing ones kept."""
    paths = []
    for r in rovers:
        for k in range(logs_per_rover if logs_per_rover is not None else r.logs):
            start = START_UNIX_S + k * DAY_S + 3600.0 * r.system_id
            path = folder / r.name / f"{time.strftime('%Y-%m-%d', time.gmtime(start))}.tlog"
            if not path.exists():
                write_log(path, r, seed=1000 * r.system_id + k, start_unix_s=start, duration_s=duration_s)
            paths.append(path)
    return paths


def accuracy_table(reports: list[Any], profile: Any) -> list[str]:
    """Truth against the fleet's per-rover calibration (the 2 % flag threshold)."""
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.fleet.rovers import rovers

    prior = BridgeCore(profile).estimate.calibration_estimate()
    found = {r.rover: r for r in rovers(reports, profile, prior, "both", 0.02)}
    lines = [f"{'rover':10s} {'logs':>4s} {'track truth':>11s} {'found':>16s} {'error':>7s} {'ratio truth':>11s} "
             f"{'found':>16s} {'error':>7s}  flagged (should be)"]
    worst = 0.0
    for t in FLEET:
        r = found[f"{t.name}#{t.system_id}"]
        e_kt, e_q = 100 * (r.track_scale / t.track_scale - 1), 100 * (r.radius_ratio / t.radius_ratio - 1)
        worst = max(worst, abs(e_kt), abs(e_q))
        should = max(abs(t.track_scale - 1), abs(t.radius_ratio - 1)) > 0.02
        lines.append(f"{t.name:10s} {r.logs:4d} {t.track_scale:11.4f} {r.track_scale:8.4f} +-{r.track_scale_sigma:.4f} "
                     f"{e_kt:+6.2f}% {t.radius_ratio:11.4f} {r.radius_ratio:8.4f} +-{r.radius_ratio_sigma:.4f} "
                     f"{e_q:+6.2f}%  {'yes' if r.flagged else 'no':3s} ({'yes' if should else 'no'})"
                     f"{'' if r.flagged == should else '  WRONG'}")
    lines.append(f"worst error {worst:.2f} % (target 0.5 %)")
    return lines


def main(argv: list[str] | None = None) -> int:
    from rover_bridge.app.replay import replay
    from rover_bridge.fleet.analysis import fleet_profile
    from rover_bridge.fleet.cluster import DaskMap
    from rover_bridge.fleet.jobs import expand
    from rover_bridge.params import load_profile

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs-dir", default=None, help="where the fleet's logs are (written if missing)")
    parser.add_argument("--duration-s", type=float, default=90.0, help="each log's length (default %(default)s)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="cluster sizes (default 1 2)")
    parser.add_argument("--params", default=str(Path(__file__).resolve().parents[1] / "params" / "default.toml"))
    args = parser.parse_args(argv)
    folder = Path(args.logs_dir or Path(tempfile.gettempdir()) / "rover-bridge-fleet-bench")
    t0 = time.perf_counter()
    paths = write_fleet(folder, args.duration_s)
    print(f"fleet: {len(paths)} logs of {args.duration_s:.0f} s in {folder} ({time.perf_counter() - t0:.0f} s to "
          f"write or find), {os.cpu_count()} cores")
    autogroup = Path("/proc/sys/kernel/sched_autogroup_enabled")
    if autogroup.exists() and autogroup.read_text().strip() == "1":
        print("note: the kernel's autogroup scheduling is on: this session's processes (both workers included) share "
              "one session's CPU share against other sessions, so the speed-up is only meaningful on a quiet machine")
    profile = fleet_profile(load_profile(args.params))
    jobs = expand([str(folder)])
    loads = [os.getloadavg()[0]]
    runs: dict[int, list[Any]] = {}
    totals: dict[int, float] = {}
    cpu_per_log: dict[int, float] = {}
    print("\nthe same logs on a LocalCluster of N worker processes (start-up: cluster up, workers warmed up):")
    print(f"{'workers':>7s} {'start-up s':>10s} {'run s':>8s} {'total s':>8s} {'logs/s':>7s} {'speed-up':>8s} "
          f"{'worker CPU s/log':>16s} {'CPU / (wall x workers)':>22s}")
    for n in args.workers:
        t0 = time.perf_counter()
        with DaskMap(None, n, progress=False) as dask_map:
            started = dask_map.started_s
            cpu0 = dask_map.worker_cpu_s()
            t1 = time.perf_counter()
            runs[n] = dask_map.run(jobs, profile)
            run_s = time.perf_counter() - t1
            cpu = dask_map.worker_cpu_s() - cpu0
        totals[n] = time.perf_counter() - t0
        cpu_per_log[n] = cpu / len(jobs)
        loads.append(os.getloadavg()[0])
        print(f"{n:7d} {started:10.1f} {run_s:8.1f} {totals[n]:8.1f} {len(jobs) / totals[n]:7.2f} "
              f"{totals[args.workers[0]] / totals[n]:7.2f}x {cpu_per_log[n]:16.2f} {cpu / (run_s * n):22.2f}")
    same = len({tuple(repr(r) for r in v) for v in runs.values()}) == 1
    print("reports identical, field for field, for every cluster size" if same else "REPORTS DIFFER")
    # Per-log throughput: replay alone in this process against the same logs on a 1-worker cluster, in turns
    # (a shared machine's speed drifts: measured side by side, the best of the rounds).
    sample = jobs[:: max(1, len(jobs) // 4)][:4]
    alone_wall, alone_cpu, task_wall, task_cpu = [], [], [], []
    with DaskMap(None, 1, progress=False) as dask_map:
        for _ in range(3):
            t0, c0 = time.perf_counter(), time.process_time()
            for j in sample:
                replay(j.path, profile)
            alone_wall.append((time.perf_counter() - t0) / len(sample))
            alone_cpu.append((time.process_time() - c0) / len(sample))
            t0, c0 = time.perf_counter(), dask_map.worker_cpu_s()
            dask_map.run(sample, profile)
            task_wall.append((time.perf_counter() - t0) / len(sample))
            task_cpu.append((dask_map.worker_cpu_s() - c0) / len(sample))
    loads.append(os.getloadavg()[0])
    print(f"\nper log ({len(sample)} logs, 3 rounds in turns, best round): `replay` alone in this process "
          f"{min(alone_wall):.2f} s wall, {min(alone_cpu):.2f} s CPU; as a task on a 1-worker cluster "
          f"{min(task_wall):.2f} s wall ({100 * (min(task_wall) / min(alone_wall) - 1):+.1f} %), {min(task_cpu):.2f} s "
          f"CPU ({100 * (min(task_cpu) / min(alone_cpu) - 1):+.1f} %)")
    print("\naccuracy (combined per rover, the profile's prior taken out of each log; 2 % flag threshold):")
    print("\n".join(accuracy_table(runs[args.workers[-1]], profile)))
    print(f"\nload average (1 min) before and after each stage: {' '.join(f'{x:.2f}' for x in loads)}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
