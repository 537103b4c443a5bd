"""Per rover: what a rover's logs agree on (pure: LogReports in, RoverReports out).

Which logs are one rover's (`rover_by`): the autopilot's system id, the log's folder, or both (the default:
fleets often give every rover system id 1, or keep every rover's logs in one folder).

Each log's filter starts from the profile's geometry with a prior uncertainty; that prior is taken out of
every log's estimate (information form: 1/sigma^2 - 1/sigma0^2) before the logs are combined, weighted by
their information, and put back once. Where the logs scatter more than their sigmas say, the combined sigma
is widened by the Birge ratio sqrt(chi^2 / (n - 1)). The trend is the weighted straight line through the
logs' own estimates against their start times (per 30 days), with at least MIN_TREND_LOGS logs over a day
or more. A rover is flagged where its combined track scale or radius ratio is off the profile's by more
than the threshold; its profile patch is the [robot] section `rover-bridge calibrate` writes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

from rover_bridge.app.calibration import radii_for_ratio, robot_patch_lines
from rover_bridge.estimate.core import CalibrationEstimate
from rover_bridge.fleet.analysis import LogReport
from rover_bridge.params import Profile

ROVER_BY = ("both", "sysid", "folder")
MIN_TREND_LOGS = 3
TREND_PERIOD_S = 30 * 86_400.0
MIN_INFORMATION_FRACTION = 0.01  # a log must add this much to the prior's information to count


@dataclass(frozen=True, slots=True)
class Combined:
    value: float
    sigma: float
    logs: int  # logs that carried information
    trend_per_30d: float = math.nan
    trend_sigma: float = math.nan


@dataclass(frozen=True, slots=True)
class RoverReport:
    """One row of the per-rover table."""

    rover: str
    system_id: int
    folder: str
    logs: int  # used
    skipped: int
    first_unix_s: float
    last_unix_s: float
    distance_m: float
    track_scale: float
    track_scale_sigma: float
    track_scale_trend_per_30d: float
    track_scale_trend_sigma: float
    radius_ratio: float
    radius_ratio_sigma: float
    radius_ratio_trend_per_30d: float
    radius_ratio_trend_sigma: float
    calibration_logs: int
    drift_pct_max: float
    slip_events: int
    stalls: int
    wiring: str
    flagged: bool
    flags: str
    track_width_m: float  # what the profile should say
    left_radius_m: float
    right_radius_m: float

    @staticmethod
    def columns() -> tuple[str, ...]:
        return tuple(f.name for f in fields(RoverReport))

    def patch_toml(self, profile_path: str) -> str:
        header = (f"rover-bridge fleet: rover {self.rover}, {self.calibration_logs} logs, profile {profile_path}\n"
                  f"track scale {self.track_scale:.4f} +- {self.track_scale_sigma:.4f}, radius ratio "
                  f"{self.radius_ratio:.4f} +- {self.radius_ratio_sigma:.4f} (1 sigma) against the profile\n"
                  "copy these keys into the profile (its other keys stay as they are)")
        return "\n".join(robot_patch_lines(header, self.track_width_m, self.right_radius_m / self.left_radius_m,
                                           self.left_radius_m, self.right_radius_m,
                                           f"from {self.calibration_logs} logs against the gyro")) + "\n"


def rover_key(report: LogReport, rover_by: str) -> str:
    if rover_by == "sysid":
        return f"sysid {report.system_id}"
    if rover_by == "folder":
        return report.folder
    return f"{report.folder}#{report.system_id}"


def combine(values: Sequence[tuple[float, float, float]], prior_value: float, prior_sigma: float) -> Combined:
    """(value, sigma, start_unix_s) per log -> the value they agree on (see the module docstring)."""
    prior_info = 1.0 / prior_sigma ** 2
    points = []  # (data-only value, its information, time)
    for value, sigma, t in values:
        if not (math.isfinite(value) and sigma > 0.0):
            continue
        info = 1.0 / sigma ** 2 - prior_info
        if info > MIN_INFORMATION_FRACTION * prior_info:
            points.append(((value / sigma ** 2 - prior_value * prior_info) / info, info, t))
    if not points:
        return Combined(prior_value, prior_sigma, 0)
    total = sum(w for _, w, _ in points) + prior_info
    mean = (sum(v * w for v, w, _ in points) + prior_value * prior_info) / total
    sigma = 1.0 / math.sqrt(total)
    if len(points) > 1:
        chi2 = sum(w * (v - mean) ** 2 for v, w, _ in points)
        sigma *= max(1.0, math.sqrt(chi2 / (len(points) - 1)))
    slope, slope_sigma = _trend([(t, v, w) for v, w, t in points if math.isfinite(t)])
    return Combined(mean, sigma, len(points), slope * TREND_PERIOD_S, slope_sigma * TREND_PERIOD_S)


def _trend(points: list[tuple[float, float, float]]) -> tuple[float, float]:
    """Weighted least-squares slope (per second) of (t, value, weight), with its sigma widened like the mean's."""
    if len(points) < MIN_TREND_LOGS or max(t for t, _, _ in points) - min(t for t, _, _ in points) < 86_400.0:
        return math.nan, math.nan
    sw = sum(w for _, _, w in points)
    t0 = sum(t * w for t, _, w in points) / sw
    v0 = sum(v * w for _, v, w in points) / sw
    stt = sum(w * (t - t0) ** 2 for t, _, w in points)
    slope = sum(w * (t - t0) * (v - v0) for t, v, w in points) / stt
    chi2 = sum(w * (v - v0 - slope * (t - t0)) ** 2 for t, v, w in points)
    return slope, math.sqrt(1.0 / stt) * max(1.0, math.sqrt(chi2 / (len(points) - 2)))


