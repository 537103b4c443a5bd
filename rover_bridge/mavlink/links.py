"""MAVLink endpoints (I/O): pymavlink connections chosen by connection string.

`udpin:HOST:PORT` listens, `udpout:HOST:PORT` sends to a listener, `tcp:HOST:PORT` connects,
`tcpin:HOST:PORT` listens, `/dev/ttyACM0,921600` is a serial port. Reads never block: the
runner waits on the file descriptors with select() and then reads the readable links.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import socket
import struct
import sys
import time
from typing import Any

from rover_bridge.errors import ConfigError, LinkError
from rover_bridge.mavlink import fastcodec
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink, mavutil
from rover_bridge.mavlink.framing import Framer, crc_ok, msg_id
from rover_bridge.mavlink.wire import Link

log = logging.getLogger("rover_bridge.mavlink.links")

# Receive buffer asked for UDP links (the kernel caps it at net.core.rmem_max).
UDP_RCVBUF_BYTES = 1 << 20
# Largest write of forwarded frames: several frames per datagram, but within a 1500-byte Ethernet or
# Wi-Fi MTU (IP and UDP headers included), so no datagram is ever fragmented on the way to a GCS.
MAX_WRITE_BYTES = 1400
# Bytes asked of a stream link (tcp, serial) per read; a UDP link returns one whole datagram anyway.
RECV_CHUNK = 4096
# A UDP read asks for this much: more than any datagram (as mavutil's UDP_MAX_PACKET_LEN).
UDP_MAX_BYTES = 65535
# The kernel's receive time of each datagram on a listening UDP link (Linux SO_TIMESTAMPNS, 35 in the
# generic socket ABI that x86 and Arm use; Python does not export it: a struct timespec on the realtime
# clock, in the ancillary data of recvmsg). None elsewhere: frames then arrive when they are read.
_SO_TIMESTAMPNS: int | None = getattr(socket, "SO_TIMESTAMPNS", 35 if sys.platform.startswith("linux") else None)
_TIMESPEC = struct.Struct("@ll")
_ANC_BYTES = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0
# What a non-blocking UDP read raises when there is nothing to read (mavutil's recv returns "" for these).
_UDP_EMPTY = (BlockingIOError, InterruptedError, ConnectionRefusedError)
# What decoding may raise on hostile input; caught per frame, counted as bad, never fatal.
_DECODE_ERRORS = (mavlink.MAVError, ValueError, IndexError, TypeError, OSError, struct.error)

_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:", "serial:")


def _receive_time(anc: list[tuple[int, int, bytes]]) -> float:
    """The kernel's receive time (realtime clock, s) in a datagram's ancillary data; 0.0 if absent."""
    for _level, kind, data in anc:  # SOL_SOCKET's: the only level this socket asks for
        if kind == _SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(data)
            return float(sec) + float(nsec) * 1e-9
    return 0.0


def check_url(url: str) -> str | None:
    """A problem with a connection string, or None if it looks usable."""
    if not url:
        return "empty connection string"
    if url.startswith(_PREFIXES):
        rest = url.split(":", 1)[1]
        if url.startswith(("udp", "tcp")):
            host, _, port = rest.rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                return f"{url!r}: expected HOST:PORT after the prefix, e.g. udpin:127.0.0.1:14550"
        return None
    if url.startswith("/dev/") or url.upper().startswith("COM"):
        return None
    return (f"{url!r}: not a pymavlink connection string (udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, "
            "tcpin:HOST:PORT or /dev/ttyXXX,BAUD)")


def open_problem(url: str, role: Link, exc: BaseException) -> str:
    """One line for a link that did not open: which link, what happened, what to check."""
    what, flag = ("autopilot", "--autopilot") if role is Link.AUTOPILOT else ("ground-station", "--gcs")
    head = f"cannot open the {what} link {url}"
    code = getattr(exc, "errno", None)
    if isinstance(exc, ImportError):
        return f"{head}: serial links need pyserial (pip install pyserial)"
    if isinstance(exc, ConnectionRefusedError):
        return (f"{head}: connection refused, nothing listens there: start the autopilot (or SITL, or the router) "
                f"first, or give its address with {flag}")
    if isinstance(exc, socket.gaierror):
        return f"{head}: unknown host: check the address given with {flag}"
    if code == errno.EADDRINUSE:
        return (f"{head}: the address is in use: another program (MAVProxy, QGroundControl, another rover-bridge) "
                f"listens there: stop it, or choose another port with {flag}")
    if code == errno.EADDRNOTAVAIL:
        return f"{head}: not an address of this machine: listen on 0.0.0.0 or on one of its addresses"
    if code == errno.ENOENT:
        device = "autopilot" if role is Link.AUTOPILOT else "radio"
        return (f"{head}: no such device: is the {device} plugged in and powered, and is the name right? "
                "(ls /dev/serial/by-id/)")
    if code in (errno.EBUSY, errno.EAGAIN):
        return (f"{head}: the device is busy: another program holds it (MAVProxy, ModemManager, another "
                "rover-bridge): stop it")
    if code == errno.EACCES:
        return (f"{head}: permission denied: add this user to the dialout group (sudo usermod -aG dialout $USER, "
                "then log in again)")
    return f"{head}: {getattr(exc, 'strerror', None) or exc}"


def _probe_listen(address: str) -> None:
    """Bind HOST:PORT for a moment without SO_REUSEADDR: pymavlink binds a listening UDP link with it, and on
    Linux that shares the port silently with any other program that set it too (each then sees part of the
    traffic). The probe fails with EADDRINUSE if anyone else holds the port."""
    host, _, port = address.rpartition(":")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, int(port)))
    finally:
        probe.close()


class Endpoint:
    """One MAVLink link: non-blocking reads of decoded frames, raw forwarding, packing with given ids."""

    def __init__(self, url: str, role: Link, *, source_system: int = 1, source_component: int = 191) -> None:
        problem = check_url(url)
        if problem:
            raise ConfigError([problem])
        self.url = url
        self.role = role
        device, baud = url, 115200
        if url.startswith("serial:"):
            url = url[len("serial:"):]
        if "," in url and not url.startswith(("udp", "tcp")):
            device, _, baud_text = url.partition(",")
            baud = int(baud_text)
        else:
            device = url
        try:
            if url.startswith(("udpin:", "udp:")):
                _probe_listen(url.split(":", 1)[1])
            # retries=0: one connection attempt, so a TCP autopilot that is not listening is one clear line
            # (open_problem) at once, not pymavlink's "[Errno 111] Connection refused sleeping" for seconds.
            self.conn: Any = mavutil.mavlink_connection(
                device, baud=baud, source_system=source_system, source_component=source_component,
                dialect="ardupilotmega", autoreconnect=True, robust_parsing=True, retries=0)
            if isinstance(self.conn, mavutil.mavtcp):
                self.conn.retries = 3  # once connected, a lost TCP link is retried as pymavlink does by default
            if isinstance(self.conn, mavutil.mavserial) and self.conn.fd is not None:
                self._lock_serial()
        except (OSError, ImportError) as exc:
            raise LinkError(open_problem(self.url, role, exc)) from exc
        if self.conn.WIRE_PROTOCOL_VERSION != "2.0":  # pragma: no cover - guarded by rover_bridge.mavlink.dialect
            raise ConfigError([f"{self.url}: pymavlink did not select MAVLink 2"])
        port = getattr(self.conn, "port", None)
        if isinstance(port, socket.socket) and port.type == socket.SOCK_DGRAM:
            # Room for ~0.25 s of a fast telemetry stream (Linux default: ~200 small datagrams), so a
            # bridge that a busy companion computer deschedules for a few tens of ms drops nothing.
            with contextlib.suppress(OSError):
                port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RCVBUF_BYTES)
        # A listening UDP link (udpin, no client timeout) is read and written on its socket directly:
        # mavudp's recv/write wrap each datagram in a Python call, a time.time() and a client scan, per
        # datagram the bridge's busiest code. The client set stays mavudp's own (write_raw and every
        # other link type still go through mavudp), kept as its recv keeps it.
        self._udp: socket.socket | None = None
        if (type(self.conn) is mavutil.mavudp and self.conn.udp_server and self.conn.timeout <= 0
                and isinstance(port, socket.socket)):
            self._udp = port
        # Where the kernel stamps each datagram, read() records when every frame arrived (rx_wall_s):
        # the shell then hands the autopilot's frames to the core at that time, not at the later time
        # they were read (the estimator maps the autopilot's clock by them; nothing needs a GCS's).
        self._stamped = False
        if role is Link.AUTOPILOT and self._udp is not None and _SO_TIMESTAMPNS is not None and _ANC_BYTES:
            try:
                self._udp.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self._stamped = True
            except OSError:
                pass
        self.rx_wall_s: list[float] = []  # the last read's frames' receive times (realtime clock), if stamped
        self.framer = Framer()
        self._pending: list[bytes] = []
        self._decode_ids: frozenset[int] | None = None
        self.rx_frames = 0
        self.rx_bad = 0
        self.tx_frames = 0

    def _lock_serial(self) -> None:
        """Hold the serial port exclusively (as pyserial's exclusive=True): a second bridge, or any program
        that locks it too, is told the device is busy instead of both reading half of every frame."""
        try:
            fcntl.flock(self.conn.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self.conn.close()
            raise

    @property
    def receive_stamped(self) -> bool:
        """Whether read() knows each frame's kernel receive time (rx_wall_s): a listening UDP autopilot link."""
        return self._stamped

    def fileno(self) -> int | None:
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def decode_only(self, msg_ids: frozenset[int] | None) -> None:
        """Decode only frames with these message ids; hand the others on as their bytes (None: decode all)."""
        self._decode_ids = msg_ids

    def read(self, limit: int = 10_000) -> list[MAVLinkMessage | bytes]:
        """Every frame that has arrived: decoded, or its bytes when no core reads its id (see
        decode_only: such a frame is only CRC-checked, then forwarded and logged as is); bad frames
        are counted and dropped here.

        The hot path of the bridge. It reads what the link has (one datagram, or up to RECV_CHUNK
        bytes of a stream) and delimits frames itself (rover_bridge.mavlink.framing, as pymavlink's robust
        parser would), then decodes a frame with pymavlink's `decode` only if a core reads it: most
        of an autopilot's telemetry is only forwarded, and a forwarded frame needs its CRC checked,
        not a message object. mavutil's `recv_msg` bookkeeping (per-sysid tables, loss counts) is
        skipped too; nothing here uses it. An exception on one frame drops only that frame.
        """
        out: list[MAVLinkMessage | bytes] = []
        conn = self.conn
        framer = self.framer
        wanted = self._decode_ids
        udp = self._udp
        stamped = self._stamped
        walls: list[float] = []
        self.rx_wall_s = walls
        wall = 0.0  # the receive time of the datagram being framed (a datagram holds whole frames)
        reads = 0
        while len(out) < limit:
            item = framer.next()
            if item is None:
                if reads >= limit:
                    break  # a link feeding only junk must not keep the loop here either
                reads += 1
                try:
                    if udp is None:
                        data = conn.recv(RECV_CHUNK)
                    else:
                        if stamped:
                            data, anc, _flags, addr = udp.recvmsg(UDP_MAX_BYTES, _ANC_BYTES)
                            wall = _receive_time(anc)
                        else:
                            data, addr = udp.recvfrom(UDP_MAX_BYTES)
                        if addr not in conn.clients:  # a new peer: what mavudp.recv records
                            conn.clients.add(addr)
                            conn.clients_last_alive[addr] = time.time()
                except _UDP_EMPTY:
                    break
                except OSError as exc:
                    log.debug("%s: read failed: %s", self.url, exc)
                    break
                if not data:
                    break  # nothing new arrived and no complete frame is buffered
                if conn.first_byte:
                    conn.auto_mavlink_version(data)  # as recv_msg: may swap conn.mav (MAVLink 1 peer)
                # A datagram that is one whole frame (bytes, from the socket) skips the framer's buffer.
                frame = framer.whole(data) if udp is not None else None
                if frame is None:
                    framer.feed(data)
                    continue
            else:
                good, frame = item
                if not good:
                    self.rx_bad += 1
                    continue
            if wanted is not None and msg_id(frame) not in wanted:
                if crc_ok(frame):
                    self.rx_frames += 1
                    out.append(frame)
                    if stamped:
                        walls.append(wall)
                else:
                    self.rx_bad += 1
                continue
            try:
                # The hot messages through fastcodec (exactly pymavlink's values, a fifth of the cost);
                # the rest, and every frame of a link with a signing key, through pymavlink.
                fast = fastcodec.decode(frame) if conn.mav.signing.secret_key is None else None
                msg = fast if fast is not None else conn.mav.decode(bytearray(frame))
            except _DECODE_ERRORS as exc:
                self._dropped(exc)
                continue
            self.rx_frames += 1
            out.append(msg)
            if stamped:
                walls.append(wall)
        return out

    def _dropped(self, exc: Exception) -> None:
        self.rx_bad += 1
        log.debug("%s: undecodable input dropped: %s", self.url, exc)

    def queue_frame(self, frame: bytes) -> None:
        """Forward a frame byte for byte (source ids, sequence and signature untouched) with the next
        flush() (the runner flushes after every pass)."""
        self._pending.append(frame)

    def flush(self) -> None:
        """Write the queued frames in as few writes as fit: MAVLink receivers parse a datagram (or a
        stream) as a sequence of frames, and a write (a datagram) per frame is most of the cost of
        forwarding a busy link. Datagrams stay under MAX_WRITE_BYTES (no IP fragmentation)."""
        pending = self._pending
        if not pending:
            return
        self._pending = []
        chunk: list[bytes] = []
        size = 0
        for frame in pending:
            if chunk and size + len(frame) > MAX_WRITE_BYTES:
                self._write(b"".join(chunk))
                chunk, size = [], 0
            chunk.append(frame)
            size += len(frame)
        self._write(b"".join(chunk))
        self.tx_frames += len(pending)

    def _write(self, data: bytes) -> None:
        udp = self._udp
        if udp is None:
            self.conn.write(data)
            return
        for addr in self.conn.clients:  # as mavudp.write without a client timeout: every peer heard from
            try:  # noqa: SIM105 - contextlib.suppress costs a context manager per datagram
                udp.sendto(data, addr)
            except OSError:  # as mavudp.write: a failed datagram is lost, not an error of the loop
                pass

    def send(self, msg: MAVLinkMessage, src_system: int, src_component: int) -> bytes:
        """Pack `msg` with the given source ids, write it, and return the bytes written."""
        mav = self.conn.mav
        frame: bytes | None = None
        if not mav.signing.sign_outgoing:  # fastcodec packs pymavlink's bytes for the bridge's hot messages
            frame = fastcodec.pack(msg, mav.seq, src_system, src_component)
        if frame is None:
            mav.srcSystem, mav.srcComponent = src_system, src_component
            frame = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self._write(frame)
        self.tx_frames += 1
        return frame

    def write_raw(self, data: bytes) -> None:
        """Bytes straight to the link (the stop guard's emergency stop, from its own thread)."""
        self.conn.write(data)

    def read_raw(self, size: int) -> bytes:
        """What the link has, without framing or decoding (the stop guard waiting for its answer)."""
        data = self.conn.recv(size)
        return bytes(data) if data else b""

    def close(self) -> None:
        port = getattr(self.conn, "port", None)
        if port is not None and not isinstance(port, socket.socket) and hasattr(port, "flush"):
            # A serial port: wait until the UART has sent what is queued (tcdrain), the stop included;
            # closing first may discard the kernel's output buffer.
            with contextlib.suppress(Exception):
                port.flush()
        with contextlib.suppress(OSError):  # closing a dead serial port must not mask the real error
            self.conn.close()

    def setup_signing(self, key: bytes, *, link_id: int, initial_timestamp: int, verifier: Any) -> None:
        """MAVLink 2 signing on this link ([security]): our frames signed, incoming ones verified.

        Unsigned and badly signed frames are still decoded and handed on (the callback accepts them)
        so the core can count and refuse them by reason; only a frame that `verifier` (a shared
        rover_bridge.security.SignatureVerifier) accepts is marked signed (`msg._signed`).
        """
        self.conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=lambda _mav, _msg_id: True,
                                initial_timestamp=initial_timestamp, link_id=link_id)
        verifier.install(self.conn.mav)
