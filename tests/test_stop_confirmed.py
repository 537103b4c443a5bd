"""The stop at exit is confirmed by the autopilot, not assumed (issue: the stop over TCP was lost).

ArduPilot parses its serial input on its main loop; over a stream link (SITL's TCP SERIAL0,
mavlink-router) the bytes a client sends just before it closes are never parsed as its own. The
emulator does the same (what it reads in one step is parsed in the next, and dropped if the client
closed in between), so:

- a plain client that sends neutral + release and closes at once leaves the wheels turning;
- the real `rover-bridge run` process over TCP, in rc_override and in servo mode, stops the wheels on
  SIGTERM: neutral, release, and a TIMESYNC probe whose answer it waits for before it closes.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from lockstep import finish_process
from test_process_faults import Gcs, WallClockEmulator

from rover_bridge.mavlink.dialect import mavlink
from sitl import Emulator, VehicleConfig

REPO = Path(__file__).resolve().parents[1]
TRIM = 1500


def _override(mav: Any, left: int, right: int) -> bytes:
    chans = [65535] * 8 + [0] * 10
    chans[0], chans[2] = left, right
    return bytes(mav.rc_channels_override_encode(1, 1, *chans).pack(mav))


def _connected_client(emu: Emulator) -> tuple[socket.socket, Any]:
    sock = socket.create_connection(emu.local_address)
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    emu.step(0.01)  # accepted
    return sock, mav


@pytest.mark.parametrize("linger_steps", [0, 2])
def test_the_emulator_drops_what_a_tcp_client_sent_just_before_it_closed(linger_steps: int) -> None:
    emu = Emulator(VehicleConfig(start_armed=True))
    emu.open("tcpin:127.0.0.1:0")
    try:
        sock, mav = _connected_client(emu)
        sock.sendall(_override(mav, 1700, 1700))
        for _ in range(3):
            emu.step(0.01)
        assert emu.servo_outputs[1] == 1700  # obeyed while connected
        sock.sendall(_override(mav, TRIM, TRIM) + _override(mav, 0, 0))  # neutral, release
        for _ in range(linger_steps):
            emu.step(0.01)
        sock.close()
        for _ in range(5):
            emu.step(0.01)
        if linger_steps:
            assert emu.servo_outputs[1] == TRIM and not emu.autopilot.has_override(1, emu.sim_time_us)
        else:  # closed at once: the stop was never parsed, the override runs on (RC_OVERRIDE_TIME)
            assert emu.servo_outputs[1] == 1700 and emu.autopilot.has_override(1, emu.sim_time_us)
            assert emu.counters["rx_lost_on_close_bytes"] > 0
    finally:
        emu.close()


def _profile(tmp_path: Path, mode: str) -> str:
    path = tmp_path / f"{mode}.toml"
    path.write_text(f'[output]\nmode = "{mode}"\n', encoding="utf-8")
    return str(path)


@pytest.mark.e2e
@pytest.mark.parametrize("mode", ["rc_override", "servo"])
def test_sigterm_over_tcp_stops_the_wheels_and_the_stop_is_confirmed(tmp_path: Path, mode: str) -> None:
    emu = Emulator(VehicleConfig(start_armed=True), seed=3)
    emu.open("tcpin:127.0.0.1:0")
    gcs = Gcs()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "rover_bridge", "-v", "run", "--params", _profile(tmp_path, mode), "--autopilot",
         f"tcp:127.0.0.1:{emu.local_address[1]}", "--gcs", f"udpout:127.0.0.1:{gcs.port}", "--duration", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    clock = WallClockEmulator(emu, gcs)
    try:
        clock.requests = True
        clock.run_until(lambda: emu.truth.v_m_s > 0.3 and emu.servo_outputs[1] > 1600, 60.0, "not driving")
        clock.run_for(0.2)
        proc.send_signal(signal.SIGTERM)
        t_signal = time.monotonic()
        stopped_after: float | None = None
        deadline = t_signal + 10.0
        while proc.poll() is None or time.monotonic() < t_signal + 0.5:
            assert time.monotonic() < deadline, "bridge did not exit"
            clock.tick(time.monotonic())
            if stopped_after is None and emu.servo_outputs[1] == TRIM and emu.servo_outputs[3] == TRIM:
                stopped_after = time.monotonic() - t_signal
            time.sleep(0.002)
        clock.requests = False
        clock.run_for(1.0)  # the wheels stay stopped: nothing left holding them (no override, no servo hold)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert proc.returncode == 0, out[-2000:]
        assert stopped_after is not None and stopped_after < 1.0, (stopped_after, emu.servo_outputs)
        assert emu.servo_outputs[1] == TRIM and emu.servo_outputs[3] == TRIM
        assert abs(emu.truth.v_m_s) < 0.01
        if mode == "rc_override":
            assert not emu.autopilot.has_override(1, emu.sim_time_us)
        assert "confirmed by the autopilot" in out and "NOT confirmed" not in out, out[-2000:]
    finally:
        finish_process(proc, gcs, emu)
