"""The logs replay and the fleet read, as MAVLink frames on the log's own clock: `.tlog` and ArduPilot DataFlash `.bin`.

- A `.tlog` (the bridge's `run --tlog`, MAVProxy, Mission Planner, QGroundControl) is read frame by frame
  with pymavlink; each frame's `_timestamp` is the recorder's wall clock (s).
- A DataFlash `.bin` is read with pymavlink's DFReader and turned into the MAVLink messages the estimate
  flow reads from a live autopilot, each at its own TimeUS (the autopilot's boot clock, s):
  WENC -> WHEEL_DISTANCE (Dist0, Dist1), IMU instance 0 (GYR where no IMU is logged) -> ATTITUDE with
  the gyro's z rate as yawspeed (both clockwise positive) and ATT's yaw, GPS instance 0 -> GPS_RAW_INT,
  RCIN / RCOU -> RC_CHANNELS / SERVO_OUTPUT_RAW, MODE and a 1 Hz HEARTBEAT from SYSID_THISMAV.

Both are streamed (a DataFlash log is mapped, not read into memory; DFReader keeps an index of offsets).
What the reading found is kept in `LogFrames.stats`: frames, unreadable frames, the bytes of an incomplete
last frame (a log cut mid-frame) and the log's start as UNIX time where the log says it. What pymavlink prints
about a damaged DataFlash log is captured and counted there too (rover_bridge.app.chatter), in whichever
process reads it. `format_problem` tells a file that is no log of its kind from its first bytes.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rover_bridge.app.chatter import Chatter
from rover_bridge.errors import ConfigError, RemoteError
from rover_bridge.mavlink.dialect import mavlink, mavutil

GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06
GPS_LEAP_S = 18  # GPS - UTC since 2017
WEEK_S = 604_800
DATAFLASH_TYPES = ("PARM", "MODE", "WENC", "IMU", "GYR", "ATT", "GPS", "RCIN", "RCOU")
HEARTBEAT_PERIOD_S = 1.0
SNIFF_BYTES = 4096
DATAFLASH_FMT_HEADER = b"\xa3\x95\x80"  # every DataFlash message starts A3 95; a log opens with FMT (0x80) ones


@dataclass
class LogStats:
    """What reading one log found (filled while it is read)."""

    kind: str  # "tlog" | "dataflash"
    size_bytes: int
    frames: int = 0
    bad_frames: int = 0  # unreadable (tlog: BAD_DATA) frames
    bad_bytes: int = 0  # bytes in no readable frame (between them; an incomplete last one not counted)
    trailing_bytes: int = 0  # an incomplete last frame: the log ends mid-frame
    start_unix_s: float | None = None
    reader_lines: int = 0  # lines pymavlink printed about what it skipped (captured, not shown)


def log_kind(path: Path) -> str:
    return "dataflash" if path.suffix.lower() == ".bin" else "tlog"


def format_problem(path: Path) -> str | None:
    """Why a file is plainly no log of its kind, from its first bytes (None: it may be one).

    A DataFlash log opens with its FMT messages; a .tlog is 8-byte time stamps, each followed by a MAVLink 1
    or 2 frame, so its first record ends where the second's frame begins. Random bytes pass either test
    about once in 4,000 files (DataFlash) or 16,000 (.tlog); a damaged log whose start is intact passes, to be read
    and accounted for.
    """
    with open(path, "rb") as f:
        head = f.read(SNIFF_BYTES)
    if not head:
        return None
    if log_kind(path) == "dataflash":
        return None if DATAFLASH_FMT_HEADER in head else (
            f"not an ArduPilot DataFlash log (no DataFlash message in its first {SNIFF_BYTES} bytes)")
    end = _tlog_record_end(head, 0)
    if end is not None and (end + 11 > len(head) or _tlog_record_end(head, end) is not None):
        return None
    return "not a .tlog (it does not start with time-stamped MAVLink frames)"


def _tlog_record_end(data: bytes, at: int) -> int | None:
    """Where the .tlog record at `at` ends (its frame's length from the frame's header), None without a frame."""
    if len(data) < at + 11:
        return None
    magic, payload = data[at + 8], data[at + 9]
    if magic == 0xFE:  # MAVLink 1: 6 header bytes, payload, 2 CRC bytes
        return at + 8 + 6 + payload + 2
    if magic == 0xFD:  # MAVLink 2: 10 header bytes, payload, 2 CRC bytes, 13 more when signed
        return at + 8 + 10 + payload + 2 + (13 if data[at + 10] & 1 else 0)
    return None


class LogFrames:
    """Iterate one log's frames (MAVLink messages with `_timestamp` on the log's clock); see the module docstring."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise ConfigError([f"{self.path}: no such log"])
        self.stats = LogStats(log_kind(self.path), self.path.stat().st_size)

    def contains(self, pattern: bytes, chunk_bytes: int = 1 << 20) -> bool:
        """Whether these bytes appear anywhere in the file (read in chunks: memory stays bounded)."""
        tail = b""
        with open(self.path, "rb") as f:
            while chunk := f.read(chunk_bytes):
                window = tail + chunk
                if pattern in window:
                    return True
                tail = window[max(0, len(window) - len(pattern) + 1):] if len(pattern) > 1 else b""
        return False

    def __iter__(self) -> Iterator[Any]:
        self.stats = LogStats(self.stats.kind, self.path.stat().st_size)
        if self.stats.size_bytes == 0:
            return iter(())
        if self.stats.kind == "dataflash":
            return DataFlashFrames(self.path, self.stats).frames()
        return self._tlog()

    def _tlog(self) -> Iterator[Any]:
        st = self.stats
        log: Any = mavutil.mavlink_connection(str(self.path), dialect="ardupilotmega", robust_parsing=True)
        end = good = 0  # file position after the last frame read, good or bad; bytes in good frames
        try:
            while True:
                msg = log.recv_msg()
                if msg is None:
                    break
                end = log.f.tell()
                if msg.get_type() == "BAD_DATA":
                    st.bad_frames += 1
                    continue
                st.frames += 1
                good += 8 + len(msg.get_msgbuf())  # pymavlink skips garbage silently: count what it kept
                if st.start_unix_s is None:
                    st.start_unix_s = float(msg._timestamp)
                yield msg
            # pymavlink reads exactly what a frame needs: what is left after the last one is a cut frame.
            st.trailing_bytes = st.size_bytes - end
            st.bad_bytes = end - good
        finally:
            log.close()


