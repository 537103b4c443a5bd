"""ArduPilot SITL's skid-steering rover (``plant = "ardupilot_skid"``): its body, its encoders and their timing.

What the real SITL (``--model rover-skid``) does, copied as behaviour, read in ArduPilot (Rover 4.7):

- The body (libraries/SITL/SIM_Rover.cpp, skid_steering): each motor command m in [-1, 1]; the target speed
  is 0.5 (m_left + m_right) x max_speed and the speed moves toward it with accel = max_accel x (target -
  speed) / max_speed, a first-order lag of max_speed / max_accel (4 / 14 = 0.29 s); the yaw rate is
  (m_left - m_right) x skid_turn_rate at once, with no lag at all. There are no wheels. Here max_speed is
  the vehicle's full wheel surface speed (max_rpm x wheel radius), skid_turn_rate is max_speed / the true
  track (1.637 m for 140 deg/s at 4 m/s) and the lag is ``motor_time_constant_s``. The motor imperfections
  (gains, curve, dead zone, loads) act on each m before the mix; a stalled side's m is 0. Slip does not exist
  in that model and is ignored.
- The encoders (libraries/AP_WheelEncoder/AP_WheelEncoder_SITL_Quadrature.cpp, WENC_TYPE 10): read in Rover's
  loop (Rover/Rover.cpp: update_wheel_encoder at 50 Hz, every loop at SCHED_LOOP_RATE 50), each from the
  body's speed and yaw rate at that instant, not from wheels: instance 0 at speed - yaw_rate x half_track
  (yaw rate clockwise positive: in a left turn it speeds up, so it is the RIGHT wheel), instance 1 at speed
  + yaw_rate x half_track, half_track = the mean of |WENC_POS_Y| and |WENC2_POS_Y|. Each read turns
  speed / WENCn_RADIUS x (whole milliseconds since the last read) into counts (x WENCn_CPR / 2 pi),
  truncated toward zero: the fraction of a count is lost at every read (0.6 % of the distance at 0.8 m/s
  with the default 3200 counts, 0.05 m). Distance = counts x 2 pi x WENCn_RADIUS / WENCn_CPR.
- WHEEL_DISTANCE (Rover/GCS_MAVLink_Rover.cpp send_wheel_encoder_distance): the distances of the loop's last
  read, time_usec = the loop's whole milliseconds x 1000. It goes out from the loop (GCS_Common.cpp
  update_send, every loop): a stream bucket is sent in the first loop at least its interval after its last
  send time, which then moves on by the interval (caught up to now when more than an interval behind).
  With 20 ms loops, 50 Hz asked (capped to 25 ms, sitl/streams.py) gives gaps of 20, 20, 20, 40 ms (40 Hz,
  increments of one and two loops' travel); 20 Hz gives 40 and 60 ms.
- The scheduler: a loop now and then starts a millisecond late (``loop_late_rate`` of the loops), which
  shows as gaps of 19/21 and 39/41 ms.
- The motors (Rover/Rover.cpp: read_radio first in the loop, set_servos later, GCS update_receive near its
  end): an RC override is parsed at the end of the loop it arrived in and output by the next, so it reaches the
  motors 20 to 40 ms after it arrives, and the PWM holds between loops (SITL's physics runs on the last output).

Measured on the real SITL (Rover 4.7.0-dev, rover-skid, WENC_TYPE 10, WENC_POS_Y +-0.8185, both motors at
1600 us, EXTRA1 asked for at 50 Hz, 8 s): 317 gaps: 237 of 20 ms, 76 of 40 ms, 3 of 19, 3 of 41 and 1 of 39;
every increment 15.904 mm per 20 ms (0.7952 m/s for 0.8 m/s: the truncation); at 20 Hz, 40 and 60 ms
alternating. ``sitl/vehicles/ardupilot-skid-plant.toml`` sets this plant up.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import replace

from sitl.config import VehicleConfig
from sitl.params import WHEEL_PARAM_PREFIXES
from sitl.physics import PhysicsState, StepInputs, arc_step, motor_gains, speed_fraction, wrap_pi
from sitl.sensors import gyro_reading_rad_s

ARDUPILOT_SKID = "ardupilot_skid"
LATE_US = 1000  # how late a late loop starts


def _side_command(cmd: float, gain: float, scale: float, stalled: bool, exponent: float) -> float:
    """A side's effective motor command (its fraction of max_speed), after the motor's imperfections."""
    return 0.0 if stalled else speed_fraction(cmd, exponent) * gain * scale


def step(state: PhysicsState, inputs: StepInputs, dt_s: float, vehicle: VehicleConfig) -> PhysicsState:
    """Advance the skid body by ``dt_s`` (pure). ``v_m_s`` and ``yaw_rate_rad_s`` are the values at the end of the
    step (what SITL's sensors read then); each side's wheel speed is what its SITL encoder would turn at."""
    if dt_s <= 0.0:
        return state
    left_gain, right_gain = motor_gains(vehicle, state.time_s)
    exponent = vehicle.motor_curve_exponent
    m_left = _side_command(inputs.left_cmd, left_gain, inputs.left_speed_scale, inputs.left_stalled, exponent)
    m_right = _side_command(inputs.right_cmd, right_gain, inputs.right_speed_scale, inputs.right_stalled, exponent)
    max_speed = vehicle.max_wheel_rad_s * 0.5 * (vehicle.left_radius_true_m + vehicle.right_radius_true_m)
    target = 0.5 * (m_left + m_right) * max_speed
    tau = vehicle.motor_time_constant_s
    # The first-order lag of the common speed, discretised exactly (SIM_Rover takes small Euler steps).
    v_end = target + (state.v_m_s - target) * math.exp(-dt_s / tau)
    ds = target * dt_s + (state.v_m_s - target) * tau * (1.0 - math.exp(-dt_s / tau))
    yaw_rate = (m_left - m_right) * max_speed / vehicle.track_true_m  # clockwise +, no lag
    dyaw = yaw_rate * dt_s
    dx, dy = arc_step(state.yaw_rad, ds, dyaw)
    half = 0.5 * vehicle.track_true_m
    left_ground, right_ground = ds + dyaw * half, ds - dyaw * half
    left_w = (v_end + yaw_rate * half) / vehicle.left_radius_true_m
    right_w = (v_end - yaw_rate * half) / vehicle.right_radius_true_m
    left_dangle, right_dangle = left_ground / vehicle.left_radius_true_m, right_ground / vehicle.right_radius_true_m
    gyro = gyro_reading_rad_s(yaw_rate + vehicle.gyro_bias_rad_s + inputs.gyro_noise_rad_s)
    return replace(
        state,
        time_s=state.time_s + dt_s,
        x_m=state.x_m + dx,
        y_m=state.y_m + dy,
        yaw_rad=wrap_pi(state.yaw_rad + dyaw),
        v_m_s=v_end,
        accel_m_s2=(target - v_end) / tau,
        yaw_rate_rad_s=yaw_rate,
        left_rad_s=left_w,
        right_rad_s=right_w,
        left_angle_rad=state.left_angle_rad + left_dangle,
        right_angle_rad=state.right_angle_rad + right_dangle,
        left_encoder_angle_rad=state.left_encoder_angle_rad + left_dangle,
        right_encoder_angle_rad=state.right_encoder_angle_rad + right_dangle,
        left_distance_true_m=state.left_distance_true_m + left_ground,
        right_distance_true_m=state.right_distance_true_m + right_ground,
        gyro_rad_s=gyro,
        ahrs_yaw_rad=wrap_pi(state.ahrs_yaw_rad + gyro * dt_s),
    )


class SkidLoop:
    """Rover's loop as the skid plant sees it (module doc): SITL's two encoders read in it, WHEEL_DISTANCE sent
    from it, and the motors' PWM updated only in it.

    ``update`` at every physics substep boundary (the emulator splits its substeps at ``next_loop_us``); it runs
    the loop when one is due and says whether WHEEL_DISTANCE goes out in it, stamped ``stamp_us``. ``motors``
    then gives the commands the motors run on until the next loop."""

    def __init__(self, param: Callable[[str], float], loop_period_us: int, late_rate: float, seed: int) -> None:
        self._param = param
        self._late_rate = late_rate
        self._rng = random.Random(f"sitl-loop-{seed}")
        self.reset(0, loop_period_us)

    def reset(self, boot_us: int, loop_period_us: int) -> None:
        """A boot: counts from zero, the loop's grid starts at the boot."""
        self.counts = [0, 0]
        self._boot_us = boot_us
        self._period_us = loop_period_us
        self._loop = 0
        self.next_loop_us = boot_us
        self._last_read_ms = 0
        self._last_sent_ms: int | None = None
        self._interval_ms: int | None = None
        self.stamp_us = boot_us
        self._ran = False
        self._pending = self._applied = (0.0, 0.0)

    def update(self, now_us: int, physics: PhysicsState, interval_us: int | None) -> bool:
        """Run the loop if it is due: read the encoders; True when WHEEL_DISTANCE is sent in this loop."""
        if now_us < self.next_loop_us:
            return False
        self._loop += 1
        self._ran = True
        late = LATE_US if self._late_rate and self._rng.random() < self._late_rate else 0
        self.next_loop_us = max(now_us + 1, self._boot_us + self._loop * self._period_us + late)
        now_ms = (now_us - self._boot_us) // 1000
        self._read(now_ms, physics)
        return self._bucket_due(now_ms, None if interval_us is None else max(1, interval_us // 1000))

    def _read(self, now_ms: int, physics: PhysicsState) -> None:
        dt_s = (now_ms - self._last_read_ms) / 1000.0
        if dt_s <= 0.0:
            return
        self._last_read_ms = now_ms
        half = 0.5 * sum(abs(self._param(f"{p}_POS_Y")) for p in WHEEL_PARAM_PREFIXES)
        turn = physics.yaw_rate_rad_s * half
        for i, (prefix, speed) in enumerate(zip(WHEEL_PARAM_PREFIXES, (physics.v_m_s - turn, physics.v_m_s + turn),
                                                strict=True)):
            radius = self._param(f"{prefix}_RADIUS")
            if radius > 0.0:
                self.counts[i] += int(speed / radius * dt_s / (2.0 * math.pi) * self._param(f"{prefix}_CPR"))
        self.stamp_us = self._boot_us + now_ms * 1000

    def _bucket_due(self, now_ms: int, interval_ms: int | None) -> bool:
        if interval_ms != self._interval_ms:  # a new rate: a new bucket, first sent one interval from now
            self._interval_ms, self._last_sent_ms = interval_ms, now_ms
        if interval_ms is None or self._last_sent_ms is None or now_ms - self._last_sent_ms < interval_ms:
            return False
        self._last_sent_ms += interval_ms  # keeps the average rate ...
        if now_ms - self._last_sent_ms > interval_ms:  # ... without catching up a long gap
            self._last_sent_ms = now_ms
        return True

    def motors(self, commands: tuple[float, float]) -> tuple[float, float]:
        """The motor commands from the last loop, given the ones the RC state asks for now. A loop outputs what
        the one before it parsed (read_radio at a loop's start, update_receive at its end): an override reaches
        the motors 20 to 40 ms after it arrives, and holds there for a whole loop."""
        if self._ran:
            self._ran = False
            self._applied, self._pending = self._pending, commands
        return self._applied

    def distances_m(self) -> tuple[float, float]:
        """(instance 0, instance 1) cumulative distances of the last read."""
        out = [c * 2.0 * math.pi * self._param(f"{p}_RADIUS") / max(1.0, self._param(f"{p}_CPR"))
               for c, p in zip(self.counts, WHEEL_PARAM_PREFIXES, strict=True)]
        return out[0], out[1]
