"""One log's report for the fleet: `analyse_log(path, profile, folder)`, a pure function of the log and the profile.

The log is replayed exactly as `rover-bridge replay` replays it (rover_bridge.app.replay, streamed, no row
kept); `LogAnalysis` watches the replay and keeps only running sums:

- duration (the replay's clock, which does not follow jumps of the log's clock) and distance (the replayed
  path); the calibration at the end of the log with its 1-sigma uncertainty (the filter's own);
- the estimate against GPS where the log has a good fix (drift): GPS_RAW_INT with a 3-D fix, or,
  in a log without GPS_RAW_INT, GLOBAL_POSITION_INT (the emulator's truth, an autopilot's fused position);
- slip events (the estimator's slip verdict starting), gaps and clock jumps (its counters, and the log's
  clock jumping);
- wiring-fault signs and stalls: the wheels' PWM outputs in the log (SERVO_OUTPUT_RAW / DataFlash RCOU, the
  output numbered as the profile's channel) as target speeds through the profile's output map, against the
  measured wheel speeds, through the bridge's own WiringMonitor ("still" is a stall); and the wheels' yaw
  rate against the gyro's over the whole log (a reversed encoder or swapped indices show as no or negative
  correlation).

A log the estimate cannot use is reported with the reason and no figures (status "skipped").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from rover_bridge.app.log_frames import LogUnreadableError, log_kind
from rover_bridge.app.replay import OdometryRow, ReplayResult, replay
from rover_bridge.command.outputs import OutputMap
from rover_bridge.command.wheel_control import WiringMonitor
from rover_bridge.estimate.core import EstimateCore
from rover_bridge.fleet.drift import GpsTrack
from rover_bridge.kinematics import WheelSpeeds
from rover_bridge.params import Profile

LOG_GAP_S = 2.0  # no frame at all for this long is a gap in the log
CORRUPT_FRACTION = 0.01  # more unreadable data than this: the log is corrupt, not used
TARGET_MAX_AGE_S = 1.5  # a PWM output older than this is no target for the wiring check
AGREEMENT_MIN_TURN_RAD_S = 0.2  # wheels against gyro: judged only when the rover turned at least this (rms)
AGREEMENT_MIN_SAMPLES = 50
AGREEMENT_MIN_CORRELATION = 0.5


@dataclass(frozen=True, slots=True)
class LogReport:
    """One row of the per-log table (NaN / 0 where a log has nothing to say)."""

    path: str
    folder: str
    system_id: int  # the autopilot's (0: none seen)
    kind: str
    status: str  # "used" | "skipped"
    reason: str = ""  # why skipped
    note: str = ""  # what was odd about a used log
    start_unix_s: float = math.nan
    duration_s: float = 0.0
    distance_m: float = 0.0
    rows: int = 0
    final_x_m: float = math.nan
    final_y_m: float = math.nan
    final_yaw_rad: float = math.nan
    track_scale: float = math.nan
    track_scale_sigma: float = math.nan
    radius_ratio: float = math.nan
    radius_ratio_sigma: float = math.nan
    gps_fixes: int = 0
    gps_rms_m: float = math.nan
    gps_max_m: float = math.nan
    drift_pct: float = math.nan
    slip_events: int = 0
    slip_intervals: int = 0
    stalls: int = 0
    wiring: str = ""
    wheel_gyro_slope: float = math.nan  # wheels' yaw rate over the gyro's (about the track scale)
    wheel_gyro_correlation: float = math.nan
    wheel_gaps: int = 0
    log_gaps: int = 0
    clock_jumps: int = 0
    reboots: int = 0

    @staticmethod
    def columns() -> tuple[str, ...]:
        return tuple(f.name for f in fields(LogReport))

    @property
    def used(self) -> bool:
        return self.status == "used"


@dataclass
class _Agreement:
    """Running sums of the wheels' yaw rate against the gyro's."""

    n: int = 0
    sww: float = 0.0
    sgg: float = 0.0
    swg: float = 0.0

    def add(self, wheels: float, gyro: float) -> None:
        self.n += 1
        self.sww += wheels * wheels
        self.sgg += gyro * gyro
        self.swg += wheels * gyro

    def slope_and_correlation(self) -> tuple[float, float]:
        if self.n == 0 or self.sgg <= 0.0 or self.sww <= 0.0:
            return math.nan, math.nan
        return self.swg / self.sgg, self.swg / math.sqrt(self.sww * self.sgg)

    @property
    def turned(self) -> bool:
        return self.n >= AGREEMENT_MIN_SAMPLES and math.sqrt(self.sgg / self.n) >= AGREEMENT_MIN_TURN_RAD_S


class LogAnalysis:
    """Watches one replay (a rover_bridge.app.replay.ReplayObserver); see the module docstring."""

    def __init__(self, profile: Profile) -> None:
        self.profile = profile
        self.outputs = OutputMap.from_profile(profile)
        self.monitor = WiringMonitor(profile.control, self.outputs.speed_range(left=True),
                                     self.outputs.speed_range(left=False))
        self.first_t_s: float | None = None
        self.last_t_s: float | None = None
        self.log_gaps = 0
        self.distance_m = 0.0
        self.slip_events = 0
        self.stalls = 0
        self.wiring: set[str] = set()
        self.system_id = 0
        self.gps = GpsTrack()
        self.gps_raw_seen = False
        self.agreement = _Agreement()
        self._slipping = False
        self._last_row: OdometryRow | None = None
        self._target: tuple[float, WheelSpeeds] | None = None
        self._fault: str | None = None

    # ------------------------------------------------------------------ ReplayObserver
    def frame(self, t_s: float, msg: Any, estimate: EstimateCore) -> None:
        if self.first_t_s is None:
            self.first_t_s = t_s
        elif self.last_t_s is not None and t_s - self.last_t_s > LOG_GAP_S:
            self.log_gaps += 1
        self.last_t_s = t_s if self.last_t_s is None else max(self.last_t_s, t_s)
        vehicle = estimate.identity.vehicle_system_id
        if vehicle is None or msg.get_srcSystem() != vehicle:
            return
        self.system_id = vehicle
        kind = msg.get_type()
        if kind == "GPS_RAW_INT":
            if not self.gps_raw_seen:
                self.gps_raw_seen, self.gps = True, GpsTrack()  # the real GPS replaces the autopilot's fused one
            if int(msg.fix_type) >= 3:
                self.gps.fix(t_s, int(msg.lat) * 1e-7, int(msg.lon) * 1e-7)
        elif kind == "GLOBAL_POSITION_INT" and not self.gps_raw_seen and (msg.lat != 0 or msg.lon != 0):
            self.gps.fix(t_s, int(msg.lat) * 1e-7, int(msg.lon) * 1e-7)
        elif kind == "SERVO_OUTPUT_RAW":
            self._outputs(t_s, msg)
        elif kind == "WHEEL_DISTANCE":
            self._wheels(t_s, estimate)
        slipping = estimate.slip.slipping
        if slipping and not self._slipping:
            self.slip_events += 1
        self._slipping = slipping

    def row(self, t_s: float, row: OdometryRow) -> None:
        last = self._last_row
        if last is not None and last.reset_counter == row.reset_counter:
            self.distance_m += math.hypot(row.x_m - last.x_m, row.y_m - last.y_m)
        self._last_row = row
        self.gps.row(t_s, row.x_m, row.y_m, row.reset_counter, self.distance_m)

    # ------------------------------------------------------------------ wiring, stalls, agreement
    def _outputs(self, t_s: float, msg: Any) -> None:
        o = self.outputs
        pwm = [getattr(msg, f"servo{ch}_raw", 0) for ch in (o.left_channel, o.right_channel)]
        if all(o.pwm_min - 100 <= p <= o.pwm_max + 100 for p in pwm):
            self._target = (t_s, WheelSpeeds(self._speed(pwm[0], True), self._speed(pwm[1], False)))

    def _speed(self, pwm_us: float, left: bool) -> float:
        """The wheel speed a PWM output asks for: the inverse of the profile's output map."""
        o = self.outputs
        curve = o.left_curve if left else o.right_curve
        if curve is not None:
            p, s = curve.pwm_us, curve.speed_rad_s
            pwm_us = min(max(pwm_us, p[0]), p[-1])
            i = next(k for k in range(1, len(p)) if pwm_us <= p[k])
            return s[i - 1] + (pwm_us - p[i - 1]) / (p[i] - p[i - 1]) * (s[i] - s[i - 1])
        span = o.pwm_max - o.pwm_trim if pwm_us >= o.pwm_trim else o.pwm_trim - o.pwm_min
        fraction = max(-1.0, min(1.0, (pwm_us - o.pwm_trim) / span))
        return (-fraction if (o.left_reversed if left else o.right_reversed) else fraction) * o.max_wheel_rad_s

    def _wheels(self, t_s: float, estimate: EstimateCore) -> None:
        sample = estimate.take_wheel_sample()  # replay feeds no command flow: nothing else takes it
        if sample is None:
            return
        robot = self.profile.robot
        speeds = sample.speeds
        gyro = estimate.last_gyro
        if gyro is not None:
            wheels_omega = (speeds.right_rad_s * robot.right_radius_m
                            - speeds.left_rad_s * robot.left_radius_m) / robot.track_width_m
            self.agreement.add(wheels_omega, gyro[1])
        target = self._target
        if target is None or t_s - target[0] > TARGET_MAX_AGE_S:
            self.monitor.reset()
            self._fault = None
            return
        fault = self.monitor.check(target[1], speeds, t_s)
        key = None if fault is None else f"{fault.wheel} wheel {fault.kind}"
        if key is not None and key != self._fault:
            if fault is not None and fault.kind == "still":
                self.stalls += 1
            else:
                self.wiring.add(key)
        self._fault = key

    # ------------------------------------------------------------------ the report
    def report(self, path: str, folder: str, result: ReplayResult, use_truncated: bool) -> LogReport:
        log, c = result.log, result.counters
        base = LogReport(path, folder, self.system_id, log.kind, "skipped", start_unix_s=_nan(log.start_unix_s))
        reason = skip_reason(result, use_truncated)
        if reason:
            return replace(base, reason=reason)
        slope, corr = self.agreement.slope_and_correlation()
        wiring = sorted(self.wiring)
        if self.agreement.turned and corr < AGREEMENT_MIN_CORRELATION:
            wiring.append(f"wheels against gyro correlation {corr:+.2f}: "
                          + ("encoder indices swapped or both reversed" if corr < -AGREEMENT_MIN_CORRELATION
                             else "an encoder reversed or not this wheel's"))
        note = []
        if log.trailing_bytes:
            note.append(f"truncated: ends mid-frame ({log.trailing_bytes} bytes of an incomplete frame)")
        if log.bad_frames or log.bad_bytes:
            note.append(f"unreadable data skipped ({log.bad_frames} frames, {log.bad_bytes} bytes)")
        drift = self.gps.result()
        last = result.rows[-1] if result.rows else self._last_row
        assert last is not None  # skip_reason: a used log has rows
        cal = result.calibration
        duration = (self.last_t_s or 0.0) - (self.first_t_s or 0.0)
        return replace(
            base, status="used", note="; ".join(note), duration_s=duration, distance_m=self.distance_m,
            rows=c.get("odometry_sent", 0), final_x_m=last.x_m, final_y_m=last.y_m, final_yaw_rad=last.yaw_rad,
            track_scale=cal.track_scale, track_scale_sigma=cal.track_scale_sigma, radius_ratio=cal.radius_ratio,
            radius_ratio_sigma=cal.radius_ratio_sigma, gps_fixes=drift.fixes, gps_rms_m=drift.rms_m,
            gps_max_m=drift.max_m, drift_pct=drift.pct, slip_events=self.slip_events,
            slip_intervals=c.get("wheel_slip", 0), stalls=self.stalls, wiring="; ".join(wiring),
            wheel_gyro_slope=slope, wheel_gyro_correlation=corr, wheel_gaps=c.get("wheel_gaps", 0),
            log_gaps=self.log_gaps, clock_jumps=c.get("clock_jumps", 0) + c.get("log_clock_jumps", 0),
            reboots=c.get("reboots", 0))


