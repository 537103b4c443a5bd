"""`rover-bridge fleet` end to end on Dask: an emulated fleet of 6 rovers with known, different miscalibrations
(benchmarks/bench_fleet.py), replayed on a LocalCluster started beside the test and given by --scheduler, and
on the command's own local cluster: the rovers' calibration and flags, the same results whatever runs them
and whatever else is among the logs, the same as `replay` on each log alone."""

from __future__ import annotations

import math
import shutil
import sys
import tomllib
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest

from rover_bridge.app.cli import main as cli_main
from rover_bridge.app.replay import replay
from rover_bridge.fleet.analysis import fleet_profile
from rover_bridge.fleet.cluster import DaskMap
from rover_bridge.fleet.folder import read_table
from rover_bridge.fleet.jobs import expand
from rover_bridge.params import load_profile, profile_from_dict

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import bench_fleet as bench

REPO = Path(__file__).resolve().parents[1]
PARAMS = str(REPO / "params" / "default.toml")
PROFILE = fleet_profile(load_profile(PARAMS))
LOGS_PER_ROVER = 2
DURATION_S = 45.0


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fleet")
    bench.write_fleet(folder, DURATION_S, logs_per_rover=LOGS_PER_ROVER)
    return folder


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """A LocalCluster started apart from the command, as a user's own cluster would be."""
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0")
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def report(fleet_dir: Path, scheduler: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("report")
    assert cli_main(["fleet", str(fleet_dir), "--params", PARAMS, "--out", str(out), "--scheduler", scheduler,
                     "--no-progress"]) == 0
    return out


def _rows(path: Path) -> list[dict[str, Any]]:
    return read_table(path)


def _same(a: dict[str, Any], b: dict[str, Any]) -> bool:
    return repr(a) == repr(b)  # NaN where a log has nothing to say: equal by repr, not by ==


def test_every_rover_is_recovered_within_half_a_percent_and_flagged_only_beyond_two(report: Path) -> None:
    rovers = {r["rover"]: r for r in _rows(report / "rovers.parquet")}
    assert len(rovers) == len(bench.FLEET)
    for truth in bench.FLEET:
        r = rovers[f"{truth.name}#{truth.system_id}"]
        assert r["logs"] == LOGS_PER_ROVER and r["skipped"] == 0
        assert r["track_scale"] == pytest.approx(truth.track_scale, rel=0.005), truth
        assert r["radius_ratio"] == pytest.approx(truth.radius_ratio, rel=0.005), truth
        off = max(abs(truth.track_scale - 1.0), abs(truth.radius_ratio - 1.0))
        assert r["flagged"] == (off > 0.02), (truth, r["flags"])
        assert r["stalls"] == 0 and r["wiring"] == ""
    assert sum(r["flagged"] for r in rovers.values()) == 4


def test_the_report_folder_has_the_tables_the_picture_the_summary_and_patches_the_loader_accepts(report: Path) -> None:
    logs = _rows(report / "logs.parquet")
    assert len(logs) == len(bench.FLEET) * LOGS_PER_ROVER and all(r["status"] == "used" for r in logs)
    # Against the emulator's GPS (its truth); a log that stayed within 2 m of one place has no drift figure.
    drifts = [r["drift_pct"] for r in logs if math.isfinite(r["drift_pct"])]
    assert len(drifts) >= len(logs) - 2 and max(drifts) < 1.0
    assert (report / "fleet.png").stat().st_size > 10_000
    summary = (report / "summary.txt").read_text()
    assert summary.startswith(f"{len(logs)} logs: {len(logs)} used, 0 skipped; 6 rovers (by both), 4 flagged")
    c = next(t for t in bench.FLEET if t.name == "rover-c")
    patch = profile_from_dict(tomllib.loads((report / "patches" / f"rover-c_{c.system_id}.toml").read_text()))
    assert patch.robot.track_width_m == pytest.approx(bench.NOMINAL_TRACK_M * c.track_scale, rel=0.005)


def test_each_log_is_what_replay_finds_alone(fleet_dir: Path, report: Path) -> None:
    logs = {r["path"]: r for r in _rows(report / "logs.parquet")}
    for path in sorted(logs)[::5]:
        alone = replay(path, PROFILE)
        last, r = alone.rows[-1], logs[path]
        assert (r["final_x_m"], r["final_y_m"], r["final_yaw_rad"]) == (last.x_m, last.y_m, last.yaw_rad)
        assert (r["track_scale"], r["track_scale_sigma"], r["radius_ratio"], r["radius_ratio_sigma"]) == (
            alone.calibration.track_scale, alone.calibration.track_scale_sigma, alone.calibration.radius_ratio,
            alone.calibration.radius_ratio_sigma)
        assert r["rows"] == len(alone.rows)


def test_one_local_worker_gives_what_the_separate_cluster_gave(fleet_dir: Path, report: Path) -> None:
    by_path = {r["path"]: r for r in _rows(report / "logs.parquet")}
    jobs = expand([str(fleet_dir)])[::3]
    with DaskMap(None, 1, progress=False) as dask_map:
        assert dask_map.worker_count == 1
        again = dask_map.run(jobs, PROFILE)
    assert [r.path for r in again] == [j.path for j in jobs]
    for r in again:
        assert _same(asdict(r), by_path[r.path])


def test_bad_logs_among_the_inputs_are_each_reported_and_change_nothing_else(
        fleet_dir: Path, report: Path, scheduler: str, tmp_path: Path) -> None:
    mixed = tmp_path / "mixed"
    bad = mixed / "rover-b"
    bad.mkdir(parents=True)
    good = sorted((fleet_dir / "rover-b").glob("*.tlog"))
    for p in good:
        shutil.copy(p, bad / p.name)
    data = good[0].read_bytes()
    (bad / "corrupt.tlog").write_bytes(data[:5000] + bytes(range(256)) * 100 + data[5000:])
    (bad / "truncated.tlog").write_bytes(data[: len(data) // 3 + 5])
    (bad / "empty.tlog").write_bytes(b"")
    rover_b = bench.FLEET[1]
    bench.write_log(bad / "no-encoders.tlog", rover_b, 7, bench.START_UNIX_S, 10.0, drop=("WHEEL_DISTANCE",))
    out = tmp_path / "out"
    assert cli_main(["fleet", str(mixed), "--params", PARAMS, "--out", str(out), "--scheduler", scheduler,
                     "--no-progress"]) == 0
    logs = {Path(r["path"]).name: r for r in _rows(out / "logs.parquet")}
    reasons = {name: r["reason"].split(":")[0] for name, r in logs.items() if r["status"] == "skipped"}
    assert reasons == {"corrupt.tlog": "corrupt", "truncated.tlog": "truncated", "empty.tlog": "empty",
                       "no-encoders.tlog": "no wheel encoders"}
    before = {Path(r["path"]).name: r for r in _rows(report / "logs.parquet") if r["folder"] == "rover-b"}
    assert set(before) == {p.name for p in good}
    for name, r in before.items():
        after = dict(logs[name], path=r["path"])
        assert _same(after, r)
    summary = (out / "summary.txt").read_text()
    for name in reasons:
        assert f"{bad / name}: " in summary
    rover = _rows(out / "rovers.parquet")
    assert [(r["rover"], r["logs"], r["skipped"]) for r in rover] == [(f"rover-b#{rover_b.system_id}", 2, 4)]


def test_without_dask_fleet_says_what_to_install(monkeypatch: pytest.MonkeyPatch, fleet_dir: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask[distributed] were not installed
    assert cli_main(["fleet", str(fleet_dir), "--params", PARAMS]) == 2
    err = capsys.readouterr().err
    assert "pip install -e '.[fleet]' in the clone" in err and "Dask" in err


def test_no_usable_log_is_a_failure(scheduler: str, tmp_path: Path) -> None:
    (tmp_path / "empty.tlog").write_bytes(b"")
    assert cli_main(["fleet", str(tmp_path / "empty.tlog"), "--params", PARAMS, "--out", str(tmp_path / "o"),
                     "--scheduler", scheduler, "--no-progress"]) == 1
    assert math.isnan(_rows(tmp_path / "o" / "logs.parquet")[0]["track_scale"])
