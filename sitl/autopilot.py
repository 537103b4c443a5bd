"""ArduPilot-Rover-like MAVLink behaviour, as a pure state machine (no sockets, no clocks).

``handle(msg, now_us)`` takes one decoded message; ``update(now_us, physics)`` advances the
autopilot's own timers (override timeouts, reboot), runs Rover's loop when one is due and recomputes
the servo outputs; ``emit(now_us, physics)`` returns the stream messages that are due. Outgoing
messages are collected in ``outbox`` (replies) and returned by ``emit`` (streams). Times are integer
microseconds of simulated time since the emulator started.

The pieces (each says what it copies of ArduPilot and which source files were read): sitl/rc.py (RC
inputs, overrides, servo outputs), sitl/streams.py (stream groups, SET_MESSAGE_INTERVAL), sitl/params.py,
sitl/commands.py, sitl/messages.py, sitl/mission.py + sitl/mission_protocol.py (+ sitl/fence_protocol.py),
sitl/range_sensors.py (PRX1, RNGFND1: DISTANCE_SENSOR), sitl/rover.py (the
loop, modes, home, fence, GCS failsafe) with sitl/navigation.py, sitl/wpnav.py, sitl/poscontrol.py,
sitl/scurve.py, sitl/control.py, sitl/motors.py and sitl/smartrtl.py, sitl/extnav.py; sitl/skid.py (the
ardupilot_skid plant's encoders and WHEEL_DISTANCE, sent from Rover's loop).

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
  steering demand (MANUAL: throttle RC3, steering RC1, left = throttle + steering; the driving modes:
  sitl/navigation.py), scaled by that output's SERVOn_MIN/MAX/TRIM/REVERSED (sitl/motors.py).
- MAV_CMD_DO_SET_SERVO (libraries/AP_ServoRelayEvents/AP_ServoRelayEvents.cpp): allowed only
  on outputs with function 0 (none), 1 (manual) or 51..66 (RC passthrough); otherwise a
  STATUSTEXT "ServoRelayEvent: Channel N is already in use" and MAV_RESULT_FAILED. On a
  passthrough output the value then holds, with no timeout, until the RC input moves by more
  than that RC channel's dead zone (SRV_Channel.cpp ignore_small_rcin_changes; Rover's
  default RC1_DZ = RC3_DZ = 30).
- Streams and SET_MESSAGE_INTERVAL: sitl/streams.py. REQUEST_DATA_STREAM sets the SRn_ rate of the
  group(s) and resets that group's per-message intervals. 4.7 has no internal mapping for
  WHEEL_DISTANCE: its interval is DENIED unless ``deny_wheel_distance_interval`` is False.
- MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (GCS_Common.cpp handle_preflight_reboot): refused with
  FAILED when armed; param1 must be 1 or 3 (else UNSUPPORTED); the ACK goes out first.
- WHEEL_DISTANCE (Rover/GCS_MAVLink_Rover.cpp, libraries/AP_WheelEncoder): time_usec = time
  since boot, cumulative metres since boot = counts * 2*pi*WENCn_RADIUS / WENCn_CPR.
- Modes (Rover/mode.h): every Rover custom_mode is accepted (unless its entry conditions refuse it,
  sitl/rover.py) and reported in HEARTBEAT, one sent at once after a change (Rover/system.cpp
  set_mode: gcs().send_message(MSG_HEARTBEAT)); SET_MODE gets no ACK, DO_SET_MODE its COMMAND_ACK
  while parsing (so the ACK arrives before that heartbeat); RC passthrough outputs (51..66) follow
  the RC input in every mode (SRV_Channel::output_ch has no mode check), so HOLD stops only the
  motor-function outputs.
- TIMESYNC (GCS_Common.cpp handle_timesync): tc1 == 0 is answered at once, ts1 echoed.
- Stream links (SITL's TCP UART, AP_HAL_SITL/UARTDriver.cpp): bytes are read between main loops and
  parsed in the next loop's update_receive; when the client closes, what was not parsed yet is never
  seen as that client's (the emulator drops it), so a stop sent just before a close is lost.
- Navigation uses the EKF's estimate: with GPS the truth (a compass-aided EKF does not drift like the
  gyro-integrated yaw ATTITUDE reports), with external navigation sitl/extnav.py's position and yaw.

Differences from ArduPilot, on purpose: MANUAL's mix is evaluated continuously (not at the loop
rate); GUIDED does not navigate (position targets are the bridge's to drive; it stops like Rover's
GUIDED without a target); ACRO, STEERING, LOITER, FOLLOW, SIMPLE, DOCK and CIRCLE leave the motor
outputs at trim; SCALED_IMU is sent in RAW_SENSORS beside RAW_IMU; the ground truth is sent as
SIMSTATE and LOCAL_POSITION_NED; with ``passthrough_when_disarmed`` False (the default) passthrough
outputs sit at trim while disarmed (real ArduPilot passes them through: set it True for that).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl import incoming, messages
from sitl.config import VehicleConfig
from sitl.control import NavState
from sitl.extnav import ExtNavConsumer, ExtNavSettings
from sitl.fence_protocol import FenceProtocol
from sitl.fence_store import FenceStore
from sitl.geo import lat_lon_of, north_east_of
from sitl.mav import MAVLinkMessage, mavlink
from sitl.mission import Mission, MissionItem
from sitl.mission_protocol import MissionProtocol
from sitl.modes import MODE_GUIDED, MODE_HOLD, MODE_MANUAL
from sitl.obstacles import Shape
from sitl.params import WHEEL_PARAM_PREFIXES, Param, default_params, set_value
from sitl.physics import PhysicsState, encoder_counts, pwm_to_command
from sitl.rc import RcServos
from sitl.rover import Rover
from sitl.skid import ARDUPILOT_SKID, SkidLoop
from sitl.streams import GROUP_OF_MESSAGE, HOME_POSITION, STREAM_GROUPS, STREAMABLE, Streams

__all__ = ["MODE_GUIDED", "MODE_HOLD", "MODE_MANUAL", "Autopilot", "ReceivedMessage"]

_P = mavlink
WHEEL_DISTANCE: int = _P.MAVLINK_MSG_ID_WHEEL_DISTANCE


@dataclass(frozen=True)
class ReceivedMessage:
    time_s: float
    message: MAVLinkMessage


class Autopilot:
    """The emulated flight controller's MAVLink-facing logic (the pieces are listed in the module doc)."""

    def __init__(
        self, vehicle: VehicleConfig, mav: mavlink.MAVLink, system_id: int = 1, component_id: int = 1, seed: int = 0
    ) -> None:
        self.vehicle = vehicle
        self.mav = mav  # only used to build message objects (encode); packing is elsewhere
        self.system_id = system_id
        self.component_id = component_id
        self.params: dict[str, Param] = default_params(vehicle, system_id)
        self.outbox: list[MAVLinkMessage] = []
        self.statustexts_sent: list[str] = []
        self._text_id = 0
        self.received_odometry: list[ReceivedMessage] = []
        self.counters: dict[str, int] = {}
        self.rc = RcServos(vehicle, self.param)
        self.streams = Streams()
        self.mission = Mission()  # in storage: it survives reboots
        self.fence = FenceStore()  # in storage too
        self.obstacles: tuple[Shape, ...] = ()  # the world's (the emulator's scenario): what the SITL sensors see
        self.armed = vehicle.start_armed
        self.boot_us = 0
        self.booting_until_us: int | None = None  # set while rebooting: the link is silent
        self.reboot_count = 0
        self._encoder_offset = (0, 0)  # counts at boot, per physical wheel (left, right)
        self._now_us = 0
        self.extnav = ExtNavConsumer(self._extnav_settings())
        self._extnav_last_us: int | None = None
        self._ahrs_yaw_rad = 0.0
        self._physics = PhysicsState()  # the last state update() saw
        self._boot_vehicle()
        # ArduPilot SITL's skid plant: its encoders are read, and WHEEL_DISTANCE sent, in Rover's loop (sitl/skid.py).
        self.skid_loop = SkidLoop(self.param, self.rover.loop_period_us, vehicle.loop_late_rate, seed) \
            if vehicle.plant == ARDUPILOT_SKID else None

    def _boot_vehicle(self) -> None:
        """What a boot starts afresh: the vehicle's loop, modes, home, fence, mission cursor and transfers."""
        self.rover = Rover(self.param, self.mission, self.send_text, self.streams.pending.append,
                           self._item_reached, self.lat_lon_of, self._item_position,
                           lambda: self.nav_state(self._physics))
        # The emulator swaps ``outbox`` for a new list after each step: send through it, never keep it.
        fence = FenceProtocol(self.fence, self.mav, lambda msg: self.outbox.append(msg), self.send_text)
        self.protocol = MissionProtocol(self.mission, self.mav, lambda msg: self.outbox.append(msg), self.send_text,
                                        self._home_item, self.count, fence)

    # ------------------------------------------------------------------ state others read
    @property
    def mode(self) -> int:
        return self.rover.mode

    @property
    def radio_pwm(self) -> dict[int, int]:
        return self.rc.radio_pwm

    @property
    def rebooting(self) -> bool:
        return self.booting_until_us is not None

    def time_boot_ms(self, now_us: int) -> int:
        return max(0, now_us - self.boot_us) // 1000

    def param(self, name: str) -> float:
        return self.params[name].value

    def set_param(self, name: str, value: float) -> bool:
        """Set a parameter as PARAM_SET would (integers rounded); False if it does not exist."""
        entry = self.params.get(name)
        if entry is None or not set_value(entry, value):
            return False
        if name.startswith("SR0_"):
            group = next(g for g, (pname, _) in STREAM_GROUPS.items() if pname == name)
            self.streams.reset_group(group, self._now_us)
        return True

    @property
    def now_us(self) -> int:
        return self._now_us

    def param_value_msg(self, name: str) -> MAVLinkMessage:
        names = list(self.params)
        entry = self.params[name]
        return self.mav.param_value_encode(name.encode(), entry.value, entry.type, len(names), names.index(name))

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def send_text(self, severity: int, text: str) -> None:
        """STATUSTEXT; a text longer than 50 bytes goes out in 50-byte chunks sharing an id (GCS::send_textv)."""
        self.statustexts_sent.append(text)
        data = text.encode()
        if len(data) <= 50:
            self.outbox.append(self.mav.statustext_encode(severity, data))
            return
        self._text_id = self._text_id % 65535 + 1
        for seq, start in enumerate(range(0, len(data) + 1, 50)):
            self.outbox.append(self.mav.statustext_encode(severity, data[start:start + 50], self._text_id, seq))

    def lat_lon_of(self, north_m: float, east_m: float) -> tuple[float, float]:
        return lat_lon_of(north_m, east_m, self.vehicle.origin_lat_deg, self.vehicle.origin_lon_deg)

    def _item_position(self, item: MissionItem) -> tuple[float, float]:
        v = self.vehicle
        return north_east_of(item.x * 1e-7, item.y * 1e-7, v.origin_lat_deg, v.origin_lon_deg)

    def _home_item(self) -> MissionItem:
        home = self.rover.nav.home
        if home is None:
            return MissionItem(16, frame=0)  # ArduPilot's unset home: an all-zero location
        lat, lon = self.lat_lon_of(*home)
        return MissionItem(16, frame=0, x=round(lat * 1e7), y=round(lon * 1e7), z=messages.HOME_ALT_MM / 1000.0)

    def _item_reached(self, seq: int) -> None:
        self.outbox.append(self.mav.mission_item_reached_encode(seq))

    def mission_current_msg(self, seq: int) -> MAVLinkMessage:
        """MISSION_CURRENT reporting ``seq`` (MISSION_SET_CURRENT's answer)."""
        return messages.mission_current(self, seq)

    # ------------------------------------------------------------------ the estimate
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

    def has_position(self) -> bool:
        """The EKF has a position: always with its GPS (the truth here), with external navigation only
        once it uses the companion's ODOMETRY."""
        return not self.extnav_position_source or self.extnav.position() is not None

    def heading_rad(self, s: PhysicsState) -> float:
        """ATTITUDE.yaw: the AHRS's, or external navigation's once it is in use (EK3_SRC1_YAW = 6)."""
        if self.extnav_yaw_source and self.extnav.using:
            return self.extnav.yaw_cw_rad
        return s.ahrs_yaw_rad

    def nav_state(self, s: PhysicsState) -> NavState | None:
        """The estimate navigation runs on (None without a position)."""
        yaw = self.extnav.yaw_cw_rad if self.extnav_yaw_source and self.extnav.using else s.yaw_rad
        if self.extnav_position_source:
            pos = self.extnav.position()
            if pos is None:
                return None
            return NavState(pos[0], pos[1], self.extnav.vel_n_m_s, self.extnav.vel_e_m_s, yaw, s.yaw_rate_rad_s)
        vn, ve = s.v_m_s * math.cos(s.yaw_rad), s.v_m_s * math.sin(s.yaw_rad)
        return NavState(s.x_m, s.y_m, vn, ve, yaw, s.yaw_rate_rad_s)

    # ------------------------------------------------------------------ RC, servos and wheels
    def has_override(self, ch: int, now_us: int) -> bool:
        return self.rc.has_override(ch, now_us)

    def rc_inputs(self, now_us: int) -> dict[int, int]:
        return self.rc.rc_inputs(now_us)

    def _set_override(self, ch: int, pwm: int, now_us: int) -> None:
        self.rc.set_override(ch, pwm, now_us)

    def servo_outputs(self) -> dict[int, int]:
        """PWM on every output pin (what SERVO_OUTPUT_RAW reports)."""
        return self.rc.outputs(self.armed, self.rebooting)

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

    def wheel_distances_m(self, physics: PhysicsState) -> tuple[float, float]:
        """(index 0, index 1) cumulative distances since boot, as WHEEL_DISTANCE reports them."""
        if self.skid_loop is not None:
            return self.skid_loop.distances_m()
        cpr = self.vehicle.encoder_cpr
        counts = {
            "left": encoder_counts(physics.left_encoder_angle_rad, cpr) - self._encoder_offset[0],
            "right": encoder_counts(physics.right_encoder_angle_rad, cpr) - self._encoder_offset[1],
        }
        order = ("left", "right") if self.vehicle.wheel_distance_order == "left_right" else ("right", "left")
        out = []
        for prefix, wheel in zip(WHEEL_PARAM_PREFIXES, order, strict=True):
            radius = self.param(f"{prefix}_RADIUS")
            param_cpr = max(1.0, self.param(f"{prefix}_CPR"))
            out.append(counts[wheel] * 2.0 * math.pi * radius / param_cpr)
        return out[0], out[1]

    # ------------------------------------------------------------------ in and out
    def handle(self, msg: MAVLinkMessage, now_us: int) -> None:
        """Process one decoded message (sitl/incoming.py; ignored while rebooting)."""
        self._now_us = now_us
        incoming.handle_message(self, msg, now_us)

    def take_odometry(self, msg: MAVLinkMessage, now_us: int) -> None:
        self.received_odometry.append(ReceivedMessage(now_us / 1e6, msg))
        if self.param("VISO_TYPE") == 1:
            self.extnav.settings = self._extnav_settings()
            self.extnav.odometry(msg, now_us, self._ahrs_yaw_rad)

    def update(self, now_us: int, physics: PhysicsState) -> None:
        """Advance timers (reboot), the estimate and Rover's loop, and recompute every servo output."""
        self._now_us = now_us
        self._physics = physics
        if self.booting_until_us is not None:
            if now_us < self.booting_until_us:
                self.rc.silence()
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
        enc = self.skid_loop
        if enc is not None and enc.update(now_us, physics, self.interval_us(WHEEL_DISTANCE)):
            self.outbox += messages.build_all(self, WHEEL_DISTANCE, enc.stamp_us, physics)
        rover = self.rover
        rover.update(now_us, self.boot_us, self.nav_state(physics), self.armed, self.rc.have_skid_steering())
        if rover.disarm_requested:
            rover.disarm_requested, self.armed = False, False
        if rover.clear_overrides_requested:
            rover.clear_overrides_requested = False
            self.rc.clear_overrides()
        self.protocol.update(self.time_boot_ms(now_us))
        left, right = rover.left, rover.right
        if rover.mode == MODE_MANUAL:
            left, right = self.rc.manual_mix(now_us, self.armed)
            rover.manual_mix(left, right)
        self.rc.update(now_us, left, right, self.armed)

    def emit(self, now_us: int, physics: PhysicsState) -> list[MAVLinkMessage]:
        """Stream messages due at ``now_us`` (nothing while rebooting)."""
        self._now_us = now_us
        if self.rebooting:
            return []
        out: list[MAVLinkMessage] = []
        for mid in self.streams.pending:
            out += messages.build_all(self, mid, now_us, physics)
        self.streams.pending.clear()
        extra = (HOME_POSITION,) if HOME_POSITION in self.streams.intervals_us else ()
        for mid in (*STREAMABLE, *extra):
            interval = self.interval_us(mid)
            if interval is None or (mid == WHEEL_DISTANCE and self.skid_loop is not None):
                continue  # off, or sent from the loop (the skid plant)
            if mid == _P.MAVLINK_MSG_ID_LOCAL_POSITION_NED and not self.has_position():
                continue  # ArduPilot sends no local position before its EKF has one
            if self.streams.take_due(mid, interval, now_us, self.boot_us):
                out += messages.build_all(self, mid, now_us, physics)
        return out

    def interval_us(self, msg_id: int) -> int | None:
        """Current interval of a stream (None = off)."""
        group = GROUP_OF_MESSAGE.get(msg_id)
        return self.streams.interval_us(msg_id, self.param(STREAM_GROUPS[group][0]) if group is not None else None,
                                        self.rover.loop_period_us)

    def start_reboot(self, now_us: int) -> None:
        self.booting_until_us = now_us + round(self.vehicle.reboot_silence_s * 1e6)
        self.reboot_count += 1
        self.count("reboots")

    def _finish_boot(self, now_us: int, physics: PhysicsState) -> None:
        self.booting_until_us = None
        self.boot_us = now_us
        self.armed = self.vehicle.start_armed
        self.rc.reset()
        self.streams.clear()  # SET_MESSAGE_INTERVAL lives in RAM; SRn_ params persist
        self.extnav = ExtNavConsumer(self._extnav_settings())  # a new EKF: no position until ODOMETRY again
        self.mission.reset_cursor()
        self._boot_vehicle()
        if self.skid_loop is not None:
            self.skid_loop.reset(now_us, self.rover.loop_period_us)
        cpr = self.vehicle.encoder_cpr
        self._encoder_offset = (
            encoder_counts(physics.left_encoder_angle_rad, cpr),
            encoder_counts(physics.right_encoder_angle_rad, cpr),
        )
