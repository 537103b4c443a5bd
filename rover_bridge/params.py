"""Robot profiles: TOML in, one frozen, validated `Profile` out (pure; the file read is the caller's).

Every parameter is declared exactly once, as a dataclass field whose metadata carries its
unit, valid range and one sentence of help (ros2_controllers' generated parameter
declarations are the model). Everything else is derived from those declarations: the
loader's checks, `check-params` output and the parameter reference (docs/parameters.md).

Loading a bad profile reports every problem at once, each with its key path and what was
expected, and raises `ConfigError`; nothing starts on a bad profile.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import itertools
import math
import tomllib
import types
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rover_bridge.errors import ConfigError


@dataclass(frozen=True, slots=True)
class Spec:
    """What one parameter means and which values it accepts."""

    unit: str
    help: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False  # lo itself is not allowed (e.g. a radius must be > 0)
    choices: tuple[str, ...] | None = None


def _p(default: Any, help: str, *, unit: str = "", lo: float | None = None, hi: float | None = None,
       lo_open: bool = False, choices: tuple[str, ...] | None = None) -> Any:
    spec = Spec(unit=unit, help=help, lo=lo, hi=hi, lo_open=lo_open, choices=choices)
    if isinstance(default, (list, tuple)):
        value = tuple(default)
        return field(default_factory=lambda: value, metadata={"spec": spec})
    return field(default=default, metadata={"spec": spec})


@dataclass(frozen=True, slots=True)
class RobotParams:
    wheel_radius_m: float = _p(
        0.05, "Nominal wheel radius, used for both wheels unless a per-wheel radius is given.",
        unit="m", lo=0.0, lo_open=True, hi=2.0)
    track_width_m: float = _p(
        0.30, "Wheel separation: centre of the left contact patch to centre of the right.",
        unit="m", lo=0.0, lo_open=True, hi=10.0)
    left_wheel_radius_m: float | None = _p(
        None, "Left wheel radius when it differs from wheel_radius_m (calibration).",
        unit="m", lo=0.0, lo_open=True, hi=2.0)
    right_wheel_radius_m: float | None = _p(None, "Right wheel radius when it differs from wheel_radius_m.",
                                            unit="m", lo=0.0, lo_open=True, hi=2.0)
    max_wheel_rpm: float = _p(
        200.0, "Wheel speed at full PWM; wheel commands are desaturated to it, keeping curvature.",
        unit="rpm", lo=0.0, lo_open=True, hi=20000.0)

    @property
    def left_radius_m(self) -> float:
        return self.wheel_radius_m if self.left_wheel_radius_m is None else self.left_wheel_radius_m

    @property
    def right_radius_m(self) -> float:
        return self.wheel_radius_m if self.right_wheel_radius_m is None else self.right_wheel_radius_m

    @property
    def max_wheel_rad_s(self) -> float:
        return self.max_wheel_rpm * 2.0 * math.pi / 60.0


@dataclass(frozen=True, slots=True)
class LimitsParams:
    max_linear_m_s: float = _p(0.8, "Largest forward or reverse body speed the bridge will command.",
                               unit="m/s", lo=0.0, lo_open=True, hi=50.0)
    max_angular_rad_s: float = _p(3.0, "Largest yaw rate the bridge will command, either direction.",
                                  unit="rad/s", lo=0.0, lo_open=True, hi=50.0)
    max_linear_accel_m_s2: float = _p(1.0, "Largest rate at which |v| may grow.",
                                      unit="m/s^2", lo=0.0, lo_open=True, hi=100.0)
    max_linear_decel_m_s2: float = _p(2.0, "Largest rate at which |v| may shrink (braking, timeouts).",
                                      unit="m/s^2", lo=0.0, lo_open=True, hi=100.0)
    max_angular_accel_rad_s2: float = _p(6.0, "Largest rate of change of the yaw rate.",
                                         unit="rad/s^2", lo=0.0, lo_open=True, hi=500.0)
    max_linear_jerk_m_s3: float | None = _p(
        None, "Optional jerk limit on v; unset means acceleration may step.",
        unit="m/s^3", lo=0.0, lo_open=True, hi=10000.0)
    max_angular_jerk_rad_s3: float | None = _p(None, "Optional jerk limit on omega; unset means it may step.",
                                               unit="rad/s^3", lo=0.0, lo_open=True, hi=10000.0)


@dataclass(frozen=True, slots=True)
class CommandParams:
    setpoint_timeout_s: float = _p(
        0.5, "With no valid request for this long, brake to a stop through the limiter.",
        unit="s", lo=0.05, hi=10.0)
    rate_hz: float = _p(
        20.0, "How often wheel outputs are refreshed (well inside the autopilot's override timeout).",
        unit="Hz", lo=2.0, hi=200.0)
    manual_linear_scale_m_s: float = _p(0.5, "MANUAL_CONTROL x = 1000 maps to this forward speed.",
                                        unit="m/s", lo=0.0, lo_open=True, hi=50.0)
    manual_angular_scale_rad_s: float = _p(
        1.5, "MANUAL_CONTROL r = 1000 maps to this yaw rate (a right turn).",
        unit="rad/s", lo=0.0, lo_open=True, hi=50.0)
    heading_kp_1_s: float = _p(2.0, "Earth-frame requests: commanded yaw rate per radian of heading error.",
                               unit="1/s", lo=0.0, lo_open=True, hi=50.0)
    accept_target_components: tuple[int, ...] = _p(
        (0, 1, 191),
        "Velocity requests addressed to one of these component ids (of the vehicle) are consumed.",
        lo=0, hi=255)


@dataclass(frozen=True, slots=True)
class NavigationParams:
    speed_m_s: float = _p(0.5, "Cruise speed to a position target that gives none (DO_CHANGE_SPEED changes it); "
                          "always within limits.max_linear_m_s.", unit="m/s", lo=0.0, lo_open=True, hi=50.0)
    arrival_radius_m: float = _p(0.15, "A position target is reached within this distance.", unit="m",
                                 lo=0.02, hi=10.0)
    max_distance_m: float = _p(200.0, "Position targets farther than this from the rover are refused.", unit="m",
                               lo=1.0, hi=1000.0)
    gcs_timeout_s: float = _p(
        5.0, "While a position target is followed (no request stream to time out), no ground-station "
        "HEARTBEAT for this long stops the rover: nobody is watching.", unit="s", lo=1.0, hi=60.0)
    gps_timeout_s: float = _p(
        2.0, "Global targets need the autopilot's GLOBAL_POSITION_INT no older than this; otherwise refused.",
        unit="s", lo=0.2, hi=30.0)
    turn_in_place_deg: float = _p(
        45.0, "Heading error above which the rover turns in place before it drives toward the target.",
        unit="deg", lo=5.0, hi=180.0)
    lookahead_m: float = _p(0.5, "Pure pursuit: the shortest look-ahead along the leg (it grows with speed).",
                            unit="m", lo=0.05, hi=20.0)
    yaw_tolerance_deg: float = _p(4.0, "A final heading (yaw given with the target) is reached within this.",
                                  unit="deg", lo=0.5, hi=45.0)
    report_hz: float = _p(4.0, "While a target is followed: NAV_CONTROLLER_OUTPUT and POSITION_TARGET_* to the "
                          "ground stations at this rate.", unit="Hz", lo=0.2, hi=50.0)


MODE_NUMBER = (0, 4294967295)  # HEARTBEAT custom_mode


@dataclass(frozen=True, slots=True)
class ModesParams:
    """Which driver holds the wheels in which autopilot mode (HEARTBEAT custom_mode; ArduPilot Rover's numbers
    by default). A mode in no list stops, as in `stop`."""

    gcs: tuple[int, ...] = _p(
        (0, 1, 3, 15), "Modes in which a ground station's velocity requests and MANUAL_CONTROL drive the wheels "
        "(ArduPilot Rover: 0 MANUAL, 1 ACRO, 3 STEERING, 15 GUIDED).", lo=MODE_NUMBER[0], hi=MODE_NUMBER[1])
    targets: tuple[int, ...] = _p(
        (15,), "Modes in which position targets are taken (15 GUIDED); leaving them cancels a running target, and "
        "DO_REPOSITION's change-mode flag asks the autopilot for the lowest of them.",
        lo=MODE_NUMBER[0], hi=MODE_NUMBER[1])
    autopilot: tuple[int, ...] = _p(
        (5, 6, 8, 9, 10, 11, 12), "Modes in which the autopilot navigates itself and its per-wheel demand "
        "([demand]) drives the wheels through the bridge's limits and speed loop (5 LOITER, 6 FOLLOW, 8 DOCK, "
        "9 CIRCLE, 10 AUTO, 11 RTL, 12 SMART_RTL): missions, return home, fence and failsafe actions.",
        lo=MODE_NUMBER[0], hi=MODE_NUMBER[1])
    stop: tuple[int, ...] = _p(
        (4,), "Modes in which the bridge brakes to a stop and holds neutral, refusing requests until the mode "
        "changes; a GCS asking for one stops the rover at once (4 HOLD: a GCS's Hold, Pause and Stop buttons; PX4 "
        "Hold is 50593792).", lo=MODE_NUMBER[0], hi=MODE_NUMBER[1])


@dataclass(frozen=True, slots=True)
class DemandParams:
    """The autopilot's own per-wheel demand, read from SERVO_OUTPUT_RAW while it navigates ([modes] autopilot)."""

    left_output: int = _p(
        5, "Servo output whose SERVO_OUTPUT_RAW value is the autopilot's left-wheel demand (ArduPilot: "
        "SERVOn_FUNCTION = 73 ThrottleLeft on an unconnected output).", lo=1, hi=16)
    right_output: int = _p(6, "Servo output carrying the right-wheel demand (SERVOn_FUNCTION = 74 ThrottleRight).",
                           lo=1, hi=16)
    pwm_min: int = _p(1000, "The demand outputs' full reverse (their SERVOn_MIN).", unit="us", lo=500, hi=2500)
    pwm_trim: int = _p(1500, "The demand outputs' no demand (their SERVOn_TRIM).", unit="us", lo=500, hi=2500)
    pwm_max: int = _p(2000, "The demand outputs' full forward (their SERVOn_MAX).", unit="us", lo=500, hi=2500)
    timeout_s: float = _p(
        0.3, "No SERVO_OUTPUT_RAW for this long while the autopilot drives: brake through the limiter, as a "
        "request timeout does.", unit="s", lo=0.05, hi=5.0)
    rate_hz: float = _p(
        40.0, "SERVO_OUTPUT_RAW rate asked of the autopilot (ArduPilot grants at most 0.8 x SCHED_LOOP_RATE: 40 Hz "
        "at its default 50).", unit="Hz", lo=1.0, hi=200.0)
    speed_loop: bool = _p(
        False, "Close the bridge's wheel-speed loop ([control] mode = closed_loop) around the autopilot's demand "
        "too. Off: the demand is already closed by the autopilot's own speed and turn-rate controllers, and a "
        "second loop in series corrects the same deficit again (benchmarks/bench_demand_loop.py, a 3-waypoint "
        "mission's cross-track: emulator, left motor 20 % weak, 0.72 m with it, 0.66 m without; real Rover SITL "
        "0.44-0.55 m with it, 0.44-0.56 m without, 0.36-0.50 m for ArduPilot alone).")


