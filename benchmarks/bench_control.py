"""Wheel speed control on imperfect motors: open loop beside closed loop, the same runs (lockstep).

    python benchmarks/bench_control.py            # the table
    python benchmarks/bench_control.py --patch P  # the same, open and closed loop also with a profile patch
    python benchmarks/bench_control.py --calibrate  # the patch from `calibrate`'s sequence on the same rover

The emulated rover: left motor 20 % weak, a 40 us ESC deadband, a curved PWM -> speed map
(speed = command ** 1.5), and, where a case says so, a 15 % load window or a stalled wheel. The whole
bridge core (command and estimate flows) runs against the emulator in process, on its simulated clock:
every message the emulator sends goes to BridgeCore.handle, everything the core sends to the autopilot
goes back, requests come as a ground station's SET_POSITION_TARGET_LOCAL_NED (body frame) at 10 Hz.
Speeds and headings are the emulator's ground truth.

Cases (targets of the issue in brackets):
- straight: 0.5 m/s for 10 s: mean true speed over the last 8 s against the request [within 3 %],
  heading drift over the run [under 2 deg];
- step: 0 -> 0.5 m/s at the profile's acceleration limit: time to 90 % [within 1.0 s], overshoot [<= 10 %];
- load: a 15 % load on both wheels from 4 s to 8 s of a 0.5 m/s run: time until the speed is back
  within 3 % after the load begins [within 1.5 s];
- spin: 0.8 rad/s in place: mean yaw rate [within 5 %], largest |v| [< 0.03 m/s];
- stall: the left wheel held for 3 s during a 0.5 m/s run, then released: largest speed overshoot of
  the left wheel after the release, as a fraction of its target [<= 10 %: no windup].
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from rover_bridge.app.composition import BridgeCore
from rover_bridge.frames import mavlink_yaw_rate_from_omega
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import Profile, load_profile, profile_from_dict
from sitl import Emulator, Scenario, VehicleConfig
from sitl.scenario import LoadWindow, StallWindow

STEP_S = 0.01
BODY_MASK = 0b0000_0101_1100_0111
IMPERFECT = VehicleConfig(start_armed=True, left_motor_gain=0.8, deadzone_pwm=40, motor_curve_exponent=1.5)


def bench_profile(mode: str, patch: dict[str, Any] | None = None) -> Profile:
    data: dict[str, Any] = {"control": {"mode": mode}, "estimator": {"stream_rate_hz": 20.0}}
    for section, values in (patch or {}).items():
        data.setdefault(section, {}).update(values)
    return profile_from_dict(data)


@dataclass
class Rig:
    """The bridge core and the emulator in lockstep (no sockets), a ground station's requests fed in."""

    profile: Profile
    vehicle: VehicleConfig = IMPERFECT
    scenario: Scenario = field(default_factory=Scenario)
    seed: int = 1
    step_s: float = STEP_S  # the lockstep's step: how finely the bridge sees the emulator's timing

    def __post_init__(self) -> None:
        self.emu = Emulator(self.vehicle, self.scenario, seed=self.seed, record_sent=True)
        self.core = BridgeCore(self.profile)
        self.gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.t = 0.0
        self._seen = 0
        self._next_request = 0.0
        self.texts: list[str] = []

    def _to_autopilot(self, out: Any) -> None:
        for o in out:
            if o.dest is Link.AUTOPILOT:
                self.emu.handle_message(o.msg, src_system=o.src_system, src_component=o.src_component)
            elif o.msg.get_type() == "STATUSTEXT":
                self.texts.append(o.msg.text)

    def request(self, v_m_s: float, omega_rad_s: float) -> None:
        msg = mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, mavlink.MAV_FRAME_BODY_NED, BODY_MASK, 0, 0, 0, v_m_s, 0, 0, 0, 0, 0, 0,
            mavlink_yaw_rate_from_omega(omega_rad_s))
        wired = self.gcs.decode(bytearray(msg.pack(self.gcs)))
        self._to_autopilot(self.core.handle(Incoming(Link.GCS, wired), self.t).out)

    def step(self) -> None:
        self.emu.step(self.step_s)
        self.t = self.emu.sim_time_s
        log = self.emu.sent_log
        assert log is not None
        for sent_s, msg in log[self._seen:]:
            wired = self.ap.decode(bytearray(msg.pack(self.ap)))
            self._to_autopilot(self.core.handle(Incoming(Link.AUTOPILOT, wired), sent_s).out)
        self._seen = len(log)
        if self.t >= self.core.next_deadline_s(self.t):
            self._to_autopilot(self.core.tick(self.t))

    def drive(self, seconds: float, v_m_s: float | None = None, omega_rad_s: float = 0.0,
              sample: Any = None) -> None:
        """Step for `seconds`, requesting (v, omega) at 10 Hz unless v is None; sample(rig) every step."""
        end = self.t + seconds
        while self.t < end - 1e-9:
            if v_m_s is not None and self.t >= self._next_request:
                self.request(v_m_s, omega_rad_s)
                self._next_request = self.t + 0.1
            self.step()
            if sample is not None:
                sample(self)

    def start(self) -> None:
        """Streams up, gyro bias learnt at standstill: a rover after power-up."""
        self.drive(4.0)


