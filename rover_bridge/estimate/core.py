"""The estimate flow's core (pure): autopilot telemetry + time in, ODOMETRY and requests out.

It only wires small collaborators together, each a pure class with time as an argument:

- wheel_input.WheelInput: WHEEL_DISTANCE (9000) -> checked increments (indices, signs, reboots, spikes);
- gyro.GyroSelector: which of ATTITUDE / SCALED_IMU / RAW_IMU is the yaw rate, and which samples are new;
- clock.AutopilotClock: every measurement is applied at its own autopilot stamp, never at its arrival
  time; only publishing maps now_s onto the autopilot's boot clock;
- ekf.WheelGyroEKF: the filter;
- streams.StreamRequests: asks the autopilot for WHEEL_DISTANCE and the gyro, with fallbacks;
- resets.ResetCounter: pose resets (MAV_CMD_USER_1) and reboots, as ODOMETRY.reset_counter;
- reports.SlipMonitor / CalibrationReports: what the GCS is told about slip and calibration;
- anchor.FrameAnchor: the frame ODOMETRY is in (the start pose's, or the autopilot's own, decided
  before the first ODOMETRY so that a restarted bridge continues the autopilot's frame);
- publish.OdometryPublisher: ODOMETRY at [odometry] rate_hz to [odometry] targets.

Inputs are read, never consumed (the shell still forwards them to the ground stations), except
the COMMAND_ACKs of our own stream requests and the pose-reset command addressed to the bridge.
MAVLink yaw rates are clockwise positive; frames.omega_from_mavlink_yaw_rate converts.

Time: ODOMETRY is extrapolated to now (at most EXTRAPOLATE_MAX_S past the last measurement: during a
silent link it holds; after SILENCE_S of total silence the next measurement continues from the held
pose with the speeds restarted, see _after_silence). Its time_usec is now on the autopilot's boot
clock, through WHEEL_DISTANCE.time_usec preferably (the same mapping as every measurement, so the
stamp is the time of the published pose even when the autopilot's clock drifts from ours), before
wheel data through SYSTEM_TIME.time_boot_ms; with neither, now_s (monotonic) in us. TIMESYNC is
not used (it needs a round trip); ArduPilot re-times external navigation with its own jitter filter
either way. Stamps jumping back (a reboot) restart the filter's clock from the pose published last.

Deferred fusion (`defer_fusion`, on in the running bridge): what a gyro sample or a wheel reading does to
the filter is queued, in arrival order with its own stamps and arrival times, and run when anything reads
the filter (`ekf` and every accessor go through it: ODOMETRY, navigation, a pose reset, LOCAL_POSITION_NED,
the counters) or FUSE_MAX_DELAY_S after the oldest queued one. The filter then computes exactly what it
computes eagerly (tested bit for bit); it costs less because 50 Hz of sensor cycles are fused back to back
in ODOMETRY's 30 Hz passes, where the filter's code is warm, instead of cold in every request's pass. What
does not wait: the bookkeeping of every message (clock, streams, stale samples, wheel steps and spikes) and
the measured wheel speeds the command flow's speed loop reads (take_wheel_sample). What waits: the gate's
verdicts and their STATUSTEXT, and the slip verdict (the command flow's slip compensation sees it at most
FUSE_MAX_DELAY_S, in practice one ODOMETRY period, later).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rover_bridge import frames
from rover_bridge.estimate.anchor import FrameAnchor
from rover_bridge.estimate.clock import JUMP, REBOOT, AutopilotClock
from rover_bridge.estimate.diagnostics import CalibrationReports, SlipMonitor
from rover_bridge.estimate.ekf import IB, IV, IW, IX, IY, IYAW, PUBLISHED, NoiseModel, WheelGyroEKF
from rover_bridge.estimate.gyro import ALL_GYRO_IDS, GYRO_MESSAGES, GyroSelector
from rover_bridge.estimate.publish import OdometryPublisher, quality, sigma_xy
from rover_bridge.estimate.resets import POSE_RESET_COMMAND, ResetCounter, requested_pose
from rover_bridge.estimate.streams import Stream, StreamRequests
from rover_bridge.estimate.wheel_input import StepKind, WheelInput
from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.odometry import Pose2D, arc_step, wrap_angle
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.estimate.core")

WHEEL_DISTANCE_ID = 9000
LOCAL_POSITION_RATE_HZ = 2.0  # LOCAL_POSITION_NED (to anchor ODOMETRY) and GLOBAL_POSITION_INT (targets)
FIX_HISTORY = 120  # LOCAL_POSITION_NED fixes kept with our pose (a minute at 2 Hz)
POSE_HISTORY = 256  # filter poses kept (anchoring, targets tied to a fix): a few seconds at the sensors' rates
SILENCE_S = 0.5  # no measurement at all for this long: the next one restarts the motion (see _after_silence)
GYRO_MAX_RAD_S = 50.0  # beyond any rover: such a "rate" is corrupt data, not a measurement
GYRO_FOR_SLIP_MAX_AGE_S = 0.25
GYRO_WINDOW_MAX = 64  # gyro samples kept between two wheel steps (the slip test's window)
WHEELS_STALE_S = 1.0
# Deferred fusion (see the module docstring): the longest a queued measurement waits for a reader.
FUSE_MAX_DELAY_S = 0.05


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


@dataclass(frozen=True, slots=True)
class CalibrationEstimate:
    """The filter's geometry against the profile's (WheelGyroEKF.calibration()), 1 sigma each; without
    estimator.calibrate the nominal values and their prior sigma (`estimated` False)."""

    track_scale: float  # effective track width / the profile's
    track_scale_sigma: float
    radius_ratio: float  # effective right wheel scale / left, relative to the profile's radii
    radius_ratio_sigma: float
    estimated: bool


class EstimateCore:
    """Wheel odometry + gyro EKF -> ODOMETRY; stream requests; pose resets. See the module docstring."""

    # What handle() may read from the autopilot link (BridgeCore decodes nothing else from it); of the
    # gyro messages only those `gyro_reads` names at the time.
    AUTOPILOT_READS = frozenset({"COMMAND_LONG", "HEARTBEAT", "WHEEL_DISTANCE", "ATTITUDE", "SCALED_IMU", "RAW_IMU",
                                 "SYSTEM_TIME", "COMMAND_ACK", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"})
    ALL_GYRO_IDS = ALL_GYRO_IDS

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
        self._ekf = WheelGyroEKF(robot.track_width_m, self.noise, calibrate=est.calibrate)
        # Deferred fusion: the filter's work of each measurement, queued (fn, args) in arrival order; the
        # arrival time of the oldest; what running the queue said (handed out by the next handle or tick).
        self.defer_fusion = False
        self._deferred: list[tuple[Callable[..., list[Outgoing] | None], tuple[Any, ...]]] = []
        self._deferred_since_s = 0.0
        self._fused_out: list[Outgoing] = []
        self.wheels = WheelInput(profile.encoders, robot)
        self.gyro = GyroSelector(est)
        self.clock = AutopilotClock()
        self.resets = ResetCounter(reporter)
        self.slip = SlipMonitor(reporter)
        self.calibration_reports = CalibrationReports(reporter, est.calibrate)
        self.publisher = OdometryPublisher(profile.odometry)
        self.frame = FrameAnchor(profile.odometry, reporter)
        gyro_name = self.gyro.request_name
        streams = [Stream("WHEEL_DISTANCE", WHEEL_DISTANCE_ID, mavlink.MAV_DATA_STREAM_EXTRA1),
                   Stream(gyro_name.upper(), *GYRO_MESSAGES[gyro_name])]
        # The autopilot's position: anchoring ODOMETRY in its frame (asked for at once: the first ODOMETRY
        # waits for it), and tying position targets to it (local frame, GPS; rover_bridge.command.navigation:
        # asked for only if no one else has, see streams). None before a fix (a cold start): no rate check.
        for name in ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"):
            at_once = name == "LOCAL_POSITION_NED" and self.frame.enabled
            streams.append(Stream(name, getattr(mavlink, f"MAVLINK_MSG_ID_{name}"), mavlink.MAV_DATA_STREAM_POSITION,
                                  rate_hz=LOCAL_POSITION_RATE_HZ, check_rate=False, if_missing=not at_once))
        self.streams = StreamRequests(streams, est.stream_rate_hz, identity, reporter)
        self.raw_pose = Pose2D()
        self._jumps_said: set[str] = set()
        self._counters: dict[str, int] = {
            "clock_jumps": 0,
            "gyro_samples": 0,
            "gyro_rejected": 0,
            "gyro_stale": 0,
            "wheel_rejected": 0,
            "wheel_stationary": 0,
        }
        # Gyro samples since the last wheel step (with the one before it), for the slip test.
        self._gyro_window: list[float] = []
        self._gyro_last: tuple[float, float] | None = None  # (now_s, omega)
        self._have_wheels = False
        self._last_wheel_fused_s: float | None = None
        self._recent: deque[tuple[float, Pose2D]] = deque(maxlen=POSE_HISTORY)  # (filter time, pose)
        self._wheel_sample: MeasuredWheels | None = None
        # What navigation reads (rover_bridge.command.navigation.PoseSource), each with its autopilot stamp.
        self._heading: tuple[float, float] | None = None  # (stamp, ATTITUDE yaw clockwise from north)
        # LOCAL_POSITION_NED fixes beside the estimate's pose at their stamps (stamp, x, y, yaw, north, east):
        # the autopilot's frame against ours, fitted over the track (rover_bridge.command.navigation).
        self._fixes: deque[tuple[float, float, float, float, float, float]] = deque(maxlen=FIX_HISTORY)
        self._gps: tuple[float, float, float, float] | None = None  # (arrival, stamp, lat, lon)

    # ------------------------------------------------------------------ deferred fusion
    @property
    def ekf(self) -> WheelGyroEKF:
        """The filter, with every queued measurement fused: what anything outside the queue reads."""
        self.fuse_deferred()
        return self._ekf

    @property
    def fusion_pending(self) -> int:
        """How many measurements' filter work is queued (deferred fusion)."""
        return len(self._deferred)

    def fuse_deferred(self) -> None:
        """Run the queued measurements' filter work, oldest first (nothing if none); what they said waits
        for the next handle or tick to hand it out."""
        if not self._deferred:
            return
        ops, self._deferred = self._deferred, []
        for fn, args in ops:
            said = fn(*args)
            if said:
                self._fused_out += said

    def _fuse(self, now_s: float, fn: Callable[..., list[Outgoing] | None], *args: Any) -> list[Outgoing]:
        """fn(*args) now (what it said), or queued when fusion is deferred."""
        if self.defer_fusion:
            if not self._deferred:
                self._deferred_since_s = now_s
            self._deferred.append((fn, args))
            return []
        return fn(*args) or []

    def _with_fused(self, out: list[Outgoing]) -> list[Outgoing]:
        """What the queue said since it was last handed out, then out."""
        if not self._fused_out:
            return out
        said, self._fused_out = self._fused_out, []
        return said + out

    # ------------------------------------------------------------------ accessors
    @property
    def counters(self) -> Mapping[str, int]:
        self.fuse_deferred()
        out = dict(self._counters)
        out["gyro_switches"] = self.gyro.switches
        out["wheel_slip"] = self.slip.count
        out["odometry_sent"] = self.publisher.sent
        out.update(self.resets.counters)
        out.update(self.streams.counters)
        out.update(self.wheels.counters)
        return out

    @property
    def last_gyro(self) -> tuple[float, float] | None:
        """(arrival time, yaw rate CCW rad/s, bias not removed) of the newest fused gyro sample."""
        self.fuse_deferred()
        return self._gyro_last

    def take_wheel_sample(self) -> MeasuredWheels | None:
        """The wheel speeds of the newest checked WHEEL_DISTANCE interval, once (the command flow's loop)."""
        sample, self._wheel_sample = self._wheel_sample, None
        return sample

    @property
    def reset_counter(self) -> int:
        return self.resets.value

    @property
    def pose(self) -> Pose2D:
        """The filter's pose (x forward of the start pose, y left, yaw CCW) at its last measurement."""
        return self.ekf.pose

    def pose_at(self, now_s: float) -> Pose2D:
        """The pose extrapolated to now_s (what ODOMETRY publishes), x forward, y left, yaw CCW."""
        x, _ = self.ekf.extrapolate(self.clock.autopilot_time_s(now_s))
        return Pose2D(float(x[IX]), float(x[IY]), float(x[IYAW]))

    @property
    def gyro_source(self) -> str | None:
        return self.gyro.source

    @property
    def gyro_source_id(self) -> int | None:
        """Message id of the gyro source in use (None before the first sample under 'auto')."""
        return self.gyro.source_id

    @property
    def gyro_reads(self) -> frozenset[int]:
        """Message ids of the gyro sources worth decoding now (see rover_bridge.estimate.gyro)."""
        return self.gyro.reads

    @property
    def state(self) -> EstimateState:
        x, P = self.ekf.x, self.ekf.P  # noqa: N806 - a covariance
        kt, _, q, _ = self.ekf.calibration()
        robot = self.profile.robot
        sl, sr = 2.0 / (1.0 + q), 2.0 * q / (1.0 + q)
        return EstimateState(
            time_s=self.ekf.time_s,
            pose=self.ekf.pose,
            v_m_s=float(x[IV]),
            omega_rad_s=float(x[IW]),
            gyro_bias_rad_s=float(x[IB]),
            sigma_xy_m=sigma_xy(P),
            sigma_yaw_rad=math.sqrt(float(P[IYAW, IYAW])),
            raw_pose=self.raw_pose,
            track_width_m=self.track_width_m * kt,
            left_radius_m=robot.left_radius_m * sl,
            right_radius_m=robot.right_radius_m * sr,
            reset_counter=self.resets.value,
        )

    def calibration_estimate(self) -> CalibrationEstimate:
        """Track scale and radius ratio as the filter has them now, with their uncertainty."""
        kt, kt_sigma, q, q_sigma = self.ekf.calibration()
        return CalibrationEstimate(kt, kt_sigma, q, q_sigma, self.profile.estimator.calibrate)

    # ------------------------------------------------------------------ navigation (PoseSource)
    def nav_pose(self, now_s: float) -> Pose2D | None:
        """The pose now for following a target; None without wheel data fused in the last WHEELS_STALE_S."""
        self.fuse_deferred()
        fused = self._last_wheel_fused_s
        if fused is None or now_s - fused > WHEELS_STALE_S:
            return None
        return self.pose_at(now_s)

    def nav_pose_at(self, stamp_s: float) -> Pose2D:
        """The estimate's pose at an autopilot stamp (a fix's, a LOCAL_POSITION_NED's)."""
        return self._pose_at_stamp(stamp_s)

    def autopilot_time_s(self, now_s: float) -> float:
        return self.clock.autopilot_time_s(now_s)

    @property
    def heading(self) -> tuple[float, float] | None:
        return self._heading

    @property
    def position_fixes(self) -> Sequence[tuple[float, float, float, float, float, float]]:
        return self._fixes

    @property
    def gps(self) -> tuple[float, float, float, float] | None:
        return self._gps

    def _handle_global_position(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        lat, lon = int(msg.lat) * 1e-7, int(msg.lon) * 1e-7
        # ArduPilot sends GLOBAL_POSITION_INT before it has a position, with 0/0 in it: no fix.
        if (lat == 0.0 and lon == 0.0) or abs(lat) > 90.0 or abs(lon) > 180.0:
            return []
        t, out = self._stamp(msg.time_boot_ms * 1e-3, now_s, "GLOBAL_POSITION_INT")
        self.streams.arrival("GLOBAL_POSITION_INT", now_s)
        self._gps = (now_s, t, lat, lon)
        return out

    # ------------------------------------------------------------------ SubCore
    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        mtype = msg.get_type()
        if mtype == "COMMAND_LONG":
            return self._handle_command(inc, now_s)
        if inc.link is not Link.AUTOPILOT:
            return NOTHING
        vehicle = self.identity.vehicle_system_id
        if mtype == "HEARTBEAT":
            if not self.identity.is_autopilot_heartbeat(msg):
                return NOTHING
            return Reaction(out=tuple(self.streams.on_heartbeat(now_s)))
        if vehicle is not None and msg.get_srcSystem() != vehicle:
            return NOTHING
        out: list[Outgoing] = []
        if mtype == "WHEEL_DISTANCE":
            out += self._handle_wheels(msg, now_s)
        elif mtype == "ATTITUDE":
            t_att, yaw = self.clock.rebase(msg.time_boot_ms * 1e-3, "attitude"), float(msg.yaw)
            self.frame.on_attitude(t_att, yaw)
            if math.isfinite(yaw):
                self._heading = (t_att, yaw)
            out += self._handle_gyro("attitude", msg.time_boot_ms * 1e-3, float(msg.yawspeed), now_s)
        elif mtype == "LOCAL_POSITION_NED":
            t, said = self._stamp(msg.time_boot_ms * 1e-3, now_s, "LOCAL_POSITION_NED")
            out += said
            self.streams.arrival("LOCAL_POSITION_NED", now_s)
            self.frame.on_local_position(t, float(msg.x), float(msg.y))
            if self._have_wheels and math.isfinite(float(msg.x)) and math.isfinite(float(msg.y)):
                at = self._pose_at_stamp(t)
                self._fixes.append((t, at.x_m, at.y_m, at.yaw_rad, float(msg.x), float(msg.y)))
        elif mtype == "GLOBAL_POSITION_INT":
            out += self._handle_global_position(msg, now_s)
        elif mtype == "SCALED_IMU":
            out += self._handle_gyro("scaled_imu", msg.time_boot_ms * 1e-3, msg.zgyro * 1e-3, now_s)
        elif mtype == "RAW_IMU":
            out += self._handle_gyro("raw_imu", msg.time_usec * 1e-6, msg.zgyro * 1e-3, now_s)
        elif mtype == "SYSTEM_TIME":
            # The same least-latency mapping as the sensor stamps (re-learnt when the boot clock restarts).
            out += self._stamp(msg.time_boot_ms * 1e-3, now_s, "SYSTEM_TIME")[1]
        elif mtype == "COMMAND_ACK":
            return self.streams.handle_ack(msg, now_s)
        if self._deferred:
            self._deferred.append((self._remember_pose, ()))  # after this message's filter work
        else:
            self._remember_pose()
        if self._fused_out:
            out = self._with_fused(out)
        return Reaction(out=tuple(out)) if out else NOTHING

    def tick(self, now_s: float) -> list[Outgoing]:
        if self._deferred and now_s >= self._deferred_since_s + FUSE_MAX_DELAY_S:
            self.fuse_deferred()  # nothing read the filter for that long (no ODOMETRY): its verdicts must out
        self.gyro.update_reads(now_s)  # a source that fell silent: read the others again
        out = self.streams.pump(now_s)
        out += self.streams.check_rates(now_s)
        if not self.frame.ready:
            out += self.frame.decide(now_s, self._pose_at_stamp if self._have_wheels else None)
        out += self._publish(now_s, early=False)
        st = self.state if self.calibration_reports.enabled and self._have_wheels else None
        if st is not None:
            out += self.calibration_reports.tick(now_s, True, st.track_width_m, st.left_radius_m, st.right_radius_m)
        return self._with_fused(out)

    def next_deadline_s(self, now_s: float) -> float:
        # Runs on every turn of the loop: plain comparisons, no lists.
        first = min(now_s + 1.0, self.streams.next_deadline_s(now_s))
        odom = self.publisher.deadline_s(now_s) if self._have_wheels else None
        if odom is not None:
            # Held back until the frame is decided: look again when the wait for the autopilot ends.
            if not self.frame.ready:
                odom = max(odom, now_s + min(0.1, self.frame.timeout_s))
            if odom < first:
                first = odom
        cal = self.calibration_reports.next_s
        if cal is not None and cal < first:
            first = cal
        if self._deferred and self._deferred_since_s + FUSE_MAX_DELAY_S < first:
            first = self._deferred_since_s + FUSE_MAX_DELAY_S
        return first

    def odometry_due(self, now_s: float) -> list[Outgoing]:
        """ODOMETRY if one is due or may leave early (OdometryPublisher.due): what the shell calls in a
        pass it makes anyway once next_early_s has come. tick publishes only what is due."""
        return self._with_fused(self._publish(now_s, early=True))

    def _publish(self, now_s: float, early: bool) -> list[Outgoing]:
        if self._have_wheels and self.frame.ready and self.publisher.due(now_s, early):
            return self._odometry(now_s)
        return []

    def next_early_s(self, now_s: float) -> float | None:
        """From when odometry_due may publish in a pass made anyway (None: nothing to publish yet)."""
        if not (self._have_wheels and self.frame.ready):
            return None
        return self.publisher.early_deadline_s(now_s)

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Nothing to stop: the estimate flow sends no commands that persist (what the queue says still goes)."""
        self.fuse_deferred()
        return self._with_fused([])

    # ------------------------------------------------------------------ pose resets
    def reset_pose(self, pose: Pose2D, now_s: float) -> list[Outgoing]:
        """Put the estimate (and the raw wheel odometry) at `pose` (x forward, y left, yaw CCW)."""
        self.ekf.set_pose(pose)
        self._recent.clear()  # poses before the reset are in the old frame
        self._fixes.clear()
        self.raw_pose = Pose2D(pose.x_m, pose.y_m, wrap_angle(pose.yaw_rad))
        return self.resets.pose_reset(pose, now_s)

    def _handle_command(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        if (
            msg.command != POSE_RESET_COMMAND
            or msg.target_component != self.identity.component_id
            or msg.target_system != self.identity.own_system_id
        ):
            return NOTHING
        # In the published frame (the start frame, or the autopilot's once anchored), as ODOMETRY is.
        pose = requested_pose(msg, self.frame.published(self.ekf.pose))
        out: list[Outgoing] = []
        if pose is None:
            self.resets.denied()
            result = mavlink.MAV_RESULT_DENIED
        else:
            result = mavlink.MAV_RESULT_ACCEPTED
            out = self.reset_pose(self.frame.internal(pose), now_s)
        ack = mavlink.MAVLink_command_ack_message(
            command=msg.command, result=result, progress=0, result_param2=0,
            target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent())
        out.insert(0, Outgoing(inc.link, ack, self.identity.own_system_id, self.identity.component_id))
        return Reaction(consumed=True, out=tuple(out))

    # ------------------------------------------------------------------ inputs
    def _handle_gyro(
        self, source: str, stamp_s: float, yaw_rate_cw_rad_s: float, now_s: float
    ) -> list[Outgoing]:
        if not self.gyro.accept_source(source, now_s):
            return []
        omega = frames.omega_from_mavlink_yaw_rate(yaw_rate_cw_rad_s)
        self.streams.arrival(source.upper(), now_s)
        if not (math.isfinite(omega) and abs(omega) <= GYRO_MAX_RAD_S):
            # Poison (NaN, inf, 3e38) never reaches the filter, nor the stream's clock.
            self._counters["gyro_rejected"] += 1
            return []
        t, out = self._stamp(stamp_s, now_s, source.upper())
        if self.gyro.is_stale(source, t):
            # Fusing a reordered or duplicated sample as the newest rate would also make the EKF's
            # trapezoid yaw correction count the interval since that old stamp twice. Dropped, as
            # WheelInput does for wheels.
            self._counters["gyro_stale"] += 1
            return out + self._fuse(now_s, self._after_silence, t)
        self.gyro.fused(source, t)
        self._counters["gyro_samples"] += 1
        return out + self._fuse(now_s, self._fuse_gyro, t, omega, now_s)

    def _fuse_gyro(self, t: float, omega: float, now_s: float) -> list[Outgoing] | None:
        """A gyro sample's filter work (deferred fusion: see the module docstring)."""
        self._after_silence(t)
        if not self._ekf.update_gyro(t, omega):
            self._counters["gyro_rejected"] += 1
            return self.reporter.statustext(
                mavlink.MAV_SEVERITY_WARNING, "gyro sample rejected by gate", now_s, key="gyro gate"
            )
        if len(self._gyro_window) >= GYRO_WINDOW_MAX:  # no wheel step for a long while: keep the newest
            del self._gyro_window[: len(self._gyro_window) - GYRO_WINDOW_MAX + 1]
        self._gyro_window.append(omega)
        self._gyro_last = (now_s, omega)
        return None

    def _stamp(self, stamp_s: float, now_s: float, stream: str) -> tuple[float, list[Outgoing]]:
        """The filter time of a measurement: its own autopilot stamp, on the boot clock. A restarted
        boot clock (every stream jumping back: a reboot) restarts the filter's clock from the pose
        published last; one stream on another epoch is re-based (said once per stream)."""
        published_t = self.clock.autopilot_time_s(now_s)
        st = self.clock.observe(stamp_s, now_s, stream)
        out: list[Outgoing] = []
        if st.event == REBOOT:
            self._fuse(now_s, self._restart_after_reboot, published_t, st.t_s)
        elif st.event == JUMP:
            self._counters["clock_jumps"] += 1
            if stream not in self._jumps_said and len(self._jumps_said) < 16:
                self._jumps_said.add(stream)
                log.warning("%s stamps jumped %+.6g s (another epoch, or garbage): re-based onto the boot clock",
                            stream, st.jump_s)
                out = self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING,
                                               f"RB: {stream} clock jumped {st.jump_s:+.3g} s"[:50], now_s,
                                               key=f"clock jump {stream}")
        return st.t_s, out

    def _restart_after_reboot(self, published_t: float, t: float) -> None:
        """The boot clock restarted: the filter continues from the pose published last, on the new clock."""
        if self._ekf.time_s is not None:
            self._ekf.restart_motion(published_t, new_time_s=t)

    def _after_silence(self, t: float) -> None:
        """First measurement after every sensor was silent: continue from the pose published meanwhile.

        ODOMETRY held the pose EXTRAPOLATE_MAX_S after the last measurement; predicting through the
        silence at the old speed now would jump it (a rebooting autopilot's motors stopped). Wheel
        distances, being cumulative, still move it the real distance when they come back.
        """
        if self._ekf.time_s is not None and t - self._ekf.time_s > SILENCE_S:
            self._ekf.restart_motion(t)

    def _handle_wheels(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        published_t = self.clock.autopilot_time_s(now_s)  # before a restarted clock re-learns its offset
        t, out = self._stamp(int(msg.time_usec) * 1e-6, now_s, "WHEEL_DISTANCE")
        # Re-based stamps: a wheel stream that changed epochs goes on as one interval, not a 1.7e9 s one.
        step = self.wheels.ingest(round(t * 1e6), int(msg.count), list(msg.distance))
        self.streams.arrival("WHEEL_DISTANCE", now_s)
        kind = step.kind
        if kind in (StepKind.BASELINE, StepKind.REBOOT, StepKind.RESYNC):
            out += self._fuse(now_s, self._wheel_baseline, kind is StepKind.REBOOT, published_t, t)
            self._have_wheels = True
            if kind is StepKind.REBOOT:
                self.streams.restart(now_s)
                out += self.resets.reboot(step.reason, now_s)
                out += self.streams.pump(now_s)
            return out
        if kind is StepKind.SPIKE:
            return out + self.reporter.statustext(
                mavlink.MAV_SEVERITY_WARNING, "wheel distance spike rejected", now_s, key="wheel spike"
            )
        if kind is not StepKind.STEP:
            return out
        robot = self.profile.robot
        d_left_m, d_right_m, dt_s = step.d_left_m, step.d_right_m, step.dt_s
        # The command flow's speed loop reads these at once, whether or not fusion waits.
        self._wheel_sample = MeasuredWheels(t, WheelSpeeds(d_left_m / dt_s / robot.left_radius_m,
                                                           d_right_m / dt_s / robot.right_radius_m))
        ds = 0.5 * (d_left_m + d_right_m)
        self.raw_pose = arc_step(self.raw_pose, ds, (d_right_m - d_left_m) / self.track_width_m)
        return out + self._fuse(now_s, self._fuse_wheels, t, d_left_m, d_right_m, dt_s, now_s)

    def _wheel_baseline(self, reboot: bool, published_t: float, t: float) -> None:
        """A wheel reading that starts a new baseline (the first, a reboot, a resync): the filter's part."""
        if reboot:  # continue from the pose published last (no jump); the silence is not dead-reckoned
            self._restart_after_reboot(published_t, t)
        self._ekf.predict_to(t)
        self._ekf.wheel_baseline()
        self._gyro_window.clear()

    def _fuse_wheels(self, t: float, d_left_m: float, d_right_m: float, dt_s: float,
                     now_s: float) -> list[Outgoing]:
        """A wheel step's filter work (deferred fusion: see the module docstring), with the gyro samples
        fused since the last step as the slip test's window."""
        self._after_silence(t)
        gyro_mean: float | None = None
        window = self._gyro_window
        gyro_spread = 0.0
        fresh = self._gyro_last is not None and now_s - self._gyro_last[0] <= GYRO_FOR_SLIP_MAX_AGE_S
        if window and fresh:
            gyro_mean = sum(window) / len(window)
            gyro_spread = 0.5 * (max(window) - min(window))
        self._gyro_window = window[-1:]  # the last sample also bounds the next interval
        res = self._ekf.update_wheels(t, d_left_m, d_right_m, dt_s, gyro_mean, gyro_spread)
        if res.stationary:
            self._counters["wheel_stationary"] += 1
        if not res.accepted:
            self._counters["wheel_rejected"] += 1
        else:
            self._last_wheel_fused_s = now_s
        return self.slip.interval(res.slip, now_s)

    # ------------------------------------------------------------------ output
    def odometry_time_usec(self, now_s: float) -> int:
        """now_s on the autopilot's boot clock, through the same mapping as every measurement (so pose
        and stamp agree even when the autopilot's clock drifts from ours); now_s itself (monotonic) until
        the first autopilot stamp arrives."""
        return self.clock.time_usec(now_s)

    def odometry_message(self, now_s: float) -> MAVLinkMessage:
        """ODOMETRY for the estimate extrapolated to now_s (see rover_bridge.estimate.publish)."""
        x, P = self.ekf.extrapolate(self.clock.autopilot_time_s(now_s), PUBLISHED)  # noqa: N806 - a covariance
        fresh = self._last_wheel_fused_s is not None and now_s - self._last_wheel_fused_s <= WHEELS_STALE_S
        return self.publisher.message(x, P, self.clock.time_usec(now_s), self.resets.value, quality(P, fresh),
                                      self.frame.anchor)

    def _pose_at_stamp(self, stamp_s: float) -> Pose2D:
        """The estimate's pose at an autopilot stamp: extrapolated ahead of the filter's time, interpolated
        in the recent history behind it (a LOCAL_POSITION_NED half a second old on a moving rover)."""
        t = self.ekf.time_s
        if t is None or stamp_s >= t or not self._recent:
            x, _ = self.ekf.extrapolate(stamp_s)
            return Pose2D(float(x[IX]), float(x[IY]), float(x[IYAW]))
        recent = self._recent
        if stamp_s <= recent[0][0]:
            return recent[0][1]
        after = next(i for i, (ts, _) in enumerate(recent) if ts >= stamp_s)
        (t0, a), (t1, b) = recent[after - 1], recent[after]
        f = (stamp_s - t0) / (t1 - t0) if t1 > t0 else 1.0
        return Pose2D(a.x_m + f * (b.x_m - a.x_m), a.y_m + f * (b.y_m - a.y_m),
                      wrap_angle(a.yaw_rad + f * wrap_angle(b.yaw_rad - a.yaw_rad)))

    def _remember_pose(self) -> None:
        """The filter's pose at its time, for _pose_at_stamp (anchoring, targets tied to an older fix)."""
        ekf = self._ekf  # run in order after the queue's work (handle), never a reason to run it
        t = ekf.time_s
        if t is None:
            return
        if self._recent and t < self._recent[-1][0]:
            self._recent.clear()  # the filter's clock restarted (a reboot): older poses are another epoch
            self._fixes.clear()
        if not self._recent or t > self._recent[-1][0]:
            self._recent.append((t, ekf.pose))

    def _odometry(self, now_s: float) -> list[Outgoing]:
        msg = self.odometry_message(now_s)
        return [
            Outgoing(link, msg, self.identity.own_system_id, self.identity.component_id)
            for link in self.publisher.links
        ]
