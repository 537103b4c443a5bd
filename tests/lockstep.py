"""End-to-end harness: the real bridge shell and core, the sitl emulator and a scripted GCS,
talking real MAVLink 2 over UDP loopback (the autopilot optionally over TCP), all stepped on one
simulated clock.

Loopback UDP delivers a datagram before sendto() returns, so stepping the emulator, then the
bridge, then the GCS, each draining its socket, is deterministic for a given seed.
"""

from __future__ import annotations

import math
import subprocess
from dataclasses import dataclass, field
from typing import Any, Protocol

from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.demo import free_udp_port
from rover_bridge.app.loop import Runner, TlogWriter
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink, mavutil
from rover_bridge.mavlink.links import Endpoint
from rover_bridge.mavlink.wire import Link
from rover_bridge.params import Profile
from sitl import Emulator, FaultConfig, VehicleConfig

GCS_SYSID = 255
GCS_COMPID = 190


WALL_STEP_S = 0.01  # the wall-clock helpers' largest emulator step
CATCH_UP_S = 2.0  # beyond this much lag, the rest is one step (the emulator must not fall further behind)


def step_wall(emu: Emulator, elapsed_s: float) -> None:
    """Advance an emulator that runs on the wall clock by ``elapsed_s``, in steps of at most 10 ms.

    A starved caller (a loaded machine) then catches up through the steps it missed, each sending the stream
    messages due in it, stamped at their own simulated time: the bridge sees the same sensor streams at any
    load, only later. One long step would send one sample of each stream for the whole gap (a gyro sample per
    200 ms in a turn is a heading error of degrees)."""
    remaining_us = max(1000, round(elapsed_s * 1e6))  # whole microseconds: the emulator's own time unit
    step_us, caught_up_us = round(WALL_STEP_S * 1e6), 0
    while remaining_us > 0:
        dt_us = min(step_us, remaining_us) if caught_up_us < CATCH_UP_S * 1e6 else remaining_us
        emu.step(dt_us / 1e6)
        remaining_us -= dt_us
        caught_up_us += dt_us


class _Closable(Protocol):
    def close(self) -> None: ...


def finish_process(proc: subprocess.Popen[Any], *closables: _Closable) -> None:
    """End a test's bridge process if it is still running, close its output pipe, then close the
    harness pieces around it (GCS, emulator) in the order given."""
    if proc.poll() is None:
        proc.kill()
        proc.wait()
    if proc.stdout:
        proc.stdout.close()
    for item in closables:
        item.close()



@dataclass
class GcsView:
    """What the scripted ground station has received, by type."""

    messages: dict[str, list[tuple[float, MAVLinkMessage]]] = field(default_factory=dict)

    def add(self, now_s: float, msg: MAVLinkMessage) -> None:
        self.messages.setdefault(msg.get_type(), []).append((now_s, msg))

    def of(self, type_name: str) -> list[tuple[float, MAVLinkMessage]]:
        return self.messages.get(type_name, [])


