"""Record a short drive to .tlog through the real runner, replay it offline, compare with live."""

from __future__ import annotations

import csv
import functools
import math
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lockstep import Lockstep

from rover_bridge.app.cli import main as cli_main
from rover_bridge.app.log_frames import LogFrames
from rover_bridge.app.replay import compare, replay
from rover_bridge.mavlink.dialect import mavutil
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


# ---------------------------------------------------------------------------- calibration, cut logs

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_fleet  # noqa: E402 - the emulated fleet's log writer

MISCALIBRATED = bench_fleet.FLEET[5]  # track 3.5 % wider, right wheel 4.5 % larger than the profile says


@pytest.fixture(scope="module")
def ground_station_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ground station's .tlog of a miscalibrated rover (the emulator's frames only, no bridge)."""
    path = tmp_path_factory.mktemp("gcs") / "gcs.tlog"
    bench_fleet.write_log(path, MISCALIBRATED, 3, bench_fleet.START_UNIX_S, 40.0)
    return path


def _calibrating(params: str, tmp_path: Path) -> str:
    text = Path(params).read_text().replace("calibrate = false", "calibrate = true")
    assert "calibrate = true" in text
    out = tmp_path / "calibrating.toml"
    out.write_text(text)
    return str(out)


def test_replay_shows_the_calibration_estimate_in_the_summary_and_the_csv(
        ground_station_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = _calibrating(str(Path(__file__).resolve().parents[1] / "params" / "default.toml"), tmp_path)
    csv_path = tmp_path / "out.csv"
    assert cli_main(["replay", str(ground_station_log), "--params", params, "--csv", str(csv_path)]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("calibration"))
    numbers = [float(w) for w in line.replace("+-", " ").split() if w[0].isdigit()]
    track, track_sigma, ratio, ratio_sigma = numbers
    assert track == pytest.approx(MISCALIBRATED.track_scale, rel=0.005)
    assert ratio == pytest.approx(MISCALIBRATED.radius_ratio, rel=0.005)
    assert 0.0 < track_sigma < 0.005 and 0.0 < ratio_sigma < 0.005
    rows = list(csv.DictReader(csv_path.open()))
    last = rows[-1]
    assert float(last["track_scale"]) == pytest.approx(track, abs=1e-4)
    assert float(last["radius_ratio_sigma"]) == pytest.approx(ratio_sigma, abs=1e-4)
    # The estimate converges over the log: the first rows still hold the profile's geometry and its prior sigma.
    assert float(rows[0]["track_scale"]) == pytest.approx(1.0, abs=0.01)
    assert float(rows[0]["track_scale_sigma"]) > 10 * float(last["track_scale_sigma"])


def test_replay_without_calibration_says_so(ground_station_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = replay(ground_station_log, Profile())
    assert not result.calibration.estimated
    assert "not estimated (estimator.calibrate = false)" in result.summary()


@functools.cache
def _frame_ends(path: Path) -> list[int]:
    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    ends = []
    while log.recv_msg() is not None:
        ends.append(log.f.tell())
    log.close()
    return ends


@settings(max_examples=60, deadline=None)
@given(back=st.integers(1, 400))
def test_a_log_cut_anywhere_but_between_frames_is_said_to_end_mid_frame(ground_station_log: Path, back: int) -> None:
    all_ends = _frame_ends(ground_station_log)
    ends = set(all_ends[:300])  # the first 300 frames are plenty (and quick to read again and again)
    data = ground_station_log.read_bytes()[: all_ends[299]]
    cut = len(data) - back
    cut_path = ground_station_log.with_name(f"cut-{back}.tlog")
    cut_path.write_bytes(data[:cut])
    frames = LogFrames(cut_path)
    n = sum(1 for _ in frames)
    assert frames.stats.trailing_bytes == (0 if cut in ends else cut - max(e for e in ends if e <= cut))
    assert n == sum(1 for e in ends if e <= cut)


def test_replay_says_when_a_log_ends_mid_frame(ground_station_log: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    data = ground_station_log.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 11])
    params = str(Path(__file__).resolve().parents[1] / "params" / "default.toml")
    assert cli_main(["replay", str(cut), "--params", params, "--csv", str(tmp_path / "c.csv")]) == 0
    captured = capsys.readouterr()
    assert "WARNING: the log ends mid-frame" in captured.out
    assert "ends mid-frame: it was cut short" in captured.err
    assert cli_main(["replay", str(ground_station_log), "--params", params, "--csv", str(tmp_path / "w.csv")]) == 0
    assert "mid-frame" not in capsys.readouterr().out
