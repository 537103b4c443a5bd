"""The fleet report's parts without Dask: one log's analysis (skip reasons, stalls, slips, wiring signs, drift
against GPS), the per-rover combination, the inputs, the tables. Logs come from the sitl emulator
(benchmarks/bench_fleet.py writes them), each a pure function of its seed."""

from __future__ import annotations

import math
import random
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.app.replay import replay
from rover_bridge.errors import ConfigError
from rover_bridge.estimate.core import CalibrationEstimate
from rover_bridge.fleet.analysis import LogReport, analyse_log, fleet_profile
from rover_bridge.fleet.drift import GpsTrack
from rover_bridge.fleet.folder import figure, no_drift_reason, read_table, write_table
from rover_bridge.fleet.jobs import expand
from rover_bridge.fleet.rovers import combine, rovers
from rover_bridge.params import Profile
from sitl import Scenario
from sitl.scenario import SlipWindow, StallWindow

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_fleet as bench

PROFILE = fleet_profile(Profile())
ROVER = bench.FLEET[0]
# Stop, straight, spin, straight, stop: every wheel commanded well above the wiring check's threshold.
SCRIPT = [(3.0, 1500, 1500), (10.0, 1800, 1800), (3.0, 1300, 1700), (10.0, 1800, 1800), (2.0, 1500, 1500)]
CASES: dict[str, dict[str, object]] = {
    "clean": {},
    "stall": {"scenario": Scenario(stalls=(StallWindow("right", 5.0, 8.0),))},
    "slip": {"scenario": Scenario(slips=(SlipWindow("left", 19.0, 22.0, 0.4),))},
    "backwards": {"left_reversed": True},  # the left motor wired the wrong way round
    "swapped": {"wheel_distance_order": "right_left"},  # the encoders' indices swapped
    "no-encoders": {"drop": ("WHEEL_DISTANCE",)},
}


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("cases")
    out = {}
    for name, kwargs in CASES.items():
        out[name] = folder / f"{name}.tlog"
        bench.write_log(out[name], ROVER, 1, bench.START_UNIX_S, 28.0, script=SCRIPT, **kwargs)  # type: ignore[arg-type]
    good = out["clean"].read_bytes()
    damaged = bytearray(good)
    rng = random.Random(5)
    start = len(good) // 3
    damaged[start:start + len(good) // 20] = bytes(rng.randrange(256) for _ in range(len(good) // 20))
    out["corrupt"] = folder / "corrupt.tlog"
    out["corrupt"].write_bytes(bytes(damaged))
    out["truncated"] = folder / "truncated.tlog"
    out["truncated"].write_bytes(good[: len(good) // 2 + 7])
    out["empty"] = folder / "empty.tlog"
    out["empty"].write_bytes(b"")
    return out


@pytest.fixture(scope="module")
def reports(logs: dict[str, Path]) -> dict[str, LogReport]:
    return {name: analyse_log(str(path), PROFILE, "cases") for name, path in logs.items()}


def test_a_clean_log_has_nothing_to_report_and_the_truth_within_half_a_percent(reports: dict[str, LogReport]) -> None:
    r = reports["clean"]
    assert r.used and r.reason == "" and r.note == ""
    assert r.system_id == ROVER.system_id
    assert (r.stalls, r.slip_events, r.wiring, r.log_gaps, r.clock_jumps) == (0, 0, "", 0, 0)
    assert r.track_scale == pytest.approx(ROVER.track_scale, rel=0.005)
    assert r.radius_ratio == pytest.approx(ROVER.radius_ratio, rel=0.005)
    assert r.wheel_gyro_correlation > 0.99
    assert r.duration_s == pytest.approx(28.0, abs=0.1)
    assert 10.0 < r.distance_m < 30.0
    assert r.gps_fixes > 40 and r.drift_pct < 1.0


def test_each_fault_shows_as_its_own_sign(reports: dict[str, LogReport]) -> None:
    assert reports["stall"].stalls == 1 and reports["stall"].wiring == ""
    assert reports["slip"].slip_events >= 1 and reports["slip"].stalls == 0 and reports["slip"].wiring == ""
    assert reports["backwards"].wiring == "left wheel backwards"
    swapped = reports["swapped"]
    assert "swapped" in swapped.wiring and swapped.wheel_gyro_correlation < -0.9
    for name in ("stall", "slip", "backwards", "swapped"):
        assert reports[name].used, name


def test_a_log_the_estimate_cannot_use_says_why(reports: dict[str, LogReport]) -> None:
    reasons = {name: r.reason for name, r in reports.items() if not r.used}
    assert set(reasons) == {"no-encoders", "corrupt", "truncated", "empty"}
    assert reasons["no-encoders"].startswith("no wheel encoders")
    assert reasons["corrupt"].startswith("corrupt:")
    assert reasons["truncated"].startswith("truncated: ends mid-frame")
    assert reasons["empty"] == "empty: 0 bytes"
    assert math.isnan(reports["empty"].track_scale)


def test_a_truncated_log_is_used_up_to_the_cut_when_asked(logs: dict[str, Path]) -> None:
    r = analyse_log(str(logs["truncated"]), PROFILE, "cases", use_truncated=True)
    assert r.used and r.note.startswith("truncated: ends mid-frame")
    assert 10.0 < r.duration_s < 18.0


def test_the_per_log_figures_are_the_replays(logs: dict[str, Path], reports: dict[str, LogReport]) -> None:
    result = replay(logs["slip"], PROFILE)
    r = reports["slip"]
    last = result.rows[-1]
    assert (r.final_x_m, r.final_y_m, r.final_yaw_rad) == (last.x_m, last.y_m, last.yaw_rad)
    assert (r.track_scale, r.radius_ratio) == (result.calibration.track_scale, result.calibration.radius_ratio)
    assert r.rows == len(result.rows)
    assert r.slip_intervals == result.counters["wheel_slip"]


def test_a_jump_of_the_log_clock_is_counted_and_not_ticked_through(logs: dict[str, Path], tmp_path: Path) -> None:
    # A companion without a real-time clock: its wall clock steps a year forward at an NTP sync.
    data = logs["clean"].read_bytes()
    out = bytearray()
    from rover_bridge.mavlink.dialect import mavutil
    log = mavutil.mavlink_connection(str(logs["clean"]), dialect="ardupilotmega")
    pos = 0
    while (msg := log.recv_msg()) is not None:
        end = log.f.tell()
        stamp = int.from_bytes(data[pos:pos + 8], "big")
        if msg._timestamp > bench.START_UNIX_S + 14.0:
            stamp += 365 * 86_400 * 10 ** 6
        out += stamp.to_bytes(8, "big") + data[pos + 8:end]
        pos = end
    log.close()
    jumped = tmp_path / "jumped.tlog"
    jumped.write_bytes(bytes(out))
    r = analyse_log(str(jumped), PROFILE, "cases")
    clean = analyse_log(str(logs["clean"]), PROFILE, "cases")
    assert r.clock_jumps == 1 and clean.clock_jumps == 0
    assert r.duration_s == pytest.approx(clean.duration_s, abs=0.1)
    assert r.track_scale == pytest.approx(clean.track_scale, rel=1e-3)
    assert math.hypot(r.final_x_m - clean.final_x_m, r.final_y_m - clean.final_y_m) < 0.05


# ---------------------------------------------------------------------------- drift against GPS

@settings(max_examples=50, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-500, 500), st.floats(-500, 500), st.integers(0, 10_000))
def test_a_track_rotated_and_moved_has_no_drift_and_an_added_error_is_measured(
        angle: float, north0: float, east0: float, seed: int) -> None:
    rng = random.Random(seed)
    track = GpsTrack()
    err_track = GpsTrack()
    x = y = heading = dist = 0.0
    c, s = math.cos(angle), math.sin(angle)
    for k in range(400):
        t = 0.1 * k
        heading += rng.uniform(-0.2, 0.2)
        step = rng.uniform(0.0, 0.2)
        x, y, dist = x + step * math.cos(heading), y + step * math.sin(heading), dist + step
        north, east = north0 + c * x - s * y, east0 + s * x + c * y
        lat, lon = math.degrees(north / 6_378_137.0), math.degrees(east / 6_378_137.0)
        for tr, extra in ((track, 0.0), (err_track, 0.5 if k == 399 else 0.0)):
            tr.row(t, x + extra, y, 0, dist)
            if k % 5 == 0 or k == 399:
                tr.fix(t, lat, lon)
            tr.row(t + 0.05, x + extra, y, 0, dist)
    d = track.result()
    if math.isnan(d.max_m):  # a track too small to orient: said so, never a number
        assert d.fixes >= 10
        return
    assert d.max_m < 0.02
    e = err_track.result()
    assert 0.4 < e.max_m < 0.55  # the last fix's 0.5 m error, less what the fit spreads over the rest
    assert e.pct == pytest.approx(100.0 * e.max_m / e.distance_m)


def test_without_enough_fixes_there_is_no_drift_figure() -> None:
    track = GpsTrack()
    for k in range(5):
        track.row(k, k, 0.0, 0, k)
        track.fix(k, 0.0, math.degrees(k / 6_378_137.0))
    assert math.isnan(track.result().pct)


# ---------------------------------------------------------------------------- per rover

@settings(max_examples=100)
@given(st.lists(st.tuples(st.floats(0.9, 1.1), st.floats(0.001, 0.02)), min_size=1, max_size=12))
def test_combining_takes_the_prior_out_of_each_log_and_puts_it_back_once(logs: list[tuple[float, float]]) -> None:
    prior_sigma = 0.05
    combined = combine([(v, s, 0.0) for v, s in logs], 1.0, prior_sigma)
    # Each log's estimate is its data combined with the prior: recover the data, combine, add the prior once.
    data = [((v / s ** 2 - 1.0 / prior_sigma ** 2) / (1 / s ** 2 - 1 / prior_sigma ** 2),
             1 / s ** 2 - 1 / prior_sigma ** 2) for v, s in logs]
    info = sum(w for _, w in data) + 1 / prior_sigma ** 2
    expected = (sum(v * w for v, w in data) + 1.0 / prior_sigma ** 2) / info
    assert combined.value == pytest.approx(expected, rel=1e-9)
    assert combined.sigma >= 1 / math.sqrt(info) * (1 - 1e-12)
    assert combined.logs == len(logs)


def test_agreeing_logs_give_a_tight_value_and_a_steady_trend() -> None:
    logs = [(1.03 + 0.0005 * (-1) ** k, 0.002, k * 86_400.0) for k in range(8)]
    c = combine(logs, 1.0, 0.05)
    assert c.value == pytest.approx(1.03, abs=0.0005)
    assert c.sigma < 0.001
    assert abs(c.trend_per_30d) < 3 * c.trend_sigma
    worn = combine([(1.0 + 0.001 * k, 0.0005, k * 86_400.0) for k in range(8)], 1.0, 0.05)
    assert worn.trend_per_30d == pytest.approx(0.03, rel=0.01)  # 0.1 % a day


def test_rovers_are_grouped_flagged_and_patched() -> None:
    def log(folder: str, sysid: int, kt: float, q: float, used: bool = True) -> LogReport:
        return LogReport(f"/{folder}/{kt}.tlog", folder, sysid, "tlog", "used" if used else "skipped",
                         track_scale=kt, track_scale_sigma=0.002, radius_ratio=q, radius_ratio_sigma=0.002)

    prior = CalibrationEstimate(1.0, 0.05, 1.0, 0.03, True)
    reports = [log("a", 1, 1.04, 1.0), log("a", 1, 1.04, 1.0), log("b", 1, 1.0, 0.99), log("b", 0, 0, 0, False)]
    by_both = rovers(reports, PROFILE, prior, "both", 0.02)
    assert [(r.rover, r.logs, r.skipped, r.flagged) for r in by_both] == [("a#1", 2, 0, True), ("b#1", 1, 1, False)]
    assert by_both[0].flags == "track +4.0 %"
    assert by_both[0].track_width_m == pytest.approx(PROFILE.robot.track_width_m * 1.04, rel=1e-4)
    by_sysid = rovers(reports, PROFILE, prior, "sysid", 0.02)
    assert [(r.rover, r.logs) for r in by_sysid] == [("sysid 1", 3)]
    patch = by_both[0].patch_toml("params/default.toml")
    import tomllib

    from rover_bridge.params import profile_from_dict
    patched = profile_from_dict(tomllib.loads(patch))
    assert patched.robot.track_width_m == pytest.approx(0.312, abs=1e-4)



def test_an_empty_drift_panel_says_why() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def log(name: str, fixes: int, drift_pct: float) -> LogReport:
        return LogReport(f"/a/{name}.tlog", "a", 1, "tlog", "used", start_unix_s=1.79e9, distance_m=30.0,
                         track_scale=1.0, track_scale_sigma=0.002, radius_ratio=1.0, radius_ratio_sigma=0.002,
                         gps_fixes=fixes, drift_pct=drift_pct)

    prior = CalibrationEstimate(1.0, 0.05, 1.0, 0.03, True)
    panels = {}
    for case, reports in (("gps", [log("x", 50, 0.2), log("y", 0, math.nan)]),
                          ("no gps", [log("x", 0, math.nan), log("y", 0, math.nan)]),
                          ("few fixes", [log("x", 6, math.nan), log("y", 0, math.nan)])):
        fig = figure(plt, reports, rovers(reports, PROFILE, prior, "both", 0.02), lambda r: f"{r.folder}#1", 0.02)
        panels[case] = (len(fig.axes[2].lines), [t.get_text() for t in fig.axes[2].texts])
        plt.close(fig)
    assert panels["gps"] == (1, [])
    assert panels["no gps"][0] == 0 and panels["no gps"][1][0].startswith("no GPS fix in these 2 logs:")
    assert "GLOBAL_POSITION_INT" in panels["no gps"][1][0]
    assert panels["few fixes"][0] == 0 and panels["few fixes"][1][0].startswith("GPS fixes in 1 of 2 logs, too few")
    assert no_drift_reason([]) == "no log used:\nno drift against GPS"


# ---------------------------------------------------------------------------- inputs and tables

def test_inputs_are_files_folders_and_globs_each_once(tmp_path: Path) -> None:
    for rel in ("logs/rover-1/2026/a.tlog", "logs/rover-1/b.BIN", "logs/c.tlog", "logs/rover-2/notes.txt"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    jobs = expand([str(tmp_path / "logs"), str(tmp_path / "logs/rover-1/*/*.tlog"), str(tmp_path / "logs/c.tlog")])
    assert [(Path(j.path).name, j.folder) for j in jobs] == [("c.tlog", "logs"), ("a.tlog", "rover-1"),
                                                             ("b.BIN", "rover-1")]
    with pytest.raises(ConfigError) as err:
        expand([str(tmp_path / "missing"), str(tmp_path / "logs/*.nothing")])
    assert len(err.value.problems) == 2 and "no such file" in err.value.problems[0]


def test_tables_are_parquet_or_csv_where_no_parquet_library_is_installed(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rows = [LogReport("/x.tlog", "x", 3, "tlog", "used", track_scale=1.01), LogReport("/y.tlog", "y", 0, "tlog",
                                                                                     "skipped", reason="empty")]
    parquet = write_table(rows, LogReport.columns(), tmp_path / "logs")
    assert parquet.suffix == ".parquet"
    back = read_table(parquet)
    assert back[0]["track_scale"] == 1.01 and back[1]["reason"] == "empty"
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)  # as if pyarrow were not installed
    csv_path = write_table(rows, LogReport.columns(), tmp_path / "logs")
    assert csv_path.suffix == ".csv"
    back_csv = read_table(csv_path)
    assert list(back_csv[0]) == list(LogReport.columns())
    assert float(back_csv[0]["track_scale"]) == 1.01 and back_csv[1]["reason"] == "empty"


@settings(max_examples=200)
@given(st.binary(max_size=200), st.binary(min_size=1, max_size=6), st.integers(1, 16))
def test_a_byte_pattern_is_found_across_chunk_borders(data: bytes, pattern: bytes, chunk: int) -> None:
    import tempfile

    from rover_bridge.app.log_frames import LogFrames

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "x.tlog"
        path.write_bytes(data)
        assert LogFrames(path).contains(pattern, chunk_bytes=chunk) == (pattern in data)