@dataclass(frozen=True, slots=True)
class OutputParams:
    mode: str = _p(
        "rc_override", "How wheels are driven: RC_CHANNELS_OVERRIDE (times out safely) or DO_SET_SERVO "
        "(held by ArduPilot with no timeout).", choices=("rc_override", "servo"))
    left_channel: int = _p(
        1, "RC input channel (rc_override) or servo output (servo) that drives the left wheel.",
        lo=1, hi=16)
    right_channel: int = _p(3, "RC input channel (rc_override) or servo output (servo) for the right wheel.",
                            lo=1, hi=16)
    pwm_min: int = _p(1000, "PWM for full reverse.", unit="us", lo=500, hi=2500)
    pwm_trim: int = _p(1500, "PWM for a stopped wheel (neutral).", unit="us", lo=500, hi=2500)
    pwm_max: int = _p(2000, "PWM for full forward.", unit="us", lo=500, hi=2500)
    left_reversed: bool = _p(False, "Left motor is mounted so that pwm_max drives it backwards.")
    right_reversed: bool = _p(False, "Right motor is mounted so that pwm_max drives it backwards.")
    override_source_system: int = _p(
        255, "System id the overrides are sent from: ArduPilot obeys RC_CHANNELS_OVERRIDE only from "
        "MAV_GCS_SYSID (default 255) and silently ignores every other sender.", lo=1, hi=255)


