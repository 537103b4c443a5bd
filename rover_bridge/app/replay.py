"""Offline estimation over a recorded .tlog (or an ArduPilot DataFlash .bin, see log_frames): the same
core, fed the recorded frames at their recorded times, so a log from the rover can be re-run with other
estimator parameters.

Which frames were the autopilot's: a .tlog does not say which link a frame came in on, so a
frame counts as the autopilot's when it comes from the vehicle's system id (learned from its
first autopilot HEARTBEAT, or `mavlink.vehicle_system_id`) and not from the bridge's own
component. The bridge's own frames in the log (its ODOMETRY, overrides) are the "live" record
that a replay can be compared with.

The log's clock drives the estimator's clock, except where it jumps by more than LOG_JUMP_S either way
(a companion without a real-time clock stepping its wall clock at an NTP sync): there the replay's clock
goes on from where it was, as a monotonic clock would, instead of ticking through the jump.
"""

from __future__ import annotations

import bisect
import csv
import itertools
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from rover_bridge.app import deadlines
from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.log_frames import LogFrames, LogStats
from rover_bridge.estimate.core import CalibrationEstimate, EstimateCore
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import Profile

CSV_COLUMNS = ("time_usec", "x_m", "y_m", "yaw_rad", "vx_m_s", "yawspeed_rad_s", "var_x_m2", "var_y_m2",
               "var_yaw_rad2", "var_vx", "var_yawspeed", "reset_counter", "quality", "track_scale",
               "track_scale_sigma", "radius_ratio", "radius_ratio_sigma")
LOG_JUMP_S = 60.0  # the log's clock stepping by more than this (either way) is a jump, not a gap


@dataclass(frozen=True, slots=True)
class OdometryRow:
    """One ODOMETRY, as published (LOCAL_FRD / BODY_FRD: y right, yaw clockwise)."""

    time_usec: int
    x_m: float
    y_m: float
    yaw_rad: float
    vx_m_s: float
    yawspeed_rad_s: float
    var_x_m2: float
    var_y_m2: float
    var_yaw_rad2: float
    var_vx: float
    var_yawspeed: float
    reset_counter: int
    quality: int
    # The filter's calibration when the row was published (replayed rows; NaN in the live ones).
    track_scale: float = math.nan
    track_scale_sigma: float = math.nan
    radius_ratio: float = math.nan
    radius_ratio_sigma: float = math.nan

    @classmethod
    def from_message(cls, msg: Any, cal: CalibrationEstimate | None = None) -> OdometryRow:
        w, _, _, z = msg.q
        pc, vc = msg.pose_covariance, msg.velocity_covariance
        geometry = (cal.track_scale, cal.track_scale_sigma, cal.radius_ratio, cal.radius_ratio_sigma) if cal \
            else (math.nan,) * 4
        # Diagonal positions in a row-major 6x6 upper triangle: 0, 6, 11, 15, 18, 20.
        return cls(int(msg.time_usec), float(msg.x), float(msg.y), 2.0 * math.atan2(z, w), float(msg.vx),
                   float(msg.yawspeed), float(pc[0]), float(pc[6]), float(pc[20]), float(vc[0]), float(vc[20]),
                   int(msg.reset_counter), int(msg.quality), *geometry)

    def as_row(self) -> list[str]:
        return [repr(getattr(self, c)) for c in CSV_COLUMNS]