def rovers(reports: Sequence[LogReport], profile: Profile, prior: CalibrationEstimate, rover_by: str = "both",
           threshold: float = 0.02) -> list[RoverReport]:
    """The per-rover table, rovers in name order. A skipped log whose system id is unknown counts for the
    rover of its folder where the folder has one rover, and for no rover otherwise."""
    groups: dict[str, list[LogReport]] = {}
    for r in reports:
        if r.system_id or rover_by == "folder":
            groups.setdefault(rover_key(r, rover_by), []).append(r)
    for r in reports:
        if not r.system_id and rover_by != "folder":
            mine = {k for k, logs in groups.items() if logs[0].folder == r.folder}
            if rover_by == "both" and len(mine) == 1:
                groups[mine.pop()].append(r)
    return [_rover(name, logs, profile, prior, threshold) for name, logs in sorted(groups.items())]


def _rover(name: str, logs: list[LogReport], profile: Profile, prior: CalibrationEstimate,
           threshold: float) -> RoverReport:
    used = [r for r in logs if r.used]
    kt = combine([(r.track_scale, r.track_scale_sigma, r.start_unix_s) for r in used], prior.track_scale,
                 prior.track_scale_sigma)
    q = combine([(r.radius_ratio, r.radius_ratio_sigma, r.start_unix_s) for r in used], prior.radius_ratio,
                prior.radius_ratio_sigma)
    flags = []
    if kt.logs and abs(kt.value - 1.0) > threshold:
        flags.append(f"track {100 * (kt.value - 1.0):+.1f} %")
    if q.logs and abs(q.value - 1.0) > threshold:
        flags.append(f"radius ratio {100 * (q.value - 1.0):+.1f} %")
    robot = profile.robot
    # The filter's ratio is relative to the profile's radii; the patch says the absolute one.
    left, right = radii_for_ratio(0.5 * (robot.left_radius_m + robot.right_radius_m),
                                  q.value * robot.right_radius_m / robot.left_radius_m)
    starts = [r.start_unix_s for r in used if math.isfinite(r.start_unix_s)]
    drifts = [r.drift_pct for r in used if math.isfinite(r.drift_pct)]
    ids = {r.system_id for r in logs}
    folders = {r.folder for r in logs}
    return RoverReport(
        rover=name, system_id=ids.pop() if len(ids) == 1 else 0, folder=folders.pop() if len(folders) == 1 else "",
        logs=len(used), skipped=len(logs) - len(used), first_unix_s=min(starts, default=math.nan),
        last_unix_s=max(starts, default=math.nan), distance_m=sum(r.distance_m for r in used),
        track_scale=kt.value, track_scale_sigma=kt.sigma, track_scale_trend_per_30d=kt.trend_per_30d,
        track_scale_trend_sigma=kt.trend_sigma, radius_ratio=q.value, radius_ratio_sigma=q.sigma,
        radius_ratio_trend_per_30d=q.trend_per_30d, radius_ratio_trend_sigma=q.trend_sigma,
        calibration_logs=min(kt.logs, q.logs), drift_pct_max=max(drifts, default=math.nan),
        slip_events=sum(r.slip_events for r in used), stalls=sum(r.stalls for r in used),
        wiring="; ".join(sorted({w for r in used for w in r.wiring.split("; ") if w})),
        flagged=bool(flags), flags=", ".join(flags), track_width_m=robot.track_width_m * kt.value,
        left_radius_m=left, right_radius_m=right)