@dataclass(frozen=True, slots=True)
class ControlParams:
    mode: str = _p(
        "closed_loop", "closed_loop: a per-wheel speed loop (feedforward from the PWM map plus PI on the speed "
        "measured from WHEEL_DISTANCE) between the kinematics and the PWM; open_loop: the PWM map alone.",
        choices=("closed_loop", "open_loop"))
    # The defaults assume nothing of the plant (rover_bridge/command/wheel_control.py): no P, a slow integrator.
    # `rover-bridge calibrate` measures the plant and writes all six by the lambda rule it states.
    kp: float = _p(0.0, "Driving (the wheels' common speed): wheel speed command added per unit of speed error "
                   "against the reference model.", unit="(rad/s)/(rad/s)", lo=0.0, hi=20.0)
    ki_1_s: float = _p(2.0, "Driving: wheel speed command added per second per unit of speed error.",
                       unit="1/s", lo=0.0, hi=200.0)
    reference_s: float = _p(
        0.3, "Driving: the response expected of the wheels' common speed to the feedforward (first-order time "
        "constant: motor lag, the body's inertia); the error is taken against the target through this lag, so "
        "a ramp does not wind the integrator up.", unit="s", lo=0.01, hi=2.0)
    turn_kp: float = _p(0.0, "Turning (half the wheels' difference): as kp.", unit="(rad/s)/(rad/s)", lo=0.0, hi=20.0)
    turn_ki_1_s: float = _p(4.0, "Turning: as ki_1_s.", unit="1/s", lo=0.0, hi=200.0)
    turn_reference_s: float = _p(
        0.3, "Turning: as reference_s (a skid rover may turn at once: ArduPilot's SITL model does).",
        unit="s", lo=0.01, hi=2.0)
    integrator_max_fraction: float = _p(
        0.5, "Largest correction the integrator may hold, as a fraction of the wheel's top speed.",
        lo=0.0, lo_open=True, hi=1.0)
    speed_window_s: float = _p(
        0.1, "The measured wheel speeds are the mean over this long of WHEEL_DISTANCE samples (uneven increments "
        "average out).", unit="s", lo=0.0, hi=1.0)
    encoder_timeout_s: float = _p(
        0.5, "No WHEEL_DISTANCE for this long: the loop falls back to feedforward only (said once) and resumes "
        "when data returns.", unit="s", lo=0.05, hi=10.0)
    slip_compensation: bool = _p(
        True, "While the estimator reports wheel slip, hold the wheel targets at their values when slip began "
        "(no further acceleration) and freeze the integrators, until wheels and gyro agree again.")
    fault_min_fraction: float = _p(
        0.3, "Wiring fault check: only wheels commanded above this fraction of their top speed are checked.",
        lo=0.05, hi=1.0)
    fault_time_s: float = _p(
        1.0, "A checked wheel that turns the wrong way, or not at all, for this long is a wiring fault: the rover "
        "stops and the bridge says which wheel and what to check.", unit="s", lo=0.2, hi=10.0)
    left_curve_pwm_us: tuple[float, ...] = _p(
        (), "Measured PWM -> speed map of the left wheel (PWM values, increasing; written by `rover-bridge "
        "calibrate`); with left_curve_rad_s it replaces the linear map (and output.left_reversed) for this wheel.",
        unit="us", lo=500.0, hi=2500.0)
    left_curve_rad_s: tuple[float, ...] = _p(
        (), "The left wheel's steady speed (forward +) at each left_curve_pwm_us value (non-decreasing, spanning 0).",
        unit="rad/s", lo=-20000.0, hi=20000.0)
    right_curve_pwm_us: tuple[float, ...] = _p((), "As left_curve_pwm_us, for the right wheel.", unit="us",
                                              lo=500.0, hi=2500.0)
    right_curve_rad_s: tuple[float, ...] = _p((), "As left_curve_rad_s, for the right wheel.", unit="rad/s",
                                             lo=-20000.0, hi=20000.0)


@dataclass(frozen=True, slots=True)
class EncoderParams:
    left_index: int = _p(
        0, "Index of the left wheel in WHEEL_DISTANCE.distance (depends on the WENC parameters).",
        lo=0, hi=15)
    right_index: int = _p(1, "Index of the right wheel in WHEEL_DISTANCE.distance.", lo=0, hi=15)
    left_reversed: bool = _p(False, "Left encoder counts down when the wheel drives forward.")
    right_reversed: bool = _p(False, "Right encoder counts down when the wheel drives forward.")


