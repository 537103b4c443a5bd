"""sitl configuration files, the no-rover_bridge-import rule, and the command line."""

from __future__ import annotations

import ast
import os
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

import sitl
from sitl import ConfigError, Emulator, PortInUseError, VehicleConfig, load_scenario, load_vehicle
from sitl.cli import main
from sitl.endpoint import ConnectionStringError
from sitl.mav import mavlink, mavutil

SITL_DIR = Path(sitl.__file__).resolve().parent
REPO = SITL_DIR.parent


def test_nothing_in_sitl_imports_rover_bridge() -> None:
    files = sorted(SITL_DIR.rglob("*.py"))
    assert len(files) >= 10
    for path in files:
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            elif isinstance(node, ast.Call) and getattr(node.func, "id", "") == "__import__":
                names = [
                    a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)
                ]
            for name in names:
                assert name.split(".")[0] != "rover_bridge", f"{path} imports {name}"


def test_no_class_in_sitl_is_over_300_lines() -> None:
    sizes = {}
    for path in sorted(SITL_DIR.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                sizes[f"{path.name}:{node.name}"] = (node.end_lineno or node.lineno) - node.lineno + 1
    assert "autopilot.py:Autopilot" in sizes
    assert {name: n for name, n in sizes.items() if n > 300} == {}


def test_vehicle_profile_loads_and_bad_profile_lists_every_problem(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text("[vehicle]\ntrue_track_width_m = 0.32\nencoder_cpr = 2048\nstart_armed = true\n")
    v = load_vehicle(good)
    assert (v.track_true_m, v.track_width_m, v.encoder_cpr, v.start_armed) == (0.32, 0.30, 2048, True)
    bad = tmp_path / "bad.toml"
    bad.write_text("wheel_radius_m = -1.0\nencoder_cpr = 'many'\nwheel_base = 3\n")
    with pytest.raises(ConfigError) as err:
        load_vehicle(bad)
    assert {"encoder_cpr: wrong type str", "unknown key 'wheel_base'"} <= set(err.value.problems)
    with pytest.raises(ConfigError, match="wheel_radius_m must be a positive"):
        VehicleConfig(wheel_radius_m=-1.0)
    with pytest.raises(ConfigError, match="pwm_min < pwm_trim"):
        VehicleConfig(pwm_trim=900)


def test_shipped_vehicle_and_scenario_files_load() -> None:
    for path in sorted((SITL_DIR / "vehicles").glob("*.toml")):
        load_vehicle(path)
    scenarios = sorted((SITL_DIR / "scenarios").glob("*.toml"))
    assert scenarios
    for path in scenarios:
        load_scenario(path)


def test_vehicle_params_table_sets_boot_values_and_unknown_or_bad_ones_are_all_listed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "v.toml"
    path.write_text("[vehicle]\nleft_function = 51\n[vehicle.params]\nSERVO5_FUNCTION = 73\nWP_SPEED = 2.5\n")
    emu = Emulator(load_vehicle(path))
    assert (emu.get_param("SERVO5_FUNCTION"), emu.get_param("WP_SPEED")) == (73.0, 2.5)
    emu.reboot()
    emu.step(2.0)
    assert emu.get_param("WP_SPEED") == 2.5  # parameters persist over a reboot
    bad = tmp_path / "bad.toml"
    bad.write_text('[vehicle.params]\nNO_SUCH = 1\nALSO_NOT = 2\nWP_SPEED = "fast"\n')
    with pytest.raises(ConfigError, match="WP_SPEED"):
        load_vehicle(bad)
    bad.write_text("[vehicle.params]\nNO_SUCH = 1\nALSO_NOT = 2\n")
    with pytest.raises(ConfigError) as err:
        Emulator(load_vehicle(bad))
    assert set(err.value.problems) == {"unknown parameter 'NO_SUCH'", "unknown parameter 'ALSO_NOT'"}
    assert main(["--vehicle", str(bad), "--duration", "0.1"]) == 2
    assert "unknown parameter 'NO_SUCH'" in capsys.readouterr().err


def test_scenario_file_and_errors(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(
        '[[event]]\ntype = "slip"\nwheel = "left"\nstart_s = 1.0\nend_s = 2.0\nratio = 0.3\n'
        '[[event]]\ntype = "reboot"\nat_s = 5.0\n'
    )
    s = load_scenario(path)
    assert s.slip_ratio("left", 1.5, 0.0, 0.0) == 0.3
    assert s.slip_ratio("right", 1.5, 0.0, 0.0) == 0.0
    assert s.slip_ratio("left", 2.0, 0.0, 0.0) == 0.0
    assert [r.at_s for r in s.reboots] == [5.0]
    path.write_text('[[event]]\nkind = "encoder_dropout"\nwheel = "right"\nstart_s = 6.0\nduration_s = 4.0\n')
    assert not load_scenario(path).encoder_ok("right", 9.9) and load_scenario(path).encoder_ok("right", 10.0)
    path.write_text(
        '[[event]]\ntype = "slip"\nwheel = "middle"\nstart_s = 2.0\nend_s = 1.0\nratio = 1.5\n'
        '[[event]]\ntype = "meteor"\n'
    )
    with pytest.raises(ConfigError) as err:
        load_scenario(path)
    text = str(err.value)
    assert "wheel must be one of" in text and "ratio must be in" in text and "unknown type 'meteor'" in text


def test_open_reports_busy_port_and_bad_string() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        port = holder.getsockname()[1]
        emu = Emulator()
        with pytest.raises(PortInUseError, match="address already in use"):
            emu.open(f"udpin:127.0.0.1:{port}")
    with pytest.raises(ConnectionStringError):
        Emulator().open("serial:/dev/null")
    with pytest.raises(ConnectionStringError):
        Emulator().open("udpin:127.0.0.1:notaport")


def test_cli_bad_option_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--no-such-option"]) == 2
    assert main(["--connect", "udpin:127.0.0.1"]) == 2
    assert "bad connection string" in capsys.readouterr().err
    assert main(["--sysid", "0"]) == 2


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def test_cli_busy_port_exits_2() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 0))
        port = holder.getsockname()[1]
        proc = subprocess.run(
            [sys.executable, "-m", "sitl", "--connect", f"udpin:127.0.0.1:{port}", "--duration", "1"],
            capture_output=True,
            text=True,
            timeout=60,
            env=_env(),
            cwd=REPO,
        )
    assert proc.returncode == 2
    assert "already in use" in proc.stderr


def test_cli_answers_heartbeat_and_exits_0_on_sigterm() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "sitl", "--connect", f"udpin:127.0.0.1:{port}", "--speedup", "4"],
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        cwd=REPO,
    )
    gcs = None
    try:
        assert proc.stderr is not None
        ready, _, _ = select.select([proc.stderr], [], [], 30.0)
        assert ready, "emulator did not report that it is listening"
        assert "bound to" in proc.stderr.readline()
        gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        heartbeat = None
        deadline = time.monotonic() + 30.0  # a bound on the wait, not a timing assertion
        while heartbeat is None and time.monotonic() < deadline:
            gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            heartbeat = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
        assert heartbeat is not None
        assert heartbeat.type == mavlink.MAV_TYPE_GROUND_ROVER
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if gcs is not None:
            gcs.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