class Lockstep:
    def __init__(self, profile: Profile, vehicle: VehicleConfig | None = None, *, seed: int = 0,
                 faults: FaultConfig | None = None, scenario: Any = None, start_armed: bool = True,
                 dt_s: float = 0.01, tlog_path: str | None = None, autopilot_tcp: bool = False) -> None:
        self.dt_s = dt_s
        self.t_s = 0.0
        ap_port, gcs_port = free_udp_port(), free_udp_port()
        self.emu = Emulator(vehicle=vehicle or VehicleConfig(), scenario=scenario,
                            faults=faults or FaultConfig(), seed=seed, system_id=1)
        # The autopilot over UDP, or over TCP as ArduPilot SITL serves it (a stream: frames split
        # across reads, several per read).
        self.emu.open("tcpin:127.0.0.1:0" if autopilot_tcp else f"udpin:127.0.0.1:{ap_port}")
        ap_url = f"tcp:127.0.0.1:{self.emu.local_address[1]}" if autopilot_tcp else f"udpout:127.0.0.1:{ap_port}"
        if start_armed:
            self.emu.set_armed(True)
        self._ap_url, self._gcs_port = ap_url, gcs_port
        self._start_bridge(profile, tlog_path)
        self.gcs: Any = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=GCS_SYSID,
                                                   source_component=GCS_COMPID, dialect="ardupilotmega")
        self.view = GcsView()
        self.gcs_heartbeat()

    def _start_bridge(self, profile: Profile, tlog_path: str | None = None) -> None:
        self.core = BridgeCore(profile)
        ids = {"source_system": self.core.identity.own_system_id, "source_component": self.core.identity.component_id}
        self.autopilot = Endpoint(self._ap_url, Link.AUTOPILOT, **ids)
        self.gcs_endpoint = Endpoint(f"udpin:127.0.0.1:{self._gcs_port}", Link.GCS, **ids)
        # The .tlog is stamped on the simulated clock, so a replay sees exactly the live timing.
        tlog = TlogWriter(open(tlog_path, "wb"), wall_clock=lambda: self.t_s) if tlog_path else None  # noqa: SIM115
        self.runner = Runner(self.core, self.autopilot, [self.gcs_endpoint], tlog=tlog)

    def restart_bridge(self, profile: Profile) -> None:
        """The bridge process restarts (systemd after an update, a crash): it stops the rover the way a
        SIGTERM'd bridge does, and a new one with nothing of the old one's state takes its links."""
        self.stop()
        self.runner.close()
        self._start_bridge(profile)

    # -- the scripted ground station -------------------------------------------------------
    def gcs_heartbeat(self) -> None:
        self.gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def send_body_velocity(self, vx_m_s: float, yaw_rate_cw_rad_s: float, frame: int = 8,
                           type_mask: int = 0b0000_0101_1100_0111) -> None:
        """SET_POSITION_TARGET_LOCAL_NED with body velocity and yaw rate (MAVLink: yaw rate clockwise +)."""
        self.gcs.mav.set_position_target_local_ned_send(
            int(self.t_s * 1000), 1, 1, frame, type_mask, 0, 0, 0, vx_m_s, 0, 0, 0, 0, 0, 0, yaw_rate_cw_rad_s)

    def send_local_ned_velocity(self, vn_m_s: float, ve_m_s: float) -> None:
        mask = 0b0000_1101_1100_0111  # use vx, vy, vz; ignore position, accel, yaw, yaw rate
        self.gcs.mav.set_position_target_local_ned_send(
            int(self.t_s * 1000), 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask, 0, 0, 0, vn_m_s, ve_m_s, 0, 0, 0, 0, 0, 0)

    # -- time ------------------------------------------------------------------------------
    def step(self) -> None:
        self.t_s = round(self.t_s + self.dt_s, 9)
        self.emu.step(self.dt_s)
        self.runner.step(self.t_s)
        while True:
            msg = self.gcs.recv_msg()
            if msg is None:
                break
            if msg.get_type() != "BAD_DATA":
                self.view.add(self.t_s, msg)

    def run_for(self, duration_s: float, every_s: float = 0.1, send: Any = None,
                before_step: Any = None, after_step: Any = None) -> None:
        """Step for `duration_s`; call `send()` every `every_s` (a GCS sending at 10 Hz) if given,
        heartbeat from the GCS at 1 Hz, and run the optional hooks around every step."""
        steps = round(duration_s / self.dt_s)
        every = max(1, round(every_s / self.dt_s))
        for i in range(steps):
            if send is not None and i % every == 0:
                send()
            if i % round(1.0 / self.dt_s) == 0:
                self.gcs_heartbeat()
            if before_step is not None:
                before_step()
            self.step()
            if after_step is not None:
                after_step()

    def stop(self, max_s: float = 1.0) -> None:
        """The shell's exit path in lockstep: neutral, release and probe, then steps until the core has
        the autopilot's answer (or its timeout), then a few more so the last datagrams land."""
        self.runner.begin_stop(self.t_s)
        end = self.t_s + max_s
        while not self.core.stop_settled and self.t_s < end:
            self.step()
        for _ in range(5):
            self.step()

    def close(self) -> None:
        self.stop()
        self.runner.close()
        self.gcs.close()
        self.emu.close()


def circle_fit_radius(points: list[tuple[float, float]]) -> float:
    """Least-squares (Kasa) circle radius through planar points."""
    import numpy as np

    pts = np.asarray(points, dtype=float)
    x, y = pts[:, 0], pts[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    b = x * x + y * y
    cx2, cy2, c = np.linalg.lstsq(a, b, rcond=None)[0]
    cx, cy = cx2 / 2.0, cy2 / 2.0
    return float(math.sqrt(c + cx * cx + cy * cy))
