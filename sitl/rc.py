"""RC inputs (radio and RC_CHANNELS_OVERRIDE) and the servo outputs, as ArduPilot makes them.

Read in ArduPilot: libraries/RC_Channel/RC_Channel.cpp (has_override), libraries/SRV_Channel
(SRV_Channel_aux.cpp output_ch, ignore_small_rcin_changes; SRV_Channel.cpp pwm_from_angle),
libraries/AP_ServoRelayEvents (DO_SET_SERVO). See sitl/autopilot.py for the behaviour list.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from sitl.config import VehicleConfig
from sitl.motors import FUNC_THROTTLE_LEFT, FUNC_THROTTLE_RIGHT, pwm_from_angle

FUNC_NONE = 0
FUNC_MANUAL = 1
FUNC_RCIN1 = 51
FUNC_RCIN16 = 66
NUM_SERVOS = 16
NUM_RC = 18


@dataclass
class _RcChannel:
    override_pwm: int = 0
    last_override_us: int = 0


@dataclass
class _Servo:
    output_pwm: int = 0
    ignore_small_rcin: bool = False  # DO_SET_SERVO hold on a passthrough output
    previous_radio_in: int = 0
    set_by_command: bool = False  # unassigned output set by DO_SET_SERVO


def is_passthrough(func: int) -> bool:
    return func == FUNC_MANUAL or FUNC_RCIN1 <= func <= FUNC_RCIN16


class RcServos:
    """The RC channels' inputs and the 16 outputs' PWM."""

    def __init__(self, vehicle: VehicleConfig, param: Callable[[str], float]) -> None:
        self.vehicle = vehicle
        self._param = param
        self.radio_pwm: dict[int, int] = {ch: 1500 for ch in range(1, NUM_RC + 1)}  # no radio: trim
        self.reset()

    def reset(self) -> None:
        """A reboot: overrides, DO_SET_SERVO holds and outputs are gone."""
        self._rc = {ch: _RcChannel() for ch in range(1, NUM_RC + 1)}
        self._servos = {n: _Servo() for n in range(1, NUM_SERVOS + 1)}

    # ------------------------------------------------------------------ RC
    def has_override(self, ch: int, now_us: int) -> bool:
        rc = self._rc[ch]
        if rc.override_pwm == 0:
            return False
        timeout_s = self._param("RC_OVERRIDE_TIME")
        if timeout_s < 0.0:
            return True  # timeouts disabled
        if timeout_s == 0.0:
            return False  # overrides disabled
        return now_us - rc.last_override_us < round(timeout_s * 1e6)

    def rc_input(self, ch: int, now_us: int) -> int:
        return self._rc[ch].override_pwm if self.has_override(ch, now_us) else self.radio_pwm[ch]

    def rc_inputs(self, now_us: int) -> dict[int, int]:
        return {ch: self.rc_input(ch, now_us) for ch in range(1, NUM_RC + 1)}

    def set_override(self, ch: int, pwm: int, now_us: int) -> None:
        self._rc[ch].override_pwm = pwm
        self._rc[ch].last_override_us = now_us

    def clear_overrides(self) -> None:
        """RC_Channels::clear_overrides (a failsafe)."""
        for rc in self._rc.values():
            rc.override_pwm = 0

    def normalised(self, ch: int, now_us: int) -> float:
        """The input in [-1, 1] about 1500 with the channel's dead zone taken out."""
        offset = self.rc_input(ch, now_us) - 1500
        dz = self._param(f"RC{ch}_DZ")
        if abs(offset) <= dz:
            return 0.0
        return max(-1.0, min(1.0, (offset - (dz if offset > 0 else -dz)) / (500.0 - dz)))

    def manual_mix(self, now_us: int, armed: bool) -> tuple[float, float]:
        """Rover skid steering in MANUAL: throttle from RC3, steering from RC1 (RCMAP defaults)."""
        if not armed:
            return 0.0, 0.0
        throttle, steering = self.normalised(3, now_us), self.normalised(1, now_us)
        left, right = throttle + steering, throttle - steering
        scale = max(1.0, abs(left), abs(right))  # keep the turn when saturated
        return left / scale, right / scale

    # ------------------------------------------------------------------ outputs
    def function(self, n: int) -> int:
        return int(self._param(f"SERVO{n}_FUNCTION"))

    def functions(self) -> set[int]:
        return {self.function(n) for n in self._servos}

    def have_skid_steering(self) -> bool:
        funcs = self.functions()
        return FUNC_THROTTLE_LEFT in funcs and FUNC_THROTTLE_RIGHT in funcs

    def do_set_servo(self, n: int, pwm: int) -> bool:
        """False when the output has a function DO_SET_SERVO may not touch."""
        func = self.function(n)
        if not (func == FUNC_NONE or is_passthrough(func)):
            return False
        servo = self._servos[n]
        servo.output_pwm = pwm
        servo.ignore_small_rcin = True
        servo.set_by_command = True
        return True

    def _motor_pwm(self, n: int, value: float, armed: bool) -> int:
        trim = int(self._param(f"SERVO{n}_TRIM"))
        if not armed:
            return trim  # AP_MotorsUGV: disarmed motor outputs sit at trim
        return pwm_from_angle(1000.0 * value, int(self._param(f"SERVO{n}_MIN")), int(self._param(f"SERVO{n}_MAX")),
                              trim, self._param(f"SERVO{n}_REVERSED") != 0)

    def update(self, now_us: int, left: float, right: float, armed: bool) -> None:
        """Recompute every output; ``left``/``right`` in [-1, 1] drive the ThrottleLeft/Right outputs."""
        for n, servo in self._servos.items():
            func = self.function(n)
            if is_passthrough(func):
                ch = n if func == FUNC_MANUAL else func - FUNC_RCIN1 + 1
                radio_in = self.rc_input(ch, now_us)
                if not servo.ignore_small_rcin:
                    servo.output_pwm = radio_in
                    servo.previous_radio_in = radio_in
                elif abs(radio_in - servo.previous_radio_in) > self._param(f"RC{ch}_DZ"):
                    servo.output_pwm = radio_in  # the RC input moved: the DO_SET_SERVO hold ends
                    servo.ignore_small_rcin = False
                    servo.previous_radio_in = radio_in
            elif func in (FUNC_THROTTLE_LEFT, FUNC_THROTTLE_RIGHT):
                servo.output_pwm = self._motor_pwm(n, left if func == FUNC_THROTTLE_LEFT else right, armed)
            elif func == FUNC_NONE:
                if not servo.set_by_command:
                    servo.output_pwm = 0
            else:
                servo.output_pwm = int(self._param(f"SERVO{n}_TRIM"))

    def silence(self) -> None:
        for servo in self._servos.values():
            servo.output_pwm = 0  # a rebooting board emits no pulses

    def outputs(self, armed: bool, rebooting: bool) -> dict[int, int]:
        """PWM on every output pin (what SERVO_OUTPUT_RAW reports).

        Disarmed with ``passthrough_when_disarmed`` False, passthrough pins show trim while the
        servo keeps its passthrough/hold state, so arming resumes where ArduPilot would be.
        """
        out = {n: s.output_pwm for n, s in self._servos.items()}
        if not armed and not self.vehicle.passthrough_when_disarmed and not rebooting:
            for n in out:
                if is_passthrough(self.function(n)):
                    out[n] = int(self._param(f"SERVO{n}_TRIM"))
        return out
