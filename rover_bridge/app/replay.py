"""Offline estimation over a recorded .tlog: the same core, fed the recorded frames at their
recorded times, so a log from the rover can be re-run with other estimator parameters.

Which frames were the autopilot's: a .tlog does not say which link a frame came in on, so a
frame counts as the autopilot's when it comes from the vehicle's system id (learned from its
first autopilot HEARTBEAT, or `mavlink.vehicle_system_id`) and not from the bridge's own
component. The bridge's own frames in the log (its ODOMETRY, overrides) are the "live" record
that a replay can be compared with.
"""

from __future__ import annotations

import bisect
import csv
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rover_bridge.app import deadlines
from rover_bridge.app.composition import BridgeCore
from rover_bridge.errors import ConfigError
from rover_bridge.mavlink.dialect import mavlink, mavutil
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import Profile

CSV_COLUMNS = ("time_usec", "x_m", "y_m", "yaw_rad", "vx_m_s", "yawspeed_rad_s", "var_x_m2", "var_y_m2",
               "var_yaw_rad2", "var_vx", "var_yawspeed", "reset_counter", "quality")


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

    @classmethod
    def from_message(cls, msg: Any) -> OdometryRow:
        w, _, _, z = msg.q
        pc, vc = msg.pose_covariance, msg.velocity_covariance
        # Diagonal positions in a row-major 6x6 upper triangle: 0, 6, 11, 15, 18, 20.
        return cls(int(msg.time_usec), float(msg.x), float(msg.y), 2.0 * math.atan2(z, w), float(msg.vx),
                   float(msg.yawspeed), float(pc[0]), float(pc[6]), float(pc[20]), float(vc[0]), float(vc[20]),
                   int(msg.reset_counter), int(msg.quality))

    def as_row(self) -> list[str]:
        return [repr(getattr(self, c)) for c in CSV_COLUMNS]


@dataclass(frozen=True, slots=True)
class ReplayResult:
    rows: tuple[OdometryRow, ...]
    live: tuple[OdometryRow, ...]  # the ODOMETRY the bridge itself published in the log
    frames: int
    autopilot_frames: int
    counters: dict[str, int]
    calibration: str
    timing: str = ""  # the bridge's own outputs against their deadlines, from the log's stamps

    def summary(self) -> str:
        if not self.rows:
            return f"{self.frames} frames read, {self.autopilot_frames} from the autopilot: no ODOMETRY produced"
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
        if self.calibration:
            lines.append(f"calibration                 {self.calibration}")
        if self.timing:
            lines.append(f"timing (log stamps)         {self.timing}")
        interesting = {k: v for k, v in sorted(self.counters.items()) if v}
        if interesting:
            lines.append("estimator counters          " + ", ".join(f"{k}={v}" for k, v in interesting.items()))
        return "\n".join(lines)


def _span_s(rows: tuple[OdometryRow, ...]) -> float:
    """Time covered, counting only ordinary steps: the stamps switch from the bridge's clock to the
    autopilot's once SYSTEM_TIME is known, and restart after an autopilot reboot."""
    return sum(dt for a, b in itertools.pairwise(rows) if 0 < (dt := (b.time_usec - a.time_usec) / 1e6) < 1.0)


def _frames(path: Path) -> Iterator[Any]:
    if not path.exists():
        raise ConfigError([f"{path}: no such log"])
    log: Any = mavutil.mavlink_connection(str(path), dialect="ardupilotmega", robust_parsing=True)
    try:
        while True:
            msg = log.recv_msg()
            if msg is None:
                return
            if msg.get_type() != "BAD_DATA":
                yield msg
    finally:
        log.close()


def replay(path: str | Path, profile: Profile) -> ReplayResult:
    """Run the estimate flow over a .tlog; deterministic: same log and profile, same rows.

    When the log holds the bridge's own ODOMETRY (a `run --tlog` recording), the estimator ticks
    exactly where the live one published, in the same order relative to the frames it had read;
    otherwise (e.g. a MAVProxy log) it ticks at its own deadlines on the log's clock.
    """
    path = Path(path)
    own_comp = profile.mavlink.component_id
    ticks_from_log = any(m.get_srcComponent() == own_comp and m.get_type() == "ODOMETRY" for m in _frames(path))
    core = BridgeCore(profile)
    rows: list[OdometryRow] = []
    live: list[OdometryRow] = []
    frames = ap_frames = 0
    clock: float | None = None
    written: list[tuple[str, float]] = []  # the bridge's own periodic outputs, as the log stamped them

    def tick(at_s: float, early: bool) -> None:
        # Where the live loop published, ODOMETRY may have left early (in a pass it made anyway).
        out = core.estimate.tick(at_s) + (core.estimate.odometry_due(at_s) if early else [])
        rows.extend(OdometryRow.from_message(o.msg) for o in out
                    if o.msg.get_msgId() == mavlink.MAVLINK_MSG_ID_ODOMETRY)

    for msg in _frames(path):
        frames += 1
        t = float(msg._timestamp)
        if msg.get_srcComponent() == own_comp:
            if (output := deadlines.output_of(msg)) is not None:
                written.append((output, t))
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
    calibration = getattr(core.estimate, "calibration_report", lambda: "")()
    timing = deadlines.summary_line(deadlines.from_log(profile, written))
    return ReplayResult(tuple(rows), tuple(live), frames, ap_frames, dict(core.estimate.counters), str(calibration),
                        timing)


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
