"""The estimate flow's state machine (pure): autopilot telemetry + time in, ODOMETRY and requests out.

Inputs (read, never consumed: the shell still forwards them to the ground stations)
- WHEEL_DISTANCE (9000) -> rover_bridge.estimate.wheel_input (indices, signs, reboots, spikes);
- the gyro, per [estimator] gyro_source: ATTITUDE.yawspeed (rad/s), SCALED_IMU.zgyro (mrad/s) or
  RAW_IMU.zgyro (assumed mrad/s: ArduPilot fills RAW_IMU with scaled values, not ADC counts);
  'auto' uses the highest-priority one that is arriving (ATTITUDE, SCALED_IMU, RAW_IMU in that
  order). MAVLink yaw rates are clockwise positive; frames.omega_from_mavlink_yaw_rate converts.
- SYSTEM_TIME.time_boot_ms: the autopilot's time base for ODOMETRY.time_usec (see below);
- HEARTBEAT and COMMAND_ACK: stream management.

Sensor time: the filter runs on the autopilot's boot clock: every measurement is applied at its
own stamp (WHEEL_DISTANCE.time_usec, ATTITUDE/SCALED_IMU.time_boot_ms, RAW_IMU.time_usec: one
clock for all streams), never at its arrival time, so network and scheduling jitter cannot shift
the gyro against the wheels or stretch an interval. Only publishing needs "now" on that clock:
one offset = the smallest arrival latency seen over every stream (allowed to creep up by
CLOCK_DRIFT of a second per second, so a drifting clock is followed) maps now_s to it; stamps
jumping back (a reboot) re-learn the offset and restart the filter's clock.

Streams: after the autopilot's first heartbeat, after a heartbeat gap (link back or reboot) and after
a detected reboot, the bridge asks for WHEEL_DISTANCE and the gyro message at
[estimator] stream_rate_hz with MAV_CMD_SET_MESSAGE_INTERVAL (one request outstanding at a time, so
each COMMAND_ACK is unambiguous); on DENIED / UNSUPPORTED / FAILED, or no ACK after
STREAM_ACK_ATTEMPTS tries, it falls back to REQUEST_DATA_STREAM for the message's group (EXTRA1 for
WHEEL_DISTANCE and ATTITUDE, RAW_SENSORS for the IMU messages; ArduPilot 4.7 refuses the interval
for WHEEL_DISTANCE). Arrival rates are measured over RATE_WINDOW_S; a stream below
SLOW_FRACTION of the requested rate is re-requested and reported (STATUSTEXT, rate-limited).

Output: ODOMETRY (331) at [odometry] rate_hz to [odometry] targets, extrapolated to now (at most
0.2 s past the last measurement: during a silent link it holds; after 0.5 s of total silence the
next measurement continues from the held pose with the speeds restarted, see _after_silence):
- time_usec: the autopilot's boot time. Preferably through WHEEL_DISTANCE.time_usec (ArduPilot's
  boot clock), mapped exactly as the estimate's own measurements are, so the stamp is the time of
  the published pose even when the autopilot's clock drifts from ours; before wheel data, through
  SYSTEM_TIME.time_boot_ms (same mapping); TIMESYNC is not used (it needs a round trip the pure core
  would have to schedule). With neither: now_s (monotonic) in us.
  ArduPilot re-times external navigation with its own jitter filter either way.
- frame_id MAV_FRAME_LOCAL_FRD (origin and axes of the start pose), child_frame_id MAV_FRAME_BODY_FRD;
  x forward, y right, z = 0; q from the FRD (clockwise) yaw; vx forward, vy = 0, vz = 0, yawspeed CW+.
- covariances: the filter's x, y, yaw, v, yaw-rate blocks with the FRD sign flips
  (frames.covariance_frd_from_flu); vy has a finite variance (LATERAL_SIGMA_* below: the wheels do
  not side-slip much, but not never); z, roll, pitch and their rates are unobserved: each gets
  [odometry] unobserved_variance (default 1e4 m^2 or rad^2, i.e. sigma 100: "unknown", as a number
  rather than the NaN-first-element convention, which many receivers mishandle).
- reset_counter: +1 on every pose reset (MAVLink command or CLI) and on every autopilot reboot
  detected in the wheel distances (the odometry re-bases there: exactly once per reboot).
- estimator_type MAV_ESTIMATOR_TYPE_UNKNOWN: the enum has no wheel/inertial dead-reckoning member;
  NAIVE claims no covariance (PX4 then ignores the covariance) and VIO claims a camera, both false.
- quality: 100 / (1 + sigma_xy / QUALITY_POS_M + sigma_yaw / QUALITY_YAW_RAD), rounded, clamped to
  1..100 (sigma_xy: the larger principal standard deviation of x, y); 0 when no wheel data has
  been fused for WHEELS_STALE_S (the estimate is then a blind extrapolation).

Pose reset: COMMAND_LONG MAV_CMD_USER_1 (31010) addressed to the bridge (target_system = the
vehicle, target_component = [mavlink] component_id): param1 x (m, forward of the start pose),
param2 y (m, right), param3 yaw (deg, clockwise); NaN leaves that coordinate as it is. Answered
with COMMAND_ACK; the CLI uses `reset_pose`.
"""

