"""The issue 29 anchor, flown in the sitl emulator: ArduPilot's own navigation against the measured figures.

Three NAV_WAYPOINTs 10 m apart (10 m north, then 10 m east, then 10 m south: two 90 deg corners, so
the skid-steering rover pivots), WP_SPEED 3, on the rover-skid body (sitl/vehicles/ardupilot-skid-*.toml),
every message through the emulator's MAVLink handling (sitl/gcs.py, in process, simulated time). Rows:

- "ArduPilot alone": SERVO1/3 = 73/74 drive the motors (sitl/vehicles/ardupilot-skid-anchor.toml);
- "copy loop at N Hz": the bridge setup (motors on passthrough 51/53, SERVO5/6 = 73/74 with MIN/MAX
  1000-2000) and a ground station that copies each SERVO_OUTPUT_RAW's servo5/servo6 into the overrides
  of channels 1/3 while the autopilot drives itself, SERVO_OUTPUT_RAW asked for at N Hz.

RTL: driven 5 m north in MANUAL, stopped, RTL: time until within 3 m of home, then distance from home
once stopped. SMART_RTL: driven 5 m north then 5 m east in MANUAL, SMART_RTL: distance from home once
stopped. The issue's measured rows (real Rover 4.7 SITL) are printed below for comparison.

    python benchmarks/bench_sitl_anchor.py
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from sitl import Emulator, load_vehicle
from sitl.gcs import InProcessGcs
from sitl.mav import mavlink
from sitl.modes import MODE_AUTO, MODE_HOLD, MODE_MANUAL, MODE_RTL, MODE_SMART_RTL

VEHICLES = Path(__file__).resolve().parents[1] / "sitl" / "vehicles"
WAYPOINTS = [(10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
DRIVING = (MODE_AUTO, MODE_RTL, MODE_SMART_RTL)
MEASURED = [
    ("measured: ArduPilot alone (SERVO1/3 = 73/74, the anchor)", "28.6 s", "0.14 / 0.17 / 0.20 m", "7.0 s / 0.32 m",
     "0.14 m"),
    ("measured: copy loop at 40 Hz, SERVO5/6 range 1000-2000", "29.0 s", "0.18 / 0.20 / 0.21 m", "7.1 s / 0.38 m",
     "1.23 m"),
    ("measured: copy loop at 1 Hz (default stream rate)", "40.6 s", "0.73 / 0.33 / 0.13 m", "14.0 s / 1.16 m",
     "0.53 m"),
]


@dataclass
class Rig:
    gcs: InProcessGcs
    copy_hz: float | None  # None: ArduPilot alone

    @property
    def emu(self) -> Emulator:
        return self.gcs.emu

    def copy(self) -> None:
        """The copy loop: the newest SERVO_OUTPUT_RAW's servo5/6 into the overrides of channels 1/3."""
        if self.copy_hz is None or self.emu.mode not in DRIVING:
            return
        raw = self.gcs.of("SERVO_OUTPUT_RAW")
        if raw and raw[-1] is not getattr(self, "_last", None):
            self._last = raw[-1]
            self.gcs.override(ch1=raw[-1].servo5_raw, ch3=raw[-1].servo6_raw)

    def drive(self, throttle: float, steering: float) -> None:
        """MANUAL driving with sticks in [-1, 1] (throttle RC3 / steering RC1, or both wheels on passthrough)."""
        if self.copy_hz is None:
            self.gcs.override(ch1=round(1500 + 500 * steering), ch3=round(1500 + 500 * throttle))
        else:
            left, right = throttle + steering, throttle - steering
            self.gcs.override(ch1=round(1500 + 500 * left), ch3=round(1500 + 500 * right))


def make_rig(copy_hz: float | None) -> Rig:
    name = "ardupilot-skid-anchor.toml" if copy_hz is None else "ardupilot-skid-bridge.toml"
    emu = Emulator(load_vehicle(VEHICLES / name), seed=0, record_sent=True)
    gcs = InProcessGcs(emu)
    gcs.heartbeat()
    gcs.run(0.5)
    if copy_hz is not None:
        for n in (5, 6):
            emu.set_param(f"SERVO{n}_MIN", 1000)
            emu.set_param(f"SERVO{n}_MAX", 2000)
        gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, 1e6 / copy_hz)
    assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED
    return Rig(gcs, copy_hz)


