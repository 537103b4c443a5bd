"""What each measurement does to the filter, now or queued (pure): the estimate flow's filter side.

- The filter (ekf.WheelGyroEKF) is built on first use, or when the shell says so (`start`): building
  it imports filterpy and scipy (about 0.65 s), which `rover-bridge run` does after its first pass,
  so the first HEARTBEAT does not wait for it.
- Deferred fusion (`defer`, on in the running bridge): what a gyro sample or a wheel reading does to
  the filter is queued, in arrival order with its own stamps and arrival times, and run when anything
  reads the filter (`filter`: ODOMETRY, navigation, a pose reset, the counters) or FUSE_MAX_DELAY_S
  after the oldest queued one (the core's tick). The filter computes exactly what it computes eagerly
  (tested bit for bit); it costs less because the sensor cycles are fused back to back in ODOMETRY's
  passes, where the filter's code is warm, instead of cold in every request's pass. What waits: the
  gate's verdicts and their STATUSTEXT, and the slip verdict (the command flow's slip compensation
  sees it at most FUSE_MAX_DELAY_S, in practice one ODOMETRY period, later).
- Silence: the first measurement after SILENCE_S without any continues from the pose published
  meanwhile (restart_motion); a restarted boot clock (a reboot) too, on the new clock.
- The slip test's window: the gyro samples fused since the last wheel step.
- The filter's recent poses, for the pose at an older autopilot stamp (anchoring), and the autopilot's
  position fixes beside the pose at their stamps (navigation).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

from rover_bridge.estimate.diagnostics import SlipMonitor
from rover_bridge.estimate.ekf import WheelGyroEKF
from rover_bridge.estimate.models import NoiseModel
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing
from rover_bridge.odometry import Pose2D, wrap_angle

FIX_HISTORY = 120  # LOCAL_POSITION_NED fixes kept with our pose (a minute at 2 Hz)
POSE_HISTORY = 256  # filter poses kept (anchoring, targets tied to a fix): a few seconds at the sensors' rates
SILENCE_S = 0.5  # no measurement at all for this long: the next one restarts the motion (see after_silence)
GYRO_FOR_SLIP_MAX_AGE_S = 0.25
GYRO_WINDOW_MAX = 64  # gyro samples kept between two wheel steps (the slip test's window)
FUSE_MAX_DELAY_S = 0.05  # deferred fusion: the longest a queued measurement waits for a reader

Op = tuple[Callable[..., list[Outgoing] | None], tuple[Any, ...]]


class Fusion:
    """The filter, and each measurement's work on it (module docstring)."""

    def __init__(self, track_width_m: float, noise: NoiseModel, calibrate: bool, slip: SlipMonitor,
                 reporter: Reporter) -> None:
        self._args = (track_width_m, noise, calibrate)
        self._ekf: WheelGyroEKF | None = None
        self.slip = slip
        self.reporter = reporter
        self.defer = False
        self._queue: list[Op] = []
        self.queued_since_s = 0.0  # arrival time of the oldest queued measurement
        self._said: list[Outgoing] = []  # what running the queue said, for the next handle or tick
        self.counters = {"gyro_rejected": 0, "wheel_rejected": 0, "wheel_stationary": 0}
        self.gyro_window: list[float] = []  # gyro samples since the last wheel step (with the one before it)
        self.last_gyro: tuple[float, float] | None = None  # (arrival time, omega) of the newest fused sample
        self.last_wheel_fused_s: float | None = None
        self._recent: deque[tuple[float, Pose2D]] = deque(maxlen=POSE_HISTORY)  # (filter time, pose)
        # LOCAL_POSITION_NED fixes beside the estimate's pose at their stamps (stamp, x, y, yaw, north, east):
        # the autopilot's frame against ours, fitted over the track (rover_bridge.command.navigation).
        self.fixes: deque[tuple[float, float, float, float, float, float]] = deque(maxlen=FIX_HISTORY)

    # ------------------------------------------------------------------ the filter and the queue
    def start(self) -> WheelGyroEKF:
        """The filter, built now if it was not (this imports filterpy: see the module docstring)."""
        if self._ekf is None:
            self._ekf = WheelGyroEKF(*self._args)
        return self._ekf

    @property
    def filter(self) -> WheelGyroEKF:
        """The filter with every queued measurement fused: what anything outside the queue reads."""
        self.run()
        return self.start()

    @property
    def pending(self) -> int:
        return len(self._queue)

    def run(self) -> None:
        """Run the queued measurements' work, oldest first; what they said waits for take_said."""
        if not self._queue:
            return
        ops, self._queue = self._queue, []
        for fn, args in ops:
            said = fn(*args)
            if said:
                self._said += said

    def submit(self, now_s: float, fn: Callable[..., list[Outgoing] | None], *args: Any) -> list[Outgoing]:
        """fn(*args) now (what it said), or queued when fusion is deferred."""
        if self.defer:
            if not self._queue:
                self.queued_since_s = now_s
            self._queue.append((fn, args))
            return []
        return fn(*args) or []

    def after_message(self) -> None:
        """A message was handled: remember the filter's pose after its work (queued behind it, if any)."""
        if self._queue:
            self._queue.append((self._remember_pose, ()))
        else:
            self._remember_pose()

    def take_said(self, out: list[Outgoing]) -> list[Outgoing]:
        """What the queue said since it was last handed out, then out."""
        if not self._said:
            return out
        said, self._said = self._said, []
        return said + out

    # ------------------------------------------------------------------ the measurements' work
    def gyro(self, t: float, omega: float, now_s: float) -> list[Outgoing] | None:
        """A gyro sample (CCW rad/s, bias included) at filter time t."""
        ekf = self.start()
        self.after_silence(t)
        if not ekf.update_gyro(t, omega):
            self.counters["gyro_rejected"] += 1
            return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, "gyro sample rejected by gate", now_s,
                                            key="gyro gate")
        window = self.gyro_window
        if len(window) >= GYRO_WINDOW_MAX:  # no wheel step for a long while: keep the newest
            del window[: len(window) - GYRO_WINDOW_MAX + 1]
        window.append(omega)
        self.last_gyro = (now_s, omega)
        return None

    def wheels(self, t: float, d_left_m: float, d_right_m: float, dt_s: float, now_s: float) -> list[Outgoing]:
        """A wheel step, with the gyro samples fused since the last one as the slip test's window."""
        ekf = self.start()
        self.after_silence(t)
        gyro_mean: float | None = None
        window = self.gyro_window
        gyro_spread = 0.0
        if window and self.last_gyro is not None and now_s - self.last_gyro[0] <= GYRO_FOR_SLIP_MAX_AGE_S:
            gyro_mean = sum(window) / len(window)
            gyro_spread = 0.5 * (max(window) - min(window))
        self.gyro_window = window[-1:]  # the last sample also bounds the next interval
        res = ekf.update_wheels(t, d_left_m, d_right_m, dt_s, gyro_mean, gyro_spread)
        if res.stationary:
            self.counters["wheel_stationary"] += 1
        if not res.accepted:
            self.counters["wheel_rejected"] += 1
        else:
            self.last_wheel_fused_s = now_s
        return self.slip.interval(res.slip, now_s)

    def baseline(self, reboot: bool, published_t: float, t: float) -> None:
        """A wheel reading that starts a new baseline (the first, a reboot, a resync)."""
        ekf = self.start()
        if reboot:  # continue from the pose published last (no jump); the silence is not dead-reckoned
            self.reboot(published_t, t)
        ekf.predict_to(t)
        ekf.wheel_baseline()
        self.gyro_window.clear()

    def reboot(self, published_t: float, t: float) -> None:
        """The boot clock restarted: the filter continues from the pose published last, on the new clock."""
        ekf = self.start()
        if ekf.time_s is not None:
            ekf.restart_motion(published_t, new_time_s=t)

    def after_silence(self, t: float) -> None:
        """First measurement after every sensor was silent: continue from the pose published meanwhile.

        ODOMETRY held the pose EXTRAPOLATE_MAX_S after the last measurement; predicting through the
        silence at the old speed now would jump it (a rebooting autopilot's motors stopped). Wheel
        distances, being cumulative, still move it the real distance when they come back.
        """
        ekf = self.start()
        if ekf.time_s is not None and t - ekf.time_s > SILENCE_S:
            ekf.restart_motion(t)

    # ------------------------------------------------------------------ poses at older stamps
    def forget_poses(self) -> None:
        """Poses (and fixes beside them) before a pose reset or a restarted clock are in another frame."""
        self._recent.clear()
        self.fixes.clear()

    def add_fix(self, stamp_s: float, north_m: float, east_m: float) -> None:
        at = self.pose_at_stamp(stamp_s)
        self.fixes.append((stamp_s, at.x_m, at.y_m, at.yaw_rad, north_m, east_m))

    def _remember_pose(self) -> None:
        ekf = self._ekf  # runs in order after the queue's work, never a reason to run it
        t = None if ekf is None else ekf.time_s
        if ekf is None or t is None:
            return
        recent = self._recent
        if recent and t < recent[-1][0]:
            self.forget_poses()  # the filter's clock restarted (a reboot): older poses are another epoch
        if not recent or t > recent[-1][0]:
            recent.append((t, ekf.peek_pose()))

    def pose_at_stamp(self, stamp_s: float) -> Pose2D:
        """The estimate's pose at an autopilot stamp: extrapolated ahead of the filter's time, interpolated
        in the recent history behind it (a LOCAL_POSITION_NED half a second old on a moving rover)."""
        ekf = self.filter
        t = ekf.time_s
        recent = self._recent
        if t is None or stamp_s >= t or not recent:
            return ekf.pose_at(stamp_s)
        if stamp_s <= recent[0][0]:
            return recent[0][1]
        after = next(i for i, (ts, _) in enumerate(recent) if ts >= stamp_s)
        (t0, a), (t1, b) = recent[after - 1], recent[after]
        f = (stamp_s - t0) / (t1 - t0) if t1 > t0 else 1.0
        return Pose2D(a.x_m + f * (b.x_m - a.x_m), a.y_m + f * (b.y_m - a.y_m),
                      wrap_angle(a.yaw_rad + f * wrap_angle(b.yaw_rad - a.yaw_rad)))
