"""Vehicle profile: a TOML table -> a frozen, validated ``VehicleConfig``.

Nominal values (``wheel_radius_m``, ``track_width_m``) are what the bridge is told and what
the emulated autopilot's WENC_RADIUS parameters start at; the ``true_*`` values are the
physical robot. Making them differ is how a calibration error is simulated: the encoders
report rotation times the nominal radius while the body moves by the true one.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A vehicle profile or scenario file is invalid; the message lists every problem."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = tuple(problems)
        super().__init__(f"{source}: " + "; ".join(problems))


WHEEL_ORDERS = ("left_right", "right_left")
# "wheels": each wheel's motor lags on its own (both the common and the differential mode lag);
# "ardupilot_skid": ArduPilot SITL's rover-skid body, encoders and their timing (sitl/skid.py).
PLANTS = ("wheels", "ardupilot_skid")


@dataclass(frozen=True)
class VehicleConfig:
    """Physical robot plus the autopilot settings the emulator boots with (all SI units)."""

    # What the bridge is told (and WENC_RADIUS / WENC2_RADIUS boot values).
    wheel_radius_m: float = 0.05
    track_width_m: float = 0.30
    # The physical truth; None means "equal to nominal".
    true_left_radius_m: float | None = None
    true_right_radius_m: float | None = None
    true_track_width_m: float | None = None
    # Motors: PWM -> normalised command -> target wheel speed -> first-order lag.
    max_rpm: float = 200.0
    pwm_min: int = 1000
    pwm_trim: int = 1500
    pwm_max: int = 2000
    deadzone_pwm: int = 10
    motor_time_constant_s: float = 0.1
    # Imperfect motors (the defaults are ideal ones): per-wheel speed gain (0.8 = a 20 % weak motor),
    # curved command -> speed map (steady speed fraction = sign(c) * |c| ** exponent), and a battery
    # that sags both gains by this fraction of their start value per simulated minute (floor 50 %).
    left_motor_gain: float = 1.0
    right_motor_gain: float = 1.0
    motor_curve_exponent: float = 1.0
    battery_sag_per_min: float = 0.0
    # The body's model (PLANTS) and, for "ardupilot_skid", the fraction of Rover loops that start 1 ms late.
    plant: str = "wheels"
    loop_late_rate: float = 0.0
    # Wiring: which servo output drives which wheel, and the boot SERVOn_FUNCTION values.
    left_servo: int = 1
    right_servo: int = 3
    left_function: int = 51  # RCIN1 passthrough
    right_function: int = 53  # RCIN3 passthrough
    left_reversed: bool = False
    right_reversed: bool = False
    # Encoders: counts per wheel revolution (the hardware); optional random drop-outs.
    encoder_cpr: int = 1024
    encoder_dropout_rate: float = 0.0
    wheel_distance_order: str = "left_right"
    # Gyro (z, clockwise positive): bias + white noise (standard deviation per sample).
    gyro_bias_rad_s: float = 0.002
    gyro_noise_rad_s: float = 0.002
    # Autopilot behaviour.
    start_armed: bool = False
    passthrough_when_disarmed: bool = False
    strict_prearm: bool = False
    rc_override_time_s: float = 3.0
    gcs_sysid: int = 255
    deny_wheel_distance_interval: bool = True
    # Boot with ArduPilot set up to navigate on the companion's ODOMETRY (VISO_TYPE 1, EK3_SRC1_POSXY,
    # VELXY and YAW = 6): LOCAL_POSITION_NED and ATTITUDE's heading then come from it (sitl/extnav.py).
    external_nav: bool = False
    reboot_silence_s: float = 1.5
    physics_dt_s: float = 0.005
    # Stream group rates (Hz) at boot: SR0_* parameters.
    rate_raw_sensors_hz: float = 1.0
    rate_ext_status_hz: float = 1.0
    rate_rc_channels_hz: float = 1.0
    rate_position_hz: float = 1.0
    rate_extra1_hz: float = 1.0
    rate_extra2_hz: float = 0.0
    rate_extra3_hz: float = 1.0
    # Ground-truth origin for SIMSTATE lat/lng (ArduPilot's CMAC SITL home) and the heading the robot
    # starts with (degrees clockwise from north; ArduPilot's SITL starts CMAC at 353).
    origin_lat_deg: float = -35.363261
    origin_lon_deg: float = 149.165230
    start_heading_deg: float = 0.0
    # A depth camera on the companion (sitl/range_sensors.py): OBSTACLE_DISTANCE at this rate (0 = none)
    # from this component of the autopilot's system, over this field of view (centred forward) and range.
    obstacle_distance_hz: float = 0.0
    obstacle_distance_component: int = 196  # MAV_COMP_ID_OBSTACLE_AVOIDANCE
    obstacle_distance_fov_deg: float = 360.0
    obstacle_distance_min_m: float = 0.2
    obstacle_distance_max_m: float = 20.0
    # Autopilot parameters' boot values (name, value), as a defaults .parm file sets them; in a profile
    # a table: [vehicle.params] SERVO5_FUNCTION = 73. Unknown names are refused when the emulator starts.
    params: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ConfigError("VehicleConfig", problems)

    @property
    def left_radius_true_m(self) -> float:
        return self.wheel_radius_m if self.true_left_radius_m is None else self.true_left_radius_m

    @property
    def right_radius_true_m(self) -> float:
        return self.wheel_radius_m if self.true_right_radius_m is None else self.true_right_radius_m

    @property
    def track_true_m(self) -> float:
        return self.track_width_m if self.true_track_width_m is None else self.true_track_width_m

    @property
    def max_wheel_rad_s(self) -> float:
        return self.max_rpm * 2.0 * math.pi / 60.0

    def problems(self) -> list[str]:
        """Every invalid value, so a bad profile is reported all at once."""
        out: list[str] = []

        def positive(name: str, value: float | None) -> None:
            if value is not None and not (math.isfinite(value) and value > 0.0):
                out.append(f"{name} must be a positive number, got {value!r}")

        for name in (
            "wheel_radius_m",
            "track_width_m",
            "true_left_radius_m",
            "true_right_radius_m",
            "true_track_width_m",
            "max_rpm",
            "motor_time_constant_s",
            "physics_dt_s",
            "left_motor_gain",
            "right_motor_gain",
        ):
            positive(name, getattr(self, name))
        if not 0.0 < self.motor_curve_exponent <= 5.0:
            out.append(f"motor_curve_exponent must be in (0, 5] (1 = linear), got {self.motor_curve_exponent!r}")
        if not 0.0 <= self.battery_sag_per_min <= 0.5:
            out.append(
                f"battery_sag_per_min must be in [0, 0.5] (fraction of the motor gain lost per minute), "
                f"got {self.battery_sag_per_min!r}"
            )
        if not self.pwm_min < self.pwm_trim < self.pwm_max:
            out.append(
                f"need pwm_min < pwm_trim < pwm_max, got {self.pwm_min}/{self.pwm_trim}/{self.pwm_max}"
            )
        if not 0 <= self.deadzone_pwm < min(self.pwm_trim - self.pwm_min, self.pwm_max - self.pwm_trim):
            out.append(
                f"deadzone_pwm must be >= 0 and smaller than the PWM half range, got {self.deadzone_pwm}"
            )
        for name in ("left_servo", "right_servo"):
            if not 1 <= getattr(self, name) <= 16:
                out.append(f"{name} must be a servo output 1..16, got {getattr(self, name)}")
        if self.left_servo == self.right_servo:
            out.append("left_servo and right_servo must differ")
        if self.encoder_cpr < 1:
            out.append(f"encoder_cpr must be >= 1, got {self.encoder_cpr}")
        if not 0.0 <= self.encoder_dropout_rate <= 1.0:
            out.append(f"encoder_dropout_rate must be in [0, 1], got {self.encoder_dropout_rate}")
        if self.wheel_distance_order not in WHEEL_ORDERS:
            out.append(
                f"wheel_distance_order must be one of {WHEEL_ORDERS}, got {self.wheel_distance_order!r}"
            )
        if self.plant not in PLANTS:
            out.append(f"plant must be one of {PLANTS}, got {self.plant!r}")
        elif self.plant == "ardupilot_skid" and self.wheel_distance_order != "right_left":
            out.append("plant ardupilot_skid reports the right wheel first (SITL's encoder instance 0): "
                       "set wheel_distance_order = \"right_left\"")
        if not 0.0 <= self.loop_late_rate <= 1.0:
            out.append(f"loop_late_rate must be in [0, 1], got {self.loop_late_rate}")
        if self.gyro_noise_rad_s < 0.0:
            out.append(f"gyro_noise_rad_s must be >= 0, got {self.gyro_noise_rad_s}")
        if not 1 <= self.gcs_sysid <= 255:
            out.append(f"gcs_sysid must be 1..255, got {self.gcs_sysid}")
        if self.reboot_silence_s < 0.0:
            out.append(f"reboot_silence_s must be >= 0, got {self.reboot_silence_s}")
        if not (0.0 <= self.obstacle_distance_hz <= 50.0 and 1 <= self.obstacle_distance_component <= 255
                and 0.0 < self.obstacle_distance_fov_deg <= 360.0
                and 0.0 <= self.obstacle_distance_min_m < self.obstacle_distance_max_m <= 655.0):
            out.append("obstacle_distance_*: need hz in [0, 50], component 1..255, fov_deg in (0, 360], "
                       "0 <= min_m < max_m <= 655")
        for f in dataclasses.fields(self):
            if f.name.startswith("rate_") and getattr(self, f.name) < 0.0:
                out.append(f"{f.name} must be >= 0, got {getattr(self, f.name)}")
        return out

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], source: str = "vehicle") -> VehicleConfig:
        """Build from a TOML-like mapping; unknown keys and wrong types are all reported."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        problems: list[str] = []
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            field = fields.get(key)
            if field is None:
                problems.append(f"unknown key {key!r}")
                continue
            if key == "params":
                pairs = _param_pairs(value, problems)
                if pairs is not None:
                    kwargs[key] = pairs
                continue
            default = field.default
            if value is None and default is None:
                ok = True  # an optional value left unset ("equal to nominal")
            elif isinstance(default, bool) or key in ("start_armed",):
                ok = isinstance(value, bool)
            elif isinstance(default, int) and not isinstance(default, bool):
                ok = isinstance(value, int) and not isinstance(value, bool)
            elif isinstance(default, str):
                ok = isinstance(value, str)
            else:  # float or optional float
                ok = isinstance(value, int | float) and not isinstance(value, bool)
                value = float(value) if ok else value
            if not ok:
                problems.append(f"{key}: wrong type {type(value).__name__}")
                continue
            kwargs[key] = value
        if problems:
            raise ConfigError(source, problems)
        try:
            return cls(**kwargs)
        except ConfigError as exc:
            raise ConfigError(source, list(exc.problems)) from None


