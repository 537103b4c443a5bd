"""check-params and ik through the real CLI entry point (exit codes, printed tables)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from rover_bridge.app.cli import main

REPO = Path(__file__).resolve().parents[1]
DEFAULT = str(REPO / "params" / "default.toml")


@pytest.fixture
def bad_profile(tmp_path: Path) -> str:
    f = tmp_path / "bad.toml"
    f.write_text('[robot]\nwheel_radius_m = -1.0\ntrack_widht_m = 0.3\n[output]\nmode = "pwm"\n',
                 encoding="utf-8")
    return str(f)


def test_check_params_prints_the_resolved_profile(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-params", DEFAULT]) == 0
    out = capsys.readouterr().out
    assert "OK" in out
    assert "wheel_radius_m = 0.05" in out and "[limits]" in out
    assert "setpoint_timeout_s = 0.5" in out  # defaults resolved too


def test_check_params_lists_every_problem_and_exits_2(bad_profile: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-params", bad_profile]) == 2
    err = capsys.readouterr().err
    assert "robot.wheel_radius_m: -1.0 is out of range" in err
    assert "robot.track_widht_m: unknown key (did you mean 'track_width_m'?)" in err
    assert "output.mode: expected one of rc_override, servo" in err


def row_for(out: str, v: float, omega: float) -> list[str]:
    for line in out.splitlines():
        cells = line.split()
        if not line.startswith("#") and len(cells) > 2 and cells[:2] == [f"{v:.3f}", f"{omega:.3f}"]:
            return cells
    raise AssertionError(f"no row for {v}, {omega} in:\n{out}")


def test_ik_one_request(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ik", "--params", DEFAULT, "--v", "0.5", "--omega", "1.0"]) == 0
    cells = row_for(capsys.readouterr().out, 0.5, 1.0)
    # left (0.5 - 1.0 * 0.15) / 0.05 = 7 rad/s = 66.85 RPM, right 13 rad/s = 124.14 RPM; 200 RPM limit.
    assert cells[3:5] == ["7.000", "13.000"]
    assert cells[5:7] == [f"{7 * 60 / (2 * math.pi):.2f}", f"{13 * 60 / (2 * math.pi):.2f}"]
    assert cells[5:7] == ["66.85", "124.14"]
    assert "no" in cells


def test_ik_clamped_request_reports_scale_and_achieved_twist(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ik", "--params", DEFAULT, "--v", "1.0", "--omega", "2.0"]) == 0
    line = " ".join(row_for(capsys.readouterr().out, 1.0, 2.0))
    # right wheel wants (1 + 0.3) / 0.05 = 26 rad/s > 200 RPM = 20.944 rad/s: scale 0.8055.
    scale = (200 * 2 * math.pi / 60) / 26
    assert f"yes (x{scale:.3f})" in line
    assert line.endswith(f"{1.0 * scale:.3f} {2.0 * scale:.3f}")  # same curvature, slower
    assert "20.944" in line and f"{14 * scale:.3f}" in line


def test_ik_grid_has_25_requests(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ik", "--params", DEFAULT]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln and not ln.startswith("#") and "|" in ln]
    assert len(rows) == 1 + 25  # header + 5 x 5 grid


def test_ik_bad_profile_and_bad_number_exit_2(bad_profile: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ik", "--params", bad_profile]) == 2
    assert "robot.wheel_radius_m" in capsys.readouterr().err
    assert main(["ik", "--params", DEFAULT, "--omega", "inf"]) == 2
    assert "--omega: expected a finite number" in capsys.readouterr().err


def test_python_dash_m_entry_point() -> None:
    done = subprocess.run([sys.executable, "-m", "rover_bridge", "check-params", "params/default.toml"],
                          cwd=REPO, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert "params/default.toml: OK" in done.stdout
