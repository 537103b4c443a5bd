"""A bridge that hangs still stops the rover: sd_notify watchdog pings, and a stop that does not wait for the core.

- SystemdNotifier against a fake $NOTIFY_SOCKET: READY=1, WATCHDOG=1 every quarter of $WATCHDOG_USEC on a
  grid, STOPPING=1.
- StopGuard on its own (pipes, a fake link, a recorded exit): signal with a loop that stops / does not
  stop in time, a loop that stalls, the answer to its probe.
- The real process with a core that stalls on purpose (a busy loop inside `handle`, as a long computation
  would): SIGTERM is obeyed within 200 ms with neutral and release, and a stall with nobody signalling
  stops the pings and ends in the same stop and exit 1 (systemd's restart).
"""

from __future__ import annotations

import math
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
from test_process_faults import Gcs, OverrideSpy, WallClockEmulator

from rover_bridge.app.guard import EXIT_STALLED, LINGER_S, StopGuard
from rover_bridge.app.systemd import SystemdNotifier
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.links import Endpoint
from rover_bridge.mavlink.wire import Link
from sitl import Emulator, VehicleConfig

REPO = Path(__file__).resolve().parents[1]
LEFT, RIGHT, TRIM = 1, 3, 1500


def _notify_socket(tmp_path: Path) -> tuple[socket.socket, str]:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(0.0)
    return sock, path


