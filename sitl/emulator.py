"""The in-process facade: physics + autopilot + scenario + faults + one MAVLink endpoint.

Lockstep: ``step(dt_s)`` (1) fires due scenario events, (2) reads every datagram that has already
arrived (non-blocking) and hands the due ones, through the inbound fault model, to the autopilot
(bytes of a stream link, TCP, are handed on one step later, and lost if the client closes before
then, as ArduPilot's SITL serial port does), (3) advances physics by ``dt_s`` of simulated time in
substeps of at most ``vehicle.physics_dt_s`` (and split at Rover's loop instants for the skid plant, whose
encoders are read and motors updated only there: sitl/skid.py), recomputing the servo outputs before each substep, and
(4) sends the replies and every stream message that is due, through the outbound fault model.
Simulated time is kept in integer microseconds, so a run is a pure function of the seed and the
input sequence.
``run_realtime`` calls ``step`` on a wall clock for the CLI.
"""

from __future__ import annotations

import math
import random
import threading
import time
from dataclasses import replace

from sitl import physics, skid
from sitl.autopilot import Autopilot, ReceivedMessage
from sitl.config import VehicleConfig
from sitl.endpoint import Endpoint
from sitl.faults import FaultConfig, FaultyLink
from sitl.mav import MAVLinkMessage, mavlink
from sitl.obstacles import obstacle_distance_m
from sitl.physics import PhysicsState, TruthState
from sitl.range_sensors import DepthCamera
from sitl.scenario import Scenario

OBSTACLE_DISTANCE: int = mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE  # sent as the depth camera's component


class _Collector:
    """A write()-able sink: pymavlink's ``send`` writes each packed packet here."""

    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.packets.append(bytes(data))


class _World:
    """What acts on the robot in a physics step besides its motors: the scenario and the sensors' noise.

    Independent seeded streams, so enabling faults does not change the sensor noise."""

    def __init__(self, vehicle: VehicleConfig, scenario: Scenario, seed: int) -> None:
        self.vehicle = vehicle
        self.scenario = scenario
        self._noise_rng = random.Random(f"sitl-noise-{seed}")
        self._dropout_rng = random.Random(f"sitl-dropout-{seed}")

    def inputs(self, s: PhysicsState, t_us: int, left_cmd: float, right_cmd: float) -> physics.StepInputs:
        time_s = t_us / 1e6
        half = 0.5 * self.vehicle.track_true_m
        # Wheel contact points in NED: body y is to the right, the left wheel at -track/2.
        lx, ly = s.x_m + half * math.sin(s.yaw_rad), s.y_m - half * math.cos(s.yaw_rad)
        rx, ry = s.x_m - half * math.sin(s.yaw_rad), s.y_m + half * math.cos(s.yaw_rad)
        sc = self.scenario
        rate = self.vehicle.encoder_dropout_rate
        noise = (
            self._noise_rng.gauss(0.0, self.vehicle.gyro_noise_rad_s)
            if self.vehicle.gyro_noise_rad_s
            else 0.0
        )
        left_ok = sc.encoder_ok("left", time_s) and not (rate and self._dropout_rng.random() < rate)
        right_ok = sc.encoder_ok("right", time_s) and not (rate and self._dropout_rng.random() < rate)
        return physics.StepInputs(
            left_cmd=left_cmd,
            right_cmd=right_cmd,
            left_slip=sc.slip_ratio("left", time_s, lx, ly),
            right_slip=sc.slip_ratio("right", time_s, rx, ry),
            left_encoder_ok=left_ok,
            right_encoder_ok=right_ok,
            gyro_noise_rad_s=noise,
            left_speed_scale=sc.speed_scale("left", time_s),
            right_speed_scale=sc.speed_scale("right", time_s),
            left_stalled=sc.stalled("left", time_s),
            right_stalled=sc.stalled("right", time_s),
        )


