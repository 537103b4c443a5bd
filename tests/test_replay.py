"""Record a short drive to .tlog through the real runner, replay it offline, compare with live."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from lockstep import Lockstep

from rover_bridge.app.cli import main as cli_main
from rover_bridge.app.replay import compare, replay
from rover_bridge.params import Profile
from sitl import VehicleConfig

pytestmark = pytest.mark.e2e


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tlog") / "drive.tlog"
    rig = Lockstep(Profile(), VehicleConfig(), seed=11, tlog_path=str(path))
    try:
        rig.run_for(1.0)
        rig.run_for(4.0, send=lambda: rig.send_body_velocity(0.4, 0.4))  # a right-hand arc
        rig.run_for(3.0, send=lambda: rig.send_body_velocity(0.3, -0.6))  # then a left one
        rig.run_for(1.5)  # timeout and stop
    finally:
        rig.close()
    return path


def test_replayed_estimate_matches_the_live_one(recorded: Path) -> None:
    result = replay(recorded, Profile())
    assert len(result.live) > 200  # 30 Hz over ~9 s was published live
    assert len(result.rows) > 200
    pos, yaw, matched = compare(result.rows, result.live, max_dt_usec=1_000)
    assert matched >= 0.9 * len(result.live)
    # Same frames, same order, same instants: equal up to ODOMETRY's float32 fields.
    assert pos < 1e-4
    assert math.degrees(yaw) < 0.01
    # It really drove: the replayed path ends metres away from the start, turned.
    assert math.hypot(result.rows[-1].x_m, result.rows[-1].y_m) > 1.5


def test_replay_is_deterministic_and_writes_csv(recorded: Path, tmp_path: Path) -> None:
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    params = str(Path(__file__).resolve().parents[1] / "params" / "default.toml")
    assert cli_main(["replay", str(recorded), "--params", params, "--csv", str(a)]) == 0
    assert cli_main(["replay", str(recorded), "--params", params, "--csv", str(b)]) == 0
    text = a.read_text()
    assert text == b.read_text()
    header, first = text.splitlines()[:2]
    assert header.startswith("time_usec,x_m,y_m,yaw_rad")
    assert len(first.split(",")) == len(header.split(","))


def test_replay_of_a_missing_log_is_a_clear_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["replay", str(tmp_path / "nope.tlog"), "--params",
                     str(Path(__file__).resolve().parents[1] / "params" / "default.toml")]) == 2
    assert "no such log" in capsys.readouterr().err


def test_replay_plot_none_draws_nothing_and_a_path_draws_there(recorded: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert cli_main(["replay", str(recorded), "--csv", "r.csv", "--plot", "none"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]  # no none.png
    assert cli_main(["replay", str(recorded), "--csv", "r.csv", "--plot", "path.png"]) == 0
    assert (tmp_path / "path.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