# Kalman-filter notation (P for a covariance) reads better than pep8 names here.
# ruff: noqa: N803, N806
from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from rover_bridge import frames
from rover_bridge.estimate.ekf import IB, IV, IW, IX, IY, IYAW, NoiseModel, WheelGyroEKF
from rover_bridge.estimate.wheel_input import StepKind, WheelInput
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.odometry import Pose2D, arc_step, wrap_angle
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.estimate.core")

POSE_RESET_COMMAND = mavlink.MAV_CMD_USER_1
# A pose reset beyond these is garbage (a corrupted frame, degrees for metres), not a place: denied.
POSE_RESET_MAX_M = 1e6
POSE_RESET_MAX_YAW_DEG = 360.0
WHEEL_DISTANCE_ID = 9000
GYRO_MESSAGES = {  # source name -> (message id, stream group), in 'auto' priority order
    "attitude": (mavlink.MAVLINK_MSG_ID_ATTITUDE, mavlink.MAV_DATA_STREAM_EXTRA1),
    "scaled_imu": (mavlink.MAVLINK_MSG_ID_SCALED_IMU, mavlink.MAV_DATA_STREAM_RAW_SENSORS),
    "raw_imu": (mavlink.MAVLINK_MSG_ID_RAW_IMU, mavlink.MAV_DATA_STREAM_RAW_SENSORS),
}
GYRO_PRIORITY = tuple(GYRO_MESSAGES)
SILENCE_S = 0.5  # no measurement at all for this long: the next one restarts the motion (see _after_silence)
GYRO_MAX_RAD_S = 50.0  # beyond any rover: such a "rate" is corrupt data, not a measurement
GYRO_SILENT_S = 3.0  # 'auto' falls back to a lower-priority source after this long without the current one

STREAM_ACK_TIMEOUT_S = 1.0
STREAM_ACK_ATTEMPTS = 3
STREAM_RESTART_HOLDOFF_S = 2.0  # several reboot signs close together restart the requests once
HEARTBEAT_GAP_S = 3.0
RATE_WINDOW_S = 5.0
RATE_GRACE_S = 2.0  # let a freshly requested stream speed up before measuring it
SLOW_FRACTION = 0.7
SLOW_REPORT_INTERVAL_S = 30.0

# s/s: how fast a stream's latency offset may creep up. Generous, so a sender's clock that runs
# slow against ours (an emulator behind real time on a loaded machine) is followed within seconds.
CLOCK_DRIFT = 0.05
REORDER_WINDOW_S = 0.5
GYRO_FOR_SLIP_MAX_AGE_S = 0.25
SLIP_REPORT_INTERVAL_S = 5.0
SLIP_MIN_INTERVALS = 2  # consecutive disagreeing wheel intervals before slip is counted and reported
CAL_REPORT_INTERVAL_S = 30.0
WHEELS_STALE_S = 1.0

LATERAL_SIGMA_M_S = 0.02  # vy: skid-steer side slip, plus ...
LATERAL_SIGMA_PER_M_S = 0.05  # ... a fraction of the forward speed ...
LATERAL_SIGMA_PER_RAD_S = 0.05  # ... and of the yaw rate (m/s per rad/s)
QUALITY_POS_M = 0.5
QUALITY_YAW_RAD = math.radians(5.0)

ACK_FAILURES = {mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED, mavlink.MAV_RESULT_FAILED}


def upper_triangle_21(cov: list[list[float]]) -> list[float]:
    """The 21 numbers MAVLink carries for a symmetric 6x6: row-major upper triangle incl. diagonal."""
    return [float(cov[i][j]) for i in range(6) for j in range(i, 6)]


class _StreamClock:
    """Maps the autopilot's boot clock onto the caller's time line (offset = smallest latency seen)."""

    def __init__(self) -> None:
        self.offset_s: float | None = None
        self._last_stamp_s: float | None = None
        self._last_now_s = 0.0

    def map(self, stamp_s: float, now_s: float) -> bool:
        """Learn from one stamp; True when the stamps jumped back (the autopilot restarted its clock)."""
        restarted = self._last_stamp_s is not None and stamp_s < self._last_stamp_s - REORDER_WINDOW_S
        if restarted:
            self.offset_s = None
        self._last_stamp_s = stamp_s
        latency = now_s - stamp_s
        if self.offset_s is None:
            self.offset_s = latency
        else:
            self.offset_s = min(self.offset_s + CLOCK_DRIFT * max(0.0, now_s - self._last_now_s), latency)
        self._last_now_s = now_s
        return restarted


@dataclass
class _Stream:
    name: str
    msg_id: int
    group: int
    state: str = "idle"  # idle | queued | awaiting_ack | requested
    attempts: int = 0
    sent_s: float = 0.0
    window_start_s: float | None = None
    arrivals: int = 0
    last_slow_report_s: float = -math.inf
    measured_hz: float | None = None