@dataclass
class Row:
    case: str
    values: dict[str, float]


def straight(profile: Profile, vehicle: VehicleConfig = IMPERFECT) -> dict[str, float]:
    rig = Rig(profile, vehicle)
    rig.start()
    yaw0 = rig.emu.truth.yaw_rad
    speeds: list[float] = []
    rig.drive(2.0, 0.5)
    rig.drive(8.0, 0.5, sample=lambda r: speeds.append(r.emu.truth.v_m_s))
    drift = abs(math.degrees(math.remainder(rig.emu.truth.yaw_rad - yaw0, 2 * math.pi)))
    mean = sum(speeds) / len(speeds)
    return {"speed_m_s": mean, "speed_error_pct": 100.0 * (mean - 0.5) / 0.5, "heading_drift_deg": drift}


def step_response(profile: Profile, vehicle: VehicleConfig = IMPERFECT) -> dict[str, float]:
    rig = Rig(profile, vehicle)
    rig.start()
    t0 = rig.t
    trace: list[tuple[float, float]] = []
    rig.drive(4.0, 0.5, sample=lambda r: trace.append((r.t - t0, r.emu.truth.v_m_s)))
    t90 = next((t for t, v in trace if v >= 0.45), math.inf)
    peak = max(v for _, v in trace)
    return {"t90_s": t90, "overshoot_pct": max(0.0, 100.0 * (peak - 0.5) / 0.5)}


def load_recovery(profile: Profile, vehicle: VehicleConfig = IMPERFECT) -> dict[str, float]:
    start = 4.0 + 4.0  # after start(): 4 s into the run
    scenario = Scenario(loads=(LoadWindow(start, start + 4.0, 0.15),))
    rig = Rig(profile, vehicle, scenario)
    rig.start()
    trace: list[tuple[float, float]] = []
    rig.drive(8.0, 0.5, sample=lambda r: trace.append((r.t, r.emu.truth.v_m_s)))
    during = [(t, v) for t, v in trace if start <= t < start + 4.0]
    worst = min(v for _, v in during)
    # Back within 3 %: the first moment after the load began from which the speed stays within 3 %.
    back = math.inf
    for i, (t, _v) in enumerate(during):
        if all(abs(v2 - 0.5) <= 0.015 for _, v2 in during[i:]):
            back = t - start
            break
    return {"recovered_s": back, "dip_pct": 100.0 * (worst - 0.5) / 0.5}


def spin(profile: Profile, vehicle: VehicleConfig = IMPERFECT) -> dict[str, float]:
    rig = Rig(profile, vehicle)
    rig.start()
    rig.drive(2.0, 0.0, 0.8)
    rates: list[float] = []
    speeds: list[float] = []

    def sample(r: Rig) -> None:
        rates.append(-r.emu.truth.yaw_rate_rad_s)  # truth is clockwise positive
        speeds.append(abs(r.emu.truth.v_m_s))

    rig.drive(6.0, 0.0, 0.8, sample=sample)
    mean = sum(rates) / len(rates)
    return {"yaw_rate_rad_s": mean, "yaw_rate_error_pct": 100.0 * (mean - 0.8) / 0.8, "max_abs_v_m_s": max(speeds)}


def stall(profile: Profile, vehicle: VehicleConfig = IMPERFECT) -> dict[str, float]:
    start = 4.0 + 3.0
    scenario = Scenario(stalls=(StallWindow("left", start, start + 3.0),))
    rig = Rig(replace(profile, control=replace(profile.control, fault_time_s=10.0)), vehicle, scenario)
    rig.start()
    target = 0.5 / profile.robot.left_radius_m
    left: list[tuple[float, float]] = []
    rig.drive(9.0, 0.5, sample=lambda r: left.append((r.t, r.emu.truth.left_wheel_rad_s)))
    after = [w for t, w in left if t >= start + 3.0]
    return {"overshoot_pct": max(0.0, 100.0 * (max(after) - target) / target),
            "final_left_rad_s": after[-1]}


