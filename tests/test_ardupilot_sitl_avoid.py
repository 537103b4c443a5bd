"""Issue 43 item 6 (obstacles) on a real ArduPilot Rover SITL: a wall 10 m ahead, GUIDED, vx 1.0 m/s for 20 s.

ArduPilot alone (its own skid mixer, SERVO1/3_FUNCTION 73/74, the requests sent to it directly) is the anchor,
in the same run; then the bridge (per-wheel passthrough and SITL's wheel encoders, `rover-bridge run` with
params/ardupilot-sitl-skid.toml). Each SITL boots with `PRX1_TYPE 10` (SITL's proximity sensor sees the inclusion
polygon fence as walls; it needs a reboot, so it is in the boot's .parm), `FENCE_ENABLE 0` (nothing breaches),
`AVOID_ENABLE 2` (proximity only), `AVOID_MARGIN 2`. After GPS and EKF settle a 20 m x 40 m inclusion fence is
uploaded with the mission protocol, its near wall 10 m ahead of the rover (from the truth's position and yaw).
The rover's distance to that wall is measured from the simulator's truth (SIMSTATE) against the wall's line.

Through the bridge the rover must come no closer than 1.0 m nor than ArduPilot alone's closest less 0.3 m, rest
no farther than ArduPilot alone's rest distance plus 1.0 m (not timid), and back away when asked (vx -0.5 m/s
for 3 s). The bridge must have seen the autopilot's DISTANCE_SENSOR (its --stats-json), so a failure is about
avoidance, not a missing sensor. About 3 minutes (the two SITLs one after the other).

Runs only when ROVER_BRIDGE_ARDUROVER names an `ardurover` binary. SITL instances 11 (bridge) and 12 (alone).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_sitl_control as bench
from ardupilot_rig import BINARY, REAL_SITL, WALL_AHEAD_M, Bridge, Sitl, alone, through_bridge, wall_ahead

pytestmark = REAL_SITL
INSTANCE_BRIDGE, INSTANCE_ALONE = 11, 12
AVOID_PARAMS = "PRX1_TYPE 10\nFENCE_ENABLE 0\nAVOID_ENABLE 2\nAVOID_MARGIN 2\n"
DRIVE_M_S, DRIVE_S = 1.0, 20.0
BACK_M_S, BACK_S = -0.5, 3.0
REST_WINDOW_S = 1.0  # the rest distance: the mean over the drive's last second


@dataclass(frozen=True)
class Approach:
    closest_m: float
    rest_m: float
    backed_m: float  # how much farther from the wall after backing


def approach(driver: bench.Driver) -> Approach:
    """The fence, GUIDED, armed; vx 1.0 m/s for 20 s, then vx -0.5 m/s for 3 s; distances from the truth."""
    sitl = driver.sitl
    bench.wait_ready(sitl)
    n0, e0, yaw = wall_ahead(sitl)
    time.sleep(2.0)  # the proximity sensor's first sweep of the new walls

    def to_wall_m(t0: float, t1: float) -> list[float]:
        return [WALL_AHEAD_M - ((n - n0) * math.cos(yaw) + (e - e0) * math.sin(yaw))
                for n, e in sitl.track(t0, t1)]

    driver.set_mode(bench.MANUAL)
    driver.arm()
    driver.set_mode(bench.GUIDED)
    driver.velocity(0.0, 0.0)
    time.sleep(1.0)
    t0 = time.monotonic()
    driver.velocity(DRIVE_M_S, 0.0)
    time.sleep(DRIVE_S)
    t1 = time.monotonic()
    driver.velocity(BACK_M_S, 0.0)
    time.sleep(BACK_S)
    t2 = time.monotonic()
    driver.velocity(0.0, 0.0)
    time.sleep(1.0)
    driver.gcs.each = None
    drive = to_wall_m(t0, t1)
    rest = to_wall_m(t1 - REST_WINDOW_S, t1)
    back = to_wall_m(t2 - 0.5, t2)
    assert drive and rest and back, "no truth"
    rest_m = sum(rest) / len(rest)
    return Approach(min(drive), rest_m, sum(back) / len(back) - rest_m)


def run_alone(workdir: Path) -> Approach:
    with alone(BINARY, INSTANCE_ALONE, bench.COMMON + AVOID_PARAMS, workdir, bench.STREAMS) as (sitl, gcs):
        return approach(bench.Driver("ArduPilot alone", sitl, gcs))


def run_bridge(workdir: Path) -> tuple[tuple[Approach, int], dict[str, int]]:
    """The approach through the bridge and how many DISTANCE_SENSOR its GCS saw; its `command` counters."""
    def drive(sitl: Sitl, bridge: Bridge) -> tuple[Approach, int]:
        return approach(bench.Driver("bridge", sitl, bridge.gcs)), len(bridge.gcs.of("DISTANCE_SENSOR"))

    return through_bridge(BINARY, INSTANCE_BRIDGE, bench.BRIDGE_PARAMS + AVOID_PARAMS, workdir, bench.STREAMS, drive)


def test_the_bridge_stops_short_of_a_wall_as_ardupilot_alone_does(tmp_path: Path) -> None:
    alone = run_alone(tmp_path)
    (ours, forwarded), counters = run_bridge(tmp_path)
    avoid = {k: v for k, v in counters.items() if k.startswith("avoid.")}
    table = (f"closest {ours.closest_m:.2f} m / alone {alone.closest_m:.2f} m; rest {ours.rest_m:.2f} m / alone "
             f"{alone.rest_m:.2f} m; backed {ours.backed_m:.2f} m / alone {alone.backed_m:.2f} m; bridge {avoid}, "
             f"DISTANCE_SENSOR at its GCS {forwarded}")
    print(table)
    # The anchor itself stopped short of the wall (else PRX1_TYPE 10 or the fence did not take: nothing to judge).
    assert 0.5 < alone.closest_m < 2.5 and alone.rest_m < 3.5, table
    # The bridge saw the autopilot's proximity sectors (a failure below is the avoidance's, not a missing sensor).
    assert counters.get("avoid.sensor_seen", 0) >= 1 and forwarded > 0, table
    assert ours.closest_m >= max(1.0, alone.closest_m - 0.3), table
    assert ours.rest_m <= alone.rest_m + 1.0, table
    assert ours.backed_m >= 0.5 and alone.backed_m >= 0.5, table  # backs away when asked (1.5 m asked)
