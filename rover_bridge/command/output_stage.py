"""The output stage (pure): the twist a driver wants -> limiter -> kinematics -> desaturation -> wheel speed loop
-> PWM -> override messages, on a fixed grid.

- The limiter keeps its own time: an output that answers a fresh request steps it to the later of now and one
  period past where it stood (so a request that arrives 1 ms after an output still moves the wheels by what
  the limits allow over a period, not by 1 ms worth: 0.05 m/s at the default 1 m/s^2 and 20 Hz, where 1 ms
  worth rounds to the same PWM and the request would show only a period later); every other output steps it
  to now, or not at all while it is ahead. So the command follows the limiter's trajectory exactly, evaluated
  at most one period ahead of time after a request: the acceleration limits hold on that trajectory, and a
  burst of requests cannot run it further ahead. A step is never longer than one period (after a stalled
  loop the limiter must not allow a jump worth the whole stall). While the wheels may not move the limiter
  is held at zero.
- Closed loop (control.mode): the wheel targets go through the per-wheel speed loop
  (rover_bridge.command.wheel_control) on the speeds the estimate flow measured; while the estimator reports
  slip (control.slip_compensation) no wheel is driven faster than when the slip began.
- A wiring fault (control.fault_*) found while driving is returned to the caller, and neutral goes out.
- A periodic output keeps the fixed grid (now + period would add the loop's lateness to every period, a slow
  drift of the refresh rate); an early output (a fresh request acted on at once) or one more than a period
  late starts a new grid from now.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from rover_bridge.command.outputs import OutputMap, WheelPwm
from rover_bridge.command.wheel_control import WheelSpeedLoop, WiringFault, WiringMonitor
from rover_bridge.kinematics import DiffDrive, MeasuredWheels, Twist2D, WheelSpeeds
from rover_bridge.limits import TwistLimiter, TwistLimits
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.identity import Identity
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Link, Outgoing
from rover_bridge.params import Profile

_ZERO = Twist2D()


class OutputStage:
    """Limiter, kinematics, wheel speed loop, slip, wiring monitor and PWM: one output per call (module doc)."""

    def __init__(self, profile: Profile, identity: Identity, reporter: Reporter,
                 count: Callable[[str], None]) -> None:
        self.profile = profile
        self.identity = identity
        self.reporter = reporter
        self._count = count
        self.drive = DiffDrive.from_params(profile.robot)
        self.outputs = OutputMap.from_profile(profile)
        self.limiter = TwistLimiter(TwistLimits.from_params(profile.limits))
        self.period_s = 1.0 / profile.command.rate_hz
        c = profile.control
        ranges = (self.outputs.speed_range(left=True), self.outputs.speed_range(left=False))
        self.loop = WheelSpeedLoop(c, *ranges, self._wheel_accel_rad_s2()) if c.mode == "closed_loop" else None
        self.wiring = WiringMonitor(c, *ranges)
        self.last_wheel_pwm: WheelPwm | None = None
        self.last_output_s: float | None = None
        self.limiter_s: float | None = None  # the time the limiter's state stands for (module doc)
        self.next_output_s: float | None = None
        self._open_measured: tuple[float, WheelSpeeds] | None = None  # open loop: (arrival, speeds)
        self._loop_closed = True  # said once when it changes
        self.slipping = False
        self._slip_hold: WheelSpeeds | None = None

    def _wheel_accel_rad_s2(self) -> float:
        """The fastest a wheel's speed changes within the limiter's limits (both axes at once, either turn)."""
        lim = self.limiter.limits
        a = max(lim.accel_m_s2, lim.decel_m_s2)
        wheels = [self.drive.to_wheel_speeds(Twist2D(a, turn)) for turn in (lim.alpha_rad_s2, -lim.alpha_rad_s2)]
        return max(max(abs(w.left_rad_s), abs(w.right_rad_s)) for w in wheels)

    # ----------------------------------------------------------------- the limiter

    def step_limiter(self, target: Twist2D | None, now_s: float, answer: bool, ramping: bool) -> None:
        """Advance the limiter toward `target` (None: zero) while `ramping`; otherwise hold it at zero."""
        period = self.period_s
        at = self.limiter_s
        if at is None:
            at = now_s - period
        until = max(now_s, min(at, now_s) + period) if answer else now_s
        if ramping:
            step_s = min(period, until - at)
            if step_s > 0.0:
                self.limiter.step(target if target is not None else _ZERO, step_s)
                self.limiter_s = until
        else:
            self.limiter.reset(_ZERO)
            self.limiter_s = now_s

    # ----------------------------------------------------------------- one output

    def drive_output(self, now_s: float, moving: bool,
                     speed_loop: bool = True) -> tuple[list[Outgoing], list[Outgoing], WiringFault | None]:
        """The override for the limiter's twist now (neutral unless `moving`): (messages, reports, a fault).
        Without `speed_loop` the PWM map alone turns wheel speeds into PWM; the loop starts afresh after."""
        last = self.last_output_s
        period = self.period_s
        dt_s = period if last is None else min(period, now_s - last)  # since the last output (the speed loop)
        raw = self.drive.to_wheel_speeds(self.limiter.current)
        wheels = raw.desaturate(self.profile.robot.max_wheel_rad_s)
        said: list[Outgoing] = []
        fault: WiringFault | None = None
        if moving:
            wheels, said = self._slip_limited(wheels, now_s)
            command = wheels
            if self.loop is not None and not speed_loop:
                self.loop.reset()
            elif self.loop is not None:
                result = self.loop.command(wheels, dt_s, now_s, pre_scaled=wheels is not raw,
                                           freeze=self._slip_hold is not None)
                command = result.command
                said += self._encoders_fresh(result.closed or wheels == WheelSpeeds(), now_s)
            fault = self.wiring.check(wheels, self.measured(now_s), now_s)
            pwm = self.outputs.to_pwm(command) if fault is None else self.outputs.neutral
        else:
            self.rest()
            pwm = self.outputs.neutral
        return self._send(pwm, now_s, "outputs.sent"), said, fault

    def direct_output(self, pwm: WheelPwm, now_s: float) -> list[Outgoing]:
        """`rover-bridge calibrate`: each wheel's PWM as given (no limiter, no loop)."""
        return self._send(pwm, now_s, "outputs.direct")

    def _send(self, pwm: WheelPwm, now_s: float, counter: str) -> list[Outgoing]:
        vehicle = self.identity.vehicle_system_id
        assert vehicle is not None
        msgs = self.outputs.command(pwm, vehicle, self.identity.autopilot_component_id)
        self.last_wheel_pwm = pwm
        self.last_output_s = now_s
        nxt = self.next_output_s
        on_grid = nxt is not None and 0.0 <= now_s - nxt < self.period_s
        self.next_output_s = nxt + self.period_s if on_grid and nxt is not None else now_s + self.period_s
        self._count(counter)
        return [self.to_autopilot(m) for m in msgs]

    def release(self, now_s: float) -> list[Outgoing]:
        """Neutral, then the channels handed back to the radio (rc_override): the last output for a while."""
        vehicle = self.identity.vehicle_system_id
        assert vehicle is not None
        target = (vehicle, self.identity.autopilot_component_id)
        msgs = self.outputs.command(self.outputs.neutral, *target) + self.outputs.release(*target)
        self.last_wheel_pwm = self.outputs.neutral
        self.skip(now_s)
        self._count("outputs.released")
        return [self.to_autopilot(m) for m in msgs]

    def skip(self, now_s: float) -> None:
        """No output this period (the grid moves on, so the loop does not wake for it again at once)."""
        self.rest()
        self.last_output_s = now_s
        self.next_output_s = now_s + self.period_s

    def rest(self) -> None:
        """Wheels at neutral: the loop, the wiring monitor and the slip hold start afresh."""
        if self.loop is not None:
            self.loop.reset()
        self.wiring.reset()
        self._slip_hold = None

    def reset_after_fault(self) -> None:
        self.limiter.reset(_ZERO)
        if self.loop is not None:
            self.loop.reset()
        self.wiring.reset()

    def to_autopilot(self, msg: MAVLinkMessage) -> Outgoing:
        # ArduPilot obeys overrides only from its GCS id (MAV_GCS_SYSID): see output.override_source_system.
        return Outgoing(Link.AUTOPILOT, msg, self.identity.override_source_system, self.identity.component_id)

    # ----------------------------------------------------------------- measured wheels, slip

    def on_wheels(self, sample: MeasuredWheels, now_s: float) -> None:
        if self.loop is not None:
            self.loop.measure(sample, now_s)
        else:
            self._open_measured = (now_s, sample.speeds)

    def measured(self, now_s: float) -> WheelSpeeds | None:
        if self.loop is not None:
            return self.loop.measured if self.loop.fresh(now_s) else None
        seen = self._open_measured
        if seen is None or now_s - seen[0] >= self.profile.control.encoder_timeout_s:
            return None
        return seen[1]

    def _encoders_fresh(self, fresh: bool, now_s: float) -> list[Outgoing]:
        """Say once when the loop falls back to feedforward (stale encoders) and when it closes again."""
        if fresh == self._loop_closed:
            return []
        self._loop_closed = fresh
        self._count("control.closed" if fresh else "control.stale")
        text = ("RB: wheel encoders back: speed loop closed" if fresh
                else "RB: no wheel encoders: feedforward only")
        return self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, text, now_s, key="control.encoders")

    def _slip_limited(self, wheels: WheelSpeeds, now_s: float) -> tuple[WheelSpeeds, list[Outgoing]]:
        """Slip compensation: while the wheels slip, no wheel is driven faster than when slip began."""
        measured = self.measured(now_s)
        # Slip is a wheel spinning the way it is driven, faster than the ground moves; a wheel measured
        # the other way is a wiring fault for the monitor, not slip to hold the speeds for.
        agrees = measured is not None and (measured.left_rad_s * wheels.left_rad_s >= 0.0
                                           and measured.right_rad_s * wheels.right_rad_s >= 0.0)
        if not (self.profile.control.slip_compensation and self.slipping and agrees):
            self._slip_hold = None
            return wheels, []
        out: list[Outgoing] = []
        if self._slip_hold is None:
            self._slip_hold = wheels
            self._count("slip.limited")
            out = self.reporter.statustext(mavlink.MAV_SEVERITY_WARNING, "RB: wheel slip: holding wheel speeds",
                                           now_s, key="slip.limited")
        hold = self._slip_hold

        def capped(value: float, held: float) -> float:
            return math.copysign(min(abs(value), abs(held)), value) if value * held > 0.0 else 0.0

        return WheelSpeeds(capped(wheels.left_rad_s, hold.left_rad_s),
                           capped(wheels.right_rad_s, hold.right_rad_s)), out
