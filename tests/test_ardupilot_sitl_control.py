"""Issue 42 on a real ArduPilot Rover SITL: the bridge with the shipped SITL profile (geometry, no loop gains) drives
the speed steps, the arc, the spin, the turn and an 8 m go-to within the targets, side by side with ArduPilot alone
driving the same requests on its own skid mixer in the same run (benchmarks/bench_sitl_control.py's table, about
4 minutes: the two SITLs one after the other).

Runs only when ROVER_BRIDGE_ARDUROVER names an `ardurover` binary (.ci/run sets it to ../shared's prebuilt one).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_sitl_control as bench
from ardupilot_rig import BINARY, REAL_SITL

pytestmark = REAL_SITL
INSTANCE = 8  # SITL's ports 5760 + 10 x instance (and + 1 for ArduPilot alone): not the other real-SITL tests' 4-6
STEPS = ("step 0->0.5", "step 0.5->1.0", "step 1.0->1.5")


def test_steps_turns_and_a_brisk_go_to_against_ardupilot_alone(tmp_path: Path) -> None:
    ours = bench.figures(bench.run_bridge(BINARY, INSTANCE, tmp_path, bench.default_profile(tmp_path), None))
    alone = bench.figures(bench.run_alone(BINARY, INSTANCE + 1, tmp_path))
    table = "\n".join(f"{k}: {ours[k]:.3f} / alone {alone.get(k, float('nan')):.3f}" for k in ours)
    assert ours["SITL clock / wall clock"] > 0.97, f"SITL starved: the figures mean nothing\n{table}"
    for step in STEPS:
        assert ours[f"{step} overshoot %"] <= 10.0, table
        assert abs(ours[f"{step} steady error %"]) <= 2.0, table
    for motion in ("arc", "spin", "turn"):
        assert abs(ours[f"{motion} yaw-rate error %"]) <= 5.0, table
    assert ours["straights yaw-rate rms deg/s"] <= 1.0, table  # no ringing
    assert abs(ours["ODOMETRY path error %"]) <= 2.0, table
    # The go-to: at rest within 1.2 x ArduPilot alone's time, on the target, never past it by more than 0.1 m.
    assert ours["go-to at rest after s"] <= 1.2 * alone["go-to at rest after s"], table
    assert ours["go-to final error m"] <= 0.15 and ours["go-to max past target m"] <= 0.1, table
