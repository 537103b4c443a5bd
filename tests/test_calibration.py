"""`rover-bridge calibrate`: its sequence in lockstep (what it identifies, how it refuses bad wiring), and the
real command against the emulator (exit, patch written and accepted by the profile loader, Ctrl-C)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
from lockstep import finish_process
from test_process_faults import OverrideSpy, WallClockEmulator

from rover_bridge.params import load_profile, profile_from_dict
from sitl import Emulator, VehicleConfig

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_control as bench

REPO = Path(__file__).resolve().parents[1]


def test_calibration_identifies_a_weak_curved_motor_within_the_targets() -> None:
    cal, _ = bench.calibrate(bench.bench_profile("closed_loop"))  # left 20 % weak, 40 us deadband, command^1.5
    res = cal.result
    assert res is not None, cal.error
    assert res.left.gain_forward == pytest.approx(0.8, rel=0.05)
    assert res.left.gain_reverse == pytest.approx(0.8, rel=0.05)
    assert res.right.gain_forward == pytest.approx(1.0, rel=0.05)
    assert res.track_width_m == pytest.approx(0.30, rel=0.02)
    assert res.left.deadband_us[1] > 40 and res.left.deadband_us[0] < -40  # nothing moves inside the deadzone
    # The patch is a profile the loader accepts; open loop with it drives straight at the asked speed.
    patch = profile_from_dict(tomllib.loads(res.patch_toml("test")))
    patched = profile_from_dict({"control": {"mode": "open_loop", **{k: list(getattr(patch.control, k)) for k in (
        "left_curve_pwm_us", "left_curve_rad_s", "right_curve_pwm_us", "right_curve_rad_s")}},
                                 "robot": {"track_width_m": patch.robot.track_width_m},
                                 "estimator": {"stream_rate_hz": 20.0}})
    straight = bench.straight(patched)
    assert abs(straight["speed_error_pct"]) < 5.0  # open loop without it: -46 %


def test_calibration_finds_the_effective_track_and_the_radius_ratio() -> None:
    vehicle = VehicleConfig(start_armed=True, true_right_radius_m=0.051, true_track_width_m=0.309)
    cal, _ = bench.calibrate(bench.bench_profile("closed_loop"), vehicle, quick=True)
    res = cal.result
    assert res is not None, cal.error
    assert res.radius_ratio == pytest.approx(1.02, abs=0.005)
    assert res.track_width_m == pytest.approx(0.309 / 1.01, rel=0.02)  # in the units of the reported distances
    assert 0.5 * (res.left_radius_m + res.right_radius_m) == pytest.approx(0.05)


@pytest.mark.parametrize(("vehicle", "profile", "words"), [
    (VehicleConfig(start_armed=True, left_reversed=True), {}, "left motor runs backwards"),
    (VehicleConfig(start_armed=True), {"encoders": {"left_reversed": True}}, "left encoder counts backwards"),
    (VehicleConfig(start_armed=True, left_function=53, right_function=51), {}, "swapped"),
    (VehicleConfig(start_armed=True, left_function=0), {}, "left wheel did not move"),
])
def test_calibration_refuses_bad_wiring_and_says_what_to_fix(vehicle: VehicleConfig, profile: dict[str, object],
                                                            words: str) -> None:
    cal, rig = bench.calibrate(profile_from_dict({"estimator": {"stream_rate_hz": 20.0}, **profile}), vehicle,
                               quick=True)
    assert cal.result is None and cal.error is not None and words in cal.error, cal.error
    assert rig.core.command.state.value != "direct"  # back to neutral on the way out


# ------------------------------------------------------------------ the command, against the emulator


def _start(emu: Emulator, tmp_path: Path, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "calibrate", "--quick", "--yes", "--params",
         str(REPO / "params" / "default.toml"), "--autopilot", f"udpout:127.0.0.1:{emu.local_address[1]}",
         "--out", str(tmp_path / "patch.toml"), *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))


@pytest.mark.e2e
def test_calibrate_against_the_emulator_writes_a_patch_the_profile_loader_accepts(tmp_path: Path) -> None:
    emu = Emulator(VehicleConfig(start_armed=True, left_motor_gain=0.85, deadzone_pwm=40), seed=21)
    emu.open("udpin:127.0.0.1:0")
    proc = _start(emu, tmp_path)
    clock = WallClockEmulator(emu, None)
    try:
        deadline = time.monotonic() + 120.0
        while proc.poll() is None:
            assert time.monotonic() < deadline, "calibrate did not finish"
            clock.tick(time.monotonic())
            time.sleep(0.004)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert proc.returncode == 0, out[-2000:]
        assert "effective track width" in out and "profile patch" in out
        patch = load_profile(tmp_path / "patch.toml")
        assert patch.control.left_curve_pwm_us and patch.control.right_curve_rad_s
        assert patch.control.left_curve_rad_s[-1] == pytest.approx(0.85 * patch.robot.max_wheel_rad_s, rel=0.05)
        assert patch.robot.track_width_m == pytest.approx(0.30, rel=0.03)
    finally:
        finish_process(proc, emu)


@pytest.mark.e2e
def test_calibrate_stops_the_rover_on_ctrl_c(tmp_path: Path) -> None:
    emu = Emulator(VehicleConfig(start_armed=True), seed=22)
    emu.open("udpin:127.0.0.1:0")
    spy = OverrideSpy(emu)
    proc = _start(emu, tmp_path)
    clock = WallClockEmulator(emu, None)
    try:
        clock.run_until(lambda: any(pwm > 1600 for _, pwm in spy.log), 60.0, "calibrate never drove")
        proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10.0
        while proc.poll() is None:
            assert time.monotonic() < deadline
            clock.tick(time.monotonic())
            time.sleep(0.004)
        clock.run_for(0.2)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert proc.returncode == 1 and "interrupted" in out, out[-1500:]
        assert spy.wheel(1)[-2:] == [1500, 0] and spy.wheel(3)[-2:] == [1500, 0]  # neutral, then release
        assert not (tmp_path / "patch.toml").exists()
    finally:
        finish_process(proc, emu)
