"""The harness every subcommand of bench_bridge.py shares: it plays the autopilot and the ground station with
plain UDP sockets (kernel receive stamps, the autopilot's answers to stream requests) and frames packed once by
pymavlink, so its own cost stays small next to the bridge's; the nominal traffic of the cpu table; the tables.
"""

from __future__ import annotations

import math
import os
import random
import re
import socket
import struct
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rover_bridge.mavlink.dialect import mavlink

REPO = Path(__file__).resolve().parents[2]
DISPATCHER = Path(__file__).resolve().parents[1] / "bench_bridge.py"  # the helper processes' entry
DEFAULT_PROFILE = REPO / "params" / "default.toml"
LOCAL = "127.0.0.1"
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux value; Python does not export it
MSG_OVERRIDE = mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE
MSG_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
MSG_ODOMETRY = mavlink.MAVLINK_MSG_ID_ODOMETRY
MSG_COMMAND_ACK = mavlink.MAVLINK_MSG_ID_COMMAND_ACK
AP_SYS, AP_COMP = 1, 1
GCS_SYS, GCS_COMP = 255, 190
BRIDGE_COMP = 191
BIG_RCVBUF = 4 * 1024 * 1024  # harness sockets must not be where datagrams are lost


# ------------------------------------------------------------------------------------- helpers

def free_udp_port() -> int:
    """A free port below the kernel's ephemeral range. Test suites running beside us pick ports the
    bind-to-0-and-close way; had we done the same, one of their emulators could be sending to a port
    it once chose and that is now our bridge's (it happened: thousands of foreign heartbeats a second)."""
    while True:
        port = random.randrange(20_000, 32_000)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((LOCAL, port))
            except OSError:
                continue
            return port


def udp_socket(timestamps: bool = False) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, BIG_RCVBUF)
    if timestamps:
        s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    s.bind((LOCAL, 0))
    s.setblocking(False)
    return s


def msg_id(frame: bytes) -> int:
    """Message id of a MAVLink 2 frame (-1 for anything else)."""
    if len(frame) < 12 or frame[0] != 0xFD:
        return -1
    return frame[7] | frame[8] << 8 | frame[9] << 16


# Harness sockets that play the autopilot: they answer the bridge's SET_MESSAGE_INTERVAL requests as
# ArduPilot Rover 4.7 does (DENIED for WHEEL_DISTANCE, ACCEPTED otherwise). An autopilot that never
# answers leaves the bridge re-asking, which is a different (start-up) load than the one measured.
AUTOPILOT_SOCKETS: set[socket.socket] = set()
_ACK_PACKER: list[Any] = []


def answer_command(sock: socket.socket, frame: bytes, addr: Any) -> None:
    if sock not in AUTOPILOT_SOCKETS or msg_id(frame) != mavlink.MAVLINK_MSG_ID_COMMAND_LONG:
        return
    payload = frame[10:10 + frame[1]].ljust(33, b"\0")  # MAVLink 2 trims trailing zeros
    param1 = struct.unpack_from("<f", payload, 0)[0]
    command = struct.unpack_from("<H", payload, 28)[0]
    if command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
        return
    result = mavlink.MAV_RESULT_DENIED if int(param1) == 9000 else mavlink.MAV_RESULT_ACCEPTED
    if not _ACK_PACKER:
        _ACK_PACKER.append(Packer(AP_SYS, AP_COMP))
    ack = mavlink.MAVLink_command_ack_message(command, result, 0, 0, frame[5], frame[6])
    sock.sendto(_ACK_PACKER[0].pack(ack), addr)


def recv_stamped(sock: socket.socket) -> tuple[bytes, float] | None:
    """One datagram and its kernel receive time (time.time() seconds), or None if none is queued."""
    try:
        data, anc, _flags, addr = sock.recvmsg(2048, 64)
    except BlockingIOError:
        return None
    answer_command(sock, data, addr)
    for level, kind, payload in anc:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = struct.unpack("qq", payload[:16])
            return data, sec + nsec * 1e-9
    return data, time.time()


def drain(sock: socket.socket) -> int:
    n = 0
    while True:
        try:
            data, addr = sock.recvfrom(4096)
        except BlockingIOError:
            return n
        answer_command(sock, data, addr)
        n += 1


def keep_stamped(sock: socket.socket, out: list[tuple[bytes, float]]) -> int:
    """Every datagram queued on `sock`, with its kernel stamp, appended to `out`; how many."""
    n = 0
    while (got := recv_stamped(sock)) is not None:
        out.append(got)
        n += 1
    return n


def forwarded_frames(buf: bytearray, size: int) -> int:
    """Flood frames in one datagram from the bridge (it packs several forwarded frames into one):
    frames from the emulated autopilot, not the COMMAND_ACKs the harness sent for stream requests."""
    n, i = 0, 0
    while i + 10 <= size and buf[i] == 0xFD:
        if buf[i + 5] == AP_SYS and buf[i + 6] == AP_COMP and buf[i + 7] != mavlink.MAVLINK_MSG_ID_COMMAND_ACK:
            n += 1
        i += 12 + buf[i + 1] + (13 if buf[i + 2] & 1 else 0)
    return n


def pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (q in 0..100)."""
    ordered = sorted(values)
    k = max(0, min(len(ordered) - 1, math.ceil(q / 100.0 * len(ordered)) - 1))
    return ordered[k]


class Packer:
    """Packs messages as one MAVLink 2 sender would (own ids, incrementing sequence)."""

    def __init__(self, sysid: int, compid: int) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    def pack(self, msg: Any) -> bytes:
        frame = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return frame


def write_profile(overrides: dict[str, str], directory: str) -> str:
    """A copy of params/default.toml with `section.key` values replaced (TOML text given verbatim)."""
    section = ""
    lines = []
    for line in DEFAULT_PROFILE.read_text(encoding="utf-8").splitlines():
        m = re.match(r"\s*\[(\w+)\]", line)
        if m:
            section = m.group(1)
        kv = re.match(r"\s*#?\s*(\w+)\s*=", line)
        if kv and f"{section}.{kv.group(1)}" in overrides:
            line = f"{kv.group(1)} = {overrides[section + '.' + kv.group(1)]}"
        lines.append(line)
    path = os.path.join(directory, "bench.toml")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# ------------------------------------------------------------------------------------- messages

ROVER_STEERING, ROVER_GUIDED = 3, 15  # HEARTBEAT custom_mode: the benchmarks' default mode, issue 43's


def heartbeat_ap(armed: bool = True, custom_mode: int = ROVER_STEERING) -> Any:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             base, custom_mode, mavlink.MAV_STATE_ACTIVE, 3)


def heartbeat_gcs() -> Any:
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)


def body_velocity_request(t_ms: int, vx: float, yaw_rate: float) -> Any:
    # MAV_FRAME_BODY_NED velocity + yaw rate: the request the bridge consumes and answers with an override.
    return mavlink.MAVLink_set_position_target_local_ned_message(
        t_ms, AP_SYS, AP_COMP, 8, 0b0000_0101_1100_0111, 0, 0, 0, vx, 0, 0, 0, 0, 0, 0, yaw_rate)


class Telemetry:
    """A consistent ArduPilot-like telemetry stream of a rover driving an arc (stamps from sim time)."""

    V_M_S, OMEGA_RAD_S, TRACK_M = 0.4, 0.2, 0.30
    # ArduPilot's proximity sectors as its GCS_Common send_proximity sends them (sitl/range_sensors.py): min 0,
    # max 200 m, LASER, id 10 + sector, orientation = sector; a wall 5 m ahead, the other sectors clear (max + 1).
    SECTOR_MAX_CM, WALL_CM, PROXIMITY_ID_START = 20000, 500, 10

    def __init__(self, custom_mode: int = ROVER_STEERING) -> None:
        self.packer = Packer(AP_SYS, AP_COMP)
        self.custom_mode = custom_mode

    def _state(self, t_s: float) -> tuple[float, float, float]:
        left = (self.V_M_S - self.OMEGA_RAD_S * self.TRACK_M / 2) * t_s
        right = (self.V_M_S + self.OMEGA_RAD_S * self.TRACK_M / 2) * t_s
        return left, right, self.OMEGA_RAD_S * t_s

    def frame(self, kind: str, t_s: float) -> bytes:
        left, right, yaw_ccw = self._state(t_s)
        ms, us = int(t_s * 1000), int(t_s * 1e6)
        yaw_cw = math.remainder(-yaw_ccw, 2 * math.pi)
        msg: Any
        if kind == "WHEEL_DISTANCE":
            msg = mavlink.MAVLink_wheel_distance_message(us, 2, [left, right] + [0.0] * 14)
        elif kind == "ATTITUDE":
            msg = mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, yaw_cw, 0.0, 0.0, -self.OMEGA_RAD_S)
        elif kind == "RAW_IMU":
            msg = mavlink.MAVLink_raw_imu_message(us, 0, 0, -1000, 0, 0, int(-self.OMEGA_RAD_S * 1000), 200, 0, 400)
        elif kind == "SYS_STATUS":
            msg = mavlink.MAVLink_sys_status_message(0x3F, 0x3F, 0x3F, 250, 12000, 150, 80, 0, 0, 0, 0, 0, 0)
        elif kind == "GPS_RAW_INT":
            msg = mavlink.MAVLink_gps_raw_int_message(us, 3, 473977420, 85455940, 100000, 90, 120, 40, 1800, 12)
        elif kind == "VFR_HUD":
            msg = mavlink.MAVLink_vfr_hud_message(self.V_M_S, self.V_M_S, int(math.degrees(yaw_cw)) % 360, 40,
                                                  100.0, 0.0)
        elif kind == "SERVO_OUTPUT_RAW":
            msg = mavlink.MAVLink_servo_output_raw_message(us & 0xFFFFFFFF, 0, 1600, 1500, 1640, 1500, 0, 0, 0, 0)
        elif kind == "GLOBAL_POSITION_INT":
            msg = mavlink.MAVLink_global_position_int_message(ms, 473977420, 85455940, 100000, 0, 40, 0, 0,
                                                              int(math.degrees(yaw_cw) * 100) % 36000)
        elif kind == "SYSTEM_TIME":
            msg = mavlink.MAVLink_system_time_message(int(time.time() * 1e6), ms)
        elif kind == "HEARTBEAT":
            msg = heartbeat_ap(custom_mode=self.custom_mode)
        elif kind.startswith("SECTOR"):  # SECTOR0 .. SECTOR7: one DISTANCE_SENSOR per proximity sector
            sector = int(kind.removeprefix("SECTOR"))
            distance_cm = self.WALL_CM if sector == 0 else self.SECTOR_MAX_CM + 1
            msg = mavlink.MAVLink_distance_sensor_message(ms, 0, self.SECTOR_MAX_CM, distance_cm,
                                                          mavlink.MAV_DISTANCE_SENSOR_LASER,
                                                          self.PROXIMITY_ID_START + sector, sector, 0)
        else:  # pragma: no cover - programming error
            raise ValueError(kind)
        return self.packer.pack(msg)


FLOOD_MIX = ("ATTITUDE", "WHEEL_DISTANCE", "SYS_STATUS", "GPS_RAW_INT", "VFR_HUD", "SERVO_OUTPUT_RAW",
             "RAW_IMU", "GLOBAL_POSITION_INT", "SYSTEM_TIME", "HEARTBEAT")


def flood_frames(count: int, rate_hz: float, t0_s: float = 100.0) -> list[bytes]:
    """`count` frames of the mixed telemetry, stamped as if sent at `rate_hz`."""
    tel = Telemetry()
    return [tel.frame(FLOOD_MIX[i % len(FLOOD_MIX)], t0_s + i / rate_hz) for i in range(count)]


def print_table(title: str, header: list[str], rows: list[list[Any]]) -> None:
    print(f"\n# {title}")
    cells = [header] + [[f"{c:.3f}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for r in cells:
        print("  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))))


def self_cmd(*args: str) -> list[str]:
    return [sys.executable, str(DISPATCHER), *args]


# ------------------------------------------------------------------------------------- the nominal load

NOMINAL_AP = (("WHEEL_DISTANCE", 50.0), ("ATTITUDE", 50.0), ("RAW_IMU", 50.0), ("VFR_HUD", 10.0),
              ("GLOBAL_POSITION_INT", 10.0), ("SERVO_OUTPUT_RAW", 10.0), ("GPS_RAW_INT", 5.0),
              ("SYS_STATUS", 2.0), ("SYSTEM_TIME", 2.0), ("HEARTBEAT", 1.0))


def nominal_schedule(seconds: float, t0_s: float, sectors: int = 0,
                     sector_hz: float = 10.0) -> Iterator[tuple[float, str]]:
    """(time offset, what) events of the nominal load, in time order; with `sectors`, that many proximity
    sectors (DISTANCE_SENSOR, orientation 0..sectors-1) at `sector_hz` each on top, in one burst per period
    between the 50 Hz instants (a pass of their own: the costlier case)."""
    events: list[tuple[float, str]] = []
    for kind, hz in NOMINAL_AP:
        events += [(k / hz, kind) for k in range(int(seconds * hz))]
    if sectors > 0 and sector_hz > 0:
        events += [(k / sector_hz + 0.5 / sector_hz, f"SECTOR{s}") for k in range(int(seconds * sector_hz))
                   for s in range(sectors)]
    events += [(k / 50.0 + 0.003, "REQUEST") for k in range(int(seconds * 50))]
    events += [(k / 1.0 + 0.5, "GCS_HEARTBEAT") for k in range(int(seconds))]
    events += [(k / 5.0 + 0.1, "GCS_TIMESYNC") for k in range(int(seconds * 5))]
    events.sort()
    yield from events


def replay_frames(seconds: float, sectors: int = 0, sector_hz: float = 10.0,
                  custom_mode: int = ROVER_STEERING) -> list[tuple[float, str, bool, bytes]]:
    """(offset, kind, from the GCS, frame) of the cpu table's nominal traffic (nominal_schedule); cpu,
    contention and replay send it. `sectors`, `sector_hz`: proximity sectors on top (one sequence with the
    rest, as one autopilot sends them); `custom_mode`: the autopilot's mode in its HEARTBEAT."""
    tel, gcs = Telemetry(custom_mode), Packer(GCS_SYS, GCS_COMP)
    out = []
    for offset, what in nominal_schedule(seconds, 0.0, sectors, sector_hz):
        if what == "REQUEST":
            frame = gcs.pack(body_velocity_request(int(offset * 1000), 0.4, 0.2 * math.sin(offset)))
        elif what == "GCS_HEARTBEAT":
            frame = gcs.pack(heartbeat_gcs())
        elif what == "GCS_TIMESYNC":
            frame = gcs.pack(mavlink.MAVLink_timesync_message(0, int(offset * 1e9)))
        else:
            frame = tel.frame(what, 100.0 + offset)
        out.append((offset, what, what.startswith("GCS_") or what == "REQUEST", frame))
    return out