def distance(emu: Emulator, north: float, east: float) -> float:
    t = emu.truth
    return math.hypot(t.x_m - north, t.y_m - east)


def fly_mission(copy_hz: float | None) -> tuple[float, list[float]]:
    rig = make_rig(copy_hz)
    g = rig.gcs
    items = [g.waypoint(0, 0.0, 0.0)] + [g.waypoint(i + 1, n, e) for i, (n, e) in enumerate(WAYPOINTS)]
    assert g.upload(items) == mavlink.MAV_MISSION_ACCEPTED
    closest = [math.inf] * len(WAYPOINTS)

    def each() -> None:
        rig.copy()
        for i, (n, e) in enumerate(WAYPOINTS):
            closest[i] = min(closest[i], distance(rig.emu, n, e))

    assert g.set_mode(MODE_AUTO) == mavlink.MAV_RESULT_ACCEPTED
    start = rig.emu.sim_time_s
    done = g.run_until(lambda: len(g.of("MISSION_ITEM_REACHED")) >= len(WAYPOINTS), 120.0, each=each)
    return (rig.emu.sim_time_s - start if done else math.nan), closest


def drive_manual(rig: Rig, until: Callable[[], bool], throttle: float, steering: float) -> None:
    rig.gcs.set_mode(MODE_MANUAL)
    rig.gcs.run_until(until, 30.0, each=lambda: rig.drive(throttle, steering))
    rig.gcs.run_until(lambda: abs(rig.emu.truth.v_m_s) < 0.01, 10.0, each=lambda: rig.drive(0.0, 0.0))


def settle(rig: Rig) -> float:
    """Distance from home once the mode has said "Reached destination" and the rover has stopped."""
    rig.gcs.run_until(lambda: "Reached destination" in rig.gcs.texts(), 60.0, each=rig.copy)
    rig.gcs.run_until(lambda: abs(rig.emu.truth.v_m_s) < 0.01 and abs(rig.emu.truth.yaw_rate_rad_s) < 0.01, 30.0,
                      each=rig.copy)
    rig.gcs.run(1.0, each=rig.copy)
    return distance(rig.emu, 0.0, 0.0)


def fly_rtl(copy_hz: float | None) -> tuple[float, float]:
    rig = make_rig(copy_hz)
    drive_manual(rig, lambda: rig.emu.truth.x_m >= 5.0, 0.5, 0.0)
    assert rig.gcs.set_mode(MODE_RTL) == mavlink.MAV_RESULT_ACCEPTED
    start = rig.emu.sim_time_s
    within = rig.gcs.run_until(lambda: distance(rig.emu, 0.0, 0.0) < 3.0, 30.0, each=rig.copy)
    within_s = rig.emu.sim_time_s - start if within else math.nan
    return within_s, settle(rig)


def fly_smart_rtl(copy_hz: float | None) -> float:
    rig = make_rig(copy_hz)
    drive_manual(rig, lambda: rig.emu.truth.x_m >= 5.0, 0.5, 0.0)
    drive_manual(rig, lambda: rig.emu.truth.yaw_rad >= math.radians(75.0), 0.0, 0.3)  # pivot to about east
    drive_manual(rig, lambda: rig.emu.truth.y_m >= 5.0, 0.5, 0.0)
    rig.gcs.set_mode(MODE_HOLD)
    assert rig.gcs.set_mode(MODE_SMART_RTL) == mavlink.MAV_RESULT_ACCEPTED
    return settle(rig)


def main() -> None:
    rows = []
    for label, copy_hz in (("emulator: ArduPilot alone (SERVO1/3 = 73/74)", None),
                           ("emulator: copy loop at 40 Hz, SERVO5/6 range 1000-2000", 40.0),
                           ("emulator: copy loop at 1 Hz, SERVO5/6 range 1000-2000", 1.0)):
        done_s, closest = fly_mission(copy_hz)
        within_s, rtl_final = fly_rtl(copy_hz)
        srtl_final = fly_smart_rtl(copy_hz)
        rows.append((label, f"{done_s:.1f} s", " / ".join(f"{c:.2f}" for c in closest) + " m",
                     f"{within_s:.1f} s / {rtl_final:.2f} m", f"{srtl_final:.2f} m"))
    print("| who drives | mission done | closest approach to WP 1/2/3 | RTL: within 3 m / final | SMART_RTL final |")
    print("|---|---|---|---|---|")
    for row in rows + MEASURED:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
