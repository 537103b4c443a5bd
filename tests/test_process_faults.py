"""Process faults: signals during motion, and an exception inside a handler.

- 20 trials (10 SIGTERM, 10 SIGINT, two at a time): the real `python -m rover_bridge run` process
  against an in-process emulator, a GCS driving the rover; the signal arrives at a seeded moment
  during motion; every trial must exit 0 with neutral, then release, received by the autopilot.
- A BridgeCore whose handle raises on a chosen message, run through the CLI in-process: the loop's error
  path sends neutral, then release, and the exit status is 1.

A spy on the emulator records every RC override it applies (channel, pwm), so the order of the
safe-stop messages is checked, not only the final state.
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from lockstep import GCS_COMPID, GCS_SYSID, finish_process, step_wall

from rover_bridge.app import cli
from rover_bridge.app.commands import run as run_command
from rover_bridge.app.composition import BridgeCore
from rover_bridge.mavlink.dialect import mavlink, mavutil
from rover_bridge.mavlink.wire import Incoming, Reaction
from rover_bridge.params import Profile
from sitl import Emulator, VehicleConfig

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]
PARAMS = str(REPO / "params" / "default.toml")
LEFT, RIGHT = Profile().output.left_channel, Profile().output.right_channel
TRIM = Profile().output.pwm_trim
TRIALS = [(i, signal.SIGTERM if i % 2 == 0 else signal.SIGINT) for i in range(20)]


class OverrideSpy:
    """Records every (channel, pwm) the emulated autopilot applies from RC_CHANNELS_OVERRIDE."""

    def __init__(self, emu: Emulator) -> None:
        self.log: list[tuple[int, int]] = []
        autopilot = emu.autopilot
        original = autopilot._set_override

        def spy(ch: int, pwm: int, now_us: int) -> None:
            self.log.append((ch, pwm))
            original(ch, pwm, now_us)

        autopilot._set_override = spy  # type: ignore[method-assign]

    def wheel(self, ch: int) -> list[int]:
        return [pwm for c, pwm in self.log if c == ch]


def assert_neutral_then_released(spy: OverrideSpy, emu: Emulator) -> None:
    now_us = emu.sim_time_us
    for ch in (LEFT, RIGHT):
        values = spy.wheel(ch)
        assert any(v > TRIM for v in values), values[-10:]  # it was driving
        assert values[-2:] == [TRIM, 0], values[-10:]  # neutral, then release: the last two it received
        assert not emu.autopilot.has_override(ch, now_us)


class Gcs:
    """Listens on a port of its own choosing (`port`); the bridge sends to it (`--gcs udpout:`) and it
    answers the address the bridge's first frame came from. Ports are bound at 0, never picked and
    then bound: with trials in parallel, a port found free can be taken before it is bound."""

    def __init__(self) -> None:
        self.conn: Any = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=GCS_SYSID,
                                                    source_component=GCS_COMPID, dialect="ardupilotmega")
        self.port: int = self.conn.port.getsockname()[1]
        self.seen: set[str] = set()

    def heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def forward(self, vx_m_s: float = 0.5) -> None:
        self.conn.mav.set_position_target_local_ned_send(0, 1, 1, 8, 0b0101_1100_0111, 0, 0, 0, vx_m_s, 0, 0, 0, 0,
                                                         0, 0, 0.0)

    def drain(self) -> None:
        while (m := self.conn.recv_msg()) is not None:
            if m.get_type() == "HEARTBEAT":
                self.seen.add("bridge" if m.get_srcComponent() == 191 else "vehicle")

    def close(self) -> None:
        self.conn.close()


class WallClockEmulator:
    """Steps an emulator in wall-clock time; optionally a GCS heartbeats and requests at 10 Hz."""

    def __init__(self, emu: Emulator, gcs: Gcs | None) -> None:
        self.emu, self.gcs = emu, gcs
        self._last = time.monotonic()
        self._next_req = 0.0
        self.requests = False

    def run_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (now := time.monotonic()) < end:
            self.tick(now)
            time.sleep(0.004)

    def run_until(self, cond: Any, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not cond():
            assert time.monotonic() < deadline, what
            self.tick(time.monotonic())
            time.sleep(0.004)

    def tick(self, now: float) -> None:
        if self.gcs is not None and now >= self._next_req:
            self.gcs.heartbeat()
            if self.requests:
                self.gcs.forward()
            self._next_req = now + 0.1
        step_wall(self.emu, now - self._last)
        self._last = now
        if self.gcs is not None:
            self.gcs.drain()


def one_signal_trial(trial: int, signum: int) -> str:
    """Returns '' on success, else a description of what went wrong (collected across threads)."""
    rng = random.Random(1000 + trial)
    emu = Emulator(VehicleConfig(start_armed=True), seed=trial)
    emu.open("udpin:127.0.0.1:0")
    ap_port = emu.local_address[1]
    gcs = Gcs()
    spy = OverrideSpy(emu)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "run", "--params", PARAMS, "--autopilot",
         f"udpout:127.0.0.1:{ap_port}", "--gcs", f"udpout:127.0.0.1:{gcs.port}", "--duration", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    clock = WallClockEmulator(emu, gcs)
    try:
        # Requests from the start: the first ones the bridge can act on set the rover moving (start-up
        # takes seconds on a loaded machine, and nothing is sent before the vehicle is known).
        clock.requests = True

        def moving() -> bool:
            return emu.truth.v_m_s > 0.2 and emu.autopilot.has_override(LEFT, emu.sim_time_us)

        clock.run_until(moving, 120.0, "not moving")
        clock.run_for(rng.uniform(0.0, 0.3))  # a seeded moment during motion
        # On a loaded machine a request can come late and the bridge brake meanwhile: the signal goes once the
        # rover moves again (the deadline only bounds a hang; what is checked is the stop from motion).
        clock.run_until(moving, 120.0, "not moving again")
        assert moving()
        proc.send_signal(signum)
        deadline = time.monotonic() + 15.0
        while proc.poll() is None:  # keep the emulator (and the GCS) alive while the bridge stops
            assert time.monotonic() < deadline, "bridge did not exit"
            clock.tick(time.monotonic())
            time.sleep(0.004)
        clock.requests = False
        clock.run_for(0.3)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert proc.returncode == 0, f"exit {proc.returncode}: {out[-2000:]}"
        assert_neutral_then_released(spy, emu)
        return ""
    except AssertionError as exc:
        return f"trial {trial} ({signal.Signals(signum).name}): {exc}"
    finally:
        finish_process(proc, gcs, emu)


def test_sigterm_and_sigint_during_motion_release_the_overrides_in_20_trials() -> None:
    with ThreadPoolExecutor(max_workers=3) as pool:  # start-up is CPU, the rest mostly waiting: 3 at a time
        failures = [f for f in pool.map(lambda t: one_signal_trial(*t), TRIALS) if f]
    assert failures == [], "\n".join(failures)


class ExplodingCore(BridgeCore):
    """A BridgeCore whose handle raises on the Nth velocity request (a bug in a handler)."""

    explode_on = "SET_POSITION_TARGET_LOCAL_NED"
    after = 15

    def __init__(self, profile: Profile) -> None:
        super().__init__(profile)
        self.seen = 0

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        if inc.msg.get_type() == self.explode_on:
            self.seen += 1
            if self.seen > self.after:
                raise RuntimeError("injected handler fault")
        return super().handle(inc, now_s)


def test_an_exception_in_a_handler_ends_in_neutral_then_release_and_exit_status_1(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr(run_command, "BridgeCore", ExplodingCore)
    emu = Emulator(VehicleConfig(start_armed=True), seed=99)
    emu.open("udpin:127.0.0.1:0")
    ap_port = emu.local_address[1]
    spy = OverrideSpy(emu)
    gcs = Gcs()
    clock = WallClockEmulator(emu, gcs)
    clock.requests = True
    stop = threading.Event()
    lock = threading.Lock()

    def background() -> None:  # the emulator and the GCS live in a thread; the CLI needs the main one
        while not stop.is_set():
            with lock:
                clock.tick(time.monotonic())
            time.sleep(0.004)

    worker = threading.Thread(target=background, daemon=True)
    worker.start()
    try:
        code = cli.main(["run", "--params", PARAMS, "--autopilot", f"udpout:127.0.0.1:{ap_port}",
                         "--gcs", f"udpout:127.0.0.1:{gcs.port}", "--duration", "30"])
        time.sleep(0.3)  # the last datagrams reach the emulator
    finally:
        stop.set()
        worker.join(timeout=5.0)
    try:
        with lock:
            clock.requests = False
            clock.run_for(0.1)
        assert code == 1
        assert "injected handler fault" in caplog.text  # logged with its traceback, not swallowed
        assert_neutral_then_released(spy, emu)
    finally:
        gcs.close()
        emu.close()
