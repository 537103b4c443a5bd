"""Issue 42's yardstick: the wheel loop, with the default [control], right on every plant (benchmarks/plants.py:
the plants, the robot, the drive, the metrics and their targets; `python benchmarks/bench_plants.py` prints the
table). One case per plant, one lockstep drive each (about 2.5 s of CPU), every metric against its target.

Each plant must meet every target with the packaged defaults: no plant is excused.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import plants


def cases() -> list[object]:
    return [pytest.param(plant, id=plant.replace(" ", "")) for plant in plants.PLANTS]


@pytest.mark.parametrize("plant", cases())
def test_the_default_loop_meets_the_issue_targets_on_every_plant(plant: str) -> None:
    m = plants.measure(plant)
    over = {name: round(getattr(m, name), 2) for name in plants.failing(m)}
    assert over == {}, f"{plant}: over target {over} (targets {plants.TARGETS})"


def test_every_plant_is_measured() -> None:
    assert set(plants.PLANTS) == {"ideal", "lagged", "weak 20 %", "deadband", "curved", "skid"}
    assert plants.PLANTS["skid"].plant == "ardupilot_skid"
    assert {v.plant for name, v in plants.PLANTS.items() if name != "skid"} == {"wheels"}


def test_the_metrics_flag_exactly_the_values_over_target() -> None:
    ok = plants.TARGETS
    assert plants.failing(ok) == []
    worse = plants.PlantMetrics(**{**ok.__dict__, "overshoot_pct": 10.01, "yaw_rms_deg_s": 1.5})
    assert plants.failing(worse) == ["overshoot_pct", "yaw_rms_deg_s"]