@dataclass(frozen=True, slots=True)
class SafetyParams:
    heartbeat_timeout_s: float = _p(
        3.0, "Autopilot heartbeat silent this long: stop commanding; resume only on a "
        "fresh request.", unit="s", lo=0.5, hi=60.0)
    require_armed: bool = _p(True, "Drive only while the autopilot reports armed; otherwise hold neutral.")
    attitude_timeout_s: float = _p(1.0, "Earth-frame (heading) requests need an ATTITUDE yaw younger than "
                                   "this; a stale yaw brakes the rover like a request timeout.",
                                   unit="s", lo=0.05, hi=10.0)
    loop_watchdog_s: float = _p(
        0.7, "If the bridge's loop has not completed a pass for this long (a hang), a separate thread sends "
        "neutral and release and ends the process with exit 1 (systemd restarts it); 0 disables. Keep it "
        "below the unit's WatchdogSec.", unit="s", lo=0.0, hi=30.0)
    stop_confirm_timeout_s: float = _p(
        0.3, "On exit, after neutral and release, wait at most this long for the autopilot's proof that it "
        "processed them (its answer to a TIMESYNC sent after them; resent every 0.1 s), then close the link.",
        unit="s", lo=0.05, hi=5.0)


@dataclass(frozen=True, slots=True)
class TimingParams:
    budget_fraction: float = _p(
        0.8, "Each periodic output (overrides, ODOMETRY, heartbeats): the work of the pass that sends it "
        "(wake-up to the frame written) should take at most this fraction of its period; longer passes are "
        "counted (over_budget).", lo=0.0, lo_open=True, hi=1.0)
    deadline_fraction: float = _p(
        0.95, "Each periodic output must leave within this fraction of its period after its scheduled time "
        "on its grid (the previous one's scheduled time plus the period); later ones are counted as late and "
        "reported to the ground station (STATUSTEXT) while it lasts.", lo=0.0, lo_open=True, hi=1.0)
    report_window_s: float = _p(
        10.0, "Late outputs are reported when they start, at most once per this window while they go on "
        "(with the count over it), and as over once a whole window passes without one.", unit="s",
        lo=1.0, hi=600.0)
    log_interval_s: float = _p(
        60.0, "How often the loop logs its timing (outputs sent, late, over budget, worst): INFO, WARNING if "
        "any output was late; 0 disables.", unit="s", lo=0.0, hi=86400.0)


@dataclass(frozen=True, slots=True)
class MavlinkParams:
    vehicle_system_id: int = _p(0, "The vehicle's system id; 0 learns it from the autopilot's heartbeat.",
                                lo=0, hi=255)
    component_id: int = _p(191, "The bridge's own component id (MAV_COMP_ID_ONBOARD_COMPUTER).", lo=1, hi=255)
    autopilot_batch_ms: float = _p(
        25.0, "After reading the autopilot link, wait this long before waking for it again: its telemetry is "
        "then read in the wake-ups the bridge makes anyway (a request, an output) or after this time, about "
        "half the wake-ups at 50 Hz telemetry, but forwarded to the GCS up to this much later. Only on a link "
        "whose datagrams the kernel time-stamps (udpin), so the estimator still sees each frame's arrival "
        "time; serial, TCP and udpout links are read as frames arrive. 0 wakes for every datagram. "
        "Ground-station links always wake at once.",
        unit="ms", lo=0.0, hi=50.0)


@dataclass(frozen=True, slots=True)
class EstimatorParams:
    gyro_source: str = _p(
        "auto", "Where the yaw rate comes from; auto takes the first of ATTITUDE, SCALED_IMU, "
        "RAW_IMU that arrives.", choices=("auto", "attitude", "raw_imu", "scaled_imu"))
    calibrate: bool = _p(False, "Estimate effective track width and left/right radius ratio online.")
    stream_rate_hz: float = _p(50.0, "Rate requested from the autopilot for WHEEL_DISTANCE and the gyro. ODOMETRY "
                               "extrapolates up to one period: a turn that starts or stops changes its rate by about "
                               "10 rad/s^2, half a degree over 50 ms (20 Hz), a tenth over 20 ms.",
                               unit="Hz", lo=1.0, hi=200.0)
    gyro_noise_rad_s: float = _p(0.005, "Gyro yaw-rate noise per sample (1 sigma).", unit="rad/s",
                                 lo=0.0, lo_open=True, hi=1.0)
    wheel_noise_m: float = _p(0.0001, "Noise of one WHEEL_DISTANCE reading (1 sigma: its quantisation, about a "
                              "third of one encoder count's distance).", unit="m", lo=0.0, lo_open=True, hi=0.1)
    wheel_noise_fraction: float = _p(
        0.02, "Wheel speed noise as a fraction of the speed (geometry error, small slip; 1 sigma).",
        lo=0.0, lo_open=True, hi=1.0)
    gate_sigma: float = _p(
        4.0, "Mahalanobis gate per sensor, in standard deviations; also the wheel/gyro yaw-rate "
        "disagreement that counts as wheel slip.", lo=1.0, hi=100.0)


