"""The autopilot's telemetry into the estimate flow (pure): stamps, wheel steps, gyro samples, positions.

- Every measurement is stamped on the autopilot's boot clock (clock.AutopilotClock): its own stamp,
  never its arrival time. A restarted boot clock (every stream jumping back: a reboot) restarts the
  filter's clock from the pose published last; one stream on another epoch is re-based (said once); a
  "reboot" that one stamp faked is undone at the next stamp that goes on from before it, the same way,
  and the wheel baseline is taken afresh.
- WHEEL_DISTANCE: checked increments (wheel_input.WheelInput) -> the filter, the raw wheel odometry
  (for comparison) and the measured wheel speeds the command flow's speed loop reads at once.
- The gyro: the source in use (gyro.GyroSelector), poison and reordered samples dropped -> the filter.
- ATTITUDE's heading, LOCAL_POSITION_NED and GLOBAL_POSITION_INT: what navigation and the frame
  anchor read.
"""

from __future__ import annotations

import logging
import math

from rover_bridge import frames
from rover_bridge.estimate.anchor import FrameAnchor
from rover_bridge.estimate.clock import JUMP, REBOOT, RESTORED, AutopilotClock
from rover_bridge.estimate.fusion import Fusion
from rover_bridge.estimate.gyro import GyroSelector
from rover_bridge.estimate.resets import ResetCounter
from rover_bridge.estimate.streams import StreamRequests
from rover_bridge.estimate.wheel_input import StepKind, WheelInput
from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing
from rover_bridge.odometry import Pose2D, arc_step
from rover_bridge.params import Profile

log = logging.getLogger("rover_bridge.estimate.inputs")

GYRO_MAX_RAD_S = 50.0  # beyond any rover: such a "rate" is corrupt data, not a measurement
MAX_JUMPS_SAID = 16  # streams whose clock jump is reported (each once)


