"""ArduPilot-Rover-like MAVLink behaviour, as a pure state machine (no sockets, no clocks).

``handle(msg, now_us)`` takes one decoded message; ``update(now_us, physics)`` advances the
autopilot's own timers (override timeouts, reboot) and recomputes the servo outputs;
``emit(now_us, physics)`` returns the stream messages that are due. Outgoing messages are
collected in ``outbox`` (replies) and returned by ``emit`` (streams). Times are integer
microseconds of simulated time since the emulator started.

Behaviour copied from ArduPilot (read in its source; behaviour only, no code):
- RC_CHANNELS_OVERRIDE (libraries/GCS_MAVLink/GCS_Common.cpp handle_rc_channels_override):
  only from MAV_GCS_SYSID; ch1-8: UINT16_MAX ignores, 0 releases; ch9-18: 0 and UINT16_MAX
  ignore, UINT16_MAX-1 releases. Per channel, an override lives while
  ``now - last_override < RC_OVERRIDE_TIME`` (libraries/RC_Channel/RC_Channel.cpp has_override:
  a negative time never expires, 0 disables overrides).
- Message routing (libraries/GCS_MAVLink/MAVLink_routing.cpp): a message with target ids is
  processed only if target_system is 0 or ours and target_component is 0 or ours.
- SERVOn_FUNCTION (libraries/SRV_Channel): 1 = same-numbered RC input, 51..66 = RCIN1..16
  passthrough of the (overridden) RC input; 73/74 = ThrottleLeft/Right from the mode's skid
  steering mix (MANUAL: throttle RC3, steering RC1, left = throttle + steering).
- MAV_CMD_DO_SET_SERVO (libraries/AP_ServoRelayEvents/AP_ServoRelayEvents.cpp): allowed only
  on outputs with function 0 (none), 1 (manual) or 51..66 (RC passthrough); otherwise a
  STATUSTEXT "ServoRelayEvent: Channel N is already in use" and MAV_RESULT_FAILED. On a
  passthrough output the value then holds, with no timeout, until the RC input moves by more
  than that RC channel's dead zone (SRV_Channel.cpp ignore_small_rcin_changes; Rover's
  default RC1_DZ = RC3_DZ = 30).
- Stream groups (libraries/GCS_MAVLink/GCS_MAVLink_Parameters.cpp, 4.7): RAW_SENSORS has
  RAW_IMU; RC_CHANNELS has SERVO_OUTPUT_RAW and RC_CHANNELS; POSITION has GLOBAL_POSITION_INT (lat/lon 0
  before the EKF has a position: send_global_position_int ignores get_location's result) and
  LOCAL_POSITION_NED;
  EXTRA1 has ATTITUDE, SIMSTATE and (Rover) WHEEL_DISTANCE; EXTRA2 VFR_HUD; EXTRA3 SYSTEM_TIME.
  REQUEST_DATA_STREAM sets the SRn_ rate of the group(s) and resets that group's per-message
  intervals. SET_MESSAGE_INTERVAL for an id without an internal mapping answers
  MAV_RESULT_DENIED with "No ap_message for mavlink id (N)" (GCS_Common.cpp); 4.7 does that for
  WHEEL_DISTANCE, and so does the emulator unless ``deny_wheel_distance_interval`` is False.
- MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (GCS_Common.cpp handle_preflight_reboot): refused with
  FAILED when armed; param1 must be 1 or 3 (else UNSUPPORTED); the ACK goes out first.
- WHEEL_DISTANCE (Rover/GCS_MAVLink_Rover.cpp, libraries/AP_WheelEncoder): time_usec = time
  since boot, cumulative metres since boot = counts * 2*pi*WENCn_RADIUS / WENCn_CPR.

- Modes (Rover/mode.h): every Rover custom_mode is accepted and reported in HEARTBEAT, one sent at once
  after a change (Rover/system.cpp set_mode: gcs().send_message(MSG_HEARTBEAT)); SET_MODE gets no ACK,
  DO_SET_MODE its COMMAND_ACK while parsing (so the ACK arrives before that heartbeat); RC
  passthrough outputs (51..66) follow the RC input in every mode (SRV_Channel::output_ch has no
  mode check), so HOLD stops only the motor-function outputs.
- TIMESYNC (GCS_Common.cpp handle_timesync): tc1 == 0 is answered at once, ts1 echoed.
- Stream links (SITL's TCP UART, AP_HAL_SITL/UARTDriver.cpp): bytes are read between main loops and
  parsed in the next loop's update_receive; when the client closes, what was not parsed yet is never
  seen as that client's (the emulator drops it), so a stop sent just before a close is lost.

Differences from ArduPilot, on purpose: the emulator flies only MANUAL's skid mix and does no
navigation in GUIDED, AUTO or any other mode (motor-function outputs stay at trim); SCALED_IMU is
sent in RAW_SENSORS beside RAW_IMU; the ground truth is sent as SIMSTATE and LOCAL_POSITION_NED;
with ``passthrough_when_disarmed`` False (the default) passthrough outputs sit at trim while
disarmed (real ArduPilot passes them through: set it True for that).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.config import VehicleConfig
from sitl.extnav import ExtNavConsumer, ExtNavSettings
from sitl.mav import MAVLinkMessage, mavlink
from sitl.physics import PhysicsState, encoder_counts, pwm_to_command
from sitl.sensors import G_M_S2, accel_reading_m_s2, fitted, wire_int

# Rover/mode.h Mode::Number: the custom_mode values Rover reports (there are no modes 2, 13, 14).
MODE_MANUAL = 0
MODE_HOLD = 4
MODE_GUIDED = 15
MODE_NAMES = {0: "MANUAL", 1: "ACRO", 3: "STEERING", 4: "HOLD", 5: "LOITER", 6: "FOLLOW", 7: "SIMPLE",
              8: "DOCK", 9: "CIRCLE", 10: "AUTO", 11: "RTL", 12: "SMART_RTL", 15: "GUIDED", 16: "INITIALISING"}

FUNC_NONE = 0
FUNC_MANUAL = 1
FUNC_RCIN1 = 51
FUNC_RCIN16 = 66
FUNC_THROTTLE_LEFT = 73
FUNC_THROTTLE_RIGHT = 74

UINT16_MAX = 65535
NUM_SERVOS = 16
NUM_RC = 18
FORCE_ARM_MAGIC = 21196  # ArduPilot's param2 to skip pre-arm checks

_P = mavlink
ACCEPTED: int = _P.MAV_RESULT_ACCEPTED
DENIED: int = _P.MAV_RESULT_DENIED
FAILED: int = _P.MAV_RESULT_FAILED
UNSUPPORTED: int = _P.MAV_RESULT_UNSUPPORTED
_INT = _P.MAV_PARAM_TYPE_INT16
_INT8 = _P.MAV_PARAM_TYPE_INT8
_REAL = _P.MAV_PARAM_TYPE_REAL32

# Stream group id -> (SRn parameter, MAVLink message ids in the group).
STREAM_GROUPS: dict[int, tuple[str, tuple[int, ...]]] = {
    _P.MAV_DATA_STREAM_RAW_SENSORS: (
        "SR0_RAW_SENS",
        (_P.MAVLINK_MSG_ID_RAW_IMU, _P.MAVLINK_MSG_ID_SCALED_IMU),
    ),
    _P.MAV_DATA_STREAM_EXTENDED_STATUS: ("SR0_EXT_STAT", (_P.MAVLINK_MSG_ID_SYS_STATUS,)),
    _P.MAV_DATA_STREAM_RC_CHANNELS: (
        "SR0_RC_CHAN",
        (_P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW, _P.MAVLINK_MSG_ID_RC_CHANNELS),
    ),
    _P.MAV_DATA_STREAM_POSITION: (
        "SR0_POSITION",
        (_P.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    ),
    _P.MAV_DATA_STREAM_EXTRA1: (
        "SR0_EXTRA1",
        (_P.MAVLINK_MSG_ID_ATTITUDE, _P.MAVLINK_MSG_ID_SIMSTATE, _P.MAVLINK_MSG_ID_WHEEL_DISTANCE),
    ),
    _P.MAV_DATA_STREAM_EXTRA2: ("SR0_EXTRA2", (_P.MAVLINK_MSG_ID_VFR_HUD,)),
    _P.MAV_DATA_STREAM_EXTRA3: ("SR0_EXTRA3", (_P.MAVLINK_MSG_ID_SYSTEM_TIME,)),
}
GROUP_OF_MESSAGE = {m: g for g, (_, ids) in STREAM_GROUPS.items() for m in ids}
STREAMABLE = (_P.MAVLINK_MSG_ID_HEARTBEAT, *GROUP_OF_MESSAGE)


@dataclass
class Param:
    value: float
    type: int


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


@dataclass(frozen=True)
class ReceivedMessage:
    time_s: float
    message: MAVLinkMessage


def _wheel_param_prefixes() -> tuple[str, str]:
    return ("WENC", "WENC2")


class Autopilot:
    """The emulated flight controller's MAVLink-facing logic."""

    def __init__(
        self, vehicle: VehicleConfig, mav: mavlink.MAVLink, system_id: int = 1, component_id: int = 1
    ) -> None:
        self.vehicle = vehicle
        self.mav = mav  # only used to build message objects (encode); packing is elsewhere
        self.system_id = system_id
        self.component_id = component_id
        self.params: dict[str, Param] = self._default_params()
        self.outbox: list[MAVLinkMessage] = []
        self.statustexts_sent: list[str] = []
        self.received_odometry: list[ReceivedMessage] = []
        self.counters: dict[str, int] = {}
        self.radio_pwm: dict[int, int] = {ch: 1500 for ch in range(1, NUM_RC + 1)}  # no radio: trim
        self._rc = {ch: _RcChannel() for ch in range(1, NUM_RC + 1)}
        self._servos = {n: _Servo() for n in range(1, NUM_SERVOS + 1)}
        self._intervals_us: dict[int, int] = {}  # SET_MESSAGE_INTERVAL overrides (-1 = off)
        self._next_due_us: dict[int, int] = {}
        self.armed = vehicle.start_armed
        self.mode = MODE_MANUAL
        self.boot_us = 0
        self.booting_until_us: int | None = None  # set while rebooting: the link is silent
        self.reboot_count = 0
        self._encoder_offset = (0, 0)  # counts at boot, per physical wheel (left, right)
        self._now_us = 0
        self._pending_requests: list[int] = []  # REQUEST_MESSAGE ids to send with the next emit
        self.extnav = ExtNavConsumer(self._extnav_settings())
        self._extnav_last_us: int | None = None
        self._ahrs_yaw_rad = 0.0

    # ------------------------------------------------------------------ parameters
    def _default_params(self) -> dict[str, Param]:
        v = self.vehicle
        p: dict[str, Param] = {
            "SYSID_THISMAV": Param(float(self.system_id), _INT),
            "MAV_GCS_SYSID": Param(float(v.gcs_sysid), _INT),
            "RC_OVERRIDE_TIME": Param(v.rc_override_time_s, _REAL),
        }
        for n in range(1, NUM_SERVOS + 1):
            func = v.left_function if n == v.left_servo else v.right_function if n == v.right_servo else 0
            p[f"SERVO{n}_FUNCTION"] = Param(float(func), _INT)
            p[f"SERVO{n}_TRIM"] = Param(float(v.pwm_trim), _INT)
        for ch in range(1, 17):
            # Rover gives its steering (RC1) and throttle (RC3) channels a 30 us dead zone.
            p[f"RC{ch}_DZ"] = Param(30.0 if ch in (1, 3) else 0.0, _INT)
        order = ("left", "right") if v.wheel_distance_order == "left_right" else ("right", "left")
        for prefix, wheel in zip(_wheel_param_prefixes(), order, strict=True):
            p[f"{prefix}_TYPE"] = Param(1.0, _INT8)
            p[f"{prefix}_CPR"] = Param(float(v.encoder_cpr), _INT)
            p[f"{prefix}_RADIUS"] = Param(v.wheel_radius_m, _REAL)
            p[f"{prefix}_POS_Y"] = Param(
                -0.5 * v.track_width_m if wheel == "left" else 0.5 * v.track_width_m, _REAL
            )
        rates = {
            "SR0_RAW_SENS": v.rate_raw_sensors_hz,
            "SR0_EXT_STAT": v.rate_ext_status_hz,
            "SR0_RC_CHAN": v.rate_rc_channels_hz,
            "SR0_POSITION": v.rate_position_hz,
            "SR0_EXTRA1": v.rate_extra1_hz,
            "SR0_EXTRA2": v.rate_extra2_hz,
            "SR0_EXTRA3": v.rate_extra3_hz,
        }
        for name, hz in rates.items():
            p[name] = Param(float(hz), _INT)
        # External navigation from ODOMETRY (AP_VisualOdom, EKF3 sources): off unless the vehicle says so.
        ext = v.external_nav
        p["VISO_TYPE"] = Param(1.0 if ext else 0.0, _INT8)
        for name in ("EK3_SRC1_POSXY", "EK3_SRC1_VELXY"):
            p[name] = Param(6.0 if ext else 3.0, _INT8)  # 6 ExtNav, 3 GPS
        p["EK3_SRC1_YAW"] = Param(6.0 if ext else 1.0, _INT8)  # 6 ExtNav, 1 Compass
        p["VISO_POS_M_NSE"] = Param(0.2, _REAL)
        p["VISO_YAW_M_NSE"] = Param(0.2, _REAL)
        p["EK3_POS_I_GATE"] = Param(500.0, _INT)
        p["EK3_YAW_I_GATE"] = Param(300.0, _INT)
        return p

    def has_position(self) -> bool:
        """The EKF has a position: always with its GPS (the truth here), with external navigation only
        once it uses the companion's ODOMETRY."""
        return not self.extnav_position_source or self.extnav.position() is not None

    def heading_rad(self, s: PhysicsState) -> float:
        """ATTITUDE.yaw: the AHRS's, or external navigation's once it is in use (EK3_SRC1_YAW = 6)."""
        if self.extnav_yaw_source and self.extnav.using:
            return self.extnav.yaw_cw_rad
        return s.ahrs_yaw_rad

    def _extnav_settings(self) -> ExtNavSettings:
        return ExtNavSettings(pos_noise_m=self.param("VISO_POS_M_NSE"), yaw_noise_rad=self.param("VISO_YAW_M_NSE"),
                              pos_gate=max(0.01 * self.param("EK3_POS_I_GATE"), 1.0),
                              yaw_gate=max(0.01 * self.param("EK3_YAW_I_GATE"), 1.0),
                              use_yaw=self.param("EK3_SRC1_YAW") == 6)

    @property
    def extnav_position_source(self) -> bool:
        """The autopilot's position comes from ODOMETRY (VISO_TYPE 1, EK3_SRC1_POSXY 6)."""
        return self.param("VISO_TYPE") == 1 and self.param("EK3_SRC1_POSXY") == 6

    @property
    def extnav_yaw_source(self) -> bool:
        return self.param("VISO_TYPE") == 1 and self.param("EK3_SRC1_YAW") == 6

    def param(self, name: str) -> float:
        return self.params[name].value

    def set_param(self, name: str, value: float) -> bool:
        """Set a parameter as PARAM_SET would (integers rounded); False if it does not exist."""
        entry = self.params.get(name)
        if entry is None or not math.isfinite(value):
            return False
        entry.value = float(round(value)) if entry.type != _REAL else float(value)
        if name.startswith("SR0_"):
            group = next(g for g, (pname, _) in STREAM_GROUPS.items() if pname == name)
            self._reset_group(group)
        return True

    def _param_value_msg(self, name: str) -> MAVLinkMessage:
        names = list(self.params)
        entry = self.params[name]
        return self.mav.param_value_encode(
            name.encode(), entry.value, entry.type, len(names), names.index(name)
        )

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def send_text(self, severity: int, text: str) -> None:
        self.statustexts_sent.append(text)
        self.outbox.append(self.mav.statustext_encode(severity, text.encode()[:50]))

    def _ack(self, msg: MAVLinkMessage, command: int, result: int) -> None:
        self.outbox.append(
            self.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        )

    def _for_us(self, msg: MAVLinkMessage) -> bool:
        """ArduPilot's routing rule: broadcast (0) or our ids."""
        ts = getattr(msg, "target_system", None)
        tc = getattr(msg, "target_component", None)
        if ts is None and hasattr(msg, "target"):
            ts = msg.target
        if ts is not None and ts not in (0, self.system_id):
            return False
        return tc is None or tc in (0, self.component_id)

    @property
    def rebooting(self) -> bool:
        return self.booting_until_us is not None

    def time_boot_ms(self, now_us: int) -> int:
        return max(0, now_us - self.boot_us) // 1000

    # ------------------------------------------------------------------ RC and servos
    def has_override(self, ch: int, now_us: int) -> bool:
        rc = self._rc[ch]
        if rc.override_pwm == 0:
            return False
        timeout_s = self.param("RC_OVERRIDE_TIME")
        if timeout_s < 0.0:
            return True  # timeouts disabled
        if timeout_s == 0.0:
            return False  # overrides disabled
        return now_us - rc.last_override_us < round(timeout_s * 1e6)

    def rc_input(self, ch: int, now_us: int) -> int:
        return self._rc[ch].override_pwm if self.has_override(ch, now_us) else self.radio_pwm[ch]

    def rc_inputs(self, now_us: int) -> dict[int, int]:
        return {ch: self.rc_input(ch, now_us) for ch in range(1, NUM_RC + 1)}

    def _set_override(self, ch: int, pwm: int, now_us: int) -> None:
        self._rc[ch].override_pwm = pwm
        self._rc[ch].last_override_us = now_us

    def _servo_function(self, n: int) -> int:
        return int(self.param(f"SERVO{n}_FUNCTION"))

    def _skid_mix(self, now_us: int) -> tuple[float, float]:
        """Rover skid steering in MANUAL: throttle from RC3, steering from RC1 (RCMAP defaults)."""
        if not self.armed or self.mode != MODE_MANUAL:
            return 0.0, 0.0

        def norm(ch: int) -> float:
            offset = self.rc_input(ch, now_us) - 1500
            dz = self.param(f"RC{ch}_DZ")
            if abs(offset) <= dz:
                return 0.0
            return max(-1.0, min(1.0, (offset - math.copysign(dz, offset)) / (500.0 - dz)))

        throttle, steering = norm(3), norm(1)
        left, right = throttle + steering, throttle - steering
        scale = max(1.0, abs(left), abs(right))  # keep the turn when saturated
        return left / scale, right / scale

    def update(self, now_us: int, physics: PhysicsState) -> None:
        """Advance timers (reboot), the external-navigation estimate, and recompute every servo output."""
        self._now_us = now_us
        if self.booting_until_us is not None:
            if now_us < self.booting_until_us:
                for servo in self._servos.values():
                    servo.output_pwm = 0  # a rebooting board emits no pulses
                return
            self._finish_boot(now_us, physics)
        if self._extnav_last_us is not None and now_us > self._extnav_last_us:
            self.extnav.predict((now_us - self._extnav_last_us) / 1e6, physics.gyro_rad_s, physics.accel_m_s2,
                                physics.v_m_s * physics.yaw_rate_rad_s)
        self._extnav_last_us = now_us
        self._ahrs_yaw_rad = physics.ahrs_yaw_rad
        text = self.extnav.update(now_us)
        if text is not None and self.param("VISO_TYPE") == 1:
            self.send_text(_P.MAV_SEVERITY_INFO, text)
        left_mix, right_mix = self._skid_mix(now_us)
        for n, servo in self._servos.items():
            func = self._servo_function(n)
            trim = int(self.param(f"SERVO{n}_TRIM"))
            if func == FUNC_MANUAL or FUNC_RCIN1 <= func <= FUNC_RCIN16:
                ch = n if func == FUNC_MANUAL else func - FUNC_RCIN1 + 1
                radio_in = self.rc_input(ch, now_us)
                if not servo.ignore_small_rcin:
                    servo.output_pwm = radio_in
                    servo.previous_radio_in = radio_in
                elif abs(radio_in - servo.previous_radio_in) > self.param(f"RC{ch}_DZ"):
                    servo.output_pwm = radio_in  # the RC input moved: the DO_SET_SERVO hold ends
                    servo.ignore_small_rcin = False
                    servo.previous_radio_in = radio_in
            elif func in (FUNC_THROTTLE_LEFT, FUNC_THROTTLE_RIGHT):
                mix = left_mix if func == FUNC_THROTTLE_LEFT else right_mix
                servo.output_pwm = round(trim + mix * 500.0)
            elif func == FUNC_NONE:
                if not servo.set_by_command:
                    servo.output_pwm = 0
            else:
                servo.output_pwm = trim

    def servo_outputs(self) -> dict[int, int]:
        """PWM on every output pin (what SERVO_OUTPUT_RAW reports).

        Disarmed with ``passthrough_when_disarmed`` False, passthrough pins show trim while the
        servo keeps its passthrough/hold state, so arming resumes where ArduPilot would be.
        """
        out = {n: s.output_pwm for n, s in self._servos.items()}
        if not self.armed and not self.vehicle.passthrough_when_disarmed and not self.rebooting:
            for n in out:
                func = self._servo_function(n)
                if func == FUNC_MANUAL or FUNC_RCIN1 <= func <= FUNC_RCIN16:
                    out[n] = int(self.param(f"SERVO{n}_TRIM"))
        return out

    def wheel_commands(self) -> tuple[float, float]:
        """Normalised commands reaching the left and right motors."""
        if self.rebooting:
            return 0.0, 0.0
        if not self.armed and not self.vehicle.passthrough_when_disarmed:
            return 0.0, 0.0  # a disarmed rover's motors do not turn
        v = self.vehicle
        out = self.servo_outputs()
        return (
            pwm_to_command(out[v.left_servo], v, v.left_reversed),
            pwm_to_command(out[v.right_servo], v, v.right_reversed),
        )

    # ------------------------------------------------------------------ reboot
    def start_reboot(self, now_us: int) -> None:
        self.booting_until_us = now_us + round(self.vehicle.reboot_silence_s * 1e6)
        self.reboot_count += 1
        self._count("reboots")

    def _finish_boot(self, now_us: int, physics: PhysicsState) -> None:
        self.booting_until_us = None
        self.boot_us = now_us
        self.armed = self.vehicle.start_armed
        self.mode = MODE_MANUAL
        self._rc = {ch: _RcChannel() for ch in range(1, NUM_RC + 1)}
        self._servos = {n: _Servo() for n in range(1, NUM_SERVOS + 1)}
        self._intervals_us.clear()  # SET_MESSAGE_INTERVAL lives in RAM; SRn_ params persist
        self._next_due_us.clear()
        self.extnav = ExtNavConsumer(self._extnav_settings())  # a new EKF: no position until ODOMETRY again
        cpr = self.vehicle.encoder_cpr
        self._encoder_offset = (
            encoder_counts(physics.left_encoder_angle_rad, cpr),
            encoder_counts(physics.right_encoder_angle_rad, cpr),
        )

    # ------------------------------------------------------------------ incoming
    def handle(self, msg: MAVLinkMessage, now_us: int) -> None:
        """Process one decoded message (ignored while rebooting)."""
        self._now_us = now_us
        if self.rebooting:
            self._count("rx_while_rebooting")
            return
        self._count("rx_messages")
        msg_id = msg.get_msgId()
        if msg_id < 0:
            self._count("rx_bad_data")
            return
        if not self._for_us(msg):
            self._count("rx_not_for_us")
            if msg_id == _P.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE:
                self._count("override_wrong_target")
            return
        if msg_id == _P.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE:
            self._handle_override(msg, now_us)
        elif msg_id == _P.MAVLINK_MSG_ID_COMMAND_LONG:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
            self._handle_command(msg, msg.command, params, now_us)
        elif msg_id == _P.MAVLINK_MSG_ID_COMMAND_INT:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
            self._handle_command(msg, msg.command, params, now_us)
        elif msg_id == _P.MAVLINK_MSG_ID_SET_MODE:
            self._set_mode(msg.base_mode, msg.custom_mode)
        elif msg_id == _P.MAVLINK_MSG_ID_REQUEST_DATA_STREAM:
            self._handle_request_data_stream(msg, now_us)
        elif msg_id == _P.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
            for name in self.params:
                self.outbox.append(self._param_value_msg(name))
        elif msg_id == _P.MAVLINK_MSG_ID_PARAM_REQUEST_READ:
            self._handle_param_read(msg)
        elif msg_id == _P.MAVLINK_MSG_ID_PARAM_SET:
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
            if self.set_param(name, float(msg.param_value)):
                self.outbox.append(self._param_value_msg(name))
            else:
                self._count("param_set_unknown")
        elif msg_id == _P.MAVLINK_MSG_ID_ODOMETRY:
            self.received_odometry.append(ReceivedMessage(now_us / 1e6, msg))
            if self.param("VISO_TYPE") == 1:
                self.extnav.settings = self._extnav_settings()
                self.extnav.odometry(msg, now_us, self._ahrs_yaw_rad)
        elif msg_id == _P.MAVLINK_MSG_ID_HEARTBEAT:
            self._count("rx_heartbeats")
        elif msg_id == _P.MAVLINK_MSG_ID_TIMESYNC and msg.tc1 == 0:
            # GCS_Common.cpp handle_timesync: a request (tc1 == 0) is answered while parsing, ts1 echoed,
            # so its reply proves every byte before it on this link was handled.
            self._count("timesync_replies")
            self.outbox.append(self.mav.timesync_encode(max(1, now_us * 1000), msg.ts1))

    def _handle_override(self, msg: MAVLinkMessage, now_us: int) -> None:
        if msg.get_srcSystem() != int(self.param("MAV_GCS_SYSID")):
            self._count("override_rejected_sysid")  # silently, as ArduPilot does
            return
        self._count("override_accepted")
        for ch in range(1, NUM_RC + 1):
            value = int(getattr(msg, f"chan{ch}_raw", UINT16_MAX if ch <= 8 else 0))
            if ch <= 8:
                if value != UINT16_MAX:
                    self._set_override(ch, value, now_us)  # 0 releases the channel
            elif value not in (0, UINT16_MAX):
                self._set_override(ch, 0 if value == UINT16_MAX - 1 else value, now_us)

    def _handle_param_read(self, msg: MAVLinkMessage) -> None:
        names = list(self.params)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self.outbox.append(self._param_value_msg(names[msg.param_index]))
            return
        name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else str(msg.param_id)
        if name in self.params:
            self.outbox.append(self._param_value_msg(name))
        else:
            self._count("param_read_unknown")

    def _handle_request_data_stream(self, msg: MAVLinkMessage, now_us: int) -> None:
        if msg.start_stop == 0:
            hz = 0
        elif msg.start_stop == 1:
            hz = int(msg.req_message_rate)
        else:
            return
        if msg.req_stream_id == _P.MAV_DATA_STREAM_ALL:
            groups = list(STREAM_GROUPS)
        elif msg.req_stream_id in STREAM_GROUPS:
            groups = [msg.req_stream_id]
        else:
            return
        for group in groups:
            self.set_param(STREAM_GROUPS[group][0], float(hz))

    def _reset_group(self, group: int) -> None:
        for mid in STREAM_GROUPS[group][1]:
            self._intervals_us.pop(mid, None)
            self._next_due_us[mid] = self._now_us  # the new rate starts at once

    def _set_mode(self, base_mode: int, custom_mode: int) -> bool:
        if not base_mode & _P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return False
        if custom_mode not in MODE_NAMES:
            self.send_text(_P.MAV_SEVERITY_WARNING, f"Mode change to {custom_mode} failed: not emulated")
            return False
        if custom_mode != self.mode:
            self._pending_requests.append(_P.MAVLINK_MSG_ID_HEARTBEAT)  # announced at once, as Rover does
        self.mode = custom_mode
        return True

    def _handle_command(
        self, msg: MAVLinkMessage, command: int, params: tuple[float, ...], now_us: int
    ) -> None:
        self._count("commands")
        p1, p2 = params[0], params[1]
        result = _P.MAV_RESULT_UNSUPPORTED
        reboot = False
        if command == _P.MAV_CMD_COMPONENT_ARM_DISARM:
            if p1 == 1.0:
                result = self._arm(force=int(p2) == FORCE_ARM_MAGIC)
            elif p1 == 0.0:
                self.armed = False
                result = _P.MAV_RESULT_ACCEPTED
        elif command == _P.MAV_CMD_DO_SET_MODE:
            ok = self._set_mode(int(p1), int(p2))
            result = _P.MAV_RESULT_ACCEPTED if ok else _P.MAV_RESULT_FAILED
        elif command == _P.MAV_CMD_DO_SET_SERVO:
            result = self._do_set_servo(wire_int(p1, "uint8_t"), wire_int(p2, "uint16_t"), now_us)  # C's casts
        elif command == _P.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_message_interval(int(p1), p2)
        elif command == _P.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(int(p1))
        elif command == _P.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self.outbox.append(self._autopilot_version())
            result = _P.MAV_RESULT_ACCEPTED
        elif command == _P.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if self.armed:
                result = _P.MAV_RESULT_FAILED  # ArduPilot refuses to reboot when armed
            elif p1 in (1.0, 3.0):
                result = _P.MAV_RESULT_ACCEPTED
                reboot = True
        if result == _P.MAV_RESULT_UNSUPPORTED:
            self._count("commands_unsupported")
        self._ack(msg, command, result)
        if reboot:
            self.start_reboot(now_us)  # after the ACK is queued, as ArduPilot sends it first

    def _arm(self, force: bool) -> int:
        if self.armed:
            return ACCEPTED
        if self.vehicle.strict_prearm and not force:
            funcs = {self._servo_function(n) for n in self._servos}
            if not funcs & {FUNC_THROTTLE_LEFT, FUNC_THROTTLE_RIGHT}:
                self.send_text(
                    _P.MAV_SEVERITY_CRITICAL, "PreArm: no motor, sail or scripting outputs defined"
                )
                return FAILED
        self.armed = True
        return ACCEPTED

    def _do_set_servo(self, n: int, pwm: int, now_us: int) -> int:
        if not 1 <= n <= NUM_SERVOS:
            return FAILED
        func = self._servo_function(n)
        if not (func in (FUNC_NONE, FUNC_MANUAL) or FUNC_RCIN1 <= func <= FUNC_RCIN16):
            self.send_text(_P.MAV_SEVERITY_INFO, f"ServoRelayEvent: Channel {n} is already in use")
            return FAILED
        servo = self._servos[n]
        servo.output_pwm = pwm
        servo.ignore_small_rcin = True
        servo.set_by_command = True
        self._count("servo_commands")
        return ACCEPTED

    def _mapped(self, msg_id: int) -> bool:
        if msg_id == _P.MAVLINK_MSG_ID_WHEEL_DISTANCE and self.vehicle.deny_wheel_distance_interval:
            return False
        return msg_id in STREAMABLE

    def _set_message_interval(self, msg_id: int, interval_us: float) -> int:
        if not self._mapped(msg_id):
            self.send_text(_P.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msg_id})")
            return DENIED
        if interval_us < 0:
            self._intervals_us[msg_id] = -1
        elif interval_us == 0:
            self._intervals_us.pop(msg_id, None)  # back to the default (group) rate
        else:
            self._intervals_us[msg_id] = int(interval_us)
        self._next_due_us[msg_id] = self._now_us
        return ACCEPTED

    def _request_message(self, msg_id: int) -> int:
        if msg_id == _P.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self.outbox.append(self._autopilot_version())
            return ACCEPTED
        if not self._mapped(msg_id):
            return FAILED
        self._pending_requests.append(msg_id)
        return ACCEPTED

    def _autopilot_version(self) -> MAVLinkMessage:
        caps = (
            _P.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | _P.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | _P.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
        )
        version = (4 << 24) | (7 << 16) | (0 << 8) | 255  # "4.7.0 official", emulated
        zeros8 = [0] * 8
        return self.mav.autopilot_version_encode(
            caps, version, 0, 0, 0, zeros8, zeros8, zeros8, 0, 0, self.system_id
        )

    # ------------------------------------------------------------------ outgoing streams
    def interval_us(self, msg_id: int) -> int | None:
        """Current interval of a stream (None = off)."""
        if msg_id == _P.MAVLINK_MSG_ID_HEARTBEAT and msg_id not in self._intervals_us:
            return 1_000_000
        override = self._intervals_us.get(msg_id)
        if override is not None:
            return None if override < 0 else override
        group = GROUP_OF_MESSAGE.get(msg_id)
        if group is None:
            return None
        hz = self.param(STREAM_GROUPS[group][0])
        return None if hz <= 0 else round(1e6 / hz)

    def emit(self, now_us: int, physics: PhysicsState) -> list[MAVLinkMessage]:
        """Stream messages due at ``now_us`` (nothing while rebooting)."""
        self._now_us = now_us
        if self.rebooting:
            return []
        out: list[MAVLinkMessage] = []
        for mid in self._pending_requests:
            out.append(self.build(mid, now_us, physics))
        self._pending_requests.clear()
        for mid in STREAMABLE:
            interval = self.interval_us(mid)
            if interval is None:
                continue
            due = self._next_due_us.get(mid, self.boot_us)
            if now_us < due:
                continue
            if mid == _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not self.has_position():
                continue  # ArduPilot sends no local position before its EKF has one
            out.append(self.build(mid, now_us, physics))
            due += interval
            if due <= now_us:  # fell behind (a big step): skip, do not burst
                due = now_us + interval
            self._next_due_us[mid] = due
        return out

    def wheel_distances_m(self, physics: PhysicsState) -> tuple[float, float]:
        """(index 0, index 1) cumulative distances since boot, as WHEEL_DISTANCE reports them."""
        cpr = self.vehicle.encoder_cpr
        counts = {
            "left": encoder_counts(physics.left_encoder_angle_rad, cpr) - self._encoder_offset[0],
            "right": encoder_counts(physics.right_encoder_angle_rad, cpr) - self._encoder_offset[1],
        }
        order = ("left", "right") if self.vehicle.wheel_distance_order == "left_right" else ("right", "left")
        out = []
        for prefix, wheel in zip(_wheel_param_prefixes(), order, strict=True):
            radius = self.param(f"{prefix}_RADIUS")
            param_cpr = max(1.0, self.param(f"{prefix}_CPR"))
            out.append(counts[wheel] * 2.0 * math.pi * radius / param_cpr)
        return out[0], out[1]

    @fitted  # every field saturates at its wire type's range, as the C conversions on the autopilot do
    def build(self, msg_id: int, now_us: int, s: PhysicsState) -> MAVLinkMessage:
        """Build one message of a stream from the current state."""
        boot_ms = self.time_boot_ms(now_us)
        boot_us = max(0, now_us - self.boot_us)
        m = self.mav
        if msg_id == _P.MAVLINK_MSG_ID_HEARTBEAT:
            base = _P.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | _P.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            if self.mode == MODE_GUIDED:
                base |= _P.MAV_MODE_FLAG_GUIDED_ENABLED | _P.MAV_MODE_FLAG_STABILIZE_ENABLED
            if self.armed:
                base |= _P.MAV_MODE_FLAG_SAFETY_ARMED
            # GCS_MAVLINK_Rover::vehicle_system_status: armed and not holding is ACTIVE.
            status = _P.MAV_STATE_ACTIVE if self.armed and self.mode != MODE_HOLD else _P.MAV_STATE_STANDBY
            return m.heartbeat_encode(
                _P.MAV_TYPE_GROUND_ROVER, _P.MAV_AUTOPILOT_ARDUPILOTMEGA, base, self.mode, status, 3
            )
        if msg_id == _P.MAVLINK_MSG_ID_WHEEL_DISTANCE:
            d0, d1 = self.wheel_distances_m(s)
            return m.wheel_distance_encode(boot_us, 2, [d0, d1] + [0.0] * 14)
        if msg_id == _P.MAVLINK_MSG_ID_ATTITUDE:
            return m.attitude_encode(boot_ms, 0.0, 0.0, self.heading_rad(s), 0.0, 0.0, s.gyro_rad_s)
        if msg_id in (_P.MAVLINK_MSG_ID_RAW_IMU, _P.MAVLINK_MSG_ID_SCALED_IMU):
            # mG and mrad/s in FRD: x forward, y right, z down (gravity reads -1 g); the accelerometer
            # saturates at +-16 g, the gyro (already in its range) at int16 in mrad/s (sitl/sensors.py).
            ax = accel_reading_m_s2(s.accel_m_s2) / G_M_S2 * 1000.0
            ay = accel_reading_m_s2(s.v_m_s * s.yaw_rate_rad_s) / G_M_S2 * 1000.0
            gz = s.gyro_rad_s * 1000.0
            if msg_id == _P.MAVLINK_MSG_ID_RAW_IMU:
                return m.raw_imu_encode(boot_us, ax, ay, -1000, 0, 0, gz, 0, 0, 0)
            return m.scaled_imu_encode(boot_ms, ax, ay, -1000, 0, 0, gz, 0, 0, 0)
        if msg_id == _P.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW:
            out = self.servo_outputs()
            return m.servo_output_raw_encode(boot_us & 0xFFFFFFFF, 0, *[out[n] for n in range(1, 17)])
        if msg_id == _P.MAVLINK_MSG_ID_RC_CHANNELS:
            rc = self.rc_inputs(now_us)
            return m.rc_channels_encode(boot_ms, NUM_RC, *[rc[ch] for ch in range(1, NUM_RC + 1)], 255)
        if msg_id == _P.MAVLINK_MSG_ID_SYSTEM_TIME:
            return m.system_time_encode(0, boot_ms)  # no GPS: no UNIX time, as ArduPilot
        if msg_id == _P.MAVLINK_MSG_ID_SYS_STATUS:
            return m.sys_status_encode(0, 0, 0, 0, 12000, -1, -1, 0, 0, 0, 0, 0, 0)
        if msg_id == _P.MAVLINK_MSG_ID_VFR_HUD:
            heading: int = round(math.degrees(s.ahrs_yaw_rad)) % 360
            return m.vfr_hud_encode(abs(s.v_m_s), abs(s.v_m_s), heading, 0, 0.0, 0.0)
        if msg_id == _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            ext = self.extnav.position() if self.extnav_position_source else None
            if ext is not None:  # the EKF navigates on the companion's ODOMETRY
                return m.local_position_ned_encode(boot_ms, ext[0], ext[1], 0.0, self.extnav.vel_n_m_s,
                                                   self.extnav.vel_e_m_s, 0.0)
            vx = s.v_m_s * math.cos(s.yaw_rad)
            vy = s.v_m_s * math.sin(s.yaw_rad)
            return m.local_position_ned_encode(boot_ms, s.x_m, s.y_m, 0.0, vx, vy, 0.0)
        if msg_id == _P.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat_deg = lon_deg = 0.0  # no position yet: ArduPilot sends zeros
            if self.has_position():
                ext = self.extnav.position() if self.extnav_position_source else None
                lat_deg, lon_deg = self._lat_lon_of(*(ext if ext is not None else (s.x_m, s.y_m)))
            vn, ve = s.v_m_s * math.cos(s.yaw_rad), s.v_m_s * math.sin(s.yaw_rad)
            hdg = round(math.degrees(self.heading_rad(s)) * 100.0) % 36000
            return m.global_position_int_encode(boot_ms, lat_deg * 1e7, lon_deg * 1e7, 584_000, 0,
                                                vn * 100.0, ve * 100.0, 0, hdg)
        if msg_id == _P.MAVLINK_MSG_ID_SIMSTATE:
            lat_deg, lon_deg = self._lat_lon(s)
            lateral_m_s2 = s.v_m_s * s.yaw_rate_rad_s
            return m.simstate_encode(
                0.0,
                0.0,
                s.yaw_rad,
                s.accel_m_s2,
                lateral_m_s2,
                -9.80665,
                0.0,
                0.0,
                s.yaw_rate_rad_s,
                lat_deg * 1e7,
                lon_deg * 1e7,
            )
        raise ValueError(f"cannot build message id {msg_id}")

    def _lat_lon(self, s: PhysicsState) -> tuple[float, float]:
        return self._lat_lon_of(s.x_m, s.y_m)

    def _lat_lon_of(self, north_m: float, east_m: float) -> tuple[float, float]:
        """A point north/east of the origin (vehicle origin_lat/lon_deg), on a sphere of the WGS-84 radius."""
        earth_radius_m = 6378137.0
        lat0 = self.vehicle.origin_lat_deg
        lat = lat0 + math.degrees(north_m / earth_radius_m)
        lon = self.vehicle.origin_lon_deg + math.degrees(east_m / (earth_radius_m * math.cos(math.radians(lat0))))
        return lat, lon
