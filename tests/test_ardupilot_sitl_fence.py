"""Issue 43 item 6 (the circle fence) on a real ArduPilot Rover SITL: GUIDED, vx 1.5 m/s for 15 s from home.

ArduPilot alone (its own skid mixer, the requests sent to it directly) is the anchor, in the same run; then the
bridge (per-wheel passthrough, `rover-bridge run` with params/ardupilot-sitl-skid.toml). Each SITL boots with a
circle fence of 12 m around home, `FENCE_MARGIN 2`, `FENCE_ACTION 0` (report only: a breach is measured, not
masked by an RTL or a HOLD), `AVOID_ENABLE 1` (fence only) and no proximity sensor (`PRX1_TYPE 0`). The farthest
distance from home is measured from the simulator's truth (SIMSTATE) against the autopilot's HOME_POSITION, asked
for after arming (Rover moves home there).

Through the bridge the rover must never cross the fence (farthest < FENCE_RADIUS), stop where ArduPilot would
(farthest <= FENCE_RADIUS - FENCE_MARGIN + 0.5 m), not timidly (farthest >= ArduPilot alone's - 1.0 m), and the
bridge must have counted a fence limit (its --stats-json `avoid.fence_*`); what it said (STATUSTEXT "RB: ...")
is printed. About 2 minutes (the two SITLs one after the other).

A second test stores an inclusion polygon over another link (the SITL's own monitor link, as a ground station on a
radio straight to the autopilot would): no MISSION_ACK passes the bridge, so its periodic download must find it
(rover_bridge.command.fence_watch.STORED_REFRESH_S); GUIDED vx 1.0 m/s at its near edge 10 m ahead, the rover must
rest FENCE_MARGIN inside it (within 0.3 m). About 1.5 minutes.

Runs only when ROVER_BRIDGE_ARDUROVER names an `ardurover` binary. SITL instances 14 (bridge) and 15 (alone), 16
(the polygon).
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

from rover_bridge.command.fence_watch import STORED_REFRESH_S
from rover_bridge.mavlink.dialect import mavlink

pytestmark = REAL_SITL
INSTANCE_BRIDGE, INSTANCE_ALONE, INSTANCE_POLYGON = 14, 15, 16
FENCE_RADIUS_M, FENCE_MARGIN_M = 12.0, 2.0
POLYGON_PARAMS = (f"PRX1_TYPE 0\nFENCE_ENABLE 1\nFENCE_TYPE 4\nFENCE_MARGIN {FENCE_MARGIN_M:g}\nFENCE_ACTION 0\n"
                  "AVOID_ENABLE 1\n")
FENCE_PARAMS = (f"PRX1_TYPE 0\nFENCE_ENABLE 1\nFENCE_TYPE 2\nFENCE_RADIUS {FENCE_RADIUS_M:g}\n"
                f"FENCE_MARGIN {FENCE_MARGIN_M:g}\nFENCE_ACTION 0\nAVOID_ENABLE 1\n")
# The truth and outputs as the other real-SITL checks ask for them, and home at 1 Hz (to see that it stays put).
STREAMS = {**bench.STREAMS, mavlink.MAVLINK_MSG_ID_HOME_POSITION: 1_000_000}
DRIVE_M_S, DRIVE_S = 1.5, 15.0  # 22.5 m asked for: far past the fence
REST_WINDOW_S = 1.0  # the rest distance: the mean over the drive's last second


@dataclass(frozen=True)
class Reach:
    farthest_m: float  # from home, over the drive and the second after it
    rest_m: float  # from home, the mean over the drive's last second


def drive_out(driver: bench.Driver) -> Reach:
    """Armed, GUIDED, home read; vx 1.5 m/s straight ahead for 15 s, then 0; distances from the truth."""
    sitl = driver.sitl
    bench.wait_ready(sitl)
    driver.set_mode(bench.MANUAL)
    driver.arm()
    driver.set_mode(bench.GUIDED)
    lat_deg, lon_deg = sitl.home_from_autopilot()
    driver.velocity(0.0, 0.0)
    time.sleep(1.0)
    t0 = time.monotonic()
    driver.velocity(DRIVE_M_S, 0.0)
    time.sleep(DRIVE_S)
    t1 = time.monotonic()
    driver.velocity(0.0, 0.0)
    time.sleep(1.0)
    driver.gcs.each = None
    # Distances are from the home read before the drive: it must not have moved since.
    moved = [(h.latitude, h.longitude) for h in sitl.monitor.of("HOME_POSITION", t0)
             if abs(h.latitude * 1e-7 - lat_deg) > 1e-7 or abs(h.longitude * 1e-7 - lon_deg) > 1e-7]
    assert not moved, f"home moved during the drive: {moved[:3]}"
    drive = [math.hypot(n, e) for n, e in sitl.track(t0)]
    rest = [math.hypot(n, e) for n, e in sitl.track(t1 - REST_WINDOW_S, t1)]
    assert drive and rest, "no truth"
    return Reach(max(drive), sum(rest) / len(rest))


def run_alone(workdir: Path) -> Reach:
    with alone(BINARY, INSTANCE_ALONE, bench.COMMON + FENCE_PARAMS, workdir, STREAMS) as (sitl, gcs):
        return drive_out(bench.Driver("ArduPilot alone", sitl, gcs))


def run_bridge(workdir: Path) -> tuple[tuple[Reach, list[str]], dict[str, int]]:
    """The drive through the bridge and what it said about fences at its GCS; its `command` counters."""
    def drive(sitl: Sitl, bridge: Bridge) -> tuple[Reach, list[str]]:
        result = drive_out(bench.Driver("bridge", sitl, bridge.gcs))
        return result, [t for t in bridge.gcs.texts() if t.startswith("RB:") and "fence" in t.lower()]

    return through_bridge(BINARY, INSTANCE_BRIDGE, bench.BRIDGE_PARAMS + FENCE_PARAMS, workdir, STREAMS, drive)


def test_the_bridge_stays_inside_the_circle_fence_as_ardupilot_alone_does(tmp_path: Path) -> None:
    anchor = run_alone(tmp_path)
    (ours, said), counters = run_bridge(tmp_path)
    avoid = {k: v for k, v in counters.items() if k.startswith("avoid.")}
    table = (f"farthest from home {ours.farthest_m:.2f} m / alone {anchor.farthest_m:.2f} m; at rest "
             f"{ours.rest_m:.2f} m / alone {anchor.rest_m:.2f} m (fence {FENCE_RADIUS_M:g} m, margin "
             f"{FENCE_MARGIN_M:g} m); bridge {avoid}, said {said[:3]}")
    print(table)
    # The anchor itself stopped inside the margin (else the fence or AVOID_ENABLE did not take: nothing to judge).
    assert FENCE_RADIUS_M - FENCE_MARGIN_M - 1.0 < anchor.farthest_m < FENCE_RADIUS_M, table
    assert ours.farthest_m < FENCE_RADIUS_M, table  # never crossed
    assert ours.farthest_m <= FENCE_RADIUS_M - FENCE_MARGIN_M + 0.5, table  # stops where ArduPilot would
    assert ours.farthest_m >= anchor.farthest_m - 1.0, table  # not timid
    assert any("fence" in k and v > 0 for k, v in counters.items()), table  # the bridge's fence limit did it


def test_a_polygon_stored_over_another_link_is_found_and_kept(tmp_path: Path) -> None:
    def drive(sitl: Sitl, bridge: Bridge) -> tuple[float, float]:
        driver = bench.Driver("bridge", sitl, bridge.gcs)
        bench.wait_ready(sitl)
        n0, e0, yaw = wall_ahead(sitl)  # on the SITL's monitor link: nothing of it passes the bridge
        time.sleep(STORED_REFRESH_S + 2.0)
        driver.set_mode(bench.MANUAL)
        driver.arm()
        driver.set_mode(bench.GUIDED)
        driver.velocity(0.0, 0.0)
        time.sleep(1.0)
        t0 = time.monotonic()
        driver.velocity(1.0, 0.0)
        time.sleep(15.0)
        t1 = time.monotonic()
        driver.velocity(0.0, 0.0)
        driver.gcs.each = None
        gaps = [WALL_AHEAD_M - ((n - n0) * math.cos(yaw) + (e - e0) * math.sin(yaw)) for n, e in sitl.track(t0, t1)]
        assert gaps, "no truth"
        return min(gaps), gaps[-1]

    (closest_m, rest_m), counters = through_bridge(BINARY, INSTANCE_POLYGON, bench.BRIDGE_PARAMS + POLYGON_PARAMS,
                                                   tmp_path, bench.STREAMS, drive)
    table = f"closest {closest_m:.2f} m, at rest {rest_m:.2f} m from the polygon's edge; {counters}"
    print(table)
    assert closest_m >= FENCE_MARGIN_M - 0.3 and rest_m <= FENCE_MARGIN_M + 0.3, table
    assert counters.get("avoid.fence_stop", 0) >= 1, table
