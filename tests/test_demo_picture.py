"""The demo's naming and picture, without running the demo: every scenario in `demo --help` with its own
picture, and a picture drawn from a made-up run (segments named, a zoom that holds every estimate's end)."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rover_bridge.app.cli import build_parser
from rover_bridge.app.demo import SCENARIO_HELP, SCENARIOS, picture_name
from rover_bridge.app.demo_picture import _spans, _zoom_window, plot
from rover_bridge.app.demo_series import GotoLeg, Series

REPO = Path(__file__).resolve().parents[1]


def test_demo_help_lists_every_scenario() -> None:
    out = subprocess.run([sys.executable, "-m", "rover_bridge", "demo", "--help"], capture_output=True, text=True,
                         timeout=120, check=True, cwd=REPO, env=dict(os.environ, COLUMNS="400")).stdout
    flat = " ".join(out.split())
    for name in SCENARIOS:
        assert f"{name}: {' '.join(SCENARIO_HELP[name].replace('%%', '%').split())}" in flat, name


def test_each_scenario_has_its_own_picture() -> None:
    names = [picture_name(s) for s in SCENARIOS]
    assert names[0] == picture_name("clean") == "demo.png"
    assert len(set(names)) == len(names)
    assert picture_name("goto") == "demo-goto.png" and picture_name("slip") == "demo-slip.png"
    assert build_parser().parse_args(["demo", "--scenario", "goto"]).plot is None  # the default: its own name


def _made_up_run() -> Series:
    """A 10 s run: 4 s north at 0.5 m/s, a 2 s spin, 4 s east; the estimates drift apart at the end."""
    s = Series()
    for i in range(101):
        t = 100.0 + 0.1 * i
        north, east = min(t - 100.0, 4.0) * 0.5, max(0.0, t - 106.0) * 0.5
        yaw = 0.0 if t < 104.0 else min(1.0, (t - 104.0) / 2.0) * math.pi / 2
        s.truth.append((t, north, east, yaw))
        drift = 0.01 * (t - 100.0)
        s.wheel.append((t, north + drift, east - drift, yaw + 0.01))
        s.ekf.append((t, north - 0.3 * drift, east + 0.2 * drift, yaw - 0.005))
        if i in (0, 40, 60):
            s.mark({0: "straight", 40: "spin", 60: "east"}[i])
    s.goto.append(GotoLeg(2.0, 2.0, "LOCAL_NED", 0.05, 8.0))
    return s


def test_the_segments_span_the_run_in_order() -> None:
    spans = _spans(_made_up_run())
    assert [(n, round(a, 6), round(b, 6)) for n, a, b in spans] == [("straight", 100.0, 104.0),
                                                                   ("spin", 104.0, 106.0), ("east", 106.0, 110.0)]


def test_the_zoom_holds_the_nearer_estimates_end() -> None:
    s = _made_up_run()
    n, e, half = _zoom_window(s)
    assert (n, e) == (s.truth[-1][1], s.truth[-1][2])
    assert abs(s.ekf[-1][1] - n) < half and abs(s.ekf[-1][2] - e) < half  # 3.6 cm off: inside
    assert abs(s.wheel[-1][1] - n) > half  # 10 cm off each way: the map shows that one


def test_a_picture_is_drawn(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    s = _made_up_run()
    errs = [(t - 100.0, 0.01, 0.005, 1.0, 0.5) for t, *_ in s.truth]
    plot(s, errs, tmp_path / "p.png", "made up")
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_empty_panel_says_why(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from rover_bridge.app.demo_picture import NO_ERRORS, NO_TRUTH, figure

    s = _made_up_run()
    fig = figure(dataclasses.replace(s, truth=[]), [], "made up")
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    plt.close(fig)
    assert texts.count(NO_ERRORS) == 2 and NO_TRUTH in texts
    full = figure(s, [(t - 100.0, 0.01, 0.005, 1.0, 0.5) for t, *_ in s.truth], "made up")
    assert not {NO_ERRORS, NO_TRUTH} & {t.get_text() for ax in full.axes for t in ax.texts}
    plt.close(full)


def test_the_obstacles_the_emulator_loads_are_the_ones_the_demo_measures_against(tmp_path: Path) -> None:
    import numpy as np

    from rover_bridge.app.demo_obstacles import OBSTACLES, WALL, clearance_m, scenario_toml
    from sitl import load_scenario
    from sitl.obstacles import Polygon, obstacle_distance_m

    path = tmp_path / "scenario.toml"
    path.write_text(SCENARIOS["obstacles"][1])
    assert SCENARIOS["obstacles"][1] == scenario_toml()
    shapes = load_scenario(path).obstacles
    assert [s.vertices for s in shapes if isinstance(s, Polygon)] == [
        tuple((round(n, 4), round(e, 4)) for n, e in o.polygon) for o in OBSTACLES]
    # The demo's own geometry agrees with the emulator's truth (sitl/obstacles.py) around both obstacles.
    rng = np.random.default_rng(3)
    north, east = rng.uniform(-1.0, 10.0, 400), rng.uniform(-4.0, 7.0, 400)
    ours = np.min([clearance_m(north, east, o.polygon) for o in OBSTACLES], axis=0)
    truth = [obstacle_distance_m((float(n), float(e)), shapes) for n, e in zip(north, east, strict=True)]
    assert np.allclose(ours, np.array(truth, dtype=float), atol=1e-3)
    assert clearance_m(np.array([6.0, 8.2, 9.4]), np.array([0.0, 0.0, 0.0]), WALL.polygon).tolist() == \
        pytest.approx([2.0, 0.0, 1.0])


def test_each_leg_at_an_obstacle_says_its_closest_approach_and_where_it_rested() -> None:
    from rover_bridge.app.demo_obstacles import obstacle_legs

    s = Series()
    for i in range(81):  # 1 m/s north from 0 for 6 s, stopping at 5.9 m (2.1 m from the wall), then still
        t = 100.0 + 0.1 * i
        north = min(5.9, 0.1 * i)
        s.truth.append((t, north, 0.0, 0.0))
        s.speed.append((t, 1.0 if north < 5.9 else 0.0))
        if i in (0, 70):
            s.mark({0: "to the wall", 70: "stop"}[i])
    [leg] = obstacle_legs(s, 2.0)
    assert (leg.obstacle, leg.phase, leg.margin_m) == ("wall", "to the wall", 2.0)
    assert leg.closest_m == pytest.approx(2.1) and leg.rest_m == pytest.approx(2.1)
    assert leg.rest_ne == pytest.approx((5.9, 0.0)) and leg.rest_speed_m_s == 0.0 and not leg.touched


def test_an_obstacles_picture_without_a_run_says_why_its_panels_are_empty(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from rover_bridge.app.demo_obstacles_picture import NO_SPEED, obstacles_figure, plot_obstacles

    fig = obstacles_figure(Series(), [], "nothing")
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    plt.close(fig)
    assert NO_SPEED in texts and "the rover did not drive at the wall" in texts
    plot_obstacles(Series(), [], tmp_path / "empty.png", "nothing")
    assert (tmp_path / "empty.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