def skip_reason(result: ReplayResult, use_truncated: bool) -> str:
    """Why the estimate cannot use a log ("" when it can)."""
    log, c = result.log, result.counters
    if log.size_bytes == 0:
        return "empty: 0 bytes"
    if log.frames == 0:
        return f"corrupt: no readable frame in {log.size_bytes} bytes"
    bad = log.bad_bytes / log.size_bytes
    if bad > CORRUPT_FRACTION:
        return (f"corrupt: {100 * bad:.1f} % of the log unreadable ({log.bad_frames} bad frames, "
                f"{log.bad_bytes} bad bytes)")
    if log.trailing_bytes and not use_truncated:
        return (f"truncated: ends mid-frame ({log.trailing_bytes} bytes of an incomplete frame); "
                "--use-truncated uses what it has")
    if c.get("wheel_samples", 0) == 0:
        return "no wheel encoders: no WHEEL_DISTANCE (DataFlash: WENC) in the log"
    if c.get("gyro_samples", 0) == 0:
        return "no gyro: no ATTITUDE, SCALED_IMU or RAW_IMU (DataFlash: IMU) in the log"
    if c.get("odometry_sent", 0) == 0:
        return "no estimate: the replay published no ODOMETRY"
    return ""


def analyse_log(path: str, profile: Profile, folder: str = "", use_truncated: bool = False) -> LogReport:
    """The report of one log (pure: the same log and profile give the same report, wherever it runs)."""
    analysis = LogAnalysis(profile)
    try:
        result = replay(path, profile, observer=analysis, keep_rows=False)
    except (LogUnreadableError, OSError) as exc:
        return LogReport(path, folder, 0, log_kind(Path(path)), "skipped", reason=f"unreadable: {exc}")
    return analysis.report(path, folder, result, use_truncated)


def _nan(value: float | None) -> float:
    return math.nan if value is None else value


def fleet_profile(profile: Profile) -> Profile:
    """The profile a fleet run replays with: the user's, with the calibration estimated (estimator.calibrate)."""
    if profile.estimator.calibrate:
        return profile
    return replace(profile, estimator=replace(profile.estimator, calibrate=True))
