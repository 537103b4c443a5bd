"""The fleet report's folder: one table per level, a picture, a short summary, the rovers' profile patches.

    OUT/logs.parquet     one row per log (LogReport), skipped logs with their reason
    OUT/rovers.parquet   one row per rover (RoverReport)
    OUT/fleet.png        calibration per rover over time (each log, 1 sigma), drift against GPS per log
    OUT/summary.txt      what a person reads first (also printed)
    OUT/patches/ROVER.toml   the [robot] keys a rover's profile should have (as `rover-bridge calibrate` writes)

Tables are Parquet where pyarrow is installed, CSV otherwise (same columns, same names with .csv).
"""

from __future__ import annotations

import csv
import importlib
import math
import re
import time
from collections.abc import Sequence
from dataclasses import astuple
from pathlib import Path
from typing import Any

from rover_bridge.fleet.analysis import LogReport
from rover_bridge.fleet.drift import MIN_EXTENT_M, MIN_PAIRS
from rover_bridge.fleet.rovers import RoverReport


def _parquet() -> Any:
    """pyarrow.parquet, or None where it is not installed (imported by name: it ships no type hints)."""
    try:
        return importlib.import_module("pyarrow.parquet")
    except ImportError:
        return None


def write_table(rows: Sequence[Any], columns: tuple[str, ...], path_stem: Path) -> Path:
    """rows of frozen dataclasses -> path_stem.parquet (pyarrow) or path_stem.csv; the path written."""
    values = [astuple(r) for r in rows]
    pq = _parquet()
    if pq is not None:
        path = path_stem.with_suffix(".parquet")
        pq.write_table(importlib.import_module("pyarrow").Table.from_pydict(
            {c: [v[i] for v in values] for i, c in enumerate(columns)}), path)
        return path
    path = path_stem.with_suffix(".csv")
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        writer.writerows([repr(x) if isinstance(x, float) else x for x in v] for v in values)
    return path