def calibrate(profile: Profile, vehicle: VehicleConfig = IMPERFECT, quick: bool = False) -> tuple[Any, Rig]:
    """`rover-bridge calibrate`'s sequence in lockstep: (its Calibration, the rig it ran on)."""
    from rover_bridge.app.calibration import Calibration

    rig = Rig(profile, vehicle)
    cal = Calibration(profile, quick=quick)
    est = rig.core.estimate

    def observe(sample: Any, now_s: float) -> None:
        gyro = est.last_gyro
        cal.sample(sample, None if gyro is None else gyro[1] - est.state.gyro_bias_rad_s, now_s)

    rig.core.wheel_observers.append(observe)
    rig.drive(1.0)  # the vehicle is known, streams asked for
    last = None
    while True:
        pwm = cal.tick(rig.t)
        if pwm != last:
            rig._to_autopilot(rig.core.command.set_direct(pwm, rig.t))
            last = pwm
        if pwm is None:
            break
        rig.step()
    return cal, rig


def calibration_table(cal: Any, vehicle: VehicleConfig = IMPERFECT) -> str:
    res = cal.result
    if res is None:
        return f"calibration failed: {cal.error}"
    true_track = vehicle.track_true_m / (0.5 * (vehicle.left_radius_true_m + vehicle.right_radius_true_m)
                                        / vehicle.wheel_radius_m)
    rows = [("left gain forward / reverse", f"{res.left.gain_forward:.3f} / {res.left.gain_reverse:.3f}",
             f"{vehicle.left_motor_gain:.3f}"),
            ("right gain forward / reverse", f"{res.right.gain_forward:.3f} / {res.right.gain_reverse:.3f}",
             f"{vehicle.right_motor_gain:.3f}"),
            ("left deadband (us from trim)", f"{res.left.deadband_us[0]:+.0f} / {res.left.deadband_us[1]:+.0f}",
             f"-/+{vehicle.deadzone_pwm}"),
            ("right deadband (us from trim)", f"{res.right.deadband_us[0]:+.0f} / {res.right.deadband_us[1]:+.0f}",
             f"-/+{vehicle.deadzone_pwm}"),
            ("effective track (m)", f"{res.track_width_m:.4f}", f"{true_track:.4f}"),
            ("radius ratio right/left", f"{res.radius_ratio:.4f}",
             f"{vehicle.right_radius_true_m / vehicle.left_radius_true_m:.4f}")]
    return "\n".join(f"  {a:32s} {b:>18s}   truth {c}" for a, b, c in rows)


CASES = [("straight 0.5 m/s", straight), ("step 0 -> 0.5 m/s", step_response), ("15 % load window", load_recovery),
         ("spin 0.8 rad/s", spin), ("left wheel stalled 3 s", stall)]


def fmt(values: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:.3g}" for k, v in values.items())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--patch", default=None, help="a profile patch from `rover-bridge calibrate` for open loop")
    ap.add_argument("--calibrate", action="store_true",
                    help="run the calibration sequence first and add open loop with its patch")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    if args.calibrate:
        import tempfile

        cal, _ = calibrate(bench_profile("closed_loop"))
        print("calibrate (the sequence of `rover-bridge calibrate`, in lockstep on the same vehicle)")
        print(calibration_table(cal))
        if cal.result is not None:
            path = Path(tempfile.mkdtemp()) / "patch.toml"
            path.write_text(cal.result.patch_toml("bench_control --calibrate"))
            args.patch = str(path)
    modes: list[tuple[str, Profile]] = [("open loop", bench_profile("open_loop")),
                                        ("closed loop", bench_profile("closed_loop"))]
    if args.patch:
        patched = load_profile(args.patch)
        patched = replace(patched, estimator=replace(patched.estimator, stream_rate_hz=20.0))
        modes.append(("open loop + patch", replace(patched, control=replace(patched.control, mode="open_loop"))))
        modes.append(("closed loop + patch", replace(patched, control=replace(patched.control, mode="closed_loop"))))
    print("vehicle: left motor 20 % weak, 40 us deadband, speed = command^1.5; lockstep, ground truth")
    for name, case in CASES:
        print(f"\n{name}")
        for mode, profile in modes:
            print(f"  {mode:18s} {fmt(case(profile))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
