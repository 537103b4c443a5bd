"""MAVLink framing without decoding (pure): split bytes into frames, check the CRC of frames no core reads.

The bridge forwards most of the autopilot's telemetry untouched; decoding it into pymavlink message
objects only to forward the bytes was most of the cost of a busy link. `Framer` delimits frames
exactly as pymavlink's robust parser does (same frames, same bad-data runs, so the counters mean
the same thing); the shell decodes only the message ids a core reads and checks the CRC of the rest
(`crc_ok`), so a corrupted frame is dropped either way, never forwarded.
"""

from __future__ import annotations

from collections.abc import Callable

from rover_bridge.mavlink.dialect import mavlink

V1, V2 = mavlink.PROTOCOL_MARKER_V1, mavlink.PROTOCOL_MARKER_V2
SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
SIGNATURE_LEN = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN
HEADER_V1, HEADER_V2 = 6, 10
_CRC_EXTRA = {msg_id: cls.crc_extra for msg_id, cls in mavlink.mavlink_map.items()}
_EXTRA_BYTE = [bytes((i,)) for i in range(256)]
_mcrf4xx: Callable[[bytes, int], int] | None = getattr(mavlink, "mcrf4xx", None)


def msg_id(frame: bytes) -> int:
    """The message id of a delimited frame (MAVLink 1 or 2)."""
    if frame[0] == V2:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    return frame[5]


def crc_ok(frame: bytes) -> bool:
    """True when the frame's checksum matches (with the message's CRC_EXTRA); unknown ids pass, as
    pymavlink hands those on as MAVLink_unknown (it cannot check them either)."""
    extra = _CRC_EXTRA.get(msg_id(frame))
    if extra is None:
        return True
    sig = SIGNATURE_LEN if frame[0] == V2 and frame[2] & SIGNED else 0
    end = len(frame) - 2 - sig
    value: int
    if _mcrf4xx is not None:  # fastcrc, as pymavlink uses it: the same CRC without its wrapper object
        value = _mcrf4xx(_EXTRA_BYTE[extra], _mcrf4xx(frame[1:end], 0xFFFF))
    else:
        crc = mavlink.x25crc(frame[1:end])
        crc.accumulate(_EXTRA_BYTE[extra])
        value = crc.crc
    return value == frame[end] | frame[end + 1] << 8


def _frame_length(buf: bytes | bytearray) -> int:
    """The length of the frame that starts `buf` (a start marker, at least 3 bytes): header, payload,
    CRC and, when flagged, the signature."""
    if buf[0] == V2:
        return buf[1] + HEADER_V2 + 2 + (SIGNATURE_LEN if buf[2] & SIGNED else 0)
    return buf[1] + HEADER_V1 + 2


def _bad_flags(buf: bytes | bytearray) -> bool:
    """A MAVLink 2 frame with an incompatibility flag this parser does not know: bad as a whole."""
    return buf[0] == V2 and bool(buf[2] & ~SIGNED)


class Framer:
    """Bytes in (datagrams or pieces of a stream), whole frames and bad-data runs out.

    Mirrors pymavlink's robust parsing: bytes before a start marker form one bad run; a frame is
    the header's length plus CRC (plus signature when flagged); a MAVLink 2 frame with an unknown
    incompatibility flag is bad as a whole. Counters account for every byte fed.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bytes_fed = 0
        self.bytes_in_frames = 0
        self.bytes_bad = 0

    @property
    def buffered(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> None:
        self.bytes_fed += len(data)
        self._buf += data

    def whole(self, data: bytes) -> bytes | None:
        """`data` itself when it is exactly one good frame and nothing is buffered (a UDP datagram from
        an autopilot, nearly always), counted as feed() then next() would count it; None otherwise:
        then feed() it. The busiest path of a link, without the copy into the buffer and out again."""
        if self._buf or len(data) < 3 or (data[0] != V2 and data[0] != V1):
            return None
        n = len(data)
        if _frame_length(data) != n or _bad_flags(data):
            return None
        self.bytes_fed += n
        self.bytes_in_frames += n
        return data

    def next(self) -> tuple[bool, bytes] | None:
        """(True, frame) or (False, bad bytes), or None until more bytes arrive."""
        buf = self._buf
        if not buf:
            return None
        magic = buf[0]
        if magic != V2 and magic != V1:
            end = 1
            while end < len(buf) and buf[end] != V2 and buf[end] != V1:
                end += 1
            return self._take(end, good=False)
        if len(buf) < 3:
            return None
        length = _frame_length(buf)
        if len(buf) < length:
            return None
        return self._take(length, good=not _bad_flags(buf))

    def _take(self, n: int, good: bool) -> tuple[bool, bytes]:
        if n == len(self._buf):  # the usual datagram: exactly one frame
            chunk = bytes(self._buf)
            self._buf.clear()
        else:
            chunk = bytes(self._buf[:n])
            del self._buf[:n]
        if good:
            self.bytes_in_frames += n
        else:
            self.bytes_bad += n
        return good, chunk
