"""The README's "By hand" recipe, run as written: `rover-sitl` and `rover-bridge run` with their defaults only
(they meet on TCP 127.0.0.1:5760), and the README's pymavlink script on UDP 14550 arms the emulated rover and
drives it forward. What the bridge logs at the default verbosity is checked line for line.

The ports are the defaults', fixed: no other test uses 5760 or 14550 (they all pick free ports).
"""

from __future__ import annotations

import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[1]
RUN_LOG_LINE = re.compile(r"^\S+ \S+ (\w+) ([\w.]+): (.*)$")  # asctime (date, time), level, logger: message


def by_hand_section() -> str:
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    return readme.split("### By hand", 1)[1].split("\n#", 1)[0]


def readme_script_and_commands() -> tuple[str, list[str]]:
    section = by_hand_section()
    script = re.search(r"```python\n(.*?)```", section, re.S)
    shell = re.search(r"```sh\n(.*?)```", section, re.S)
    assert script is not None and shell is not None, "the README's By hand section lost its script or commands"
    commands = [line[2:] for line in shell.group(1).splitlines() if line.startswith("$ ")]
    return script.group(1), commands


def argv(command: str) -> list[str]:
    """A README command line as this interpreter runs it (the console scripts of this environment)."""
    words = shlex.split(command)
    if words[0] == "python":
        return [sys.executable, *words[1:]]
    script = Path(sys.executable).parent / words[0]
    if script.exists():
        return [str(script), *words[1:]]
    module = {"rover-sitl": "sitl", "rover-bridge": "rover_bridge"}[words[0]]
    return [sys.executable, "-m", module, *words[1:]]


def assert_free(kind: int, port: int) -> None:
    with socket.socket(socket.AF_INET, kind) as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError as exc:
            pytest.fail(f"port {port} is busy ({exc}): the by-hand defaults need it; stop what holds it")


def wait_for(path: Path, text: str, proc: subprocess.Popen[bytes], timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while text not in path.read_text(errors="replace"):
        assert proc.poll() is None, f"exited {proc.returncode}:\n{path.read_text(errors='replace')}"
        assert time.monotonic() < end, f"no {text!r} within {timeout_s} s:\n{path.read_text(errors='replace')}"
        time.sleep(0.05)


def test_the_readme_recipe_drives_the_emulator_with_every_default(tmp_path: Path) -> None:
    script, commands = readme_script_and_commands()
    assert commands == ["rover-sitl", "rover-bridge run", "python drive.py"]  # no endpoint options at all
    (tmp_path / "drive.py").write_text(script)
    assert_free(socket.SOCK_STREAM, 5760)
    assert_free(socket.SOCK_DGRAM, 14550)
    procs: list[subprocess.Popen[bytes]] = []
    logs = [tmp_path / "sitl.log", tmp_path / "bridge.log"]
    try:
        for command, log in zip(commands[:2], logs, strict=True):
            with open(log, "wb") as f:
                procs.append(subprocess.Popen(argv(command), cwd=tmp_path, stdout=f, stderr=subprocess.STDOUT))
            wait_for(log, "bound to" if command == "rover-sitl" else "autopilot found", procs[-1])
        drive = subprocess.run(argv(commands[2]), cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert drive.returncode == 0, drive.stdout + drive.stderr
        said = drive.stdout.splitlines()
        assert said[0] == "arm: 0", drive.stdout  # MAV_RESULT_ACCEPTED, through the bridge
        odometry = re.fullmatch(r"ODOMETRY: x (-?\d+\.\d+) m, vx (-?\d+\.\d+) m/s", said[1])
        assert odometry is not None, drive.stdout
        # 3 s of 0.5 m/s from rest (the limiter's ramp, the ODOMETRY read as it came): well over a metre.
        assert float(odometry.group(1)) > 0.8 and float(odometry.group(2)) == pytest.approx(0.5, abs=0.1)
        time.sleep(1.5)  # the request timeout (0.5 s) and the braking
        for proc in reversed(procs):  # Ctrl-C in each terminal: the bridge first, then the emulator
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=10) == 0
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    sitl_lines = logs[0].read_text().splitlines()
    assert sitl_lines[0] == ("rover-sitl: tcpin:127.0.0.1:5760 bound to 127.0.0.1:5760, sysid 1, seed 0, disarmed, "
                             "MANUAL")
    truth = re.fullmatch(r"rover-sitl: stopped after \S+ s: at x (\S+) m north, y (\S+) m east, yaw (\S+) deg",
                         sitl_lines[-1])
    assert truth is not None, sitl_lines
    assert float(truth.group(1)) > 1.0 and abs(float(truth.group(2))) < 0.1  # the emulator's truth: it drove north
    # At the default verbosity: the run's own three lines, and warnings; no other INFO.
    parsed = [RUN_LOG_LINE.match(line) for line in logs[1].read_text().splitlines()]
    assert all(m is not None for m in parsed), logs[1].read_text()
    records = [(m.group(1), m.group(2), m.group(3)) for m in parsed if m is not None]
    assert [r for r in records if r[1] == "rover_bridge.run"] == [
        ("INFO", "rover_bridge.run", "rover-bridge running: autopilot tcp:127.0.0.1:5760, gcs udpout:127.0.0.1:14550, "
                                     "profile default"),
        ("INFO", "rover_bridge.run", "autopilot found: system 1, component 1 on tcp:127.0.0.1:5760, MANUAL, disarmed"),
        ("INFO", "rover_bridge.run", "stopped (SIGINT): neutral and release sent, confirmed by the autopilot"),
    ], logs[1].read_text()
    assert all(level != "INFO" for level, name, _ in records if name != "rover_bridge.run"), logs[1].read_text()