@dataclass(frozen=True, slots=True)
class EstimateState:
    """A snapshot of the estimate in rover-bridge's convention (x forward, y left, yaw CCW)."""

    time_s: float | None
    pose: Pose2D
    v_m_s: float
    omega_rad_s: float
    gyro_bias_rad_s: float
    sigma_xy_m: float
    sigma_yaw_rad: float
    raw_pose: Pose2D  # plain wheel odometry (nominal geometry), for comparison
    track_width_m: float  # effective (calibrated) track width; the nominal one without calibration
    left_radius_m: float  # effective radii (calibrated ratio, mean kept at the profile's)
    right_radius_m: float
    reset_counter: int


class EstimateCore:
    """Wheel odometry + gyro EKF -> ODOMETRY; stream requests; pose resets. See the module docstring."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter) -> None:
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        est = profile.estimator
        robot = profile.robot
        self.track_width_m = robot.track_width_m
        self.noise = NoiseModel(
            gyro_noise_rad_s=est.gyro_noise_rad_s,
            wheel_noise_m=est.wheel_noise_m,
            wheel_noise_fraction=est.wheel_noise_fraction,
            gate_sigma=est.gate_sigma,
        )
        self.ekf = WheelGyroEKF(robot.track_width_m, self.noise, calibrate=est.calibrate)
        self.wheels = WheelInput(profile.encoders, robot)
        self.raw_pose = Pose2D()
        self.reset_counter = 0
        self._counters: dict[str, int] = {
            "gyro_samples": 0,
            "gyro_rejected": 0,
            "gyro_switches": 0,
            "gyro_stale": 0,
            "wheel_rejected": 0,
            "wheel_slip": 0,
            "wheel_stationary": 0,
            "reboots": 0,
            "pose_resets": 0,
            "pose_resets_denied": 0,
            "odometry_sent": 0,
            "stream_requests": 0,
            "stream_fallbacks": 0,
            "stream_slow": 0,
            "stream_restarts": 0,
        }
        # One mapping for every autopilot stamp (WHEEL_DISTANCE, ATTITUDE, IMU, SYSTEM_TIME all count
        # from the same boot clock): wheels and gyro then line up exactly as the autopilot measured
        # them. Separate per-stream offsets differed by arrival jitter (tens of ms on a busy machine),
        # which shifted the gyro against the wheels and cost degrees of heading at every turn-rate change.
        self._ap_clock = _StreamClock()
        self._gyro_source: str | None = None if est.gyro_source == "auto" else est.gyro_source
        self._gyro_last_seen: dict[str, float] = {}
        self._gyro_reads = frozenset(GYRO_MESSAGES[name][0] for name in GYRO_PRIORITY)
        self._update_gyro_reads(0.0)
        self._gyro_last_t: dict[str, float] = {}  # newest sender stamp (s) fused per gyro source
        # Gyro samples since the last wheel step (with the one before it), for the slip test.
        self._gyro_window: list[float] = []
        self._gyro_last: tuple[float, float] | None = None  # (now_s, omega)
        self._have_wheels = False
        self._last_wheel_fused_s: float | None = None
        self._last_hb_s: float | None = None
        self._last_restart_s = -math.inf
        self._last_slip_report_s = -math.inf
        self._slip_in_row = 0
        self._next_cal_report_s: float | None = None
        self._next_odom_s: float | None = None
        self._odom_period_s = 1.0 / profile.odometry.rate_hz
        gyro_name = "attitude" if est.gyro_source == "auto" else est.gyro_source
        self._streams = [
            _Stream("WHEEL_DISTANCE", WHEEL_DISTANCE_ID, mavlink.MAV_DATA_STREAM_EXTRA1),
            _Stream(gyro_name.upper(), *GYRO_MESSAGES[gyro_name]),
        ]
        targets = profile.odometry.targets
        self._odom_links = {
            "gcs": (Link.GCS,),
            "autopilot": (Link.AUTOPILOT,),
            "both": (Link.GCS, Link.AUTOPILOT),
            "none": (),
        }[targets]

    # ------------------------------------------------------------------ accessors
    @property
    def counters(self) -> Mapping[str, int]:
        out = dict(self._counters)
        out.update(self.wheels.counters)
        return out

    @property
    def pose(self) -> Pose2D:
        """The filter's pose (x forward of the start pose, y left, yaw CCW) at its last measurement."""
        return self.ekf.pose

    def pose_at(self, now_s: float) -> Pose2D:
        """The pose extrapolated to now_s (what ODOMETRY publishes), x forward, y left, yaw CCW."""
        x, _ = self.ekf.extrapolate(self._autopilot_time_s(now_s))
        return Pose2D(float(x[IX]), float(x[IY]), float(x[IYAW]))

    @property
    def gyro_source(self) -> str | None:
        return self._gyro_source

    @property
    def state(self) -> EstimateState:
        x, P = self.ekf.x, self.ekf.P
        kt, _, q, _ = self.ekf.calibration()
        robot = self.profile.robot
        sl, sr = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
        return EstimateState(
            time_s=self.ekf.time_s,
            pose=self.ekf.pose,
            v_m_s=float(x[IV]),
            omega_rad_s=float(x[IW]),
            gyro_bias_rad_s=float(x[IB]),
            sigma_xy_m=_sigma_xy(P),
            sigma_yaw_rad=math.sqrt(float(P[IYAW, IYAW])),
            raw_pose=self.raw_pose,
            track_width_m=self.track_width_m * kt,
            left_radius_m=robot.left_radius_m * sl,
            right_radius_m=robot.right_radius_m * sr,
            reset_counter=self.reset_counter,
        )

    # ------------------------------------------------------------------ SubCore
    # What handle() may read from the autopilot link (BridgeCore decodes nothing else from it); of the
    # gyro messages only those `gyro_reads` names at the time.
    AUTOPILOT_READS = frozenset({"COMMAND_LONG", "HEARTBEAT", "WHEEL_DISTANCE", "ATTITUDE", "SCALED_IMU", "RAW_IMU",
                                 "SYSTEM_TIME", "COMMAND_ACK"})

    ALL_GYRO_IDS = frozenset(msg_id for msg_id, _group in GYRO_MESSAGES.values())

    @property
    def gyro_reads(self) -> frozenset[int]:
        """Message ids of the gyro sources worth decoding now: the one in use and those 'auto' would
        switch to at once (higher priority); every source while none is in use or it fell silent.
        A lower-priority IMU stream at 50 Hz is then forwarded without being decoded."""
        return self._gyro_reads

    def _update_gyro_reads(self, now_s: float) -> None:
        current = self._gyro_source
        if self.profile.estimator.gyro_source != "auto" and current is not None:
            names: tuple[str, ...] = (current,)
        elif current is None or now_s - self._gyro_last_seen.get(current, -math.inf) > GYRO_SILENT_S:
            names = GYRO_PRIORITY
        else:
            names = GYRO_PRIORITY[: GYRO_PRIORITY.index(current) + 1]
        reads = frozenset(GYRO_MESSAGES[name][0] for name in names)
        if reads != self._gyro_reads:
            self._gyro_reads = reads

    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        mtype = msg.get_type()
        if mtype == "COMMAND_LONG":
            return self._handle_command(inc, now_s)
        if inc.link is not Link.AUTOPILOT:
            return NOTHING
        vehicle = self.identity.vehicle_system_id
        if mtype == "HEARTBEAT":
            return Reaction(out=tuple(self._handle_heartbeat(msg, now_s)))
        if vehicle is not None and msg.get_srcSystem() != vehicle:
            return NOTHING
        out: list[Outgoing] = []
        if mtype == "WHEEL_DISTANCE":
            out += self._handle_wheels(msg, now_s)
        elif mtype == "ATTITUDE":
            out += self._handle_gyro("attitude", msg.time_boot_ms * 1e-3, float(msg.yawspeed), now_s)
        elif mtype == "SCALED_IMU":
            out += self._handle_gyro("scaled_imu", msg.time_boot_ms * 1e-3, msg.zgyro * 1e-3, now_s)
        elif mtype == "RAW_IMU":
            out += self._handle_gyro("raw_imu", msg.time_usec * 1e-6, msg.zgyro * 1e-3, now_s)
        elif mtype == "SYSTEM_TIME":
            self._handle_system_time(msg, now_s)
        elif mtype == "COMMAND_ACK":
            return self._handle_ack(msg, now_s)
        return Reaction(out=tuple(out)) if out else NOTHING

    def tick(self, now_s: float) -> list[Outgoing]:
        self._update_gyro_reads(now_s)  # a source that fell silent: read the others again
        out = self._pump_streams(now_s)
        out += self._check_rates(now_s)
        due = self._next_odom_s is None or now_s >= self._next_odom_s
        if self._have_wheels and self._odom_links and due:
            last = self._next_odom_s
            # Keep the grid; after a stall restart it instead of bursting the missed messages.
            base = now_s if last is None or now_s - last > self._odom_period_s else last
            self._next_odom_s = base + self._odom_period_s
            out += self._odometry(now_s)
        if self.ekf.calibrate and self._have_wheels:
            if self._next_cal_report_s is None:
                self._next_cal_report_s = now_s + CAL_REPORT_INTERVAL_S
            elif now_s >= self._next_cal_report_s:
                self._next_cal_report_s = now_s + CAL_REPORT_INTERVAL_S
                out += self._calibration_report(now_s)
        return out

    def next_deadline_s(self, now_s: float) -> float:
        deadlines = [now_s + 1.0]
        if self._have_wheels and self._odom_links:
            deadlines.append(now_s if self._next_odom_s is None else self._next_odom_s)
        # Mirrors _pump_streams: one request outstanding at a time, so a queued stream waits for the
        # pending ACK's timeout, not "now" (which would spin the loop until the ACK came).
        pending = next((s for s in self._streams if s.state == "awaiting_ack"), None)
        if pending is not None:
            deadlines.append(pending.sent_s + STREAM_ACK_TIMEOUT_S)
        elif any(s.state == "queued" for s in self._streams):
            deadlines.append(now_s)
        for s in self._streams:
            if s.window_start_s is not None:
                deadlines.append(s.window_start_s + RATE_WINDOW_S)
        if self._next_cal_report_s is not None:
            deadlines.append(self._next_cal_report_s)
        return min(deadlines)

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Nothing to stop: the estimate flow sends no commands that persist."""
        return []

    # ------------------------------------------------------------------ pose resets
    def reset_pose(self, pose: Pose2D, now_s: float) -> list[Outgoing]:
        """Put the estimate (and the raw wheel odometry) at `pose` (x forward, y left, yaw CCW)."""
        self.ekf.set_pose(pose)
        self.raw_pose = Pose2D(pose.x_m, pose.y_m, wrap_angle(pose.yaw_rad))
        self.reset_counter = (self.reset_counter + 1) % 256
        self._counters["pose_resets"] += 1
        return self.reporter.statustext(
            mavlink.MAV_SEVERITY_INFO,
            f"pose reset x {pose.x_m:.2f} y {frames.y_frd_from_y_flu(pose.y_m):.2f} "
            f"yaw {math.degrees(frames.yaw_frd_from_yaw_flu(pose.yaw_rad)):.1f}",
            now_s,
            key="pose reset",
        )

    def _handle_command(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        if (
            msg.command != POSE_RESET_COMMAND
            or msg.target_component != self.identity.component_id
            or msg.target_system != self.identity.own_system_id
        ):
            return NOTHING
        current = self.ekf.pose
        # FRD in the command (x forward, y right, yaw clockwise in degrees); NaN keeps the coordinate.
        x_m = current.x_m if math.isnan(msg.param1) else float(msg.param1)
        y_m = current.y_m if math.isnan(msg.param2) else frames.y_frd_from_y_flu(float(msg.param2))
        yaw = (
            current.yaw_rad
            if math.isnan(msg.param3)
            else frames.yaw_frd_from_yaw_flu(math.radians(float(msg.param3)))
        )
        in_range = (abs(x_m) <= POSE_RESET_MAX_M and abs(y_m) <= POSE_RESET_MAX_M
                    and (math.isnan(msg.param3) or abs(float(msg.param3)) <= POSE_RESET_MAX_YAW_DEG))
        if not (all(math.isfinite(v) for v in (x_m, y_m, yaw)) and in_range):
            self._counters["pose_resets_denied"] += 1
            result = mavlink.MAV_RESULT_DENIED
            out: list[Outgoing] = []
        else:
            result = mavlink.MAV_RESULT_ACCEPTED
            out = self.reset_pose(Pose2D(x_m, y_m, yaw), now_s)
        ack = mavlink.MAVLink_command_ack_message(
            command=msg.command,
            result=result,
            progress=0,
            result_param2=0,
            target_system=msg.get_srcSystem(),
            target_component=msg.get_srcComponent(),
        )
        out.insert(0, Outgoing(inc.link, ack, self.identity.own_system_id, self.identity.component_id))
        return Reaction(consumed=True, out=tuple(out))

    # ------------------------------------------------------------------ inputs
    def _handle_heartbeat(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        if not self.identity.is_autopilot_heartbeat(msg):
            return []
        gap = self._last_hb_s is None or now_s - self._last_hb_s > HEARTBEAT_GAP_S
        self._last_hb_s = now_s
        if gap:
            self._restart_streams(now_s)
            return self._pump_streams(now_s)
        return []

    def _handle_system_time(self, msg: MAVLinkMessage, now_s: float) -> None:
        # The same least-latency mapping as the sensor stamps (re-learnt when the boot clock restarts).
        self._stamp(msg.time_boot_ms * 1e-3, now_s)

    def _handle_gyro(
        self, source: str, stamp_s: float, yaw_rate_cw_rad_s: float, now_s: float
    ) -> list[Outgoing]:
        self._gyro_last_seen[source] = now_s
        if not self._gyro_source_ok(source, now_s):
            return []
        omega = frames.omega_from_mavlink_yaw_rate(yaw_rate_cw_rad_s)
        self._stream_arrival(source.upper(), now_s)
        if not (math.isfinite(omega) and abs(omega) <= GYRO_MAX_RAD_S):
            # Poison (NaN, inf, 3e38) never reaches the filter, nor the stream's clock.
            self._counters["gyro_rejected"] += 1
            return []
        t = self._stamp(stamp_s, now_s)
        self._after_silence(t)
        last_stamp_s = self._gyro_last_t.get(source)
        if last_stamp_s is not None and last_stamp_s - REORDER_WINDOW_S <= stamp_s <= last_stamp_s:
            # Reordered or duplicated (UDP), judged on the sender's own stamps (further back is a reboot):
            # fusing it as the newest rate would also make the EKF's trapezoid yaw correction count the
            # interval since that old stamp twice. Drop, as WheelInput does for wheels.
            self._counters["gyro_stale"] += 1
            return []
        self._gyro_last_t[source] = stamp_s
        self._counters["gyro_samples"] += 1
        if not self.ekf.update_gyro(t, omega):
            self._counters["gyro_rejected"] += 1
            return self.reporter.statustext(
                mavlink.MAV_SEVERITY_WARNING, "gyro sample rejected by gate", now_s, key="gyro gate"
            )
        self._gyro_window.append(omega)
        self._gyro_last = (now_s, omega)
        return []

    def _stamp(self, stamp_s: float, now_s: float) -> float:
        """The filter time of a measurement: its own autopilot stamp. A restarted boot clock (stamps
        jumping back: a reboot) restarts the filter's clock from the pose published last."""
        published_t = self._autopilot_time_s(now_s)
        if self._ap_clock.map(stamp_s, now_s) and self.ekf.time_s is not None:
            self.ekf.restart_motion(published_t, new_time_s=stamp_s)
        return stamp_s

    def _after_silence(self, t: float) -> None:
        """First measurement after every sensor was silent: continue from the pose published meanwhile.

        ODOMETRY held the pose EXTRAPOLATE_MAX_S after the last measurement; predicting through the
        silence at the old speed now would jump it (a rebooting autopilot's motors stopped). Wheel
        distances, being cumulative, still move it the real distance when they come back.
        """
        if self.ekf.time_s is not None and t - self.ekf.time_s > SILENCE_S:
            self.ekf.restart_motion(t)

    def _gyro_source_ok(self, source: str, now_s: float) -> bool:
        if self.profile.estimator.gyro_source != "auto":
            return source == self._gyro_source
        current = self._gyro_source
        if current == source:
            return True
        rank = GYRO_PRIORITY.index
        silent = current is None or now_s - self._gyro_last_seen.get(current, -math.inf) > GYRO_SILENT_S
        if current is None or rank(source) < rank(current) or silent:
            if current is not None:
                self._counters["gyro_switches"] += 1
                log.info("gyro source %s -> %s", current, source)
            self._gyro_source = source
            self._update_gyro_reads(now_s)
            return True
        return False

    def _handle_wheels(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        step = self.wheels.ingest(int(msg.time_usec), int(msg.count), list(msg.distance))
        self._stream_arrival("WHEEL_DISTANCE", now_s)
        out: list[Outgoing] = []
        kind = step.kind
        if kind in (StepKind.BASELINE, StepKind.REBOOT, StepKind.RESYNC):
            published_t = self._autopilot_time_s(now_s)  # before a restarted clock re-learns its offset
            t = self._stamp(step.stamp_s, now_s)
            if kind is StepKind.REBOOT and self.ekf.time_s is not None:
                # Continue from the pose published last (no jump), on the restarted boot clock; the
                # silence is not dead-reckoned.
                self.ekf.restart_motion(published_t, new_time_s=t)
            self.ekf.predict_to(t)
            self.ekf.wheel_baseline()
            self._have_wheels = True
            self._gyro_window.clear()
            if kind is StepKind.REBOOT:
                self.reset_counter = (self.reset_counter + 1) % 256
                self._counters["reboots"] += 1
                self._restart_streams(now_s)
                out += self.reporter.statustext(
                    mavlink.MAV_SEVERITY_WARNING,
                    f"autopilot reboot: odometry re-based ({step.reason})"[:50],
                    now_s,
                    key="reboot",
                )
                out += self._pump_streams(now_s)
            return out
        if kind is StepKind.SPIKE:
            return self.reporter.statustext(
                mavlink.MAV_SEVERITY_WARNING, "wheel distance spike rejected", now_s, key="wheel spike"
            )
        if kind is not StepKind.STEP:
            return out
        t = self._stamp(step.stamp_s, now_s)
        self._after_silence(t)
        gyro_mean: float | None = None
        window = self._gyro_window
        gyro_spread = 0.0
        fresh = self._gyro_last is not None and now_s - self._gyro_last[0] <= GYRO_FOR_SLIP_MAX_AGE_S
        if window and fresh:
            gyro_mean = sum(window) / len(window)
            gyro_spread = 0.5 * (max(window) - min(window))
        self._gyro_window = window[-1:]  # the last sample also bounds the next interval
        ds = 0.5 * (step.d_left_m + step.d_right_m)
        self.raw_pose = arc_step(self.raw_pose, ds, (step.d_right_m - step.d_left_m) / self.track_width_m)
        res = self.ekf.update_wheels(t, step.d_left_m, step.d_right_m, step.dt_s, gyro_mean, gyro_spread)
        if res.stationary:
            self._counters["wheel_stationary"] += 1
        if not res.accepted:
            self._counters["wheel_rejected"] += 1
        else:
            self._last_wheel_fused_s = now_s
        # One interval can disagree when omega changes between the gyro's samples; slip lasts longer.
        self._slip_in_row = self._slip_in_row + 1 if res.slip else 0
        if self._slip_in_row >= SLIP_MIN_INTERVALS:
            self._counters["wheel_slip"] += 1
            if now_s - self._last_slip_report_s >= SLIP_REPORT_INTERVAL_S:
                self._last_slip_report_s = now_s
                out += self.reporter.statustext(
                    mavlink.MAV_SEVERITY_WARNING, "wheel slip", now_s, key="wheel slip"
                )
        return out

    # ------------------------------------------------------------------ streams
    def _restart_streams(self, now_s: float) -> None:
        if now_s - self._last_restart_s < STREAM_RESTART_HOLDOFF_S:
            return
        self._last_restart_s = now_s
        self._counters["stream_restarts"] += 1
        for s in self._streams:
            s.state, s.attempts, s.window_start_s, s.arrivals = "queued", 0, None, 0

    def _target(self) -> tuple[int, int]:
        return self.identity.vehicle_system_id or 1, self.identity.autopilot_component_id

    def _to_autopilot(self, msg: MAVLinkMessage) -> Outgoing:
        return Outgoing(Link.AUTOPILOT, msg, self.identity.own_system_id, self.identity.component_id)

    def _pump_streams(self, now_s: float) -> list[Outgoing]:
        """Send the next SET_MESSAGE_INTERVAL (one outstanding at a time); handle ACK timeouts."""
        out: list[Outgoing] = []
        for s in self._streams:
            if s.state == "awaiting_ack":
                if now_s < s.sent_s + STREAM_ACK_TIMEOUT_S:  # the form next_deadline_s uses (float rounding)
                    return out
                if s.attempts >= STREAM_ACK_ATTEMPTS:
                    out += self._fallback(s, now_s)
                    continue
                out.append(self._interval_request(s, now_s))
                return out
        for s in self._streams:
            if s.state == "queued":
                out.append(self._interval_request(s, now_s))
                return out
        return out

    def _interval_request(self, s: _Stream, now_s: float) -> Outgoing:
        s.state, s.sent_s = "awaiting_ack", now_s
        s.attempts += 1
        self._counters["stream_requests"] += 1
        sysid, compid = self._target()
        interval_us = 1e6 / self.profile.estimator.stream_rate_hz
        msg = mavlink.MAVLink_command_long_message(
            target_system=sysid,
            target_component=compid,
            command=mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            confirmation=s.attempts - 1,
            param1=float(s.msg_id),
            param2=float(interval_us),
            param3=0.0,
            param4=0.0,
            param5=0.0,
            param6=0.0,
            param7=0.0,
        )
        return self._to_autopilot(msg)

    def _fallback(self, s: _Stream, now_s: float) -> list[Outgoing]:
        s.state = "requested"
        s.window_start_s, s.arrivals = now_s + RATE_GRACE_S, 0
        self._counters["stream_fallbacks"] += 1
        return [self._data_stream_request(s.group)]

    def _data_stream_request(self, group: int) -> Outgoing:
        sysid, compid = self._target()
        rate = max(1, round(self.profile.estimator.stream_rate_hz))
        msg = mavlink.MAVLink_request_data_stream_message(
            target_system=sysid,
            target_component=compid,
            req_stream_id=group,
            req_message_rate=rate,
            start_stop=1,
        )
        return self._to_autopilot(msg)

    def _handle_ack(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        if msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return NOTHING
        if getattr(msg, "target_component", 0) not in (0, self.identity.component_id):
            return NOTHING  # someone else's request
        pending = next((s for s in self._streams if s.state == "awaiting_ack"), None)
        if pending is None:
            return NOTHING
        out: list[Outgoing] = []
        if msg.result == mavlink.MAV_RESULT_ACCEPTED:
            pending.state = "requested"
            pending.window_start_s, pending.arrivals = now_s + RATE_GRACE_S, 0
        elif msg.result in ACK_FAILURES:
            out += self._fallback(pending, now_s)
        else:  # TEMPORARILY_REJECTED, IN_PROGRESS: ask again after the timeout
            return Reaction(consumed=True)
        out += self._pump_streams(now_s)
        return Reaction(consumed=True, out=tuple(out))

    def _stream_arrival(self, name: str, now_s: float) -> None:
        for s in self._streams:
            if s.name == name and s.window_start_s is not None and now_s > s.window_start_s:
                s.arrivals += 1

    def _check_rates(self, now_s: float) -> list[Outgoing]:
        out: list[Outgoing] = []
        wanted = self.profile.estimator.stream_rate_hz
        for s in self._streams:
            if s.window_start_s is None or now_s < s.window_start_s + RATE_WINDOW_S:
                continue
            hz = s.arrivals / (now_s - s.window_start_s)
            s.measured_hz = hz
            s.window_start_s, s.arrivals = now_s, 0
            if hz >= SLOW_FRACTION * wanted:
                continue
            self._counters["stream_slow"] += 1
            out.append(self._data_stream_request(s.group))  # ask again: a GCS may have lowered the group
            if now_s - s.last_slow_report_s >= SLOW_REPORT_INTERVAL_S:
                s.last_slow_report_s = now_s
                out += self.reporter.statustext(
                    mavlink.MAV_SEVERITY_WARNING,
                    f"{s.name} {hz:.1f} Hz, need {SLOW_FRACTION * wanted:.0f}",
                    now_s,
                    key=f"slow {s.name}",
                )
        return out

    # ------------------------------------------------------------------ output
    def odometry_time_usec(self, now_s: float) -> int:
        """now_s on the autopilot's boot clock, through the same mapping as every measurement (so pose
        and stamp agree even when the autopilot's clock runs off ours); now_s itself (monotonic) until
        the first autopilot stamp arrives."""
        return max(0, round(self._autopilot_time_s(now_s) * 1e6))

    def _autopilot_time_s(self, now_s: float) -> float:
        offset = self._ap_clock.offset_s
        return now_s if offset is None else now_s - offset

    def odometry_message(self, now_s: float) -> MAVLinkMessage:
        """ODOMETRY for the estimate extrapolated to now_s (see the module docstring for every field)."""
        x, P = self.ekf.extrapolate(self._autopilot_time_s(now_s))
        big = self.profile.odometry.unobserved_variance
        v, w = float(x[IV]), float(x[IW])
        pose_flu = [[0.0] * 6 for _ in range(6)]
        vel_flu = [[0.0] * 6 for _ in range(6)]
        for a, ia in ((0, IX), (1, IY), (5, IYAW)):
            for b, ib in ((0, IX), (1, IY), (5, IYAW)):
                pose_flu[a][b] = float(P[ia, ib])
        for a, ia in ((0, IV), (5, IW)):
            for b, ib in ((0, IV), (5, IW)):
                vel_flu[a][b] = float(P[ia, ib])
        for k in (2, 3, 4):
            pose_flu[k][k] = vel_flu[k][k] = big
        vel_flu[1][1] = (
            LATERAL_SIGMA_M_S + LATERAL_SIGMA_PER_M_S * abs(v) + LATERAL_SIGMA_PER_RAD_S * abs(w)
        ) ** 2
        pose_cov = upper_triangle_21(frames.covariance_frd_from_flu(pose_flu))
        vel_cov = upper_triangle_21(frames.covariance_frd_from_flu(vel_flu))
        yaw_frd = frames.yaw_frd_from_yaw_flu(float(x[IYAW]))
        return mavlink.MAVLink_odometry_message(
            time_usec=self.odometry_time_usec(now_s),
            frame_id=mavlink.MAV_FRAME_LOCAL_FRD,
            child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
            x=float(x[IX]),
            y=frames.y_frd_from_y_flu(float(x[IY])),
            z=0.0,
            q=list(frames.quaternion_from_yaw(yaw_frd)),
            vx=v,
            vy=0.0,
            vz=0.0,
            rollspeed=0.0,
            pitchspeed=0.0,
            yawspeed=frames.mavlink_yaw_rate_from_omega(w),
            pose_covariance=pose_cov,
            velocity_covariance=vel_cov,
            reset_counter=self.reset_counter,
            estimator_type=mavlink.MAV_ESTIMATOR_TYPE_UNKNOWN,
            quality=self._quality(P, now_s),
        )

    def _quality(self, P: np.ndarray, now_s: float) -> int:
        if self._last_wheel_fused_s is None or now_s - self._last_wheel_fused_s > WHEELS_STALE_S:
            return 0
        sigma_yaw = math.sqrt(max(0.0, float(P[IYAW, IYAW])))
        q = 100.0 / (1.0 + _sigma_xy(P) / QUALITY_POS_M + sigma_yaw / QUALITY_YAW_RAD)
        return max(1, min(100, round(q)))

    def _odometry(self, now_s: float) -> list[Outgoing]:
        msg = self.odometry_message(now_s)
        self._counters["odometry_sent"] += 1
        return [
            Outgoing(link, msg, self.identity.own_system_id, self.identity.component_id)
            for link in self._odom_links
        ]

    def _calibration_report(self, now_s: float) -> list[Outgoing]:
        st = self.state
        log.info(
            "calibration: track_width_m %.4f left_radius_m %.5f right_radius_m %.5f",
            st.track_width_m,
            st.left_radius_m,
            st.right_radius_m,
        )
        return self.reporter.statustext(
            mavlink.MAV_SEVERITY_INFO,
            f"cal track {st.track_width_m:.4f} r {st.left_radius_m:.4f}/{st.right_radius_m:.4f}",
            now_s,
            key="calibration",
        )


def _sigma_xy(P: np.ndarray) -> float:
    """Larger principal standard deviation of the x, y block (closed form for a 2x2)."""
    a, b, c = float(P[IX, IX]), float(P[IX, IY]), float(P[IY, IY])
    half_tr = 0.5 * (a + c)
    lam = half_tr + math.sqrt(max(0.0, 0.25 * (a - c) ** 2 + b * b))
    return math.sqrt(max(0.0, lam))
