"""The stop that does not wait for the core: a thread that watches the signals and the loop.

A signal (SIGINT, SIGTERM, systemd's watchdog SIGABRT) is written by the interpreter's C-level
handler to a pipe (signal.set_wakeup_fd) the moment it arrives, whatever the main thread is doing.
This thread reads it and wakes the loop, which stops the rover the normal way (neutral, release,
confirmed by the autopilot: Runner.stop_safely). If the loop does not start that within GRACE_S
(it is stuck in a long computation, or in a C call), or does not finish it in time, this thread
sends the stop itself, from frames the loop packed beforehand (neutral, release, a TIMESYNC probe:
Runner.emergency_frames), waits up to LINGER_S for the autopilot's answer (a stream link must stay
open until the stop is parsed), and ends the process. The same happens when the loop has not
completed a pass for safety.loop_watchdog_s: a bridge that stops turning stops the rover (servo
mode would otherwise hold the last PWM forever) and exits 1, so systemd restarts it.

Only raw file descriptor I/O here: the main thread may hold any lock (logging's included) when
this thread acts.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Protocol

from rover_bridge.mavlink.dialect import mavlink

GRACE_S = 0.08  # the loop starts its own stop within this, or the guard does it
LINGER_S = 0.1  # after an emergency stop: how long to wait for the autopilot's answer before exiting
# The GIL hand-over time while the guard acts. A stuck main thread holds the GIL, and every read of
# the guard's gives it up; at CPython's 5 ms default, reading a stalled loop's backlog of 50 datagrams
# took the whole LINGER_S, so a stop that landed was reported unconfirmed. The process ends next.
EMERGENCY_SWITCH_S = 1e-4
DONE_MARGIN_S = 0.3  # the loop's own stop may take its confirmation wait plus this
# Until the loop's first pass, how often to look; after it, the thread sleeps until the moment a stall
# would be due (a wake-up costs a companion computer more CPU than its check: no polling).
POLL_S = 0.05
EXIT_STALLED = 1


class RawLink(Protocol):
    """What the guard needs of the autopilot link: write and read bytes, from another thread."""

    def write_raw(self, data: bytes) -> None: ...
    def read_raw(self, size: int) -> bytes: ...
    def fileno(self) -> int | None: ...


class StopGuard(threading.Thread):
    """See the module docstring. The loop calls `passed` every pass, `stopping` before its own stop and
    `done` after it; it keeps `frames` (the emergency stop, packed) current."""

    def __init__(self, signal_fd: int, wake_fd: int, link: RawLink, confirm_timeout_s: float,
                 stall_s: float = 0.0, probe_ts1: int = 0,
                 exit_process: Callable[[int], None] = os._exit) -> None:
        super().__init__(name="rover-bridge stop guard", daemon=True)
        self.signal_fd, self.wake_fd = signal_fd, wake_fd
        self.link = link
        self.confirm_timeout_s = confirm_timeout_s
        self.stall_s = stall_s
        self.probe_ts1 = probe_ts1
        self.exit_process = exit_process
        self.frames = b""  # written by the loop, read here: a bytes object is replaced whole
        self.signals: list[int] = []
        self.emergency_reason = ""
        self.confirmed: bool | None = None  # after an emergency stop: whether the autopilot answered
        self._last_pass_s: float | None = None
        self._stopping = threading.Event()
        self._done = threading.Event()
        self._quit = threading.Event()
        self._quit_r, self._quit_w = os.pipe()  # quit() wakes the thread's select at once
        self.wakeups = 0

    # ------------------------------------------------------------------ called by the loop
    def passed(self, now_s: float) -> None:
        self._last_pass_s = now_s

    def stopping(self) -> None:
        self._stopping.set()

    def done(self) -> None:
        self._done.set()

    def quit(self) -> None:
        """The process is ending normally: stop watching."""
        if self._quit.is_set():
            return
        self._quit.set()
        self._done.set()
        _poke(self._quit_w)
        os.close(self._quit_w)  # once: its number may be reused after this

    # ------------------------------------------------------------------ the thread
    def run(self) -> None:
        try:
            self._watch()
        finally:
            os.close(self._quit_r)

    def _watch(self) -> None:
        while not self._quit.is_set():
            readable, _, _ = select.select([self.signal_fd, self._quit_r], [], [], self._timeout_s())
            self.wakeups += 1
            if self._quit.is_set():
                return
            if self.signal_fd in readable:
                try:
                    data = os.read(self.signal_fd, 64)
                except (BlockingIOError, InterruptedError):
                    data = b""
                if data:
                    self.signals += list(data)
                    self._on_signal(data[-1])
                    return
            last = self._last_pass_s
            if (self.stall_s > 0.0 and last is not None and not self._stopping.is_set()
                    and time.monotonic() - last > self.stall_s):
                self._emergency(f"the loop has not turned for {time.monotonic() - last:.2f} s", EXIT_STALLED)
                return

    def _timeout_s(self) -> float | None:
        """Until a stall would be due (the loop's last pass + stall_s); None (a signal or quit) without
        stall watching or once the loop's own stop began, POLL_S before the first pass."""
        if self.stall_s <= 0.0 or self._stopping.is_set():
            return None
        last = self._last_pass_s
        if last is None:
            return POLL_S
        return max(0.0, last + self.stall_s - time.monotonic()) + 1e-3  # just past it: no early wake-up

    def _on_signal(self, signum: int) -> None:
        _poke(self.wake_fd)  # the loop's select wakes at once
        if signum == signal.SIGABRT:  # systemd's watchdog: it has already decided the loop is stuck
            self._emergency("watchdog signal (SIGABRT): the loop stopped pinging", EXIT_STALLED)
            return
        if not self._stopping.wait(GRACE_S):
            self._emergency(f"signal {signum}: the loop did not start its stop within {GRACE_S:.2f} s", 0)
            return
        if not self._done.wait(self.confirm_timeout_s + DONE_MARGIN_S):
            self._emergency(f"signal {signum}: the loop did not finish its stop", 0)

    def _emergency(self, reason: str, code: int) -> None:
        if self._done.is_set():
            return
        self.emergency_reason = reason
        frames = self.frames
        confirmed = False
        switch_s = sys.getswitchinterval()
        sys.setswitchinterval(EMERGENCY_SWITCH_S)
        try:
            if frames:
                self.link.write_raw(frames)
                confirmed = self._linger()
        except OSError:
            pass
        finally:
            sys.setswitchinterval(switch_s)  # as it was: only a test's process lives on after this
        self.confirmed = confirmed if frames else None
        _say(f"rover-bridge: {reason}; stop sent by the guard ({'confirmed' if confirmed else 'NOT confirmed'} "
             f"by the autopilot), exiting {code}\n" if frames else
             f"rover-bridge: {reason}; no vehicle known, nothing to stop; exiting {code}\n")
        self.exit_process(code)

    def _linger(self) -> bool:
        """Keep the link open until the autopilot answers the probe (or LINGER_S): True if it did."""
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        end = time.monotonic() + LINGER_S
        fd = self.link.fileno()
        while True:
            try:
                data = self.link.read_raw(4096)
            except OSError:
                data = b""
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() == "TIMESYNC" and msg.tc1 != 0 and msg.ts1 == self.probe_ts1:
                    return True
            if (left := end - time.monotonic()) <= 0.0:
                return False
            if data:  # a backlog is read back to back; wait only when the link had nothing
                continue
            if fd is None:
                time.sleep(min(left, 0.005))
            else:
                select.select([fd], [], [], min(left, 0.01))


def _poke(fd: int) -> None:
    with contextlib.suppress(OSError):
        os.write(fd, b"\0")


def _say(text: str) -> None:
    with contextlib.suppress(OSError):
        os.write(2, text.encode("utf-8", "replace"))
