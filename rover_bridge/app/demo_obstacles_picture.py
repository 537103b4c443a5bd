"""The `obstacles` demo's picture (demo-obstacles.png), in the style of rover_bridge.app.demo_picture: the map
with the obstacles filled, the AVOID_MARGIN line around them, the truth path (and the EKF's) and where the rover
stopped at each, the distance written; a zoom on the stop at the wall; the speed asked for against the speed
driven; the distance to each obstacle over time. Needs matplotlib (`rover-bridge[plot]`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rover_bridge.app.demo_obstacles import OBSTACLES, Obstacle, ObstacleLeg, clearance_m, nearest_point
from rover_bridge.app.demo_picture import EKF, TRUTH, _name_segments, _shade_segments, say_empty
from rover_bridge.app.demo_series import Series

OBSTACLE_STYLE = {"facecolor": "0.45", "edgecolor": "0.2", "linewidth": 0.8, "alpha": 0.85}
MARGIN_COLOR = "C3"
GRID_M = 0.04  # the margin line's grid: fine enough that its corners look round
NO_SPEED = "no speed to draw: no ground truth\nor no request reached the picture"


def plot_obstacles(series: Series, legs: Sequence[ObstacleLeg], path: Path, title: str) -> None:
    import matplotlib.pyplot as plt

    fig = obstacles_figure(series, legs, title)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _margin(legs: Sequence[ObstacleLeg]) -> float | None:
    margins = [leg.margin_m for leg in legs if np.isfinite(leg.margin_m)]
    return margins[0] if margins else None


def _draw_world(ax: Any, margin_m: float | None, bounds: tuple[float, float, float, float]) -> None:
    """The obstacles filled and, around them, the line AVOID_MARGIN away (a contour of the distance to them)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    for o in OBSTACLES:
        ax.add_patch(Polygon([(e, n) for n, e in o.polygon], closed=True, label=None, **OBSTACLE_STYLE))
    if margin_m is None:
        return
    n0, n1, e0, e1 = bounds
    north, east = np.meshgrid(np.arange(n0, n1, GRID_M), np.arange(e0, e1, GRID_M), indexing="ij")
    clearance = np.min([clearance_m(north, east, o.polygon) for o in OBSTACLES], axis=0)
    ax.contour(east, north, clearance, levels=[margin_m], colors=MARGIN_COLOR, linestyles="--", linewidths=1.0)
    ax.add_line(Line2D([], [], color=MARGIN_COLOR, linestyle="--", linewidth=1.0,
                       label=f"AVOID_MARGIN ({margin_m:.2f} m) from the obstacles"))


def _bounds(series: Series, pad_m: float) -> tuple[float, float, float, float]:
    """(north min, max, east min, max) holding the obstacles and the path, ``pad_m`` around."""
    ns = [n for o in OBSTACLES for n, _ in o.polygon] + [p[1] for p in series.truth]
    es = [e for o in OBSTACLES for _, e in o.polygon] + [p[2] for p in series.truth]
    return min(ns) - pad_m, max(ns) + pad_m, min(es) - pad_m, max(es) + pad_m


def _mark_stops(ax: Any, legs: Sequence[ObstacleLeg], obstacles: dict[str, Obstacle], fontsize: float) -> None:
    """Where the rover stopped at each obstacle, and a dimension line to it with the distance written."""
    for leg in legs:
        n, e = leg.rest_ne
        wn, we = nearest_point(n, e, obstacles[leg.obstacle].polygon)
        ax.plot(e, n, "o", color=MARGIN_COLOR, markersize=6, zorder=5)
        ax.annotate("", (we, wn), xytext=(e, n), arrowprops={"arrowstyle": "<->", "color": "0.15", "lw": 0.9})
        ax.annotate(f"stopped {leg.rest_m:.2f} m\nfrom the {leg.obstacle}", ((e + we) / 2, (n + wn) / 2),
                    xytext=(8, 4), textcoords="offset points", fontsize=fontsize, color="0.1", va="bottom",
                    bbox={"boxstyle": "round,pad=0.2", "fc": "white", "ec": "0.6", "alpha": 0.9})


