"""Driver: the autopilot's own navigation (AUTO, RTL, SMART_RTL, LOITER ...: [modes] autopilot), pure.

ArduPilot Rover navigates (AR_WPNav: desired speed and turn rate), closes its own speed and turn-rate loops
(AR_AttitudeControl: throttle = desired speed x CRUISE_THROTTLE / CRUISE_SPEED + PID on the EKF's speed;
steering = feed-forward + PID on the gyro's rate) and mixes them per wheel (AP_MotorsUGV
output_skid_steering: left = throttle + steering, right = throttle - steering, each in [-1, 1]) onto the
outputs with SERVOn_FUNCTION 73 / 74 (ThrottleLeft / Right), scaled between SERVOn_MIN, TRIM and MAX. Those
two outputs stay unconnected; SERVO_OUTPUT_RAW reports them ([demand] left_output, right_output), and this
driver turns each report into a request that goes through the bridge's whole pipeline: limiter, kinematics,
desaturation, wheel speed loop, PWM, and every safety path.

The mapping, per wheel: the demand's PWM -> a fraction of full throttle d in [-1, 1] (trim 0, the two halves
scaled separately as SRV_Channel does) -> a wheel-speed target d x the wheel's top speed in that direction
(the speed the profile's PWM map gives at full PWM) -> the twist of both wheels (forward kinematics) as the
request. So the plant ArduPilot's loops see is linear, throttle -> wheel speed, as its feed-forward assumes
(CRUISE_THROTTLE / CRUISE_SPEED is one slope), and the bridge's speed loop holds each wheel at its share
whatever the motor's deadband, curve or load; ArduPilot's slower outer loops (navigation, speed, turn rate,
on the EKF and gyro) correct what is left. The limiter shapes a demand that steps (a wound-up speed controller
at takeover, a pivot turn) into what the limits allow. Copying the PWM to the motors instead (the baseline)
gives ArduPilot the raw motor, bypasses the limits and the speed loop, and is what ArduPilot does alone.

- A fresh report is followed at once (the output answers it, as for a GCS request); no report for
  [demand] timeout_s brakes through the limiter, as a request timeout does.
- Reports are taken only in a mode the table gives the autopilot, from the vehicle's autopilot, and only
  after the safety gates (link, disarm, faults, calibrate, stop modes) let a driver hold the wheels.
- A demand output reading 0 while armed (no pulses: SERVOn_FUNCTION not 73/74) is said, and the wheels brake;
  disarmed it is no demand (MOT_SAFE_DISARM stops the pulses), never full reverse;
  so is a demand that stays at trim for STUCK_S while the autopilot reports (NAV_CONTROLLER_OUTPUT) a
  waypoint farther than STUCK_DISTANCE_M away. Both are configuration mistakes to fix, not to drive through.

PID_TUNING (GCS_PID_MASK 3) carries the same navigation one step earlier (desired speed, axis 4, and turn
rate, axis 5): a second source would be another `decode` here. It is not used: its values freeze when
ArduPilot's controller stops running, so a silent autopilot looks like a steady demand, where
SERVO_OUTPUT_RAW falls silent or reads trim.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from rover_bridge.command.drivers import CommandState, Wheels
from rover_bridge.command.modes import AUTOPILOT, ModeTable, mode_name
from rover_bridge.command.output_stage import OutputStage
from rover_bridge.command.vehicle import VehicleState
from rover_bridge.kinematics import Twist2D, WheelSpeeds
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import NOTHING, Outgoing, Reaction
from rover_bridge.params import Profile

STUCK_S = 3.0  # a demand at trim this long while the autopilot says it has far to go: not configured
STUCK_DISTANCE_M = 2.0
NAV_FRESH_S = 2.0  # NAV_CONTROLLER_OUTPUT younger than this counts as "the autopilot says"
MIN_PULSE_US = 400  # below: not a servo pulse (0 = none)
_TAKES = frozenset({CommandState.IDLE, CommandState.ACTIVE, CommandState.BRAKING, CommandState.REFUSED})


@dataclass(frozen=True, slots=True)
class Demand:
    """The autopilot's demand: each wheel's fraction of full throttle (forward +), and the twist it means."""

    left: float
    right: float
    twist: Twist2D


class AutopilotNavigation:
    """The autopilot-navigation driver (module doc)."""

    name: str = AUTOPILOT
    braking_text: tuple[int, str] | None = (mavlink.MAV_SEVERITY_WARNING, "RB: no demand from the autopilot, braking")

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter, vehicle: VehicleState,
                 modes: ModeTable, stage: OutputStage, wheels: Wheels, count: Callable[[str], None]) -> None:
        p = profile.demand
        self.params = p
        self.identity = identity
        self.reporter = reporter
        self.vehicle = vehicle
        self.modes = modes
        self.wheels = wheels
        self._count = count
        self.timeout_s = p.timeout_s
        self.speed_loop = p.speed_loop  # its demand is closed by the autopilot's own controllers (params)
        self._fields = (f"servo{p.left_output}_raw", f"servo{p.right_output}_raw")
        self._drive = stage.drive
        self._tops = tuple((-lo, hi) for lo, hi in (stage.outputs.speed_range(left=True),
                                                    stage.outputs.speed_range(left=False)))
        self.demand: Demand | None = None  # the request, while this driver holds the wheels
        self.since_s: float | None = None
        self._wp_dist: tuple[float, float] | None = None  # (arrival, metres) of the last NAV_CONTROLLER_OUTPUT
        self._trim_since: float | None = None
        self._said: str | None = None  # the configuration problem said, until the demand is right again

    # ----------------------------------------------------------------- the driver

    @property
    def request(self) -> Demand | None:
        return self.demand

    def braking(self, now_s: float) -> bool:
        return self.since_s is None or now_s >= self.since_s + self.timeout_s

    def deadline_s(self) -> float | None:
        return None if self.since_s is None else self.since_s + self.timeout_s

    def target(self, now_s: float) -> tuple[Twist2D | None, list[Outgoing]]:
        return (None if self.demand is None else self.demand.twist), []

    def drop(self) -> None:
        self.demand, self.since_s = None, None

    def hold(self, request: Demand, now_s: float) -> None:
        self.demand, self.since_s = request, now_s

    def taken_over(self, by: str, now_s: float) -> list[Outgoing]:
        self.drop()
        return []

    # ----------------------------------------------------------------- from the autopilot

    def decode(self, msg: MAVLinkMessage) -> tuple[int, int] | None:
        """The two demand outputs' PWM (us), or None for another system's or port's report."""
        if not self.identity.from_autopilot(msg) or int(msg.port) != 0:
            return None
        return int(getattr(msg, self._fields[0])), int(getattr(msg, self._fields[1]))

    def fraction(self, pwm_us: int) -> float:
        """A demand output's PWM as a fraction of full throttle, [-1, 1] (trim 0; each half its own scale). No
        pulse (0, what a disarmed ArduPilot with MOT_SAFE_DISARM reports) is no demand, never full reverse."""
        p = self.params
        if pwm_us < MIN_PULSE_US:
            return 0.0
        if pwm_us >= p.pwm_trim:
            return min(1.0, (pwm_us - p.pwm_trim) / (p.pwm_max - p.pwm_trim))
        return max(-1.0, (pwm_us - p.pwm_trim) / (p.pwm_trim - p.pwm_min))

    def to_demand(self, left_us: int, right_us: int) -> Demand:
        left, right = self.fraction(left_us), self.fraction(right_us)
        (l_rev, l_fwd), (r_rev, r_fwd) = self._tops
        wheels = WheelSpeeds(left * (l_fwd if left >= 0.0 else l_rev), right * (r_fwd if right >= 0.0 else r_rev))
        return Demand(left, right, self._drive.to_twist(wheels))

    def on_nav(self, msg: MAVLinkMessage, now_s: float) -> None:
        """NAV_CONTROLLER_OUTPUT: how far the autopilot says its waypoint is (for the stuck-at-trim check)."""
        if self.identity.from_autopilot(msg):
            self._wp_dist = (now_s, float(msg.wp_dist))

    def handle(self, msg: MAVLinkMessage, now_s: float) -> Reaction:
        """SERVO_OUTPUT_RAW: take the wheels with the demand in it, when the mode and the gates allow."""
        pwm = self.decode(msg)
        if pwm is None or not self.modes.allows(AUTOPILOT, self.vehicle.driving_mode):
            self._trim_since = None
            return NOTHING
        out = self.wheels.advance(now_s, force_output=False)  # bring link / armed / mode state up to date
        said = self._check_configured(pwm, now_s)
        if said is not None:
            return Reaction(out=(*out, *said))
        if self.wheels.state not in _TAKES:
            self._count("demand.dropped")
            return Reaction(out=tuple(out))
        self._count("demand.taken")
        out += self.wheels.take(self, self.to_demand(*pwm), now_s, "autopilot")
        return Reaction(out=tuple(out))  # telemetry: forwarded to the ground stations as always

    def _check_configured(self, pwm: tuple[int, int], now_s: float) -> list[Outgoing] | None:
        """What to say about a demand that cannot be one (None: it is fine to follow). Said once per episode."""
        if not self.vehicle.armed:
            self._trim_since = self._said = None
            return None
        outputs = (self.params.left_output, self.params.right_output)
        for value, output, function in zip(pwm, outputs, (73, 74), strict=True):
            if value < MIN_PULSE_US:
                text = f"RB: SERVO{output} reads {value}: set SERVO{output}_FUNCTION {function}"
                return self._say("demand.no_pulses", text, now_s)
        nav = self._wp_dist
        far = nav is not None and now_s - nav[0] < NAV_FRESH_S and nav[1] >= STUCK_DISTANCE_M
        if pwm != (self.params.pwm_trim, self.params.pwm_trim) or not far:
            self._trim_since = self._said = None
            return None
        since = self._trim_since = now_s if self._trim_since is None else self._trim_since
        if now_s - since < STUCK_S:
            return None
        left, right = outputs
        return self._say("demand.stuck", f"RB: {mode_name(self.vehicle.driving_mode)}: SERVO{left}/{right} at trim: "
                         "FUNCTION 73/74?", now_s)

    def _say(self, key: str, text: str, now_s: float) -> list[Outgoing]:
        self._count(key)
        if self._said == key:
            return []
        self._said = key
        return self.reporter.statustext(mavlink.MAV_SEVERITY_ERROR, text, now_s, key=key)
