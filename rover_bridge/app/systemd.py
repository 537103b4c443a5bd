"""sd_notify(3) for the systemd unit's Type=notify and WatchdogSec=: a few lines of socket code.

systemd passes $NOTIFY_SOCKET (a Unix datagram socket; '@' starts an abstract one) and, with
WatchdogSec=, $WATCHDOG_USEC (and $WATCHDOG_PID, the process it is meant for). The bridge sends
READY=1 once its links are open and its loop is about to run, WATCHDOG=1 from the loop every quarter
of the watchdog interval while the loop turns (PING_FRACTION), and STOPPING=1 when it stops. A loop
that stops turning stops the pings, and systemd kills and restarts the process (its WatchdogSignal,
SIGABRT, reaches the stop guard, which stops the rover first). Without $NOTIFY_SOCKET every call
does nothing.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Mapping

# WATCHDOG=1 every this fraction of WatchdogSec. sd_watchdog_enabled(3) asks for half or more often; a ping
# goes out in the first pass of the loop after it is due, so at exactly half every gap was half plus that
# pass's delay (measured: 0.526 s with WatchdogSec=1). At a quarter the gap stays under half as long as the
# loop turns within a quarter of the interval (250 ms at WatchdogSec=1; it turns every 50 ms at most).
PING_FRACTION = 0.25


class SystemdNotifier:
    """Sends sd_notify messages; failures are counted, never raised (the rover matters, not the log)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self.sent = 0
        self.errors = 0
        self._sock: socket.socket | None = None
        self._addr = ""
        path = env.get("NOTIFY_SOCKET", "")
        if path:
            self._addr = "\0" + path[1:] if path.startswith("@") else path
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.setblocking(False)
        self.watchdog_s: float | None = None
        usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid.isdigit() or int(pid) == os.getpid()):
            self.watchdog_s = int(usec) / 1e6
        self._next_ping_s: float | None = None

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, text: str) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(text.encode("utf-8"), self._addr)
            self.sent += 1
        except OSError:
            self.errors += 1

    def ready(self, status: str = "running") -> None:
        self.notify(f"READY=1\nSTATUS={status}")

    def ping(self, now_s: float) -> None:
        """From the loop, every pass: WATCHDOG=1 every PING_FRACTION of the interval systemd watches, on a
        fixed grid (a late ping does not push the next one later), restarted after a stall."""
        if self.watchdog_s is None:
            return
        due = self._next_ping_s
        if due is None or now_s >= due:
            interval = PING_FRACTION * self.watchdog_s
            self._next_ping_s = due + interval if due is not None and now_s - due < interval else now_s + interval
            self.notify("WATCHDOG=1")

    def stopping(self) -> None:
        self.notify("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None
