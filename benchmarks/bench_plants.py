"""The wheel loop on every plant (issue 42): one table, the issue's metrics per plant, lockstep, ground truth.

    python benchmarks/bench_plants.py             # every plant (about 10 s)
    python benchmarks/bench_plants.py --plant skid --detail
    python benchmarks/bench_plants.py --plant skid --ardupilot ../shared/ardupilot-sitl/build/sitl/bin/ardurover

The plants, the robot, the profile, the drive and the metrics: benchmarks/plants.py. A value over its target is
marked with *; tests/test_plants.py asserts the same per plant. --ardupilot adds a row: the same drive on a real
ArduPilot Rover SITL through the bridge process (benchmarks/plants_sitl.py), what the skid plant stands in for.

Measured (seed 1, the loop as of issue 42), beside the real Rover 4.7 SITL:
    skid          28.83*  0.47   60.63*  121.00*  47.17*  0.11   per step 25.9, 28.4, 28.8, 0.0 %
    ardupilot     97.46* 13.81*  31.23*  149.45*  54.28*  1.01   per step 28.0, 30.0, 97.5, 0.0 %
    ardupilot     95.95* 11.45*  58.07*  165.79*  57.75*  2.87*  per step 28.8, 23.8, 96.0, 0.0 %
    (in both it began to ring by itself 3-4 s into the 1.5 m/s step: the emulated straights are exactly
    symmetric, so the emulator's ringing waits for the arc)
"""

from __future__ import annotations

import argparse
import logging
import sys

import plants

HEADINGS = ("overshoot %", "steady %", "arc turn %", "spin turn %", "yaw rms deg/s", "odometry %")


def row(name: str, values: list[float], targets: list[float] | None = None) -> str:
    cells = []
    for i, v in enumerate(values):
        mark = "*" if targets is not None and v > targets[i] else " "
        cells.append(f"{v:>{len(HEADINGS[i]) - 1}.2f}{mark}")
    return f"{name:<12s}" + "  ".join(f"{c:>{len(h)}s}" for c, h in zip(cells, HEADINGS, strict=True))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--plant", action="append", choices=list(plants.PLANTS), help="only this plant (repeatable)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--detail", action="store_true", help="each step's overshoot and steady error, signed turns")
    ap.add_argument("--ardupilot", metavar="BINARY", help="also drive a real ardurover SITL (about 90 s)")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    targets = [getattr(plants.TARGETS, name) for name in plants.METRICS]
    profile = plants.bench_profile()
    c = profile.control
    print(f"[control] defaults: kp {c.kp}, ki {c.ki_1_s} 1/s, reference {c.reference_s} s, speed "
          f"{c.speed_window_s} s window; robot: the ardupilot-sitl-skid profile's; WHEEL_DISTANCE asked at "
          f"{profile.estimator.stream_rate_hz:g} Hz")
    print("steps 0 -> 0.5 -> 1.0 -> 1.5 -> 0 m/s, arc 0.8 m/s + 0.4 rad/s then straight, spin 0.8 rad/s")
    print(f"{'':12s}" + "  ".join(HEADINGS))
    print(row("target <=", targets))
    for name in args.plant or plants.PLANTS:
        show(name, plants.drive(name, args.seed), targets, args.detail)
    if args.ardupilot:
        import plants_sitl

        show("ardupilot", plants_sitl.drive_ardupilot(args.ardupilot), targets, args.detail)
    return 0


def show(name: str, trace: plants.Trace, targets: list[float], detail: bool) -> None:
    m = plants.metrics(trace)
    print(row(name, [getattr(m, metric) for metric in plants.METRICS], targets))
    if detail:
        over = ", ".join(f"{v:.1f}" for v in plants.step_overshoots_pct(trace))
        steady = ", ".join(f"{v:+.2f}" for v in plants.steady_errors_pct(trace))
        print(f"{'':12s}overshoot per step (0.5, 1.0, 1.5, stop) {over} %; steady (signed) {steady} %; "
              f"arc {plants.turn_error_pct(trace, 'arc', plants.ARC[1]):+.1f} %, spin "
              f"{plants.turn_error_pct(trace, 'spin', plants.SPIN_RAD_S):+.1f} %, odometry "
              f"{plants.odometry_error_pct(trace):+.2f} %")


if __name__ == "__main__":
    sys.exit(main())