def _param_pairs(value: Any, problems: list[str]) -> tuple[tuple[str, float], ...] | None:
    """A params table (or pairs) as sorted (name, value) pairs; bad entries are added to ``problems``."""
    items = value.items() if isinstance(value, Mapping) else value if isinstance(value, list | tuple) else None
    if items is None:
        problems.append("params: must be a table of NAME = number")
        return None
    pairs: list[tuple[str, float]] = []
    for entry in items:
        name, number = entry if isinstance(entry, tuple | list) and len(entry) == 2 else (entry, None)
        if not isinstance(name, str) or not isinstance(number, int | float) or isinstance(number, bool):
            problems.append(f"params: {name!r} needs a number, got {number!r}")
            continue
        pairs.append((name, float(number)))
    return tuple(sorted(pairs))


def read_toml(p: Path) -> dict[str, Any]:
    """A TOML file as a dict; an unreadable or malformed file is a ConfigError naming it."""
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(str(p), [str(exc)]) from exc


def load_vehicle(path: str | Path) -> VehicleConfig:
    """Load a vehicle profile TOML (keys at top level or under ``[vehicle]``)."""
    p = Path(path)
    data = read_toml(p)
    table = data.get("vehicle", data)
    if not isinstance(table, dict):
        raise ConfigError(str(p), ["[vehicle] must be a table"])
    return VehicleConfig.from_mapping(table, source=str(p))
