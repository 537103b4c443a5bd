"""The estimate against GPS over one log (pure: fixes and replayed rows in, at the replay's clock).

Each good fix is paired with the replayed pose at the fix's time (interpolated between the two rows
around it). The estimate's frame is its own (the start pose, or the autopilot's once anchored) and GPS's
is north/east, so the two tracks are put together by the rotation and translation that fit them best
(least squares over all pairs); what is left is the estimate's error. Drift is the largest of those
errors as a percentage of the distance driven between the first and the last pair.

Memory is bounded: past MAX_PAIRS pairs every other one is dropped and only every second fix is kept
from then on (the fit needs the shape of the track, not every fix). A pose reset (a new reset_counter
with a jump) starts a new frame: the segment with the most pairs is the one measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EARTH_RADIUS_M = 6_378_137.0
MAX_PAIRS = 4096
MAX_ROW_GAP_S = 0.5  # a fix between two rows further apart than this is not paired
MIN_PAIRS = 10
MIN_EXTENT_M = 2.0  # a track smaller than this cannot orient the fit


@dataclass(frozen=True, slots=True)
class Drift:
    fixes: int  # good fixes paired with the estimate
    rms_m: float  # after the best rigid fit; NaN without enough pairs
    max_m: float
    distance_m: float  # driven between the first and the last pair
    pct: float  # max_m / distance_m, in %


NO_DRIFT = Drift(0, math.nan, math.nan, 0.0, math.nan)


class GpsTrack:
    """Fixes paired with the replayed estimate (see the module docstring)."""

    def __init__(self) -> None:
        self._origin: tuple[float, float] | None = None  # lat, lon of the first fix (rad)
        self._pending: list[tuple[float, float, float]] = []  # (t_s, north_m, east_m) not yet paired
        self._last_row: tuple[float, float, float, float] | None = None  # t_s, x_m, y_m, distance_m
        self._reset_counter: int | None = None
        self._pairs: list[tuple[float, float, float, float, float]] = []  # x, y, north, east, distance
        self._best: list[tuple[float, float, float, float, float]] = []
        self._stride = 1
        self._seen = 0

    def fix(self, t_s: float, lat_deg: float, lon_deg: float) -> None:
        lat, lon = math.radians(lat_deg), math.radians(lon_deg)
        if self._origin is None:
            self._origin = (lat, lon)
        lat0, lon0 = self._origin
        self._pending.append((t_s, (lat - lat0) * EARTH_RADIUS_M, (lon - lon0) * EARTH_RADIUS_M * math.cos(lat0)))

    def row(self, t_s: float, x_m: float, y_m: float, reset_counter: int, distance_m: float) -> None:
        if reset_counter != self._reset_counter:
            if len(self._pairs) > len(self._best):
                self._best = self._pairs
            self._pairs, self._reset_counter, self._last_row = [], reset_counter, None
        last = self._last_row
        self._last_row = (t_s, x_m, y_m, distance_m)
        if not self._pending:
            return
        keep = []
        for fix in self._pending:
            ft, north, east = fix
            if ft > t_s:
                keep.append(fix)
            elif last is not None and last[0] <= ft and t_s - last[0] <= MAX_ROW_GAP_S:
                f = (ft - last[0]) / (t_s - last[0]) if t_s > last[0] else 1.0
                self._pair(last[1] + f * (x_m - last[1]), last[2] + f * (y_m - last[2]), north, east,
                           last[3] + f * (distance_m - last[3]))
        self._pending = keep

    def _pair(self, x: float, y: float, north: float, east: float, distance: float) -> None:
        self._seen += 1
        if self._seen % self._stride:
            return
        self._pairs.append((x, y, north, east, distance))
        if len(self._pairs) >= MAX_PAIRS:
            self._pairs = self._pairs[::2]
            self._stride *= 2

    def result(self) -> Drift:
        pairs = self._pairs if len(self._pairs) > len(self._best) else self._best
        if len(pairs) < MIN_PAIRS:
            return Drift(len(pairs), math.nan, math.nan, 0.0, math.nan)
        a = np.asarray(pairs, dtype=float)
        est, gps = a[:, 0:2], a[:, 2:4]
        distance = float(a[-1, 4] - a[0, 4])
        est_c, gps_c = est - est.mean(axis=0), gps - gps.mean(axis=0)
        if float(np.max(np.hypot(gps_c[:, 0], gps_c[:, 1]))) < MIN_EXTENT_M or distance <= 0.0:
            return Drift(len(pairs), math.nan, math.nan, distance, math.nan)
        # The rotation taking the estimate's centred track onto GPS's (2-D Kabsch: a proper rotation).
        h = est_c.T @ gps_c
        theta = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
        c, s = math.cos(theta), math.sin(theta)
        rotated = est_c @ np.array([[c, s], [-s, c]])
        err = np.hypot(*(rotated - gps_c).T)
        max_m = float(err.max())
        return Drift(len(pairs), float(np.sqrt(np.mean(err ** 2))), max_m, distance, 100.0 * max_m / distance)
