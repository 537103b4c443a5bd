"""Go to a point: five targets around a ~10 m course, each sent once, judged by the emulator's truth; and an
8 m go-to straight ahead on the emulator's ArduPilot rover-skid bridge setup with the shipped SITL profile.

    python benchmarks/bench_goto.py               # default profile, ideal and imperfect motors; the 8 m go-to
    python benchmarks/bench_goto.py --frame global # the same course as lat/lon (MISSION_ITEM_INT current=2)

The whole bridge core runs against the emulator in process, on its simulated clock (bench_control.Rig);
a ground station heartbeats at 1 Hz, puts the autopilot in GUIDED and sends each target once, the next
when the bridge has reported the last one reached and the rover has stopped. Targets are LOCAL_NED
positions in the autopilot's frame (the emulator's LOCAL_POSITION_NED: its truth), or the same points
as lat/lon.

Per leg (targets of the issue in brackets):
- arrival: distance from the target where the rover stopped, by truth [<= arrival_radius_m, <= 0.2 m];
- overshoot: how far the rover went past the target along the leg [<= 0.1 m, issue 42];
- cross-track: largest distance from the straight leg, away from its ends (0.25 m) [<= 0.1 m];
- time: from the target sent to "reached", against the ideal: a pivot (when the bearing is more than
  turn_in_place_deg off) at the angular limits, then the leg at the linear limits (up at the acceleration
  limit, the cruise speed, down at the deceleration limit) [within 20 % on the ideal motors; the imperfect ones
  are slower until calibrated: the default loop learns each leg's weak-wheel correction anew].

The 8 m go-to (issue 42: "a brisk go-to"): the time to "reached" and to rest (truth |v| < 0.01 m/s), the
final error and the most it went past the target, against the ideal trapezoid; with the shipped SITL profile (no
loop gains), and on the default emulated rover with the default profile [at rest within 2.0 s of the ideal: the
curve brakes for the lag the default loop assumes, then the motor decays at its own lag; <= 0.15 m off, <= 0.1 m
past]. Against ArduPilot alone on a real SITL: tests/test_ardupilot_sitl_control.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_control import Rig

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import Profile, load_profile, profile_from_dict
from sitl import VehicleConfig, load_vehicle

COURSE = ((3.0, 0.0), (3.0, 2.0), (1.5, 3.0), (0.0, 2.0), (0.0, 0.0))  # north, east (m): 10.6 m
POSITION_ONLY = 0x0DF8  # SET_POSITION_TARGET: x, y (z) used; velocity, acceleration, yaw ignored
END_MARGIN_M = 0.25
LEG_TIMEOUT_S = 40.0
EARTH_RADIUS_M = 6378137.0
REPO = Path(__file__).resolve().parent.parent
STRAIGHT_M = 8.0
REST_M_S = 0.01


def trapezoid_s(distance: float, top: float, accel: float, decel: float) -> float:
    """The least time from rest to rest over `distance` within a top speed, an acceleration and a deceleration
    (metres or radians alike)."""
    ramps = top * top / (2.0 * accel) + top * top / (2.0 * decel)
    if ramps <= distance:
        return top / accel + top / decel + (distance - ramps) / top
    peak = math.sqrt(2.0 * distance * accel * decel / (accel + decel))
    return peak / accel + peak / decel


def ideal_s(profile: Profile, leg_m: float, turn_rad: float) -> float:
    """A pivot at the angular limits when the bearing is more than turn_in_place_deg off, then the leg."""
    lim, nav = profile.limits, profile.navigation
    cruise = min(nav.speed_m_s, lim.max_linear_m_s)
    pivot = 0.0
    if turn_rad > math.radians(nav.turn_in_place_deg):
        pivot = trapezoid_s(turn_rad, lim.max_angular_rad_s, lim.max_angular_accel_rad_s2,
                            lim.max_angular_accel_rad_s2)
    return pivot + trapezoid_s(leg_m, cruise, lim.max_linear_accel_m_s2, lim.max_linear_decel_m_s2)


class GotoRig(Rig):
    def gcs_send(self, msg: Any) -> None:
        wired = self.gcs.decode(bytearray(msg.pack(self.gcs)))
        reaction = self.core.handle(Incoming(Link.GCS, wired), self.t)
        self._to_autopilot(reaction.out)
        if not reaction.consumed:  # the shell forwards it
            self.emu.handle_message(wired, src_system=255, src_component=190)

    def heartbeat(self) -> None:
        self.gcs_send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                        0, 0, 0, 3))

    def run(self, seconds: float, sample: Any = None, until: Any = None) -> None:
        end = self.t + seconds
        while self.t < end - 1e-9:
            if int(self.t) != int(self.t + 0.01):  # once a second
                self.heartbeat()
            self.step()
            if sample is not None:
                sample(self)
            if until is not None and until(self):
                return


def lat_lon(origin: tuple[float, float], north_m: float, east_m: float) -> tuple[float, float]:
    lat0, lon0 = origin
    return (lat0 + math.degrees(north_m / EARTH_RADIUS_M),
            lon0 + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat0)))))


def target_message(frame: str, north_m: float, east_m: float, vehicle: VehicleConfig) -> Any:
    if frame == "global":
        lat, lon = lat_lon((vehicle.origin_lat_deg, vehicle.origin_lon_deg), north_m, east_m)
        return mavlink.MAVLink_mission_item_int_message(
            1, 1, 0, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_CMD_NAV_WAYPOINT, 2, 0,
            0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 0.0, mavlink.MAV_MISSION_TYPE_MISSION)
    return mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, north_m, east_m, 0, 0, 0, 0, 0, 0, 0, 0, 0)


class Leg:
    """One leg, start to target, sampled every step by truth."""

    def __init__(self, rig: GotoRig, north_m: float, east_m: float) -> None:
        truth = rig.emu.truth
        self.sx, self.sy = truth.x_m, truth.y_m
        self.length_m = math.hypot(north_m - self.sx, east_m - self.sy)
        self.ux, self.uy = (north_m - self.sx) / self.length_m, (east_m - self.sy) / self.length_m
        self.turn_rad = abs(math.remainder(math.atan2(east_m - self.sy, north_m - self.sx) - truth.yaw_rad,
                                           2.0 * math.pi))
        self.reached_before = rig.core.command.counters.get("goto.reached", 0)
        self.t0 = rig.t
        self.overshoot_m = self.crosstrack_m = 0.0
        self.reached_s: float | None = None

    def sample(self, r: GotoRig) -> None:
        t = r.emu.truth
        along = (t.x_m - self.sx) * self.ux + (t.y_m - self.sy) * self.uy
        cross = abs(-(t.x_m - self.sx) * self.uy + (t.y_m - self.sy) * self.ux)
        self.overshoot_m = max(self.overshoot_m, along - self.length_m)
        if END_MARGIN_M <= along <= self.length_m - END_MARGIN_M:
            self.crosstrack_m = max(self.crosstrack_m, cross)
        if self.reached_s is None and r.core.command.counters.get("goto.reached", 0) > self.reached_before:
            self.reached_s = r.t

    def over(self, r: GotoRig) -> bool:
        """Reached, and the rover stopped (the bridge idle again)."""
        return (self.reached_s is not None and abs(r.emu.truth.v_m_s) < 1e-3
                and r.core.command.state.value == "idle")


def course(profile: Profile, vehicle: VehicleConfig, frame: str) -> list[dict[str, float]]:
    rig = GotoRig(profile, vehicle)
    rig.run(4.0)  # streams up, gyro bias learnt at standstill
    rig.gcs_send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 15, 0, 0, 0, 0, 0))
    rig.run(1.0)
    rows: list[dict[str, float]] = []
    for north, east in COURSE:
        leg = Leg(rig, north, east)
        rig.gcs_send(target_message(frame, north, east, vehicle))
        rig.run(LEG_TIMEOUT_S, leg.sample, until=leg.over)
        truth = rig.emu.truth
        expected = ideal_s(profile, leg.length_m, leg.turn_rad)
        took = (leg.reached_s if leg.reached_s is not None else math.inf) - leg.t0
        rows.append({"north": north, "east": east, "leg_m": leg.length_m, "turn_deg": math.degrees(leg.turn_rad),
                     "arrival_m": math.hypot(truth.x_m - north, truth.y_m - east),
                     "overshoot_m": max(0.0, leg.overshoot_m), "crosstrack_m": leg.crosstrack_m,
                     "time_s": took, "expected_s": expected, "time_pct": 100.0 * (took - expected) / expected})
    return rows


def skid_profile() -> Profile:
    """The shipped SITL profile (no loop gains: the defaults); the emulator reports its wheels as 0 = left, 1 = right
    (ArduPilot's SITL encoders the other way round, which the profile is written for)."""
    p = load_profile(REPO / "params" / "ardupilot-sitl-skid.toml")
    return dataclasses.replace(p, encoders=dataclasses.replace(p.encoders, left_index=0, right_index=1))


def straight(profile: Profile, vehicle: VehicleConfig) -> dict[str, float]:
    """A body-frame target STRAIGHT_M ahead, sent once; judged by truth."""
    rig = GotoRig(profile, vehicle)
    rig.run(4.0)
    rig.gcs_send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 15, 0, 0, 0, 0, 0))
    rig.run(1.0)
    truth = rig.emu.truth
    sx, sy, ux, uy = truth.x_m, truth.y_m, math.cos(truth.yaw_rad), math.sin(truth.yaw_rad)
    t0 = rig.t
    got: dict[str, float] = {"past_m": -math.inf, "top_m_s": 0.0}
    reached_before = rig.core.command.counters.get("goto.reached", 0)

    def sample(r: GotoRig) -> None:
        t = r.emu.truth
        got["past_m"] = max(got["past_m"], (t.x_m - sx) * ux + (t.y_m - sy) * uy - STRAIGHT_M)
        got["top_m_s"] = max(got["top_m_s"], abs(t.v_m_s))
        if "reached_s" not in got and r.core.command.counters.get("goto.reached", 0) > reached_before:
            got["reached_s"] = r.t - t0

    rig.gcs_send(mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, mavlink.MAV_FRAME_BODY_NED, POSITION_ONLY, STRAIGHT_M, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    rig.run(LEG_TIMEOUT_S, sample, until=lambda r: "reached_s" in got and abs(r.emu.truth.v_m_s) < REST_M_S)
    end = rig.emu.truth
    lim = profile.limits
    return {**got, "rest_s": rig.t - t0, "reached_s": got.get("reached_s", math.inf),
            "error_m": math.hypot(end.x_m - (sx + STRAIGHT_M * ux), end.y_m - (sy + STRAIGHT_M * uy)),
            "ideal_s": trapezoid_s(STRAIGHT_M, min(profile.navigation.speed_m_s, lim.max_linear_m_s),
                                   lim.max_linear_accel_m_s2, lim.max_linear_decel_m_s2),
            "cruise_m_s": min(profile.navigation.speed_m_s, lim.max_linear_m_s)}


def straight_table() -> bool:
    skid = dataclasses.replace(load_vehicle(REPO / "sitl" / "vehicles" / "ardupilot-skid-bridge.toml"),
                               start_armed=True)
    setups = {"skid, shipped SITL profile": (skid_profile(), skid),
              "default rover and profile": (profile_from_dict({"estimator": {"stream_rate_hz": 20.0}}),
                                            VehicleConfig(start_armed=True))}
    ok = True
    print(f"\n{STRAIGHT_M:g} m go-to straight ahead (at rest: truth |v| < {REST_M_S} m/s)")
    print(f"{'setup':27} {'cruise':>6} {'ideal s':>7} {'reached':>7} {'rest s':>6} {'top m/s':>7} {'error m':>7} "
          f"{'past m':>6}")
    for name, (profile, vehicle) in setups.items():
        row = straight(profile, vehicle)
        good = row["rest_s"] <= row["ideal_s"] + 2.0 and row["error_m"] <= 0.15 and row["past_m"] <= 0.1
        ok = ok and good
        print(f"{name:27} {row['cruise_m_s']:6.1f} {row['ideal_s']:7.2f} {row['reached_s']:7.2f} {row['rest_s']:6.2f} "
              f"{row['top_m_s']:7.2f} {row['error_m']:7.3f} {row['past_m']:+6.3f}{'' if good else '  <-'}")
    return ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frame", choices=("local", "global"), default="local")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    profile = profile_from_dict({"estimator": {"stream_rate_hz": 20.0}})
    radius = profile.navigation.arrival_radius_m
    vehicles = {"ideal motors": VehicleConfig(start_armed=True),
                "imperfect motors": VehicleConfig(start_armed=True, left_motor_gain=0.8, deadzone_pwm=40,
                                                  motor_curve_exponent=1.5)}
    ok = True
    print(f"go to a point ({args.frame} targets), cruise {profile.navigation.speed_m_s} m/s, "
          f"arrival radius {radius} m")
    print(f"{'vehicle':17} {'target':>11} {'leg m':>6} {'turn':>5} {'arrive m':>8} {'over m':>7} "
          f"{'xtrack m':>8} {'time s':>7} {'expect':>7} {'time %':>7}")
    for name, vehicle in vehicles.items():
        for row in course(profile, vehicle, args.frame):
            # Time is judged on the ideal motors only: on the imperfect ones the uncalibrated loop learns each leg's
            # weak-wheel correction anew (slower is fine until `calibrate` has measured the motors).
            good = (row["arrival_m"] <= min(radius, 0.2) and row["overshoot_m"] <= 0.1
                    and row["crosstrack_m"] <= 0.1 and (abs(row["time_pct"]) <= 20.0 or name != "ideal motors"))
            ok = ok and good
            print(f"{name:17} {row['north']:5.1f},{row['east']:5.1f} {row['leg_m']:6.2f} {row['turn_deg']:5.0f} "
                  f"{row['arrival_m']:8.3f} {row['overshoot_m']:7.3f} {row['crosstrack_m']:8.3f} "
                  f"{row['time_s']:7.2f} {row['expected_s']:7.2f} {row['time_pct']:+7.1f}{'' if good else '  <-'}")
    if args.frame == "local":
        ok = straight_table() and ok
    print("all within the targets" if ok else "some missed a target (<-)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