class Telemetry:
    """What each autopilot message does to the estimate flow (module docstring)."""

    def __init__(self, profile: Profile, reporter: Reporter, fusion: Fusion, streams: StreamRequests,
                 frame: FrameAnchor, resets: ResetCounter, gyro: GyroSelector) -> None:
        self.robot = profile.robot
        self.reporter = reporter
        self.fusion = fusion
        self.streams = streams
        self.frame = frame
        self.resets = resets
        self.gyro = gyro
        self.wheels = WheelInput(profile.encoders, profile.robot)
        self.clock = AutopilotClock()
        self.raw_pose = Pose2D()  # plain wheel odometry (nominal geometry), for comparison
        self.have_wheels = False
        self.wheel_sample: MeasuredWheels | None = None  # the newest interval's speeds, until taken
        self.heading: tuple[float, float] | None = None  # (stamp, ATTITUDE yaw clockwise from north)
        self.gps: tuple[float, float, float, float] | None = None  # (arrival, stamp, lat, lon)
        self.counters = {"clock_jumps": 0, "clock_restored": 0, "gyro_samples": 0, "gyro_poison": 0,
                         "gyro_stale": 0}
        self._jumps_said: set[str] = set()

    def handle(self, msg: MAVLinkMessage, mtype: str, now_s: float) -> list[Outgoing]:
        """A message from the vehicle; what to send."""
        if mtype == "WHEEL_DISTANCE":
            return self._wheels(msg, now_s)
        if mtype == "ATTITUDE":
            t_att, yaw = self.clock.rebase(msg.time_boot_ms * 1e-3, "attitude"), float(msg.yaw)
            self.frame.on_attitude(t_att, yaw)
            if math.isfinite(yaw):
                self.heading = (t_att, yaw)
            return self._gyro("attitude", msg.time_boot_ms * 1e-3, float(msg.yawspeed), now_s)
        if mtype == "SCALED_IMU":
            return self._gyro("scaled_imu", msg.time_boot_ms * 1e-3, msg.zgyro * 1e-3, now_s)
        if mtype == "RAW_IMU":
            return self._gyro("raw_imu", msg.time_usec * 1e-6, msg.zgyro * 1e-3, now_s)
        if mtype == "LOCAL_POSITION_NED":
            t, out = self._stamp(msg.time_boot_ms * 1e-3, now_s, "LOCAL_POSITION_NED")
            self.streams.arrival("LOCAL_POSITION_NED", now_s)
            north, east = float(msg.x), float(msg.y)
            self.frame.on_local_position(t, north, east)
            if self.have_wheels and math.isfinite(north) and math.isfinite(east):
                self.fusion.add_fix(t, north, east)
            return out
        if mtype == "GLOBAL_POSITION_INT":
            return self._global_position(msg, now_s)
        if mtype == "SYSTEM_TIME":
            # The same least-latency mapping as the sensor stamps (re-learnt when the boot clock restarts).
            return self._stamp(msg.time_boot_ms * 1e-3, now_s, "SYSTEM_TIME")[1]
        return []

    def _gyro(self, source: str, stamp_s: float, yaw_rate_cw_rad_s: float, now_s: float) -> list[Outgoing]:
        if not self.gyro.accept_source(source, now_s):
            return []
        omega = frames.omega_from_mavlink_yaw_rate(yaw_rate_cw_rad_s)
        self.streams.arrival(source.upper(), now_s)
        if not (math.isfinite(omega) and abs(omega) <= GYRO_MAX_RAD_S):
            # Poison (NaN, inf, 3e38) never reaches the filter, nor the stream's clock.
            self.counters["gyro_poison"] += 1
            return []
        t, out = self._stamp(stamp_s, now_s, source.upper())
        fusion = self.fusion
        if self.gyro.is_stale(source, t):
            # Fusing a reordered or duplicated sample as the newest rate would also make the EKF's
            # trapezoid yaw correction count the interval since that old stamp twice. Dropped, as
            # WheelInput does for wheels.
            self.counters["gyro_stale"] += 1
            return out + fusion.submit(now_s, fusion.after_silence, t)
        self.gyro.fused(source, t)
        self.counters["gyro_samples"] += 1
        return out + fusion.submit(now_s, fusion.gyro, t, omega, now_s)

    def _stamp(self, stamp_s: float, now_s: float, stream: str) -> tuple[float, list[Outgoing]]:
        """The filter time of a measurement (see the module docstring)."""
        published_t = self.clock.autopilot_time_s(now_s)
        st = self.clock.observe(stamp_s, now_s, stream)
        out: list[Outgoing] = []
        if st.event == REBOOT:
            self.fusion.submit(now_s, self.fusion.reboot, published_t, st.t_s)
        elif st.event == RESTORED:
            # That "reboot" was one stamp (corrupted or forged): back on the clock from before it. The wheel
            # baseline may be that stamp's reading: the next reading is a new one, never a step from it.
            self.fusion.submit(now_s, self.fusion.reboot, published_t, st.t_s)
            self.wheels.reset()
            self.counters["clock_restored"] += 1
        elif st.event == JUMP:
            self.counters["clock_jumps"] += 1
            if stream not in self._jumps_said and len(self._jumps_said) < MAX_JUMPS_SAID:
                self._jumps_said.add(stream)
                log.warning("%s stamps jumped %+.6g s (another epoch, or garbage): re-based onto the boot clock",
                            stream, st.jump_s)
                out = self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING,
                                               f"RB: {stream} clock jumped {st.jump_s:+.3g} s"[:50], now_s,
                                               key=f"clock jump {stream}")
        return st.t_s, out

    def _global_position(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        lat, lon = int(msg.lat) * 1e-7, int(msg.lon) * 1e-7
        # ArduPilot sends GLOBAL_POSITION_INT before it has a position, with 0/0 in it: no fix.
        if (lat == 0.0 and lon == 0.0) or abs(lat) > 90.0 or abs(lon) > 180.0:
            return []
        t, out = self._stamp(msg.time_boot_ms * 1e-3, now_s, "GLOBAL_POSITION_INT")
        self.streams.arrival("GLOBAL_POSITION_INT", now_s)
        self.gps = (now_s, t, lat, lon)
        return out

    def _wheels(self, msg: MAVLinkMessage, now_s: float) -> list[Outgoing]:
        published_t = self.clock.autopilot_time_s(now_s)  # before a restarted clock re-learns its offset
        t, out = self._stamp(int(msg.time_usec) * 1e-6, now_s, "WHEEL_DISTANCE")
        # Re-based stamps: a wheel stream that changed epochs goes on as one interval, not a 1.7e9 s one.
        step = self.wheels.ingest(round(t * 1e6), int(msg.count), list(msg.distance))
        self.streams.arrival("WHEEL_DISTANCE", now_s)
        kind = step.kind
        fusion = self.fusion
        if kind in (StepKind.BASELINE, StepKind.REBOOT, StepKind.RESYNC):
            out += fusion.submit(now_s, fusion.baseline, kind is StepKind.REBOOT, published_t, t)
            self.have_wheels = True
            if kind is StepKind.REBOOT:
                self.streams.restart(now_s)
                out += self.resets.reboot(step.reason, now_s)
                out += self.streams.pump(now_s)
            return out
        if kind is StepKind.SPIKE:
            return out + self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, "wheel distance spike rejected",
                                                  now_s, key="wheel spike")
        if kind is not StepKind.STEP:
            return out
        d_left_m, d_right_m, dt_s = step.d_left_m, step.d_right_m, step.dt_s
        # The command flow's speed loop reads these at once, whether or not fusion waits.
        self.wheel_sample = MeasuredWheels(t, WheelSpeeds(d_left_m / dt_s / self.robot.left_radius_m,
                                                          d_right_m / dt_s / self.robot.right_radius_m))
        self.raw_pose = arc_step(self.raw_pose, 0.5 * (d_left_m + d_right_m),
                                 (d_right_m - d_left_m) / self.robot.track_width_m)
        return out + fusion.submit(now_s, fusion.wheels, t, d_left_m, d_right_m, dt_s, now_s)