@dataclass(frozen=True, slots=True)
class ReplayResult:
    rows: tuple[OdometryRow, ...]
    live: tuple[OdometryRow, ...]  # the ODOMETRY the bridge itself published in the log
    frames: int
    autopilot_frames: int
    counters: dict[str, int]
    calibration: CalibrationEstimate
    log: LogStats
    timing: str = ""  # the bridge's own outputs against their deadlines, from the log's stamps

    def summary(self) -> str:
        if not self.rows:
            return "\n".join([f"{self.frames} frames read, {self.autopilot_frames} from the autopilot: no ODOMETRY "
                              "produced", *self._log_notes()])
        last = self.rows[-1]
        path = sum(math.hypot(b.x_m - a.x_m, b.y_m - a.y_m) for a, b in itertools.pairwise(self.rows))
        lines = [
            f"frames read                 {self.frames} ({self.autopilot_frames} from the autopilot)",
            f"ODOMETRY rows               {len(self.rows)} over {_span_s(self.rows):.1f} s",
            f"path length                 {path:.2f} m",
            f"final pose (FRD)            x {last.x_m:+.3f} m  y {last.y_m:+.3f} m  "
            f"yaw {math.degrees(last.yaw_rad):+.1f} deg",
            f"final 1-sigma               xy {math.sqrt(max(last.var_x_m2, last.var_y_m2)):.3f} m  "
            f"yaw {math.degrees(math.sqrt(last.var_yaw_rad2)):.2f} deg  quality {last.quality}",
            f"reset_counter               {last.reset_counter}",
        ]
        if self.live:
            d = compare(self.rows, self.live)
            lines.append(f"vs live ODOMETRY in the log  max |dpos| {d[0]:.4f} m, "
                         f"max |dyaw| {math.degrees(d[1]):.3f} deg over {d[2]} matched rows")
        cal = self.calibration
        if cal.estimated:
            lines.append(f"calibration (1 sigma)       track scale {cal.track_scale:.4f} +- {cal.track_scale_sigma:.4f}"
                         f"  radius ratio {cal.radius_ratio:.4f} +- {cal.radius_ratio_sigma:.4f}")
        else:
            lines.append("calibration                 not estimated (estimator.calibrate = false)")
        if self.timing:
            lines.append(f"timing (log stamps)         {self.timing}")
        interesting = {k: v for k, v in sorted(self.counters.items()) if v}
        if interesting:
            lines.append("estimator counters          " + ", ".join(f"{k}={v}" for k, v in interesting.items()))
        return "\n".join(lines + self._log_notes())

    def _log_notes(self) -> list[str]:
        notes = []
        if self.log.trailing_bytes:
            notes.append(f"WARNING: the log ends mid-frame ({self.log.trailing_bytes} bytes of an incomplete last "
                         "frame, ignored): it was cut short")
        if self.log.bad_frames or self.log.bad_bytes or self.log.reader_lines:
            hidden = f"; pymavlink's {self.log.reader_lines} lines about it not shown" if self.log.reader_lines else ""
            notes.append(f"WARNING: unreadable data in the log ({self.log.bad_frames} bad frames, "
                         f"{self.log.bad_bytes} bad bytes), skipped{hidden}")
        return notes


def _span_s(rows: tuple[OdometryRow, ...]) -> float:
    """Time covered, counting only ordinary steps: the stamps switch from the bridge's clock to the
    autopilot's once SYSTEM_TIME is known, and restart after an autopilot reboot."""
    return sum(dt for a, b in itertools.pairwise(rows) if 0 < (dt := (b.time_usec - a.time_usec) / 1e6) < 1.0)


class ReplayObserver(Protocol):
    """Sees the replay as it goes (rover_bridge.fleet.analysis): every frame not from the bridge itself,
    after the estimator has read it, and every replayed row, each at the replay's clock (s)."""

    def frame(self, t_s: float, msg: Any, estimate: EstimateCore) -> None: ...

    def row(self, t_s: float, row: OdometryRow) -> None: ...


