"""The estimate flow's core (pure): autopilot telemetry + time in, ODOMETRY and requests out.

It only wires small collaborators together, each a pure class with time as an argument:

- wheel_input.WheelInput: WHEEL_DISTANCE (9000) -> checked increments (indices, signs, reboots, spikes);
- gyro.GyroSelector: which of ATTITUDE / SCALED_IMU / RAW_IMU is the yaw rate, and which samples are new;
- clock.AutopilotClock: every measurement is applied at its own autopilot stamp, never at its arrival
  time; only publishing maps now_s onto the autopilot's boot clock;
- fusion.Fusion: the filter (ekf.WheelGyroEKF, on filterpy) and what each measurement does to it,
  now or queued (deferred fusion, on in the running bridge), silences and reboots;
- streams.StreamRequests: asks the autopilot for WHEEL_DISTANCE and the gyro, with fallbacks;
- resets.ResetCounter: pose resets (MAV_CMD_USER_1) and reboots, as ODOMETRY.reset_counter;
- diagnostics.SlipMonitor / CalibrationReports: what the GCS is told about slip and calibration;
- anchor.FrameAnchor: the frame ODOMETRY is in (the start pose's, or the autopilot's own, decided
  before the first ODOMETRY so that a restarted bridge continues the autopilot's frame);
- publish.OdometryPublisher: ODOMETRY at [odometry] rate_hz to [odometry] targets.

Inputs are read, never consumed (the shell still forwards them to the ground stations), except
the COMMAND_ACKs of our own stream requests and the pose-reset command addressed to the bridge.
MAVLink yaw rates are clockwise positive; frames.omega_from_mavlink_yaw_rate converts.

Time: ODOMETRY is extrapolated to now (at most EXTRAPOLATE_MAX_S past the last measurement: during a
silent link it holds). Its time_usec is now on the autopilot's boot clock, through the same mapping
as every measurement (so the stamp is the time of the published pose even when the autopilot's clock
drifts from ours); before any autopilot stamp, now_s (monotonic) in us. TIMESYNC is not used (it
needs a round trip); ArduPilot re-times external navigation with its own jitter filter either way.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from rover_bridge.estimate.anchor import FrameAnchor
from rover_bridge.estimate.diagnostics import CalibrationReports, SlipMonitor
from rover_bridge.estimate.ekf import WheelGyroEKF
from rover_bridge.estimate.fusion import FUSE_MAX_DELAY_S, Fusion
from rover_bridge.estimate.gyro import ALL_GYRO_IDS, GYRO_MESSAGES, GyroSelector
from rover_bridge.estimate.inputs import Telemetry
from rover_bridge.estimate.models import IB, IV, IW, IYAW, PUBLISHED, NoiseModel
from rover_bridge.estimate.publish import OdometryPublisher, quality, sigma_xy
from rover_bridge.estimate.resets import POSE_RESET_COMMAND, ResetCounter, requested_pose
from rover_bridge.estimate.streams import Stream, StreamRequests
from rover_bridge.kinematics import MeasuredWheels
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Incoming, Link, Outgoing, Reaction
from rover_bridge.odometry import Pose2D, wrap_angle
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.estimate.core")

WHEEL_DISTANCE_ID = 9000
LOCAL_POSITION_RATE_HZ = 2.0  # LOCAL_POSITION_NED (to anchor ODOMETRY) and GLOBAL_POSITION_INT (targets)
GYRO_MAX_RAD_S = 50.0  # beyond any rover: such a "rate" is corrupt data, not a measurement
WHEELS_STALE_S = 1.0


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
    track_width_m: float  # effective track width, as the filter has learnt it
    left_radius_m: float  # effective radii (learnt ratio, mean kept at the profile's)
    right_radius_m: float
    reset_counter: int


@dataclass(frozen=True, slots=True)
class CalibrationEstimate:
    """The filter's geometry against the profile's (WheelGyroEKF.calibration()), 1 sigma each; without
    estimator.calibrate the nominal values with sigma 0, the profile's taken as exact (`estimated` False)."""

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
        self.track_width_m = profile.robot.track_width_m
        noise = NoiseModel(gyro_noise_rad_s=est.gyro_noise_rad_s, wheel_noise_m=est.wheel_noise_m,
                           wheel_noise_fraction=est.wheel_noise_fraction, gate_sigma=est.gate_sigma)
        self.slip = SlipMonitor(reporter)
        self.fusion = Fusion(self.track_width_m, noise, est.calibrate, self.slip, reporter)
        self.gyro = GyroSelector(est)
        self.resets = ResetCounter(reporter)
        self.calibration_reports = CalibrationReports(reporter, est.calibrate)
        self.publisher = OdometryPublisher(profile.odometry)
        self.frame = FrameAnchor(profile.odometry, reporter)
        streams = [Stream("WHEEL_DISTANCE", WHEEL_DISTANCE_ID, mavlink.MAV_DATA_STREAM_EXTRA1),
                   Stream(self.gyro.request_name.upper(), *GYRO_MESSAGES[self.gyro.request_name])]
        # The autopilot's position: anchoring ODOMETRY in its frame (asked for at once: the first ODOMETRY
        # waits for it), and tying position targets to it (local frame, GPS; rover_bridge.command.navigation:
        # asked for only if no one else has, see streams). None before a fix (a cold start): no rate check.
        for name in ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"):
            at_once = name == "LOCAL_POSITION_NED" and self.frame.enabled
            streams.append(Stream(name, getattr(mavlink, f"MAVLINK_MSG_ID_{name}"), mavlink.MAV_DATA_STREAM_POSITION,
                                  rate_hz=LOCAL_POSITION_RATE_HZ, check_rate=False, if_missing=not at_once))
        self.streams = StreamRequests(streams, est.stream_rate_hz, identity, reporter)
        self.telemetry = Telemetry(profile, reporter, self.fusion, self.streams, self.frame, self.resets, self.gyro)
        self.wheels = self.telemetry.wheels
        self.clock = self.telemetry.clock

    # ------------------------------------------------------------------ the filter (fusion.Fusion)
    @property
    def ekf(self) -> WheelGyroEKF:
        """The filter, with every queued measurement fused: what anything outside the queue reads."""
        return self.fusion.filter

    @property
    def defer_fusion(self) -> bool:
        return self.fusion.defer

    @defer_fusion.setter
    def defer_fusion(self, on: bool) -> None:
        self.fusion.defer = on

    @property
    def fusion_pending(self) -> int:
        """How many measurements' filter work is queued (deferred fusion)."""
        return self.fusion.pending

    def fuse_deferred(self) -> None:
        self.fusion.run()

    def start_filter(self) -> None:
        """Build the filter now (it imports filterpy and scipy, about 0.65 s; otherwise on first use)."""
        self.fusion.start()

    # ------------------------------------------------------------------ accessors
    @property
    def counters(self) -> Mapping[str, int]:
        self.fusion.run()
        out = dict(self.telemetry.counters)
        out.update(self.fusion.counters)
        out["gyro_rejected"] += out.pop("gyro_poison")
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
        self.fusion.run()
        return self.fusion.last_gyro

    def take_wheel_sample(self) -> MeasuredWheels | None:
        """The wheel speeds of the newest checked WHEEL_DISTANCE interval, once (the command flow's loop)."""
        sample, self.telemetry.wheel_sample = self.telemetry.wheel_sample, None
        return sample

    @property
    def raw_pose(self) -> Pose2D:
        """Plain wheel odometry (nominal geometry), for comparison."""
        return self.telemetry.raw_pose

    @property
    def reset_counter(self) -> int:
        return self.resets.value

    @property
    def pose(self) -> Pose2D:
        """The filter's pose (x forward of the start pose, y left, yaw CCW) at its last measurement."""
        return self.ekf.pose

    def pose_at(self, now_s: float) -> Pose2D:
        """The pose extrapolated to now_s (what ODOMETRY publishes), x forward, y left, yaw CCW."""
        return self.ekf.pose_at(self.clock.autopilot_time_s(now_s))

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
        ekf = self.ekf
        x, P = ekf.x, ekf.P  # noqa: N806 - a covariance
        kt, _, q, _ = ekf.calibration()
        robot = self.profile.robot
        return EstimateState(
            time_s=ekf.time_s, pose=ekf.pose, v_m_s=float(x[IV]), omega_rad_s=float(x[IW]),
            gyro_bias_rad_s=float(x[IB]), sigma_xy_m=sigma_xy(P), sigma_yaw_rad=math.sqrt(float(P[IYAW, IYAW])),
            raw_pose=self.raw_pose, track_width_m=self.track_width_m * kt,
            left_radius_m=robot.left_radius_m * 2.0 / (1.0 + q),
            right_radius_m=robot.right_radius_m * 2.0 * q / (1.0 + q),
            reset_counter=self.resets.value)

    def calibration_estimate(self) -> CalibrationEstimate:
        """Track scale and radius ratio as the filter has them now, with their uncertainty."""
        kt, kt_sigma, q, q_sigma = self.ekf.calibration()
        return CalibrationEstimate(kt, kt_sigma, q, q_sigma, self.profile.estimator.calibrate)

    # ------------------------------------------------------------------ navigation (PoseSource)
    def nav_pose(self, now_s: float) -> Pose2D | None:
        """The pose now for following a target; None without wheel data fused in the last WHEELS_STALE_S."""
        self.fusion.run()
        fused = self.fusion.last_wheel_fused_s
        if fused is None or now_s - fused > WHEELS_STALE_S:
            return None
        return self.pose_at(now_s)

    def nav_pose_at(self, stamp_s: float) -> Pose2D:
        """The estimate's pose at an autopilot stamp (a fix's, a LOCAL_POSITION_NED's)."""
        return self.fusion.pose_at_stamp(stamp_s)

    def autopilot_time_s(self, now_s: float) -> float:
        return self.clock.autopilot_time_s(now_s)

    @property
    def heading(self) -> tuple[float, float] | None:
        return self.telemetry.heading

    @property
    def position_fixes(self) -> Sequence[tuple[float, float, float, float, float, float]]:
        return self.fusion.fixes

    @property
    def gps(self) -> tuple[float, float, float, float] | None:
        return self.telemetry.gps

    # ------------------------------------------------------------------ SubCore
    def handle(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        mtype = msg.get_type()
        if mtype == "COMMAND_LONG":
            return self._handle_command(inc, now_s)
        if inc.link is not Link.AUTOPILOT:
            return NOTHING
        if mtype == "HEARTBEAT":
            if not self.identity.is_autopilot_heartbeat(msg):
                return NOTHING
            return Reaction(out=tuple(self.streams.on_heartbeat(now_s)))
        vehicle = self.identity.vehicle_system_id
        if vehicle is not None and msg.get_srcSystem() != vehicle:
            return NOTHING
        if mtype == "COMMAND_ACK":
            return self.streams.handle_ack(msg, now_s)
        out = self.telemetry.handle(msg, mtype, now_s)
        self.fusion.after_message()
        out = self.fusion.take_said(out)
        return Reaction(out=tuple(out)) if out else NOTHING

    def tick(self, now_s: float) -> list[Outgoing]:
        fusion = self.fusion
        if fusion.pending and now_s >= fusion.queued_since_s + FUSE_MAX_DELAY_S:
            fusion.run()  # nothing read the filter for that long (no ODOMETRY): its verdicts must out
        self.gyro.update_reads(now_s)  # a source that fell silent: read the others again
        out = self.streams.pump(now_s)
        out += self.streams.check_rates(now_s)
        if not self.frame.ready:
            out += self.frame.decide(now_s, self.fusion.pose_at_stamp if self.telemetry.have_wheels else None)
        out += self._publish(now_s, early=False)
        st = self.state if self.calibration_reports.enabled and self.telemetry.have_wheels else None
        if st is not None:
            out += self.calibration_reports.tick(now_s, True, st.track_width_m, st.left_radius_m, st.right_radius_m)
        return fusion.take_said(out)

    def next_deadline_s(self, now_s: float) -> float:
        # Runs on every turn of the loop: plain comparisons, no lists.
        first = min(now_s + 1.0, self.streams.next_deadline_s(now_s))
        odom = self.publisher.deadline_s(now_s) if self.telemetry.have_wheels else None
        if odom is not None:
            # Held back until the frame is decided: look again when the wait for the autopilot ends.
            if not self.frame.ready:
                odom = max(odom, now_s + min(0.1, self.frame.timeout_s))
            if odom < first:
                first = odom
        cal = self.calibration_reports.next_s
        if cal is not None and cal < first:
            first = cal
        if self.fusion.pending and self.fusion.queued_since_s + FUSE_MAX_DELAY_S < first:
            first = self.fusion.queued_since_s + FUSE_MAX_DELAY_S
        return first

    def odometry_due(self, now_s: float) -> list[Outgoing]:
        """ODOMETRY if one is due or may leave early (OdometryPublisher.due): what the shell calls in a
        pass it makes anyway once next_early_s has come. tick publishes only what is due."""
        return self.fusion.take_said(self._publish(now_s, early=True))

    def _publish(self, now_s: float, early: bool) -> list[Outgoing]:
        if self.telemetry.have_wheels and self.frame.ready and self.publisher.due(now_s, early):
            msg = self.odometry_message(now_s)
            own = self.identity.own_system_id, self.identity.component_id
            return [Outgoing(link, msg, *own) for link in self.publisher.links]
        return []

    def next_early_s(self, now_s: float) -> float | None:
        """From when odometry_due may publish in a pass made anyway (None: nothing to publish yet)."""
        if not (self.telemetry.have_wheels and self.frame.ready):
            return None
        return self.publisher.early_deadline_s(now_s)

    def shutdown(self, now_s: float) -> list[Outgoing]:
        """Nothing to stop: the estimate flow sends no commands that persist (what the queue says still goes)."""
        self.fusion.run()
        return self.fusion.take_said([])

    # ------------------------------------------------------------------ pose resets
    def reset_pose(self, pose: Pose2D, now_s: float) -> list[Outgoing]:
        """Put the estimate (and the raw wheel odometry) at `pose` (x forward, y left, yaw CCW)."""
        self.ekf.set_pose(pose)
        self.fusion.forget_poses()  # poses before the reset are in the old frame
        self.telemetry.raw_pose = Pose2D(pose.x_m, pose.y_m, wrap_angle(pose.yaw_rad))
        return self.resets.pose_reset(pose, now_s)

    def _handle_command(self, inc: Incoming, now_s: float) -> Reaction:
        msg = inc.msg
        if (msg.command != POSE_RESET_COMMAND or msg.target_component != self.identity.component_id
                or msg.target_system != self.identity.own_system_id):
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

    # ------------------------------------------------------------------ output
    def odometry_time_usec(self, now_s: float) -> int:
        """now_s on the autopilot's boot clock (the same mapping as every measurement); now_s itself
        (monotonic) until the first autopilot stamp arrives."""
        return self.clock.time_usec(now_s)

    def odometry_message(self, now_s: float) -> MAVLinkMessage:
        """ODOMETRY for the estimate extrapolated to now_s (see rover_bridge.estimate.publish)."""
        x, P = self.ekf.extrapolate(self.clock.autopilot_time_s(now_s), PUBLISHED)  # noqa: N806 - a covariance
        fused = self.fusion.last_wheel_fused_s
        fresh = fused is not None and now_s - fused <= WHEELS_STALE_S
        return self.publisher.message(x, P, self.clock.time_usec(now_s), self.resets.value, quality(P, fresh),
                                      self.frame.anchor)
