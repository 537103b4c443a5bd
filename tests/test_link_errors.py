"""Errors a person can act on: a link that does not open is one line that names the link and what to check,
with no third-party noise, and exit 1 (not 2: it is not the configuration's fault, and systemd tries again);
a profile that does not parse is one line too (exit 2)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from rover_bridge.app.demo import free_udp_port
from rover_bridge.errors import LinkError
from rover_bridge.mavlink.links import Endpoint, open_problem
from rover_bridge.mavlink.wire import Link

REPO = Path(__file__).resolve().parents[1]


def _run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rover_bridge", *args], capture_output=True, text=True, timeout=180,
                          check=False, cwd=cwd, env=dict(os.environ, PYTHONPATH=str(REPO)))


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_no_autopilot_listening_is_one_line_and_no_pymavlink_noise() -> None:
    url = f"tcp:127.0.0.1:{_free_tcp_port()}"
    done = _run("run", "--autopilot", url, "--gcs", "none", "--duration", "1")
    assert done.returncode == 1
    assert done.stdout == ""  # pymavlink's "[Errno 111] Connection refused sleeping" went to stdout
    assert done.stderr == (f"rover-bridge: cannot open the autopilot link {url}: connection refused, nothing listens "
                           "there: start the autopilot (or SITL, or the router) first, or give its address with "
                           "--autopilot\n")


def test_a_missing_serial_device_is_one_line() -> None:
    done = _run("run", "--autopilot", "/dev/ttyNO-SUCH-DEVICE,921600", "--gcs", "none", "--duration", "1")
    assert (done.returncode, done.stdout) == (1, "")
    assert done.stderr == ("rover-bridge: cannot open the autopilot link /dev/ttyNO-SUCH-DEVICE,921600: no such "
                           "device: is the autopilot plugged in and powered, and is the name right? "
                           "(ls /dev/serial/by-id/)\n")


def test_a_busy_serial_device_is_one_line() -> None:
    """A serial port another program holds (locked, as pyserial's exclusive=True and the bridge itself do)."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    holder = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        fcntl.flock(holder, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(LinkError) as err:
            Endpoint(f"{path},57600", Link.AUTOPILOT)
        assert str(err.value) == (f"cannot open the autopilot link {path},57600: the device is busy: another program "
                                  "holds it (MAVProxy, ModemManager, another rover-bridge): stop it")
        os.close(holder)  # released: the bridge opens it, and then holds it against a second bridge
        first = Endpoint(f"{path},57600", Link.AUTOPILOT)
        try:
            with pytest.raises(LinkError, match="the device is busy"):
                Endpoint(f"{path},57600", Link.AUTOPILOT)
        finally:
            first.close()
    finally:
        for fd in (master, slave):
            os.close(fd)
        with contextlib.suppress(OSError):  # closed above unless the test failed before
            os.close(holder)


def test_a_gcs_address_in_use_is_one_line() -> None:
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:  # e.g. a ground station listening there
        other.bind(("127.0.0.1", port))
        done = _run("run", "--autopilot", "udpout:127.0.0.1:9", "--gcs", f"udpin:127.0.0.1:{port}", "--duration", "1")
    assert (done.returncode, done.stdout) == (1, "")
    assert done.stderr == (f"rover-bridge: cannot open the ground-station link udpin:127.0.0.1:{port}: the address is "
                           "in use: another program (MAVProxy, QGroundControl, another rover-bridge) listens there: "
                           "stop it, or choose another port with --gcs\n")


def test_the_same_port_for_two_links_is_refused_too() -> None:
    """pymavlink binds with SO_REUSEADDR, which would let both links share the port silently."""
    port = free_udp_port()
    first = Endpoint(f"udpin:127.0.0.1:{port}", Link.AUTOPILOT)
    try:
        with pytest.raises(LinkError, match="the address is in use"):
            Endpoint(f"udpin:127.0.0.1:{port}", Link.GCS)
    finally:
        first.close()


def test_a_profile_that_does_not_parse_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "mine.toml"
    bad.write_text("[robot]\nwheel_radius_m = \n")
    done = _run("run", "--params", str(bad), "--gcs", "none")
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr == f"rover-bridge: {bad}: not valid TOML: Invalid value (at line 2, column 18)\n"


def test_a_silent_autopilot_is_said_once_and_start_and_stop_are_info_shown_by_default(tmp_path: Path) -> None:
    """A udpout link opens whether or not anything listens: after 5 s with no HEARTBEAT the log says so, as a
    warning. The start and the stop are INFO lines of rover_bridge.run, shown without -v."""
    done = _run("run", "--autopilot", "udpout:127.0.0.1:9", "--gcs", "none", "--duration", "8")
    assert done.returncode == 0
    lines = [ln.split(" ", 2)[2] for ln in done.stderr.splitlines()]
    assert lines == ["INFO rover_bridge.run: rover-bridge running: autopilot udpout:127.0.0.1:9, gcs none, "
                     "profile default",
                     "WARNING rover_bridge.run: no HEARTBEAT from the autopilot on udpout:127.0.0.1:9 after 5 s: "
                     "is it running and listening at that address (e.g. SITL's or mavlink-router's udpin)?",
                     "INFO rover_bridge.run: stopped (--duration 8 s over): nothing sent (no vehicle was known)"], \
        done.stderr


@pytest.mark.parametrize(("url", "role", "exc", "says"), [
    ("/dev/ttyAMA0,921600", Link.AUTOPILOT, PermissionError(13, "Permission denied"),
     "permission denied: add this user to the dialout group (sudo usermod -aG dialout $USER, then log in again)"),
    ("/dev/ttyUSB0,57600", Link.GCS, FileNotFoundError(2, "No such file or directory"),
     "no such device: is the radio plugged in and powered, and is the name right? (ls /dev/serial/by-id/)"),
    ("tcp:rover.local:5760", Link.AUTOPILOT, socket.gaierror(-2, "Name or service not known"),
     "unknown host: check the address given with --autopilot"),
    ("udpin:10.9.9.9:14550", Link.GCS, OSError(99, "Cannot assign requested address"),
     "not an address of this machine: listen on 0.0.0.0 or on one of its addresses"),
    ("/dev/ttyACM0,115200", Link.AUTOPILOT, ModuleNotFoundError("No module named 'serial'"),
     "serial links need pyserial (pip install pyserial)"),
])
def test_what_each_open_failure_says(url: str, role: Link, exc: BaseException, says: str) -> None:
    """The failures this machine cannot provoke (root opens any device; no DNS), by the error the OS gives."""
    what = "autopilot" if role is Link.AUTOPILOT else "ground-station"
    assert open_problem(url, role, exc) == f"cannot open the {what} link {url}: {says}"