@dataclass(frozen=True, slots=True)
class OdometryParams:
    rate_hz: float = _p(30.0, "How often ODOMETRY is published (on average: one may leave up to half a "
                                 "period early, with a message the bridge handles anyway).", unit="Hz", lo=0.5,
                        hi=200.0)
    targets: str = _p(
        "gcs", "Where ODOMETRY goes: the ground stations, the autopilot (external navigation), both, "
        "or nowhere.", choices=("gcs", "autopilot", "both", "none"))
    unobserved_variance: float | None = _p(
        None, "Variance published for the axes the estimator does not observe (z, roll, pitch and their "
        "rates). Unset: 1e4 ('unknown') when ODOMETRY goes only to ground stations, 0.01 when it goes to the "
        "autopilot (a rover on the ground: held by the ground, not measured), because ArduPilot folds z into "
        "its one position error and roll/pitch into its one angle error, so a large value there leaves "
        "position and yaw unweighted.", unit="m^2 | rad^2", lo=0.0, lo_open=True, hi=1e12)
    frame: str = _p(
        "auto", "The frame ODOMETRY's pose is in: 'start' (origin and axes of the bridge's start pose) or "
        "'autopilot' (north-aligned by the autopilot's ATTITUDE yaw and anchored at its LOCAL_POSITION_NED, so "
        "a restarted bridge continues the autopilot's frame); 'auto' is 'autopilot' when ODOMETRY goes to the "
        "autopilot, else 'start'.", choices=("auto", "start", "autopilot"))
    anchor_timeout_s: float = _p(
        3.0, "frame 'autopilot': how long to hold ODOMETRY back, once wheel data and ATTITUDE flow, waiting "
        "for the autopilot's LOCAL_POSITION_NED; without one (a cold start of both) the pose starts at the "
        "origin, north-aligned.", unit="s", lo=0.0, hi=60.0)


    @property
    def to_autopilot(self) -> bool:
        return self.targets in ("autopilot", "both")

    @property
    def resolved_frame(self) -> str:
        """'start' or 'autopilot' ('auto' resolved by where ODOMETRY goes)."""
        if self.frame != "auto":
            return self.frame
        return "autopilot" if self.to_autopilot else "start"

    @property
    def resolved_unobserved_variance(self) -> float:
        if self.unobserved_variance is not None:
            return self.unobserved_variance
        return AUTOPILOT_UNOBSERVED_VARIANCE if self.to_autopilot else GCS_UNOBSERVED_VARIANCE


GCS_UNOBSERVED_VARIANCE = 1e4  # sigma 100: "unknown", honest for a ground station
AUTOPILOT_UNOBSERVED_VARIANCE = 0.01  # a rover on the ground; ArduPilot's folded errors stay at their floors


@dataclass(frozen=True, slots=True)
class SecurityParams:
    require_signed_commands: bool = _p(
        False, "Accept velocity requests and commands only when MAVLink 2 signed "
        "with the key in key_file.")
    key_file: str = _p("", "File holding the 32-byte signing secret (hex or raw); must not be group/world "
                       "readable.")
    allowed_sources: tuple[str, ...] = _p(
        (), "If not empty, only these 'sysid:compid' sources (compid * for any) may send requests.")


@dataclass(frozen=True, slots=True)
class AvoidanceParams:
    enabled: bool = _p(
        True, "Slow the bridge's own drivers (GCS velocity requests, MANUAL_CONTROL, position targets) so the "
        "rover stops AVOID_MARGIN short of what the vehicle's DISTANCE_SENSOR / OBSTACLE_DISTANCE show and "
        "FENCE_MARGIN inside the autopilot's fences, as ArduPilot's simple avoidance does (AVOID_* and FENCE_* "
        "read from the autopilot); nothing changes without a range sensor or an enabled fence.")
    in_manual: bool = _p(False, "Avoid in MANUAL too (ArduPilot does not avoid in MANUAL).")
    crawl_speed_m_s: float = _p(
        0.2, "While a range sensor that was seen is silent (sensor_timeout_s), the speed in any direction is "
        "capped at this.", unit="m/s", lo=0.0, hi=5.0)
    reaction_delay_s: float = _p(
        0.3, "Time from an override to the wheels' answer (the autopilot's loop, the motors' lag); one output "
        "period is added. The speed toward an obstacle is capped so the rover stops after this delay.",
        unit="s", lo=0.0, hi=2.0)
    sector_timeout_s: float = _p(
        1.0, "A sector's reading older than this is unknown (ArduPilot's PROXIMITY_FACE_RESET_MS).",
        unit="s", lo=0.1, hi=10.0)
    sensor_timeout_s: float = _p(
        0.5, "A range sensor seen and then silent this long slows the rover to crawl_speed_m_s (ArduPilot's "
        "PROXIMITY_MAV_TIMEOUT_MS); at most sector_timeout_s.", unit="s", lo=0.1, hi=10.0)
    sensor_rate_hz: float = _p(
        10.0, "Once the autopilot sends DISTANCE_SENSOR, it is asked for at this rate (its EXTRA3 stream is often "
        "1 Hz: too slow for sensor_timeout_s); 0: not asked.", unit="Hz", lo=0.0, hi=50.0)


@dataclass(frozen=True, slots=True)
class Profile:
    """A whole robot profile. Construct through `load_profile` / `profile_from_dict`."""

    robot: RobotParams = field(default_factory=RobotParams)
    limits: LimitsParams = field(default_factory=LimitsParams)
    command: CommandParams = field(default_factory=CommandParams)
    navigation: NavigationParams = field(default_factory=NavigationParams)
    modes: ModesParams = field(default_factory=ModesParams)
    demand: DemandParams = field(default_factory=DemandParams)
    output: OutputParams = field(default_factory=OutputParams)
    control: ControlParams = field(default_factory=ControlParams)
    encoders: EncoderParams = field(default_factory=EncoderParams)
    safety: SafetyParams = field(default_factory=SafetyParams)
    timing: TimingParams = field(default_factory=TimingParams)
    mavlink: MavlinkParams = field(default_factory=MavlinkParams)
    estimator: EstimatorParams = field(default_factory=EstimatorParams)
    odometry: OdometryParams = field(default_factory=OdometryParams)
    security: SecurityParams = field(default_factory=SecurityParams)
    avoidance: AvoidanceParams = field(default_factory=AvoidanceParams)