def _received(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def test_notifier_sends_ready_watchdog_every_quarter_interval_on_a_grid_and_stopping(tmp_path: Path) -> None:
    sock, path = _notify_socket(tmp_path)
    n = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.watchdog_s == 1.0
    n.ready()
    pinged = []
    for t in (0.0, 0.1, 0.24, 0.27, 0.49, 0.52, 0.74, 0.77, 0.99, 3.0, 3.2, 3.25):
        before = n.sent
        n.ping(t)
        if n.sent > before:
            pinged.append(t)
    n.stopping()
    got = _received(sock)
    assert got[0].startswith("READY=1") and got[-1] == "STOPPING=1"
    # Due at 0, 0.25, 0.5, 0.75: a pass 20 ms late does not move the next one (no creeping past half the
    # interval); after a stall (3.0) the grid restarts from the ping.
    assert pinged == [0.0, 0.27, 0.52, 0.77, 3.0, 3.25] and got.count("WATCHDOG=1") == 6
    assert SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"}).watchdog_s \
        is None  # meant for another process
    quiet = SystemdNotifier({})
    quiet.ready()
    quiet.ping(0.0)
    assert not quiet.enabled and quiet.sent == 0


class FakeLink:
    def __init__(self, answer: bytes = b"") -> None:
        self.written: list[bytes] = []
        self.answer = answer

    def write_raw(self, data: bytes) -> None:
        self.written.append(data)

    def read_raw(self, size: int) -> bytes:
        data, self.answer = self.answer, b""
        return data

    def fileno(self) -> int | None:
        return None


class Guarded:
    def __init__(self, stall_s: float = 0.0, answer: bytes = b"") -> None:
        self.sig_r, self.sig_w = os.pipe()
        self.wake_r, self.wake_w = os.pipe()
        self.exits: list[int] = []
        self.link = FakeLink(answer)
        self.guard = StopGuard(self.sig_r, self.wake_w, self.link, confirm_timeout_s=0.3, stall_s=stall_s,
                               probe_ts1=42, exit_process=self.exits.append)
        self.guard.frames = b"STOP"
        self.guard.start()

    def signal(self, signum: int = signal.SIGTERM) -> None:
        os.write(self.sig_w, bytes([signum]))

    def close(self) -> None:
        self.guard.quit()
        self.guard.join(timeout=2.0)
        for fd in (self.sig_r, self.sig_w, self.wake_r, self.wake_w):
            os.close(fd)


def test_guard_leaves_the_stop_to_a_loop_that_responds() -> None:
    g = Guarded()
    try:
        g.signal()
        time.sleep(0.02)
        assert os.read(g.wake_r, 16)  # the loop was woken at once
        g.guard.stopping()
        time.sleep(0.1)
        g.guard.done()
        g.guard.join(timeout=2.0)
        assert g.link.written == [] and g.exits == []
    finally:
        g.close()


def test_guard_stops_the_rover_itself_when_the_loop_does_not_respond() -> None:
    reply = mavlink.MAVLink_timesync_message(tc1=7, ts1=42).pack(mavlink.MAVLink(None, 1, 1))
    g = Guarded(answer=bytes(reply))
    try:
        t0 = time.monotonic()
        g.signal()
        g.guard.join(timeout=2.0)
        assert g.link.written == [b"STOP"] and g.exits == [0]
        assert time.monotonic() - t0 < 0.2
        assert "did not start its stop" in g.guard.emergency_reason
    finally:
        g.close()


class AnsweringAutopilot:
    """The bridge's real UDP link to an autopilot socket that answers the guard's stop at once, behind a
    backlog of telemetry the stalled loop never read."""

    def __init__(self, backlog: int, answer: bytes) -> None:
        self.ap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.ap.bind(("127.0.0.1", 0))
        self.ep = Endpoint(f"udpout:127.0.0.1:{self.ap.getsockname()[1]}", Link.AUTOPILOT)
        self.ep.write_raw(b"hello")
        _, self.bridge = self.ap.recvfrom(64)
        mav = mavlink.MAVLink(None, 1, 1)
        for i in range(backlog):
            self.ap.sendto(bytes(mavlink.MAVLink_attitude_message(i, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav)), self.bridge)
        self.answer = answer
        self.written: list[bytes] = []

    def write_raw(self, data: bytes) -> None:
        self.ep.write_raw(data)
        self.written.append(self.ap.recv(65535))
        self.ap.sendto(self.answer, self.bridge)

    def read_raw(self, size: int) -> bytes:
        return self.ep.read_raw(size)

    def fileno(self) -> int | None:
        return self.ep.fileno()

    def close(self) -> None:
        self.ep.close()
        self.ap.close()


def test_guard_confirms_its_stop_behind_a_backlog_while_the_main_thread_holds_the_gil() -> None:
    # A stalled loop leaves the autopilot's telemetry unread; the guard reads through it to the answer
    # while the main thread spins in Python. At CPython's 5 ms GIL hand-over this took 50 datagrams per
    # LINGER_S, and the stop that landed was reported NOT confirmed.
    reply = bytes(mavlink.MAVLink_timesync_message(tc1=7, ts1=42).pack(mavlink.MAVLink(None, 1, 1)))
    link = AnsweringAutopilot(backlog=300, answer=reply)
    sig_r, sig_w = os.pipe()
    wake_r, wake_w = os.pipe()
    exits: list[int] = []
    guard = StopGuard(sig_r, wake_w, link, confirm_timeout_s=0.3, probe_ts1=42, exit_process=exits.append)
    guard.frames = b"STOP"
    switch_s = sys.getswitchinterval()
    try:
        guard.start()
        t0 = time.monotonic()
        os.write(sig_w, bytes([signal.SIGTERM]))
        spins = 0
        while guard.is_alive() and time.monotonic() - t0 < 5.0:
            spins += 1  # the stuck core: pure Python, never blocking
        assert link.written == [b"STOP"] and exits == [0]
        assert guard.confirmed is True, "the stop landed but the answer was not read in time"
        assert sys.getswitchinterval() == switch_s  # a process that lives on gets its GIL timing back
    finally:
        guard.quit()
        guard.join(timeout=2.0)
        link.close()
        for fd in (sig_r, sig_w, wake_r, wake_w):
            os.close(fd)


def test_guard_stops_a_loop_that_stalls_and_exits_1() -> None:
    g = Guarded(stall_s=0.2)
    try:
        g.guard.passed(time.monotonic())
        g.guard.join(timeout=2.0)
        assert g.link.written == [b"STOP"] and g.exits == [EXIT_STALLED]
        assert "has not turned" in g.guard.emergency_reason
    finally:
        g.close()


def test_guard_sleeps_while_the_loop_turns_and_still_catches_a_stall_on_time() -> None:
    g = Guarded(stall_s=0.3)
    try:
        end = time.monotonic() + 1.0
        while (now := time.monotonic()) < end:  # a loop turning every 10 ms for a second
            g.guard.passed(now)
            time.sleep(0.01)
        assert g.guard.wakeups <= 6 and g.exits == []  # polling at 50 ms would have woken 20 times
        last = time.monotonic()
        g.guard.passed(last)
        g.guard.join(timeout=2.0)  # the loop stops turning
        assert g.exits == [EXIT_STALLED]
        assert 0.3 <= time.monotonic() - last < 0.3 + LINGER_S + 0.05  # then it waits LINGER_S for an answer
    finally:
        g.close()


def test_guard_quits_at_once_however_long_it_would_sleep() -> None:
    g = Guarded(stall_s=30.0)
    try:
        g.guard.passed(time.monotonic())
        time.sleep(0.05)
        t0 = time.monotonic()
        g.guard.quit()
        g.guard.join(timeout=2.0)
        assert not g.guard.is_alive() and time.monotonic() - t0 < 0.1 and g.exits == []
    finally:
        g.close()


def test_guard_takes_the_watchdog_signal_as_a_stall() -> None:
    g = Guarded()
    try:
        g.signal(signal.SIGABRT)
        g.guard.join(timeout=2.0)
        assert g.exits == [EXIT_STALLED] and g.link.written == [b"STOP"]
    finally:
        g.close()


# ------------------------------------------------------------------ the real process, stalled on purpose

STALLING_BRIDGE = """
import sys, time
from rover_bridge.app.commands import run as run_command
from rover_bridge.app.composition import BridgeCore

class Stalling(BridgeCore):
    def handle(self, inc, now_s):
        if inc.msg.get_type() == "MANUAL_CONTROL" and inc.msg.x == 999:
            end = time.monotonic() + 30.0
            while time.monotonic() < end:  # a long computation inside the core, holding the loop
                pass
        return super().handle(inc, now_s)

run_command.BridgeCore = Stalling
sys.argv = ["rover-bridge"] + sys.argv[1:]
from rover_bridge.app.cli import console_main
console_main()
"""


def _start(tmp_path: Path, emu: Emulator, gcs: Gcs, env_extra: dict[str, str]) -> subprocess.Popen[bytes]:
    script = tmp_path / "stalling_bridge.py"
    script.write_text(STALLING_BRIDGE)
    env = dict(os.environ, PYTHONUNBUFFERED="1", **env_extra)
    return subprocess.Popen(
        [sys.executable, str(script), "run", "--params", str(REPO / "params" / "default.toml"), "--autopilot",
         f"udpout:127.0.0.1:{emu.local_address[1]}", "--gcs", f"udpout:127.0.0.1:{gcs.port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)


def _drive_then_stall(emu: Emulator, gcs: Gcs, clock: WallClockEmulator, before: Any = None) -> float:
    clock.requests = True
    clock.run_until(lambda: emu.truth.v_m_s > 0.3 and emu.autopilot.has_override(LEFT, emu.sim_time_us), 60.0,
                    "not driving")
    if before is not None:
        before()
    gcs.conn.mav.manual_control_send(1, 999, 0, 500, 0, 0)  # the core stalls on this one
    return time.monotonic()


def _stopped(spy: OverrideSpy) -> bool:
    return spy.wheel(LEFT)[-2:] == [TRIM, 0] and spy.wheel(RIGHT)[-2:] == [TRIM, 0]


@pytest.mark.e2e
def test_sigterm_during_a_stalled_core_is_obeyed_within_200_ms(tmp_path: Path) -> None:
    emu = Emulator(VehicleConfig(start_armed=True), seed=11)
    emu.open("udpin:127.0.0.1:0")
    gcs = Gcs()
    spy = OverrideSpy(emu)
    proc = _start(tmp_path, emu, gcs, {})
    clock = WallClockEmulator(emu, gcs)
    try:
        _drive_then_stall(emu, gcs, clock)
        clock.run_for(0.15)  # well into the stall
        clock.requests = False
        proc.send_signal(signal.SIGTERM)
        t_signal = time.monotonic()
        stopped_after: float | None = None
        while proc.poll() is None and time.monotonic() - t_signal < 5.0:
            clock.tick(time.monotonic())
            if stopped_after is None and _stopped(spy):
                stopped_after = time.monotonic() - t_signal
            time.sleep(0.002)
        exited_after = time.monotonic() - t_signal
        clock.run_for(0.1)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert proc.returncode == 0, out[-1500:]
        assert stopped_after is not None and stopped_after < 0.2, (stopped_after, spy.log[-6:])
        assert exited_after < 0.5, exited_after
        assert "stop sent by the guard (confirmed by the autopilot)" in out, out[-1500:]
    finally:
        finish_process(proc, gcs, emu)


@pytest.mark.e2e
def test_a_stalled_loop_stops_the_watchdog_pings_and_the_rover(tmp_path: Path) -> None:
    sock, path = _notify_socket(tmp_path)
    emu = Emulator(VehicleConfig(start_armed=True), seed=12)
    emu.open("udpin:127.0.0.1:0")
    gcs = Gcs()
    spy = OverrideSpy(emu)
    proc = _start(tmp_path, emu, gcs, {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"})
    clock = WallClockEmulator(emu, gcs)
    try:
        early: list[str] = []
        t_stall = _drive_then_stall(emu, gcs, clock, before=lambda: early.extend(_received(sock)))
        assert early[0].startswith("READY=1") and early.count("WATCHDOG=1") >= 3  # pinging while it turned
        pings: list[tuple[float, str]] = []
        while proc.poll() is None and time.monotonic() - t_stall < 5.0:
            clock.tick(time.monotonic())
            pings += [(time.monotonic(), m) for m in _received(sock)]
            time.sleep(0.002)
        clock.run_for(0.1)
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        watchdog = [t for t, m in pings if m == "WATCHDOG=1"]
        assert proc.returncode == 1, out[-1500:]  # systemd restarts on-failure
        assert _stopped(spy), spy.log[-6:]
        assert "has not turned" in out, out[-1500:]
        # No ping after the stall began (the one in flight may still land); read as they come.
        assert not [t for t in watchdog if t > t_stall + 0.15], [t - t_stall for t in watchdog]
        assert time.monotonic() - t_stall < 5.0
    finally:
        sock.close()
        finish_process(proc, gcs, emu)


def test_the_process_tells_systemd_it_is_ready_and_pings_while_it_runs(tmp_path: Path) -> None:
    sock, path = _notify_socket(tmp_path)
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="400000")
    # Read as the messages come (as systemd does): the socket queues only net.unix.max_dgram_qlen of them.
    # 6 s: READY=1 waits for the filter's import, which took over 2.8 s with the suite's workers on both cores.
    proc = subprocess.Popen([sys.executable, "-m", "rover_bridge", "run", "--params",
                             str(REPO / "params" / "default.toml"), "--autopilot", "udpout:127.0.0.1:9", "--gcs",
                             "none", "--duration", "6.0"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    got: list[str] = []
    ready_s = stopping_s = math.nan
    try:
        while proc.poll() is None:
            new = _received(sock)
            now = time.monotonic()
            if any(m.startswith("READY=1") for m in new):
                ready_s = now
            if "STOPPING=1" in new:
                stopping_s = now
            got += new
            time.sleep(0.01)
        got += _received(sock)
        stderr = proc.stderr.read() if proc.stderr else b""
    finally:
        finish_process(proc, sock)
        if proc.stderr:
            proc.stderr.close()
    assert proc.returncode == 0, stderr[-1000:]
    assert got[0].startswith("READY=1") and got[-1] == "STOPPING=1"
    # Every 0.1 s (a quarter of 0.4 s) from READY=1, which comes once the filter is built (it imports filterpy
    # and scipy after the first pass: the ready time depends on the machine), to STOPPING=1.
    if math.isnan(stopping_s):
        stopping_s = time.monotonic()
    expected = (stopping_s - ready_s) / 0.1
    assert 0.5 * expected - 1 <= got.count("WATCHDOG=1") <= 1.5 * expected + 2
    assert got.count("WATCHDOG=1") >= 3


def test_the_shipped_unit_uses_the_watchdog_and_restarts_failures_but_not_bad_profiles() -> None:
    unit = (REPO / "deploy" / "rover-bridge.service").read_text()
    settings = dict(line.split("=", 1) for line in unit.splitlines() if "=" in line and not line.startswith("#"))
    assert settings["Type"] == "notify" and settings["NotifyAccess"] == "main"
    watchdog_s = float(settings["WatchdogSec"])
    from rover_bridge.params import SafetyParams

    assert SafetyParams().loop_watchdog_s < watchdog_s <= 2.0  # the bridge stops itself first
    assert settings["Restart"] == "on-failure" and settings["RestartPreventExitStatus"] == "2"