def _header(msg: Any, system: int, t_s: float) -> Any:
    msg._header = mavlink.MAVLink_header(msg.id, srcSystem=system, srcComponent=1)
    msg._timestamp = t_s
    return msg


class DataFlashFrames:
    """One DataFlash log as the MAVLink frames of a live autopilot (see the module docstring)."""

    def __init__(self, path: Path, stats: LogStats) -> None:
        self.path = path
        self.stats = stats
        self._yaw_rad = 0.0
        self._mode = 0
        self._next_heartbeat_s = -math.inf
        self._gyro_type = "IMU"

    def frames(self) -> Iterator[Any]:
        from pymavlink import DFReader

        chatter = Chatter()  # a line per bad byte otherwise, on this process's terminal (chatter's docstring)
        try:
            with chatter.everything():
                log: Any = DFReader.DFReader_binary(str(self.path))
        except Exception as exc:  # DFReader raises whatever its parsing met on a damaged file
            raise LogUnreadableError(f"not a DataFlash log ({type(exc).__name__}: {exc})") from exc
        try:
            self._account(log)
            self._gyro_type = "IMU" if "IMU" in log.name_to_id else "GYR"
            while True:
                with chatter.python:
                    m = log.recv_match(type=set(DATAFLASH_TYPES))
                if m is None:
                    return
                for out in self._convert(m, log):
                    self.stats.frames += 1
                    yield out
        finally:
            self.stats.reader_lines = chatter.lines
            log.filehandle.close()

    def _account(self, log: Any) -> None:
        """Bytes in readable messages, unreadable ones between them, and a cut last message, from the index."""
        covered = last_end = 0
        size = self.stats.size_bytes
        for mtype, offsets in enumerate(log.offsets):
            if not offsets or mtype not in log.formats:
                continue
            length = log.formats[mtype].len
            whole = len(offsets) if offsets[-1] + length <= size else len(offsets) - 1  # the index has a cut one
            covered += whole * length
            if whole:
                last_end = max(last_end, offsets[whole - 1] + length)
        st = self.stats
        st.trailing_bytes = max(0, st.size_bytes - last_end) if last_end else st.size_bytes
        st.bad_bytes = max(0, last_end - covered)

    def _convert(self, m: Any, log: Any) -> list[Any]:
        kind = m.get_type()
        if kind in ("PARM", "ATT", "MODE"):
            if kind == "ATT":
                self._yaw_rad = math.remainder(math.radians(float(m.Yaw)), 2.0 * math.pi)
            elif kind == "MODE":
                self._mode = int(m.ModeNum)
                self._next_heartbeat_s = -math.inf  # Rover sends a heartbeat at once on a mode change
            return []
        if kind not in DATAFLASH_TYPES:
            return []  # DFReader adds MSG, STAT, ORGN, VER to any selection
        t_us = int(m.TimeUS)
        t_s = t_us * 1e-6
        system = int(log.params.get("SYSID_THISMAV", 1))
        out = []
        if t_s >= self._next_heartbeat_s:
            self._next_heartbeat_s = t_s + HEARTBEAT_PERIOD_S
            hb = mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self._mode, mavlink.MAV_STATE_ACTIVE, 3)
            out.append(_header(hb, system, t_s))
        msg = self._message(kind, m, t_us)
        if msg is not None:
            out.append(_header(msg, system, t_s))
        return out

    def _message(self, kind: str, m: Any, t_us: int) -> Any:
        if kind == "WENC":
            return mavlink.MAVLink_wheel_distance_message(t_us, 2, [float(m.Dist0), float(m.Dist1)] + [0.0] * 14)
        if kind == self._gyro_type and int(getattr(m, "I", 0)) == 0:
            return mavlink.MAVLink_attitude_message(t_us // 1000, 0.0, 0.0, self._yaw_rad, 0.0, 0.0, float(m.GyrZ))
        if kind == "GPS" and int(getattr(m, "I", 0)) == 0:
            status = int(m.Status)
            if status >= 3 and int(m.GWk) > 0 and self.stats.start_unix_s is None:
                gps_s = GPS_EPOCH_UNIX_S + int(m.GWk) * WEEK_S + int(m.GMS) * 1e-3 - GPS_LEAP_S
                self.stats.start_unix_s = gps_s - t_us * 1e-6  # the log's boot, in UNIX time
            return mavlink.MAVLink_gps_raw_int_message(
                t_us, status, round(float(m.Lat) * 1e7), round(float(m.Lng) * 1e7), round(float(m.Alt) * 1e3),
                round(float(m.HDop) * 100), 65535, 0, 0, int(m.NSats))
        if kind in ("RCIN", "RCOU"):
            values = [int(getattr(m, f"C{i}", 0)) for i in range(1, 19)]
            if kind == "RCIN":
                return mavlink.MAVLink_rc_channels_message(t_us // 1000, 18, *values, 255)
            return mavlink.MAVLink_servo_output_raw_message(t_us & 0xFFFFFFFF, 0, *values[:16])
        return None


class LogUnreadableError(RemoteError):
    """A log that cannot be read at all (the reason is the message)."""