@dataclass(frozen=True, slots=True)
class ParamInfo:
    """One declared parameter, as docs/parameters.md and check-params show it."""

    section: str
    name: str
    type_name: str
    optional: bool
    default: Any
    spec: Spec

    @property
    def path(self) -> str:
        return f"{self.section}.{self.name}"

    @property
    def range_text(self) -> str:
        if self.spec.choices:
            return " | ".join(f'"{c}"' for c in self.spec.choices)
        if self.spec.lo is None and self.spec.hi is None:
            return ""
        lo_bracket = "(" if self.spec.lo_open else "["
        lo = "-inf" if self.spec.lo is None else _num(self.spec.lo)
        hi = "inf" if self.spec.hi is None else _num(self.spec.hi)
        return f"{lo_bracket}{lo}, {hi}]"


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else repr(x)


def _base_type(annotation: Any) -> tuple[str, bool]:
    """('float' | 'int' | 'bool' | 'str' | 'list[int]' | 'list[str]', optional?) of a field annotation."""
    optional = False
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        optional = True
        annotation = args[0]
        origin = typing.get_origin(annotation)
    if origin is tuple:
        inner = typing.get_args(annotation)[0]
        return f"list[{inner.__name__}]", optional
    return annotation.__name__, optional


def iter_params() -> Iterator[ParamInfo]:
    """Every declared parameter, in declaration order."""
    for sec_field in dataclasses.fields(Profile):
        cls = _section_class(sec_field.name)
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            type_name, optional = _base_type(hints[f.name])
            if f.default is not dataclasses.MISSING:
                default: Any = f.default
            else:
                default = f.default_factory()  # type: ignore[operator]
            yield ParamInfo(sec_field.name, f.name, type_name, optional, default, f.metadata["spec"])


def _section_class(section: str) -> type[Any]:
    return type(getattr(Profile(), section))


def _check_value(info: ParamInfo, value: Any) -> tuple[Any, list[str]]:
    """Convert a TOML value to the declared type, or say what was expected."""
    where = info.path
    if value is None:
        return None, []
    t = info.type_name
    if t.startswith("list["):
        if not isinstance(value, list):
            return None, [f"{where}: expected a list of {t[5:-1]}, got {type(value).__name__} {value!r}"]
        out = []
        problems = []
        for i, item in enumerate(value):
            conv, errs = _check_scalar(f"{where}[{i}]", t[5:-1], info.spec, item)
            problems += errs
            out.append(conv)
        return tuple(out), problems
    return _check_scalar(where, t, info.spec, value)


def _check_scalar(where: str, t: str, spec: Spec, value: Any) -> tuple[Any, list[str]]:
    # bool is a subclass of int in Python; a profile that says `pwm_min = true` is a mistake.
    if t == "bool":
        if not isinstance(value, bool):
            return None, [f"{where}: expected true or false, got {type(value).__name__} {value!r}"]
        return value, []
    if t == "str":
        if not isinstance(value, str):
            return None, [f"{where}: expected a string, got {type(value).__name__} {value!r}"]
        if spec.choices and value not in spec.choices:
            hint = difflib.get_close_matches(value, spec.choices, n=1)
            extra = f" (did you mean {hint[0]!r}?)" if hint else ""
            return None, [f"{where}: expected one of {', '.join(spec.choices)}, got {value!r}{extra}"]
        return value, []
    if t == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            return None, [f"{where}: expected an integer, got {type(value).__name__} {value!r}"]
        num: float = value
    elif t == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return None, [f"{where}: expected a number, got {type(value).__name__} {value!r}"]
        if not math.isfinite(value):
            return None, [f"{where}: expected a finite number, got {value!r}"]
        num = float(value)
        value = num
    else:  # pragma: no cover - a declaration error, caught by the tests of every profile
        raise TypeError(f"unsupported parameter type {t} at {where}")
    lo_ok = spec.lo is None or (num > spec.lo if spec.lo_open else num >= spec.lo)
    hi_ok = spec.hi is None or num <= spec.hi
    if not (lo_ok and hi_ok):
        lo_b = "(" if spec.lo_open else "["
        lo = "-inf" if spec.lo is None else _num(spec.lo)
        hi = "inf" if spec.hi is None else _num(spec.hi)
        return None, [f"{where}: {value!r} is out of range, expected a value in {lo_b}{lo}, {hi}]"]
    return value, []


