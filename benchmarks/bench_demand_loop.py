"""The bridge's wheel loop closed around the autopilot's demand, or not (`[demand] speed_loop`, issue 42 item 5).

The autopilot flies the 3-waypoint mission (10 m north, 10 m east, 10 m south: two 90 deg pivots; WP_SPEED 3)
in AUTO, its per-wheel demand (SERVO5/6) driving the wheels through the bridge, once with the demand mapped to
PWM open loop (`speed_loop = false`) and once with the bridge's wheel loop closing each wheel's speed on the
encoders (`true`). Rows: mission time, cross-track error (largest / RMS distance of the true track from the
planned legs), closest approach to each waypoint.

Emulator (default): the bridge and the emulator in lockstep on one simulated clock (tests/navrig.py: the
shipped profile and .parm, sitl/vehicles/ardupilot-skid-bridge.toml: the "wheels" plant, each side lagging
0.286 s), seed 29 (the figures do not depend on it: the autopilot navigates on the truth), on three rovers:
the ideal one, the weak-motor rover (left motor 20 % weak, `left_motor_gain = 0.8`: the issue's "weak-motor
rover") and the imperfect one (bench_control's: left 20 % weak, a 40 us ESC dead zone, speed = command^1.5);
with ArduPilot alone on the same motors (SERVO1/3 = 73/74, no bridge) for comparison. A few seconds a mission.

    python benchmarks/bench_demand_loop.py

Real ArduPilot Rover SITL (`--sitl`, ROVER_BRIDGE_ARDUROVER names the `ardurover` binary): two SITLs
(instances 31 and 32), ArduPilot alone on one, the bridge (`rover-bridge run`, the shipped profile with
`speed_loop` set) on the other, as tests/test_ardupilot_sitl_nav.py sets them up. First the mission from the
boot heading (north), ArduPilot alone and the bridge open loop (`--closed-first`: closed), then `--rounds N`
rounds of alone, open, closed, each mission starting where the last ended (WP 3 facing south: a 180 deg pivot
first). Wall time: about 2 minutes to boot, 2 minutes a round.

    ROVER_BRIDGE_ARDUROVER=.../build/sitl/bin/ardurover python benchmarks/bench_demand_loop.py --sitl --rounds 2
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from navmetrics import Point, RouteFigures, route_figures  # noqa: E402
from navrig import ANCHOR, BRIDGE, WAYPOINTS, BridgeRig, shipped_profile  # noqa: E402

from rover_bridge.mavlink.dialect import mavlink  # noqa: E402
from sitl import Emulator, VehicleConfig  # noqa: E402
from sitl.gcs import InProcessGcs  # noqa: E402
from sitl.modes import MODE_AUTO  # noqa: E402

WEAK = dataclasses.replace(BRIDGE, left_motor_gain=0.8)
IMPERFECT = dataclasses.replace(BRIDGE, left_motor_gain=0.8, deadzone_pwm=40, motor_curve_exponent=1.5)
ROVERS: dict[str, VehicleConfig] = {"ideal": BRIDGE, "weak left 20 %": WEAK,
                                    "imperfect (weak, dead zone, curve)": IMPERFECT}


def emulator_mission(vehicle: VehicleConfig, speed_loop: bool, seed: int = 29) -> RouteFigures:
    """The mission through the bridge in lockstep, the shipped profile with `[demand] speed_loop` as given."""
    p = shipped_profile()
    rig = BridgeRig(dataclasses.replace(p, demand=dataclasses.replace(p.demand, speed_loop=speed_loop)), vehicle,
                    seed)
    try:
        return rig.fly_mission(WAYPOINTS)
    finally:
        rig.close()


def alone_mission(vehicle: VehicleConfig, seed: int = 29) -> RouteFigures:
    """ArduPilot alone: the same motors on SERVO1/3 = 73/74 (sitl/vehicles/ardupilot-skid-anchor.toml), no
    bridge, the same mission, in process (as tests/test_nav_e2e.py's anchor)."""
    motors = {f.name: getattr(vehicle, f.name) for f in dataclasses.fields(vehicle)
              if f.name in ("left_motor_gain", "right_motor_gain", "deadzone_pwm", "motor_curve_exponent")}
    g = InProcessGcs(Emulator(dataclasses.replace(ANCHOR, **motors), seed=seed, record_sent=True))
    g.heartbeat()
    g.run(0.5)
    assert g.arm() == mavlink.MAV_RESULT_ACCEPTED
    items = [g.waypoint(0, 0.0, 0.0)] + [g.waypoint(i + 1, n, e) for i, (n, e) in enumerate(WAYPOINTS)]
    assert g.upload(items) == mavlink.MAV_MISSION_ACCEPTED
    track: list[Point] = []
    assert g.set_mode(MODE_AUTO) == mavlink.MAV_RESULT_ACCEPTED
    start, at = g.emu.sim_time_s, (g.emu.truth.x_m, g.emu.truth.y_m)
    done = g.run_until(lambda: len(g.of("MISSION_ITEM_REACHED")) >= len(WAYPOINTS), 90.0,
                       each=lambda: track.append((g.emu.truth.x_m, g.emu.truth.y_m)))
    return route_figures(track, at, WAYPOINTS, g.emu.sim_time_s - start if done else float("nan"))


def row(label: str, fig: RouteFigures) -> str:
    return (f"| {label} | {fig.time_s:.1f} s | {fig.xtrack_max_m:.2f} / {fig.xtrack_rms_m:.2f} m | "
            + " / ".join(f"{c:.2f}" for c in fig.closest_m) + " m |")


HEADER = "| rover, who drives | mission time | cross-track max / RMS | closest approach WP 1/2/3 |\n|---|---|---|---|"


def emulator(rovers: list[str]) -> None:
    print(HEADER)
    for name in rovers:
        print(row(f"{name}, ArduPilot alone", alone_mission(ROVERS[name])), flush=True)
        figs = {loop: emulator_mission(ROVERS[name], loop) for loop in (False, True)}
        for loop, fig in figs.items():
            print(row(f"{name}, speed_loop = {str(loop).lower()}", fig), flush=True)
        ratio = figs[True].xtrack_max_m / figs[False].xtrack_max_m
        print(f"| {name}: closed / open cross-track max | {ratio:.2f} | | |", flush=True)


def profile_with(speed_loop: bool, folder: Path) -> Path:
    """The shipped SITL profile with `[demand] speed_loop` set (it does not set it itself)."""
    text = (REPO / "params" / "ardupilot-sitl-skid.toml").read_text()
    assert "speed_loop" not in text
    path = folder / f"speed_loop_{str(speed_loop).lower()}.toml"
    path.write_text(text.replace("[demand]\n", f"[demand]\nspeed_loop = {str(speed_loop).lower()}\n", 1))
    return path


def real_sitl(rounds: int, closed_first: bool = False) -> None:
    import test_ardupilot_sitl_nav as nav  # reads ROVER_BRIDGE_ARDUROVER

    assert nav.BINARY, "ROVER_BRIDGE_ARDUROVER does not name an ardurover binary"
    work = Path(tempfile.mkdtemp(prefix="bench_demand_loop_"))
    profiles = {loop: profile_with(loop, work) for loop in ((True, False) if closed_first else (False, True))}
    anchor_sitl = nav.Sitl(31, nav.ANCHOR_PARAMS, work / "anchor")
    bridge_sitl = nav.Sitl(32, nav.BRIDGE_PARAMS, work / "bridge", (nav.PARM,))
    anchor_gcs = anchor_sitl.gcs_on_serial0()
    try:
        for s in (anchor_sitl, bridge_sitl):
            assert s.monitor.wait(lambda s=s: any("is using GPS" in t for t in s.monitor.texts()), 120.0)
        time.sleep(5.0)
        anchor = nav.Side("anchor", anchor_sitl, anchor_gcs, None)
        print(f"SITL work folder {work}\n{HEADER}", flush=True)
        # Every mission ends at WP 3 facing south, and the next starts there (home is where it arms) with a 180 deg
        # pivot: only the first, from the boot heading (north, as tests/test_ardupilot_sitl_nav.py flies it), does
        # not; it is flown by the first setting alone, the rounds after it each start alike.
        for label in ["from boot", *(f"round {r + 1}" for r in range(rounds))]:
            fig, reached = nav.fly_mission(anchor)
            print(row(f"{label}: ArduPilot alone (reached {reached})", fig), flush=True)
            for loop, path in profiles.items():
                if label == "from boot" and loop != next(iter(profiles)):
                    continue
                bridge = nav.Bridge(bridge_sitl, work, profile=path)
                try:
                    fig, reached = nav.fly_mission(nav.Side("bridge", bridge_sitl, bridge.gcs, bridge))
                    print(row(f"{label}: bridge, speed_loop = {str(loop).lower()} (reached {reached})", fig),
                          flush=True)
                finally:
                    bridge.stop()
                    bridge.close()
                time.sleep(1.0)
    finally:
        anchor_gcs.close()
        bridge_sitl.close()
        anchor_sitl.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sitl", action="store_true", help="against a real ArduPilot Rover SITL")
    ap.add_argument("--rounds", type=int, default=2, help="--sitl: rounds of alone, open, closed")
    ap.add_argument("--closed-first", action="store_true", help="--sitl: the mission from boot closed loop")
    ap.add_argument("--rover", action="append", choices=list(ROVERS), help="emulator: only these rovers")
    args = ap.parse_args()
    if args.sitl:
        real_sitl(args.rounds, args.closed_first)
    else:
        emulator(args.rover or list(ROVERS))


if __name__ == "__main__":
    main()
