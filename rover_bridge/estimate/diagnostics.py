"""What the estimate flow tells the ground station about itself: wheel slip and calibration (pure).

- Slip: one wheel interval can disagree with the gyro when the turn rate changes between the
  gyro's samples; slip lasts longer, so it is counted after SLIP_MIN_INTERVALS disagreeing
  intervals in a row and reported at most every SLIP_REPORT_INTERVAL_S.
- Calibration (estimator.calibrate): the effective track width and wheel radii every
  CAL_REPORT_INTERVAL_S once wheel data flows, as STATUSTEXT and a log line.
"""

from __future__ import annotations

import logging
import math

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing

log = logging.getLogger("rover_bridge.estimate.diagnostics")

SLIP_REPORT_INTERVAL_S = 5.0
SLIP_MIN_INTERVALS = 2  # consecutive disagreeing wheel intervals before slip is counted and reported
CAL_REPORT_INTERVAL_S = 30.0


class SlipMonitor:
    """Counts and reports wheel slip from the EKF's per-interval verdicts."""

    def __init__(self, reporter: Reporter) -> None:
        self.reporter = reporter
        self.count = 0
        self._in_row = 0
        self._last_report_s = -math.inf

    def interval(self, slip: bool, now_s: float) -> list[Outgoing]:
        self._in_row = self._in_row + 1 if slip else 0
        if self._in_row < SLIP_MIN_INTERVALS:
            return []
        self.count += 1
        if now_s - self._last_report_s < SLIP_REPORT_INTERVAL_S:
            return []
        self._last_report_s = now_s
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, "wheel slip", now_s, key="wheel slip")

    @property
    def slipping(self) -> bool:
        """True while the last SLIP_MIN_INTERVALS or more wheel intervals disagreed with the gyro."""
        return self._in_row >= SLIP_MIN_INTERVALS


class CalibrationReports:
    """The periodic calibration report (only with estimator.calibrate)."""

    def __init__(self, reporter: Reporter, enabled: bool) -> None:
        self.reporter = reporter
        self.enabled = enabled
        self.next_s: float | None = None

    def tick(self, now_s: float, have_wheels: bool, track_width_m: float, left_radius_m: float,
             right_radius_m: float) -> list[Outgoing]:
        if not (self.enabled and have_wheels):
            return []
        if self.next_s is None:
            self.next_s = now_s + CAL_REPORT_INTERVAL_S
            return []
        if now_s < self.next_s:
            return []
        self.next_s = now_s + CAL_REPORT_INTERVAL_S
        log.info("calibration: track_width_m %.4f left_radius_m %.5f right_radius_m %.5f",
                 track_width_m, left_radius_m, right_radius_m)
        return self.reporter.statustext(
            mavlink.MAV_SEVERITY_INFO,
            f"cal track {track_width_m:.4f} r {left_radius_m:.4f}/{right_radius_m:.4f}",
            now_s,
            key="calibration",
        )
