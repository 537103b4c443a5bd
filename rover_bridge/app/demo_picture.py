"""The demo's picture: where the rover went by ground truth, by wheel odometry and by the EKF, and how far each
estimate was off over time; needs matplotlib (`rover-bridge[plot]`).

Truth is a wide pale band, wheel odometry dashed orange, the EKF a thin blue line on top: on the whole route
they overlap within centimetres, so a zoomed panel shows the route's end, where the drift has added up (wide
enough for the nearer estimate). Each
segment of the route (or go-here leg) is named on the map and shaded in the error plots.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

from rover_bridge.app.demo_series import Series

Errors = list[tuple[float, float, float, float, float]]  # t, wheel and EKF position errors, their heading errors

TRUTH = {"color": "black", "linewidth": 4.0, "alpha": 0.25, "solid_capstyle": "round", "label": "ground truth"}
WHEEL = {"color": "C1", "linewidth": 1.5, "linestyle": "--", "label": "wheel odometry"}
EKF = {"color": "C0", "linewidth": 1.1, "label": "EKF (published ODOMETRY)"}
MOVING_M = 0.3  # a segment shorter than this (a spin, a stop) is named at its place, not along its path


def _spans(series: Series) -> list[tuple[str, float, float]]:
    """(name, start, end) of each segment on the boot clock; the last ends with the truth."""
    end = series.truth[-1][0] if series.truth else 0.0
    marks = series.segments
    return [(name, t, marks[i + 1][1] if i + 1 < len(marks) else end) for i, (name, t) in enumerate(marks)]


def _name_segments(ax: Any, series: Series) -> None:
    """Each segment's name at the middle of its path (by distance), or at its place if it hardly moves."""
    offsets = [(12, 10), (12, -16), (-14, 14), (-14, -18)]
    still = 0
    for name, t0, t1 in _spans(series):
        pts = [(n, e) for t, n, e, _ in series.truth if t0 <= t <= t1]
        if not pts:
            continue
        steps = [math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in itertools.pairwise(pts)]
        length = sum(steps)
        if length >= MOVING_M:
            walked, i = 0.0, 0
            while i < len(steps) and walked + steps[i] < length / 2:
                walked += steps[i]
                i += 1
            n, e = pts[i]
            ax.annotate(name, (e, n), xytext=(6, 6), textcoords="offset points", fontsize=8, color="0.2",
                        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75})
        else:
            n, e = pts[len(pts) // 2]
            dx, dy = offsets[still % len(offsets)]
            still += 1
            ax.annotate(name, (e, n), xytext=(dx, dy), textcoords="offset points", fontsize=8, color="0.35",
                        style="italic", ha="left" if dx > 0 else "right",
                        arrowprops={"arrowstyle": "-", "color": "0.6", "linewidth": 0.6})


def _shade_segments(axes: list[Any], series: Series, t_origin: float, label_ax: Any) -> None:
    """Alternate pale bands per segment, named at the top of ``label_ax``."""
    for k, (name, t0, t1) in enumerate(_spans(series)):
        a, b = t0 - t_origin, t1 - t_origin
        for ax in axes:
            if k % 2:
                ax.axvspan(a, b, color="0.93", zorder=0)
        label_ax.text((a + b) / 2, 1.02, name, transform=label_ax.get_xaxis_transform(), rotation=55,
                      fontsize=7, ha="left", va="bottom", color="0.3")


def _zoom_window(series: Series) -> tuple[float, float, float]:
    """(north, east, half width) around the route's end, wide enough to hold the nearer estimate's end (the
    other may lie outside: then the map shows the difference already)."""
    n, e = series.truth[-1][1], series.truth[-1][2]
    ends = [(p[-1][1], p[-1][2]) for p in (series.wheel, series.ekf) if p]
    nearest = min((math.hypot(a - n, b - e) for a, b in ends), default=0.0)
    return n, e, max(2.5 * nearest, 0.05)


def _draw_paths(ax: Any, series: Series) -> None:
    for data, style in ((series.truth, TRUTH), (series.wheel, WHEEL), (series.ekf, EKF)):
        # East on the horizontal axis, north up: the map as seen from above.
        ax.plot([p[2] for p in data], [p[1] for p in data], **style)


NO_TRUTH = "no ground truth reached the demo\n(the emulator's SIM_STATE): nothing to zoom on"
NO_ERRORS = "no errors to draw: no estimate was judged\nagainst the truth (no ODOMETRY, or no truth)"


def say_empty(ax: Any, why: str) -> None:
    """An empty panel says why it is empty."""
    ax.text(0.5, 0.5, why, transform=ax.transAxes, ha="center", va="center", fontsize=9, color="0.35")


def plot(series: Series, errs: Errors, path: Path, title: str) -> None:
    """Map with the segments named, a zoom on the route's end, position and heading errors over time."""
    import matplotlib.pyplot as plt

    fig = figure(series, errs, title)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def figure(series: Series, errs: Errors, title: str) -> Any:
    """plot's figure, not yet saved (its panels for a test to read)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig = plt.figure(figsize=(13, 8.5))
    grid = fig.add_gridspec(3, 2, width_ratios=[1.35, 1], height_ratios=[1.25, 1, 1])
    ax_map = fig.add_subplot(grid[:, 0])
    ax_zoom = fig.add_subplot(grid[0, 1])
    ax_pos = fig.add_subplot(grid[1, 1])
    ax_hdg = fig.add_subplot(grid[2, 1], sharex=ax_pos)

    _draw_paths(ax_map, series)
    if series.goto:
        ax_map.plot([g.east_m for g in series.goto], [g.north_m for g in series.goto], "rx", markersize=9,
                    label="go-here targets")
    _name_segments(ax_map, series)
    if series.truth or series.wheel or series.ekf:
        ax_map.set_aspect("equal", adjustable="datalim")
    ax_map.set(xlabel="east [m]", ylabel="north [m]", title=title)
    ax_map.grid(True, alpha=0.3)

    if series.truth:
        n, e, half = _zoom_window(series)
        ax_map.add_patch(Rectangle((e - half, n - half), 2 * half, 2 * half, fill=False, edgecolor="0.3",
                                   linewidth=0.8, linestyle=":"))
        ax_map.annotate("zoom", (e + half, n + half), xytext=(3, 3), textcoords="offset points", fontsize=8,
                        color="0.3")
        _draw_paths(ax_zoom, series)
        for data, style in ((series.truth, TRUTH), (series.wheel, WHEEL), (series.ekf, EKF)):
            if data:
                ax_zoom.plot(data[-1][2], data[-1][1], "o", color=style["color"], markersize=5)
        ax_zoom.set_xlim(e - half, e + half)
        ax_zoom.set_ylim(n - half, n + half)
        ax_zoom.set_aspect("equal", adjustable="box")
        ax_zoom.set(title=f"zoom: the route's end, {2 * half * 100:.0f} cm across (dots: where each ends)",
                    xlabel="east [m]", ylabel="north [m]")
        ax_zoom.title.set_fontsize(9)
        ax_zoom.grid(True, alpha=0.3)
    else:
        say_empty(ax_zoom, NO_TRUTH)
    if series.truth or series.wheel or series.ekf:
        ax_map.legend(loc="best", fontsize=8)
    else:
        say_empty(ax_map, "no path to draw: neither the truth nor an estimate arrived")

    ts = [x[0] for x in errs]
    t_origin = series.truth[0][0] if series.truth else 0.0
    ax_pos.plot(ts, [x[1] for x in errs], color=WHEEL["color"], linestyle="--", label="wheel odometry")
    ax_pos.plot(ts, [x[2] for x in errs], color=EKF["color"], label="EKF")
    ax_pos.set_ylabel("position error [m]")
    ax_hdg.plot(ts, [x[3] for x in errs], color=WHEEL["color"], linestyle="--", label="wheel odometry")
    ax_hdg.plot(ts, [x[4] for x in errs], color=EKF["color"], label="EKF")
    ax_hdg.set(ylabel="heading error [deg]", xlabel="time [s]")
    _shade_segments([ax_pos, ax_hdg], series, t_origin, ax_pos)
    for ax in (ax_pos, ax_hdg):
        ax.set_ylim(bottom=0.0)
        ax.grid(True, alpha=0.3)
        if errs:
            ax.legend(loc="upper left", fontsize=8)
        else:
            say_empty(ax, NO_ERRORS)
    plt.setp(ax_pos.get_xticklabels(), visible=False)
    fig.tight_layout()
    return fig