def _cross_checks(p: Profile, bad: frozenset[str] = frozenset()) -> list[str]:
    """Relations between keys. A check is skipped when one of its keys was itself invalid (`bad`):
    it would otherwise run on the default standing in for that key and report a confusing problem."""

    def checkable(*paths: str) -> bool:
        return not bad.intersection(paths)

    problems = []
    o = p.output
    pwm_keys = ("output.pwm_min", "output.pwm_trim", "output.pwm_max")
    if checkable(*pwm_keys) and not o.pwm_min < o.pwm_trim < o.pwm_max:
        problems.append(f"output: expected pwm_min < pwm_trim < pwm_max, got {o.pwm_min} / {o.pwm_trim} / "
                        f"{o.pwm_max}")
    if checkable("output.left_channel", "output.right_channel") and o.left_channel == o.right_channel:
        problems.append(f"output: left_channel and right_channel are both {o.left_channel}; "
                        "each wheel needs its own")
    c = p.control
    for side in ("left", "right"):
        pwm_key, speed_key = f"control.{side}_curve_pwm_us", f"control.{side}_curve_rad_s"
        if not checkable(pwm_key, speed_key):
            continue
        pwm, speed = getattr(c, f"{side}_curve_pwm_us"), getattr(c, f"{side}_curve_rad_s")
        problems += [f"{side} curve: {why}" for why in curve_problems(pwm, speed)]
    e = p.encoders
    if checkable("encoders.left_index", "encoders.right_index") and e.left_index == e.right_index:
        problems.append(f"encoders: left_index and right_index are both {e.left_index}")
    if (checkable("command.rate_hz", "safety.heartbeat_timeout_s")
            and 1.0 / p.command.rate_hz >= p.safety.heartbeat_timeout_s):
        problems.append("command.rate_hz: outputs must refresh faster than safety.heartbeat_timeout_s")
    tm = p.timing
    if checkable("timing.budget_fraction", "timing.deadline_fraction") and tm.budget_fraction > tm.deadline_fraction:
        problems.append(f"timing: budget_fraction {tm.budget_fraction} is past deadline_fraction "
                        f"{tm.deadline_fraction}: the work must fit before the deadline")
    for i, src in enumerate(p.security.allowed_sources):
        parts = src.split(":")
        ok = len(parts) == 2 and parts[0].isdigit() and 0 < int(parts[0]) <= 255 and (
            parts[1] == "*" or (parts[1].isdigit() and int(parts[1]) <= 255))
        if not ok:
            problems.append(f"security.allowed_sources[{i}]: expected 'sysid:compid' or 'sysid:*', "
                            f"got {src!r}")
    problems += _mode_table_problems(p, checkable)
    if (checkable("security.require_signed_commands", "security.key_file")
            and p.security.require_signed_commands and not p.security.key_file):
        problems.append("security: require_signed_commands = true needs key_file")
    a = p.avoidance
    if (checkable("avoidance.sensor_timeout_s", "avoidance.sector_timeout_s")
            and a.sensor_timeout_s > a.sector_timeout_s):
        # Between the two a dead sensor's sectors are unknown (no cap) and it is not yet silent (no crawl).
        problems.append("avoidance: sensor_timeout_s must not exceed sector_timeout_s (a dead sensor would go "
                        "unnoticed in between)")
    return problems


def _mode_table_problems(p: Profile, checkable: Any) -> list[str]:
    """[modes]: one owner per mode; [demand]: a usable PWM range, two outputs, a timeout the rate can meet."""
    problems = []
    m = p.modes
    if checkable("modes.gcs", "modes.targets", "modes.autopilot", "modes.stop"):
        bridge = set(m.gcs) | set(m.targets)
        for mode in sorted(set(m.stop) & (bridge | set(m.autopilot))):
            problems.append(f"modes: mode {mode} is in stop and in another list; a stop mode has no driver")
        for mode in sorted(set(m.autopilot) & bridge):
            problems.append(f"modes: mode {mode} is in autopilot and in gcs/targets; in one mode either the "
                            "autopilot's navigation or the bridge's requests hold the wheels")
    d = p.demand
    if (checkable("demand.pwm_min", "demand.pwm_trim", "demand.pwm_max")
            and not d.pwm_min < d.pwm_trim < d.pwm_max):
        problems.append(f"demand: expected pwm_min < pwm_trim < pwm_max, got {d.pwm_min} / {d.pwm_trim} / "
                        f"{d.pwm_max}")
    if checkable("demand.left_output", "demand.right_output") and d.left_output == d.right_output:
        problems.append(f"demand: left_output and right_output are both {d.left_output}")
    if checkable("demand.timeout_s", "demand.rate_hz") and d.timeout_s < 2.0 / d.rate_hz:
        problems.append(f"demand.timeout_s: {d.timeout_s:g} s is shorter than two SERVO_OUTPUT_RAW periods at "
                        f"demand.rate_hz ({2.0 / d.rate_hz:g} s)")
    o = p.output
    if (o.mode == "servo" and m.autopilot and checkable("output.left_channel", "output.right_channel")
            and {o.left_channel, o.right_channel} & {d.left_output, d.right_output}):
        problems.append("output: in servo mode the wheel outputs must not be the demand outputs "
                        f"(demand.left_output {d.left_output}, right_output {d.right_output})")
    return problems


# Keys that moved: a profile still using one is refused with where it went (no two sources of truth).
MOVED_KEYS = {
    "safety.stop_modes": "stop",
    "navigation.guided_modes": "targets",
}


def curve_problems(pwm_us: tuple[float, ...], speed_rad_s: tuple[float, ...]) -> list[str]:
    """What is wrong with a PWM -> speed map (empty: usable, or both unset)."""
    if not pwm_us and not speed_rad_s:
        return []
    out = []
    if len(pwm_us) != len(speed_rad_s):
        out.append(f"{len(pwm_us)} PWM values but {len(speed_rad_s)} speeds: one speed per PWM")
    elif len(pwm_us) < 2:
        out.append("needs at least two points")
    else:
        if any(b <= a for a, b in itertools.pairwise(pwm_us)):
            out.append(f"PWM values must increase, got {list(pwm_us)}")
        if any(b < a for a, b in itertools.pairwise(speed_rad_s)):
            out.append(f"speeds must not decrease with PWM (reversed motor: calibrate again), got {list(speed_rad_s)}")
        if not speed_rad_s[0] < 0.0 < speed_rad_s[-1]:
            out.append("speeds must span both directions (a negative first and a positive last value)")
    return out


def profile_warnings(p: Profile) -> list[str]:
    """Valid but likely wrong combinations: said at start-up (and by check-params), never refused."""
    out = []
    odo = p.odometry
    if odo.to_autopilot and odo.frame == "start":
        out.append("odometry.frame = 'start' with ODOMETRY to the autopilot: a restarted bridge starts a new "
                   "frame at (0, 0, yaw 0) and ArduPilot's position runs off (it rejects the jump and fuses the "
                   "rotated velocity); and with EK3_SRC1_YAW = 6 ArduPilot's north becomes the start heading. "
                   "Use 'autopilot' (or leave 'auto').")
    if odo.to_autopilot and odo.unobserved_variance is not None and odo.unobserved_variance > 1.0:
        out.append(f"odometry.unobserved_variance = {odo.unobserved_variance:g} with ODOMETRY to the autopilot: "
                   "ArduPilot folds it into its position and angle errors and clamps them (100 m, 1.5 rad), so it "
                   "navigates on velocity and gyro alone; leave it unset (0.01 then) or set it small.")
    return out