class Emulator:
    """An ArduPilot-Rover-like autopilot on a differential-drive robot, stepped in lockstep."""

    def __init__(
        self,
        vehicle: VehicleConfig | None = None,
        scenario: Scenario | None = None,
        faults: FaultConfig | None = None,
        seed: int = 0,
        system_id: int = 1,
        component_id: int = 1,
        record_sent: bool = False,
    ) -> None:
        self.vehicle = vehicle if vehicle is not None else VehicleConfig()
        self.scenario = scenario if scenario is not None else Scenario()
        self.faults = faults if faults is not None else FaultConfig()
        self.seed = seed
        self.system_id = system_id
        self.component_id = component_id
        self._collector = _Collector()
        self._mav_out = mavlink.MAVLink(self._collector, srcSystem=system_id, srcComponent=component_id)
        self._mav_in = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self._mav_in.robust_parsing = True  # corrupted bytes become counted bad data, not exceptions
        self.autopilot = Autopilot(self.vehicle, self._mav_out, system_id, component_id, seed=seed)
        self.autopilot.obstacles = self.scenario.obstacles  # what its SITL range sensors see
        self._camera = DepthCamera(self.vehicle, self._collector, system_id)  # the companion's OBSTACLE_DISTANCE
        self._physics_step = skid.step if self.vehicle.plant == skid.ARDUPILOT_SKID else physics.step
        self._world = _World(self.vehicle, self.scenario, seed)
        self._link_in = FaultyLink(self.faults.inbound, seed=hash_seed(seed, "in"))
        self._link_out = FaultyLink(self.faults.outbound, seed=hash_seed(seed, "out"))
        start_yaw = physics.wrap_pi(math.radians(self.vehicle.start_heading_deg))
        self._phys = PhysicsState(yaw_rad=start_yaw, ahrs_yaw_rad=start_yaw)
        self._now_us = 0
        self._scenario_reboots_done = 0
        self._endpoint: Endpoint | None = None
        self._stream_pending: list[bytes] = []  # read from a stream link, parsed in the next step
        self._counters: dict[str, int] = {
            "rx_bad_data": 0,
            "rx_dropped_silence": 0,
            "tx_dropped_silence": 0,
            "tx_withheld": 0,
            "tx_messages": 0,
            "rx_lost_on_close_bytes": 0,
        }
        self.sent_log: list[tuple[float, MAVLinkMessage]] | None = [] if record_sent else None
        # Message ids the autopilot stops sending (a test's switch: its heartbeat gone silent while the rest
        # streams on, a stream that stops); built as always, dropped before the link, counted.
        self.withheld: set[int] = set()

    # ------------------------------------------------------------------ endpoint
    def open(self, connection: str) -> None:
        """Bind/connect the MAVLink endpoint (PortInUseError / ConnectionStringError on failure)."""
        if self._endpoint is not None:
            raise RuntimeError("endpoint already open")
        self._endpoint = Endpoint(connection)

    def close(self) -> None:
        if self._endpoint is not None:
            self._endpoint.close()
            self._endpoint = None

    def __enter__(self) -> Emulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound (host, port); useful with port 0."""
        if self._endpoint is None:
            raise RuntimeError("endpoint not open")
        return self._endpoint.local_address

    # ------------------------------------------------------------------ lockstep
    def step(self, dt_s: float = 0.01) -> None:
        """Advance simulated time by ``dt_s`` (see the module docstring for the order)."""
        dt_us = round(dt_s * 1e6)
        if dt_us <= 0:
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        now = self._now_us
        self._fire_scenario_reboots(now)
        self._receive(now)
        sub_max_us = max(1, round(self.vehicle.physics_dt_s * 1e6))
        t = now
        end = now + dt_us
        while t < end:
            self.autopilot.update(t, self._phys)
            enc = self.autopilot.skid_loop  # the skid plant's encoders are read at the loop's own instants
            sub = min(sub_max_us, end - t, enc.next_loop_us - t if enc is not None and enc.next_loop_us > t else end)
            commands = self.autopilot.wheel_commands()
            if enc is not None and not self.autopilot.rebooting:
                commands = enc.motors(commands)  # the output of Rover's last loop
            inputs = self._world.inputs(self._phys, t, *commands)
            self._phys = self._physics_step(self._phys, inputs, sub / 1e6, self.vehicle)
            t += sub
        self._now_us = end
        self._phys = replace(self._phys, time_s=end / 1e6)  # exact, not a sum of floats
        self.autopilot.update(end, self._phys)
        outgoing = self.autopilot.outbox + self.autopilot.emit(end, self._phys)
        outgoing += self._camera.due(end, self._phys, self.scenario.obstacles)
        self.autopilot.outbox = []
        self._transmit(outgoing, end)

    def _fire_scenario_reboots(self, now_us: int) -> None:
        due = sum(1 for r in self.scenario.reboots if r.at_s * 1e6 <= now_us)
        while self._scenario_reboots_done < due:
            self._scenario_reboots_done += 1
            self.reboot()

    def _receive(self, now_us: int) -> None:
        ep = self._endpoint
        if ep is not None:
            before = ep.disconnects
            chunks = ep.recv_all()
            if ep.is_stream:
                # SITL's TCP UART (AP_HAL_SITL/UARTDriver.cpp): bytes read between two main loops are
                # parsed by the next loop's update_receive. If the client has closed by then they are
                # never parsed as its own (_available() is 0 while disconnected): a stop sent just
                # before a close is lost. So what is read in one step is parsed in the next, unless
                # the client went away in between.
                pending, self._stream_pending = self._stream_pending, chunks
                if ep.disconnects != before:
                    self._counters["rx_lost_on_close_bytes"] += sum(len(c) for c in pending)
                    pending = []
                chunks = pending
            for data in chunks:
                self._link_in.push(data, now_us / 1e6)
        silent = self.scenario.link_silent(now_us / 1e6)
        for data in self._link_in.pop_due(now_us / 1e6):
            if silent:
                self._counters["rx_dropped_silence"] += 1
                continue
            self._parse_and_handle(data, now_us)

    def _parse_and_handle(self, data: bytes, now_us: int) -> None:
        try:
            msgs = self._mav_in.parse_buffer(data) or []
        except Exception:  # pymavlink raises plain exceptions on some malformed input
            self._counters["rx_bad_data"] += 1
            return
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self._counters["rx_bad_data"] += 1
                continue
            self.autopilot.handle(msg, now_us)

    def _transmit(self, messages: list[MAVLinkMessage], now_us: int) -> None:
        now_s = now_us / 1e6
        if messages and (self._endpoint is not None or self.sent_log is not None):
            silent = self.scenario.link_silent(now_s)
            for msg in messages:
                if silent:
                    self._counters["tx_dropped_silence"] += 1
                    continue
                if msg.get_msgId() in self.withheld:
                    self._counters["tx_withheld"] += 1
                    continue
                (self._camera.mav if msg.get_msgId() == OBSTACLE_DISTANCE else self._mav_out).send(msg)
                self._counters["tx_messages"] += 1
                if self.sent_log is not None:
                    self.sent_log.append((now_s, msg))
            for packet in self._collector.packets:
                self._link_out.push(packet, now_s)
            self._collector.packets.clear()
        for packet in self._link_out.pop_due(now_s):
            if self._endpoint is not None:
                self._endpoint.send(packet)

    # ------------------------------------------------------------------ direct access
    def handle_message(
        self, msg: MAVLinkMessage, src_system: int | None = None, src_component: int = 190
    ) -> None:
        """Inject a decoded message at the current simulated time, bypassing sockets and faults.

        With ``src_system`` the message is packed as that system and decoded again, so header
        fields (sender ids) are exactly what they would be on the wire.
        """
        if src_system is not None:
            sender = mavlink.MAVLink(None, srcSystem=src_system, srcComponent=src_component)
            parser = mavlink.MAVLink(None)
            msg = parser.decode(bytearray(msg.pack(sender)))
        self.autopilot.handle(msg, self._now_us)

    def run_realtime(self, speedup: float = 1.0, duration_s: float | None = None,
                     stop: threading.Event | None = None, step_s: float = 0.01) -> None:
        """Step on the wall clock (``speedup`` x real time) until ``stop`` is set or ``duration_s``."""
        run_realtime(self, speedup, duration_s, stop, step_s)

    # ------------------------------------------------------------------ state
    @property
    def sim_time_s(self) -> float:
        return self._now_us / 1e6

    @property
    def sim_time_us(self) -> int:
        return self._now_us

    @property
    def truth(self) -> TruthState:
        return TruthState.from_state(self._phys)

    @property
    def physics_state(self) -> PhysicsState:
        return self._phys

    @property
    def armed(self) -> bool:
        return self.autopilot.armed

    def set_armed(self, armed: bool) -> None:
        """Arm or disarm directly (no pre-arm checks)."""
        self.autopilot.armed = armed

    @property
    def mode(self) -> int:
        """ArduPilot Rover custom_mode: 0 MANUAL, 4 HOLD, 15 GUIDED."""
        return self.autopilot.mode

    @property
    def rebooting(self) -> bool:
        return self.autopilot.rebooting

    @property
    def servo_outputs(self) -> dict[int, int]:
        return self.autopilot.servo_outputs()

    @property
    def rc_inputs(self) -> dict[int, int]:
        return self.autopilot.rc_inputs(self._now_us)

    def set_radio(self, channel: int, pwm: int) -> None:
        """Set the pilot's radio value of an RC channel (what shows when no override is active)."""
        if channel not in self.autopilot.radio_pwm:
            raise ValueError(f"RC channel must be 1..18, got {channel}")
        self.autopilot.radio_pwm[channel] = pwm

    @property
    def wheel_distances_m(self) -> tuple[float, float]:
        """What WHEEL_DISTANCE would report now (index 0, index 1)."""
        return self.autopilot.wheel_distances_m(self._phys)

    @property
    def received_odometry(self) -> list[ReceivedMessage]:
        return self.autopilot.received_odometry

    @property
    def statustexts_sent(self) -> list[str]:
        return self.autopilot.statustexts_sent

    @property
    def counters(self) -> dict[str, int]:
        out = dict(self._counters)
        out.update(self.autopilot.counters)
        for name, link in (("in", self._link_in), ("out", self._link_out)):
            c = link.counters
            out[f"fault_{name}_pushed"] = c.pushed
            out[f"fault_{name}_dropped"] = c.dropped
            out[f"fault_{name}_duplicated"] = c.duplicated
            out[f"fault_{name}_corrupted"] = c.corrupted
            out[f"fault_{name}_reordered"] = c.reordered
        if self._endpoint is not None:
            out["tx_send_errors"] = self._endpoint.send_errors
            out["rx_lost_on_close_bytes"] += self._endpoint.lost_on_close_bytes
        return out

    def get_param(self, name: str) -> float:
        return self.autopilot.param(name)

    def set_param(self, name: str, value: float) -> None:
        if not self.autopilot.set_param(name, value):
            raise KeyError(f"no parameter {name!r}")

    def reboot(self) -> None:
        """Reboot the autopilot now: silent link, then WHEEL_DISTANCE and time_boot from zero."""
        self.autopilot.start_reboot(self._now_us)
        self._link_out.clear()  # whatever was in flight dies with the board

    def nearest_obstacle_m(self) -> float | None:
        """Truth: from the rover's centre to the nearest scenario obstacle (0 inside one; None without any)."""
        return obstacle_distance_m((self._phys.x_m, self._phys.y_m), self.scenario.obstacles)

    def collided(self) -> bool:
        """Truth: the rover's centre is inside a scenario obstacle (no contact physics: it drives on)."""
        return self.nearest_obstacle_m() == 0.0

    def teleport(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Place the robot (a test convenience; the wheels keep their state)."""
        self._phys = replace(self._phys, x_m=x_m, y_m=y_m, yaw_rad=physics.wrap_pi(yaw_rad))


def hash_seed(seed: int, tag: str) -> int:
    """A stable derived seed (Python's hash() of str is salted per process; this is not)."""
    value = 1469598103934665603
    for byte in f"{seed}/{tag}".encode():
        value = ((value ^ byte) * 1099511628211) & 0xFFFFFFFFFFFFFFFF
    return value


def run_realtime(emu: Emulator, speedup: float, duration_s: float | None, stop: threading.Event | None,
                 step_s: float) -> None:
    """``Emulator.run_realtime``: step ``emu`` on the wall clock."""
    if speedup <= 0:
        raise ValueError(f"speedup must be positive, got {speedup!r}")
    stop = stop if stop is not None else threading.Event()
    start_sim_us = emu.sim_time_us
    start_wall = time.monotonic()
    while not stop.is_set():
        elapsed_s = (emu.sim_time_us - start_sim_us) / 1e6
        if duration_s is not None and elapsed_s >= duration_s - 1e-9:
            break
        emu.step(step_s)
        target = start_wall + (emu.sim_time_us - start_sim_us) / 1e6 / speedup
        delay = target - time.monotonic()
        if delay > 0:
            stop.wait(delay)
        elif delay < -0.5:  # far behind (a slow machine): do not burst to catch up
            start_wall -= delay