def obstacles_figure(series: Series, legs: Sequence[ObstacleLeg], title: str) -> Any:
    """plot_obstacles' figure, not yet saved (its panels for a test to read)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig: Any = plt.figure(figsize=(13, 8.5))
    grid = fig.add_gridspec(3, 2, width_ratios=[1.35, 1], height_ratios=[1.25, 1, 1])
    ax_map = fig.add_subplot(grid[:, 0])
    ax_zoom = fig.add_subplot(grid[0, 1])
    ax_speed = fig.add_subplot(grid[1, 1])
    ax_dist = fig.add_subplot(grid[2, 1], sharex=ax_speed)
    margin = _margin(legs)
    by_name = {o.name: o for o in OBSTACLES}

    bounds = _bounds(series, 0.5 + (margin or 0.0))  # the whole margin line in view
    _draw_world(ax_map, margin, bounds)
    for o in OBSTACLES:
        e = max(p[1] for p in o.polygon)
        n = sum(p[0] for p in o.polygon) / len(o.polygon)
        ax_map.annotate(o.name, (e, n), xytext=(5, 0), textcoords="offset points", va="center", fontsize=9,
                        color="0.2", weight="bold")
    for data, style in ((series.truth, TRUTH), (series.ekf, EKF)):
        ax_map.plot([p[2] for p in data], [p[1] for p in data], **style)
    _name_segments(ax_map, series)
    _mark_stops(ax_map, legs, by_name, 8)
    ax_map.set_xlim(bounds[2], bounds[3])
    ax_map.set_ylim(bounds[0], bounds[1])
    ax_map.set_aspect("equal", adjustable="box")
    ax_map.set(xlabel="east [m]", ylabel="north [m]", title=title)
    ax_map.grid(True, alpha=0.3)
    ax_map.legend(loc="lower left", fontsize=8)
    if not series.truth:
        say_empty(ax_map, "no path to draw: no ground truth arrived")

    wall = [leg for leg in legs if leg.obstacle == "wall"]
    if wall:
        n, e = wall[-1].rest_ne
        wn, we = nearest_point(n, e, by_name["wall"].polygon)
        cn, ce, half = (n + wn) / 2, (e + we) / 2, max(1.6, 0.75 * abs(wn - n) + 0.5)
        _draw_world(ax_zoom, margin, (cn - half - 0.5, cn + half + 0.5, ce - 2 * half - 0.5, ce + 2 * half + 0.5))
        ax_zoom.plot([p[2] for p in series.truth], [p[1] for p in series.truth], **TRUTH)
        _mark_stops(ax_zoom, wall, by_name, 8)
        ax_zoom.set_xlim(ce - 2 * half, ce + 2 * half)
        ax_zoom.set_ylim(cn - half, cn + half)
        ax_zoom.set_aspect("equal", adjustable="box")
        ax_zoom.grid(True, alpha=0.3)
    else:
        say_empty(ax_zoom, "the rover did not drive at the wall")
    ax_zoom.set(title="zoom: the stop at the wall (dashed: the margin)", xlabel="east [m]", ylabel="north [m]")
    ax_zoom.title.set_fontsize(9)

    t_origin = series.truth[0][0] if series.truth else 0.0
    if series.speed and series.requested:
        ax_speed.plot([t - t_origin for t, _ in series.requested], [v for _, v in series.requested], color="C1",
                      linestyle="--", drawstyle="steps-post", label="requested by the GCS")
        ax_speed.plot([t - t_origin for t, _ in series.speed], [v for _, v in series.speed], color="C0",
                      label="driven (ground truth)")
        ax_speed.legend(loc="lower left", fontsize=8)
    else:
        say_empty(ax_speed, NO_SPEED)
    ax_speed.set_ylabel("speed [m/s]")
    ax_speed.axhline(0.0, color="0.5", linewidth=0.6)

    if series.truth:
        ts = np.array([p[0] - t_origin for p in series.truth])
        north, east = np.array([p[1] for p in series.truth]), np.array([p[2] for p in series.truth])
        for k, o in enumerate(OBSTACLES):
            ax_dist.plot(ts, clearance_m(north, east, o.polygon), color=f"C{k + 2}", label=f"to the {o.name}")
        if margin is not None:
            ax_dist.axhline(margin, color=MARGIN_COLOR, linestyle="--", linewidth=1.0, label="AVOID_MARGIN")
        ax_dist.legend(loc="upper center", ncol=3, fontsize=8)
        ax_dist.set_ylim(0.0, None)
    else:
        say_empty(ax_dist, "no ground truth: no distances")
    ax_dist.set(ylabel="distance [m]\n(rover's centre)", xlabel="time [s]")
    _shade_segments([ax_speed, ax_dist], series, t_origin, ax_speed)
    for ax in (ax_speed, ax_dist):
        ax.grid(True, alpha=0.3)
    plt.setp(ax_speed.get_xticklabels(), visible=False)
    fig.tight_layout()
    return fig