def read_table(path: Path) -> list[dict[str, Any]]:
    """A table written by write_table, as dicts (CSV values come back as text)."""
    if path.suffix == ".parquet":
        return list(_parquet().read_table(path).to_pylist())
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def patch_name(rover: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", rover).strip("_") or "rover"


def summary(logs: Sequence[LogReport], rovers: Sequence[RoverReport], threshold: float, rover_by: str) -> str:
    used = [r for r in logs if r.used]
    skipped = [r for r in logs if not r.used]
    flagged = [r for r in rovers if r.flagged]
    lines = [f"{len(logs)} logs: {len(used)} used, {len(skipped)} skipped; {len(rovers)} rovers (by {rover_by}), "
             f"{len(flagged)} flagged (calibration more than {100 * threshold:.1f} % off the profile)",
             f"{sum(r.distance_m for r in used) / 1000:.2f} km over {sum(r.duration_s for r in used) / 3600:.2f} h"]
    drifts = [r.drift_pct for r in used if math.isfinite(r.drift_pct)]
    if drifts:
        lines.append(f"drift against GPS: {len(drifts)} logs with a good fix, median {_median(drifts):.2f} %, "
                     f"worst {max(drifts):.2f} % of the distance")
    lines.append("")
    lines.append(f"{'rover':24s} {'logs':>4s} {'track scale':>17s} {'radius ratio':>17s} {'track trend/30 d':>16s}  "
                 "flags")
    for r in rovers:
        trend = (f"{100 * r.track_scale_trend_per_30d:+.2f} +-{100 * r.track_scale_trend_sigma:.2f} %"
                 if math.isfinite(r.track_scale_trend_per_30d) else "-")
        notes = [r.flags] if r.flags else []
        notes += [f"{r.stalls} stalls"] if r.stalls else []
        notes += [f"{r.slip_events} slips"] if r.slip_events else []
        notes += [f"wiring: {r.wiring}"] if r.wiring else []
        lines.append(f"{r.rover:24s} {r.logs:4d} {r.track_scale:8.4f} +-{r.track_scale_sigma:.4f} "
                     f"{r.radius_ratio:8.4f} +-{r.radius_ratio_sigma:.4f} {trend:>16s}  {'; '.join(notes)}")
    if skipped:
        lines += ["", "skipped:"] + [f"  {r.path}: {r.reason}" for r in skipped]
    noted = [r for r in used if r.note]
    if noted:
        lines += ["", "used, with notes:"] + [f"  {r.path}: {r.note}" for r in noted]
    return "\n".join(lines) + "\n"


def _median(values: list[float]) -> float:
    s = sorted(values)
    n = len(s)
    return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


def picture(logs: Sequence[LogReport], rovers: Sequence[RoverReport], rover_key: Any, threshold: float,
            path: Path) -> Path | None:
    """fleet.png (None without matplotlib): calibration per rover over time, drift against GPS."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig = figure(plt, logs, rovers, rover_key, threshold)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def figure(plt: Any, logs: Sequence[LogReport], rovers: Sequence[RoverReport], rover_key: Any,
           threshold: float) -> Any:
    """The picture's matplotlib figure (`plt`: matplotlib.pyplot, imported by the caller)."""
    fig, axes = plt.subplots(1, 3, figsize=(16, 5))
    used = [r for r in logs if r.used]
    for i, rover in enumerate(rovers):
        mine = [r for r in used if rover_key(r) == rover.rover]
        colour = f"C{i % 10}"
        for ax, value, sigma, combined in (
                (axes[0], "track_scale", "track_scale_sigma", rover.track_scale),
                (axes[1], "radius_ratio", "radius_ratio_sigma", rover.radius_ratio)):
            dated = [r for r in mine if math.isfinite(r.start_unix_s)]
            days = [(r.start_unix_s - _epoch(used)) / 86_400.0 for r in dated]
            ax.errorbar(days, [getattr(r, value) for r in dated], yerr=[getattr(r, sigma) for r in dated], fmt="o",
                        color=colour, ms=4, capsize=2, label=f"{rover.rover}{' (flagged)' if rover.flagged else ''}")
            if days:
                ax.plot([min(days), max(days)], [combined, combined], "-", color=colour, lw=1)
        drift = [(r.distance_m, r.drift_pct) for r in mine if math.isfinite(r.drift_pct)]
        if drift:
            axes[2].plot(*zip(*drift, strict=True), "o", color=colour, ms=4, label=rover.rover)
    for ax, title in ((axes[0], "track scale (effective / profile)"), (axes[1], "radius ratio (right / left)")):
        for y in (1.0 - threshold, 1.0 + threshold):
            ax.axhline(y, color="0.6", ls=":", lw=1)
        ax.axhline(1.0, color="0.3", lw=0.8)
        ax.set_title(title)
        ax.set_xlabel(f"days since {time.strftime('%Y-%m-%d', time.gmtime(_epoch(used)))}")
    if rovers and used:
        axes[0].legend(fontsize=7)
    axes[2].set_title("drift against GPS")
    axes[2].set_xlabel("distance driven in the log [m]")
    axes[2].set_ylabel("largest error after the best fit [% of distance]")
    if not axes[2].lines:  # no log has a drift figure: the panel says why instead of standing blank
        axes[2].text(0.5, 0.5, no_drift_reason(used), transform=axes[2].transAxes, ha="center", va="center",
                     fontsize=10, color="0.3")
    fig.tight_layout()
    return fig


def no_drift_reason(used: Sequence[LogReport]) -> str:
    """Why no used log has a drift figure (see rover_bridge.fleet.drift)."""
    if not used:
        return "no log used:\nno drift against GPS"
    with_fixes = sum(1 for r in used if r.gps_fixes > 0)
    if with_fixes == 0:
        return (f"no GPS fix in {'this log' if len(used) == 1 else f'these {len(used)} logs'}:\ndrift needs "
                "GPS_RAW_INT with a 3-D fix,\nor GLOBAL_POSITION_INT")
    return (f"GPS fixes in {with_fixes} of {len(used)} logs, too few to fit:\ndrift needs {MIN_PAIRS} fixes "
            f"or more\nover a track of {MIN_EXTENT_M:g} m or more")


def _epoch(used: Sequence[LogReport]) -> float:
    starts = [r.start_unix_s for r in used if math.isfinite(r.start_unix_s)]
    return min(starts) if starts else 0.0