def replay(path: str | Path, profile: Profile, observer: ReplayObserver | None = None,
           keep_rows: bool = True) -> ReplayResult:
    """Run the estimate flow over a .tlog or a DataFlash .bin; deterministic: same log and profile, same rows.

    When the log holds the bridge's own ODOMETRY (a `run --tlog` recording), the estimator ticks
    exactly where the live one published, in the same order relative to the frames it had read;
    otherwise (e.g. a MAVProxy log) it ticks at its own deadlines on the log's clock. The log is
    streamed; with keep_rows False no row is kept (an observer sees them), so memory stays bounded.
    """
    log = LogFrames(path)
    own_comp = profile.mavlink.component_id
    # The bridge's own ODOMETRY is a MAVLink 2 frame whose header holds its component id then the message id
    # (331, three bytes little-endian): a log without those four bytes (a ground station's) is not read twice.
    ticks_from_log = (log.stats.kind == "tlog" and log.contains(bytes([own_comp]) + (331).to_bytes(3, "little"))
                      and any(m.get_srcComponent() == own_comp and m.get_type() == "ODOMETRY" for m in log))
    core = BridgeCore(profile)
    rows: list[OdometryRow] = []
    live: list[OdometryRow] = []
    frames = ap_frames = jumps = 0
    clock: float | None = None
    timing = deadlines.LogTiming(profile)  # the bridge's own periodic outputs, as the log stamped them
    offset = 0.0  # replay clock - log clock: moves at each jump of the log's clock
    last_log_t: float | None = None

    def tick(at_s: float, early: bool) -> None:
        # Where the live loop published, ODOMETRY may have left early (in a pass it made anyway).
        out = core.estimate.tick(at_s) + (core.estimate.odometry_due(at_s) if early else [])
        for o in out:
            if o.msg.get_msgId() == mavlink.MAVLINK_MSG_ID_ODOMETRY:
                row = OdometryRow.from_message(o.msg, core.estimate.calibration_estimate())
                if keep_rows:
                    rows.append(row)
                if observer is not None:
                    observer.row(at_s, row)

    for msg in log:
        frames += 1
        t_log = float(msg._timestamp)
        if last_log_t is not None and abs(t_log - last_log_t) > LOG_JUMP_S:
            offset += last_log_t - t_log
            jumps += 1
        last_log_t = t_log
        t = t_log + offset
        if msg.get_srcComponent() == own_comp:
            if (output := deadlines.output_of(msg)) is not None:
                timing.written(output, t)
            if msg.get_type() == "ODOMETRY":
                live.append(OdometryRow.from_message(msg))
                if ticks_from_log:
                    tick(t, early=True)
            continue
        if clock is None:
            clock = t
        if not ticks_from_log:
            while (deadline := core.estimate.next_deadline_s(clock)) <= t:
                clock = max(clock, deadline)
                tick(clock, early=False)
                if core.estimate.next_deadline_s(clock) <= clock:
                    break  # guard: a deadline that did not move on is left for the next frame
        clock = max(clock, t)
        if _from_autopilot(core, msg):
            ap_frames += 1
            core.estimate.handle(Incoming(Link.AUTOPILOT, msg), t)
        if observer is not None:
            observer.frame(t, msg, core.estimate)
    counters = dict(core.estimate.counters)
    counters["log_clock_jumps"] = jumps
    return ReplayResult(tuple(rows), tuple(live), frames, ap_frames, counters, core.estimate.calibration_estimate(),
                        replace(log.stats), deadlines.summary_line(timing.outputs))


def _from_autopilot(core: BridgeCore, msg: Any) -> bool:
    if msg.get_type() == "HEARTBEAT":
        return core.identity.is_autopilot_heartbeat(msg)
    vehicle = core.identity.vehicle_system_id
    return vehicle is not None and msg.get_srcSystem() == vehicle


def compare(rows: tuple[OdometryRow, ...] | list[OdometryRow], live: tuple[OdometryRow, ...] | list[OdometryRow],
            max_dt_usec: int = 10_000) -> tuple[float, float, int]:
    """Largest position and yaw difference between each live row and the replayed row nearest in time.

    Live and replayed ticks fall at slightly different instants (the live loop wakes on its own
    clock), so rows are paired by nearest time_usec within `max_dt_usec`, not by equality.
    """
    times = [r.time_usec for r in rows]
    worst_pos = worst_yaw = 0.0
    matched = 0
    for lv in live:
        i = bisect.bisect_left(times, lv.time_usec)
        near = [j for j in (i - 1, i) if 0 <= j < len(rows)]
        if not near:
            continue
        r = min((rows[j] for j in near), key=lambda row: abs(row.time_usec - lv.time_usec))
        if abs(r.time_usec - lv.time_usec) > max_dt_usec or r.reset_counter != lv.reset_counter:
            continue
        matched += 1
        worst_pos = max(worst_pos, math.hypot(r.x_m - lv.x_m, r.y_m - lv.y_m))
        worst_yaw = max(worst_yaw, abs(math.remainder(r.yaw_rad - lv.yaw_rad, 2 * math.pi)))
    return worst_pos, worst_yaw, matched


def write_csv(rows: tuple[OdometryRow, ...], path: str | Path) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        writer.writerows(r.as_row() for r in rows)