def profile_from_dict(data: Mapping[str, Any], source: str = "<profile>") -> Profile:
    """Validate a parsed TOML document; raise ConfigError listing every problem (prefixed by `source`)."""
    problems: list[str] = []
    bad: set[str] = set()  # key paths whose value was rejected
    by_section: dict[str, dict[str, ParamInfo]] = {}
    for declared in iter_params():
        by_section.setdefault(declared.section, {})[declared.name] = declared
    sections: dict[str, Any] = {}
    for sec_name, table in data.items():
        if sec_name not in by_section:
            hint = difflib.get_close_matches(sec_name, list(by_section), n=1)
            extra = f" (did you mean [{hint[0]}]?)" if hint else ""
            problems.append(f"[{sec_name}]: unknown section{extra}; known: {', '.join(by_section)}")
            continue
        if not isinstance(table, dict):
            problems.append(f"{sec_name}: expected a table [{sec_name}], got {type(table).__name__}")
            continue
        values: dict[str, Any] = {}
        for key, value in table.items():
            info = by_section[sec_name].get(key)
            moved = MOVED_KEYS.get(f"{sec_name}.{key}")
            if info is None and moved is not None:
                shown = toml_value(tuple(value) if isinstance(value, list) else value)
                problems.append(f"{sec_name}.{key}: moved to the mode table: write `{moved} = {shown}` under [modes] "
                                "(which driver holds the wheels in which autopilot mode; see check-params --table)")
                continue
            if info is None:
                hint = difflib.get_close_matches(key, list(by_section[sec_name]), n=1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                problems.append(f"{sec_name}.{key}: unknown key{extra}")
                continue
            conv, errs = _check_value(info, value)
            problems += errs
            if errs:
                bad.add(info.path)
            else:
                values[key] = conv
        sections[sec_name] = values
    # Cross-field checks run on the values that were valid, so one run reports everything.
    profile = Profile()
    built = {name: dataclasses.replace(getattr(profile, name), **vals) for name, vals in sections.items()}
    profile = dataclasses.replace(profile, **built)
    problems += _cross_checks(profile, frozenset(bad))
    if problems:
        raise ConfigError([f"{source}: {p}" for p in problems])
    return profile


# The profiles shipped with the package (package data, one copy: params/ in a clone links to these).
PROFILES_DIR = Path(__file__).resolve().parent / "profiles"


def packaged_profiles() -> list[str]:
    """Names of the packaged profiles (``default``, ``ardupilot-sitl-skid``): what ``--params NAME`` takes."""
    return list(_packaged_names())


@functools.cache
def _packaged_names() -> tuple[str, ...]:
    # Listed once: the package's files do not change while it runs, and every command line's parser names them.
    return tuple(sorted(p.stem for p in PROFILES_DIR.glob("*.toml")))


def find_profile(name_or_path: str | Path) -> Path:
    """The file a ``--params`` value means: the path itself when it exists, else for a bare name
    (``default``, ``default.toml``: no directory part) the packaged profile of that name, so the
    default works from any working directory and in any install."""
    path = Path(name_or_path)
    if path.exists() or path.parent != Path("."):
        return path
    packaged = PROFILES_DIR / (path.name if path.suffix == ".toml" else f"{path.name}.toml")
    return packaged if packaged.is_file() else path


def load_profile(path: str | Path) -> Profile:
    """Read and validate a TOML profile (a path or a packaged profile's name, ``find_profile``);
    ConfigError lists every problem with its key path."""
    given = path
    path = find_profile(path)
    if path.is_dir():
        raise ConfigError([f"{given}: a folder, not a profile"])
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        hint = (f" (packaged profiles: {', '.join(packaged_profiles())}; `rover-bridge init {given}` writes one "
                "to start from)") if isinstance(exc, FileNotFoundError) else ""
        raise ConfigError([f"{given}: cannot read profile: {exc.strerror or exc}{hint}"]) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{path}: not a TOML profile: not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
                           f"offset {exc.start})"]) from exc
    if not text:
        raise ConfigError([f"{path}: the profile is empty (`rover-bridge init {given} --force` writes one to start "
                           "from)"])
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"{path}: not valid TOML: {exc}"]) from exc
    return profile_from_dict(data, source=str(path))


def profile_to_toml(profile: Profile) -> str:
    """The fully resolved profile as TOML, every key present (unset optional keys as comments)."""
    lines: list[str] = []
    current = ""
    for info in iter_params():
        if info.section != current:
            if lines:
                lines.append("")
            lines.append(f"[{info.section}]")
            current = info.section
        value = getattr(getattr(profile, info.section), info.name)
        unit = f" [{info.spec.unit}]" if info.spec.unit else ""
        if value is None:
            lines.append(f"# {info.name} = (unset){unit}")
        else:
            comment = f"  # {info.spec.unit}" if info.spec.unit else ""
            lines.append(f"{info.name} = {toml_value(value)}{comment}")
    return "\n".join(lines) + "\n"


def toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return repr(value)


def markdown_table() -> str:
    """The parameter reference (docs/parameters.md), generated from the declarations."""
    rows = ["| key | type | unit | default | valid | meaning |", "|---|---|---|---|---|---|"]
    for info in iter_params():
        default = "unset" if info.default is None else toml_value(info.default)
        type_name = info.type_name + (" (optional)" if info.optional else "")
        rows.append(f"| `{info.path}` | {type_name} | {info.spec.unit} | `{default}` | {info.range_text} | "
                    f"{info.spec.help} |")
    return "\n".join(rows) + "\n"
