"""Pure differential-drive physics: no sockets, no clocks, time is an argument.

Conventions (the same as ArduPilot and MAVLink, so the emulator never converts):
- world frame NED: x north, y east (metres); yaw clockwise from north (radians, wrapped to
  (-pi, pi]);
- body frame FRD: forward speed ``v_m_s``; yaw rate clockwise positive (seen from above), which
  is also the gyro's z axis (z down) sign;
- wheels: positive wheel speed drives that side forward. With the left wheel faster than the
  right the robot turns clockwise (to the right): ``yaw_rate = (v_left - v_right) / track``.

Each wheel's ground contact speed is ``omega * true_radius * (1 - slip)``: the encoder measures
the wheel's rotation, the body moves by the ground contact. A slip ratio of 0.3 means the
contact patch covers 30 % less ground than the wheel's circumference turned.

Motors: each wheel's target speed is ``speed_fraction(cmd) * max_wheel_rad_s * gain(t) * scale``,
where ``speed_fraction`` is the (possibly curved) steady-state map of the normalised command,
``gain(t)`` the motor's gain with battery sag (``motor_gains``) and ``scale`` the scenario's load
factor (``StepInputs.left_speed_scale``); the wheel follows the target through a first-order lag.
A stalled wheel (``StepInputs.left_stalled``) is held still: zero speed, no rotation, no counts.
With the default vehicle and inputs all factors are exactly 1, so the ideal motor is unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from sitl.config import VehicleConfig
from sitl.sensors import gyro_reading_rad_s

TWO_PI = 2.0 * math.pi


def wrap_pi(angle_rad: float) -> float:
    """Wrap to (-pi, pi]."""
    wrapped = math.fmod(angle_rad + math.pi, TWO_PI)
    if wrapped <= 0.0:
        wrapped += TWO_PI
    return wrapped - math.pi


def arc_step(yaw_rad: float, ds_m: float, dyaw_rad: float) -> tuple[float, float]:
    """The NED displacement (x north = cos(yaw), y east = sin(yaw)) of an exact arc: ds_m along it while the
    yaw turns by dyaw_rad from yaw_rad."""
    if abs(dyaw_rad) > 1e-9:
        radius = ds_m / dyaw_rad
        return (radius * (math.sin(yaw_rad + dyaw_rad) - math.sin(yaw_rad)),
                -radius * (math.cos(yaw_rad + dyaw_rad) - math.cos(yaw_rad)))
    mid = yaw_rad + 0.5 * dyaw_rad
    return ds_m * math.cos(mid), ds_m * math.sin(mid)


def pwm_to_command(pwm: int, vehicle: VehicleConfig, reversed_: bool = False) -> float:
    """Servo PWM -> normalised motor command in [-1, 1] (0 inside the deadzone or for no pulse)."""
    if pwm <= 0:  # no pulse at all: an ESC treats it as stop
        return 0.0
    offset = pwm - vehicle.pwm_trim
    dz = vehicle.deadzone_pwm
    if abs(offset) <= dz:
        cmd = 0.0
    elif offset > 0:
        cmd = (offset - dz) / (vehicle.pwm_max - vehicle.pwm_trim - dz)
    else:
        cmd = (offset + dz) / (vehicle.pwm_trim - vehicle.pwm_min - dz)
    cmd = max(-1.0, min(1.0, cmd))
    return -cmd if reversed_ else cmd


def speed_fraction(cmd: float, exponent: float) -> float:
    """Steady-state wheel speed as a fraction of the maximum at normalised command ``cmd``."""
    if exponent == 1.0:
        return cmd  # the linear motor, exactly
    return math.copysign(abs(cmd) ** exponent, cmd)


def motor_gains(vehicle: VehicleConfig, time_s: float) -> tuple[float, float]:
    """(left, right) motor gains at ``time_s`` of simulated time, battery sag included."""
    sag = vehicle.battery_sag_per_min
    left, right = vehicle.left_motor_gain, vehicle.right_motor_gain
    if sag == 0.0:
        return left, right
    factor = max(0.5, 1.0 - sag * time_s / 60.0)
    return left * factor, right * factor


def encoder_counts(encoder_angle_rad: float, cpr: int) -> int:
    """Whole encoder counts for a wheel angle: the quantisation of a real quadrature counter."""
    # A tiny epsilon keeps exact multiples of one count from flooring one count low.
    return math.floor(encoder_angle_rad / TWO_PI * cpr + 1e-9)


@dataclass(frozen=True)
class StepInputs:
    """Everything outside the robot that acts on it during one physics step."""

    left_cmd: float = 0.0  # normalised motor command [-1, 1]
    right_cmd: float = 0.0
    left_slip: float = 0.0  # slip ratio [0, 1)
    right_slip: float = 0.0
    left_encoder_ok: bool = True  # False: counts of this step are lost (drop-out)
    right_encoder_ok: bool = True
    gyro_noise_rad_s: float = 0.0  # this step's white-noise sample (drawn by the caller)
    left_speed_scale: float = 1.0  # factor on the target speed: 1 - load fraction (scenario)
    right_speed_scale: float = 1.0
    left_stalled: bool = False  # True: the wheel is held still for this step (scenario stall)
    right_stalled: bool = False


@dataclass(frozen=True)
class PhysicsState:
    """Full physical state; everything the sensors and the ground truth are made from."""

    time_s: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    v_m_s: float = 0.0
    yaw_rate_rad_s: float = 0.0
    left_rad_s: float = 0.0
    right_rad_s: float = 0.0
    left_angle_rad: float = 0.0  # true wheel rotation since start
    right_angle_rad: float = 0.0
    left_encoder_angle_rad: float = 0.0  # rotation the encoder saw (minus drop-outs)
    right_encoder_angle_rad: float = 0.0
    left_distance_true_m: float = 0.0  # signed ground-contact path of each wheel
    right_distance_true_m: float = 0.0
    gyro_rad_s: float = 0.0  # last gyro z sample: true rate + bias + noise, within the gyro's range
    ahrs_yaw_rad: float = 0.0  # integral of the gyro (drifts like an AHRS without compass)
    accel_m_s2: float = 0.0  # forward acceleration of the ground contact at the end of the last step


def step(state: PhysicsState, inputs: StepInputs, dt_s: float, vehicle: VehicleConfig) -> PhysicsState:
    """Advance the robot by ``dt_s`` seconds. Pure: same inputs, same result."""
    if dt_s <= 0.0:
        return state
    # First-order motor lag, discretised exactly so a big dt cannot overshoot.
    alpha = 1.0 - math.exp(-dt_s / vehicle.motor_time_constant_s)
    max_w = vehicle.max_wheel_rad_s
    exponent = vehicle.motor_curve_exponent
    left_gain, right_gain = motor_gains(vehicle, state.time_s)
    # Evaluated left to right, so with every factor 1.0 the target is exactly cmd * max_w.
    left_target = speed_fraction(inputs.left_cmd, exponent) * max_w * left_gain * inputs.left_speed_scale
    right_target = speed_fraction(inputs.right_cmd, exponent) * max_w * right_gain * inputs.right_speed_scale
    left_w = state.left_rad_s + (left_target - state.left_rad_s) * alpha
    right_w = state.right_rad_s + (right_target - state.right_rad_s) * alpha
    # Trapezoid over the step: the wheel speeds change smoothly within it.
    left_dangle = 0.5 * (state.left_rad_s + left_w) * dt_s
    right_dangle = 0.5 * (state.right_rad_s + right_w) * dt_s
    # A stalled wheel does not turn at all; once released it spins up from rest through the lag.
    if inputs.left_stalled:
        left_w = left_dangle = 0.0
    if inputs.right_stalled:
        right_w = right_dangle = 0.0
    left_ground = left_dangle * vehicle.left_radius_true_m * (1.0 - inputs.left_slip)
    right_ground = right_dangle * vehicle.right_radius_true_m * (1.0 - inputs.right_slip)
    ds = 0.5 * (left_ground + right_ground)
    dyaw = (left_ground - right_ground) / vehicle.track_true_m  # clockwise positive
    dx, dy = arc_step(state.yaw_rad, ds, dyaw)
    yaw_rate = dyaw / dt_s
    gyro = gyro_reading_rad_s(yaw_rate + vehicle.gyro_bias_rad_s + inputs.gyro_noise_rad_s)
    # The forward acceleration at the end of the step from the motor model itself (the lag's derivative),
    # not a difference of step-average speeds: that one, over a 1 us sub-step after a 5 ms one, gave
    # 10^4 m/s^2. A stall or a change of slip changes the speed at once here, with no acceleration.
    tau = vehicle.motor_time_constant_s
    left_accel = 0.0 if inputs.left_stalled else (left_target - left_w) / tau
    right_accel = 0.0 if inputs.right_stalled else (right_target - right_w) / tau
    accel = 0.5 * (left_accel * vehicle.left_radius_true_m * (1.0 - inputs.left_slip)
                   + right_accel * vehicle.right_radius_true_m * (1.0 - inputs.right_slip))
    return replace(
        state,
        time_s=state.time_s + dt_s,
        x_m=state.x_m + dx,
        y_m=state.y_m + dy,
        yaw_rad=wrap_pi(state.yaw_rad + dyaw),
        v_m_s=ds / dt_s,
        accel_m_s2=accel,
        yaw_rate_rad_s=yaw_rate,
        left_rad_s=left_w,
        right_rad_s=right_w,
        left_angle_rad=state.left_angle_rad + left_dangle,
        right_angle_rad=state.right_angle_rad + right_dangle,
        left_encoder_angle_rad=state.left_encoder_angle_rad
        + (left_dangle if inputs.left_encoder_ok else 0.0),
        right_encoder_angle_rad=state.right_encoder_angle_rad
        + (right_dangle if inputs.right_encoder_ok else 0.0),
        left_distance_true_m=state.left_distance_true_m + left_ground,
        right_distance_true_m=state.right_distance_true_m + right_ground,
        gyro_rad_s=gyro,
        ahrs_yaw_rad=wrap_pi(state.ahrs_yaw_rad + gyro * dt_s),
    )


@dataclass(frozen=True)
class TruthState:
    """Ground truth for tests (NED, yaw clockwise from north, yaw rate clockwise positive)."""

    x_m: float
    y_m: float
    yaw_rad: float
    v_m_s: float
    yaw_rate_rad_s: float
    left_wheel_rad_s: float
    right_wheel_rad_s: float
    left_distance_true_m: float
    right_distance_true_m: float
    time_s: float

    @classmethod
    def from_state(cls, s: PhysicsState) -> TruthState:
        return cls(
            x_m=s.x_m,
            y_m=s.y_m,
            yaw_rad=s.yaw_rad,
            v_m_s=s.v_m_s,
            yaw_rate_rad_s=s.yaw_rate_rad_s,
            left_wheel_rad_s=s.left_rad_s,
            right_wheel_rad_s=s.right_rad_s,
            left_distance_true_m=s.left_distance_true_m,
            right_distance_true_m=s.right_distance_true_m,
            time_s=s.time_s,
        )
