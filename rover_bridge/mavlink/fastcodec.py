"""Fast, exact MAVLink codec for the bridge's hot messages; pymavlink stays the reference and the codec of the rest.

pymavlink's `decode` and `pack` were about a quarter of the bridge's CPU: per frame they re-parse the
header, copy the buffer several times, walk the field order in Python and build two objects. Here the
layouts come from pymavlink's own generated classes (its `unpacker` struct, `orders`, `lengths`,
`crc_extra`), compiled once at import into one straight-line function per message, so the values and
bytes are pymavlink's by construction (tests/test_fastcodec.py checks that differentially).

Decoding (`decode`): a delimited frame (MAVLink 1 or 2, signed or not) of one of DECODE_IDS becomes a
light message object (`FastMessage`, a __slots__ class per message type) with every field under
pymavlink's name, type and value (arrays as lists; char fields as pymavlink's constructors leave
them: str, with the bytes in `_<name>_raw`; none of DECODE_IDS has one) and pymavlink's getters
(get_type, get_msgId, get_srcSystem, get_srcComponent, get_seq, get_msgbuf, get_header, get_payload,
get_crc, get_signed, get_fieldnames, to_dict, format_attr, str()). It is no MAVLink_message:
isinstance, `==` with pymavlink's and new attributes do not work. The CRC is checked (with
CRC_EXTRA) as pymavlink's decode does. `decode` returns None, and the caller uses pymavlink (which
then raises or decodes exactly as before), for: another message id, a bad CRC, a length that does
not match the header, an unknown incompatibility flag.

Use it only when `can_decode_fast(mav)`: with a signing key on the parsing link pymavlink verifies
signatures and consults allow_unsigned_callback (the bridge's SignatureVerifier), so that link keeps
pymavlink. Without a key the only difference is pymavlink's `mav.signing.sig_count` (signed frames
seen), which fastcodec does not count. `_signed` is always False (as pymavlink's without a key).

Packing: `pack(msg, seq, src_system, src_component)` packs a pymavlink message object of one of
PACK_IDS, and `pack_heartbeat`, `pack_timesync`, `pack_rc_channels_override`, `pack_odometry` pack from
field values without building a pymavlink object. The bytes are those of pymavlink's `msg.pack(mav)`
for an unsigned MAVLink 2 frame with mav.seq / srcSystem / srcComponent = seq / src_system /
src_component (payload zero-trimmed, CRC with CRC_EXTRA, fastcrc when pymavlink uses it), and values
pymavlink cannot pack raise the same exception types. Unlike `msg.pack`, nothing is stored on `msg`
(its _header, _msgbuf, ... stay as they were) and the caller advances its own sequence number.
Signing: when `can_pack_fast(mav)` is False (mav.signing.sign_outgoing), pack with pymavlink.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Final

from rover_bridge.mavlink.dialect import mavlink

V1: Final = mavlink.PROTOCOL_MARKER_V1
V2: Final = mavlink.PROTOCOL_MARKER_V2
_SIGNED: Final = mavlink.MAVLINK_IFLAG_SIGNED
_SIG_LEN: Final = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN

DECODE_IDS: Final = frozenset({
    mavlink.MAVLINK_MSG_ID_HEARTBEAT,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME,
    mavlink.MAVLINK_MSG_ID_SCALED_IMU,
    mavlink.MAVLINK_MSG_ID_RAW_IMU,
    mavlink.MAVLINK_MSG_ID_ATTITUDE,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    mavlink.MAVLINK_MSG_ID_MISSION_ACK,
    mavlink.MAVLINK_MSG_ID_COMMAND_LONG,
    mavlink.MAVLINK_MSG_ID_COMMAND_ACK,
    mavlink.MAVLINK_MSG_ID_TIMESYNC,
    mavlink.MAVLINK_MSG_ID_WHEEL_DISTANCE,
    # The ground station's side: velocity requests at 10-50 Hz, and what the command flow reads.
    mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED,
    mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT,
    mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL,
    mavlink.MAVLINK_MSG_ID_COMMAND_INT,
    mavlink.MAVLINK_MSG_ID_MISSION_ITEM_INT,
    # The autopilot's own navigation feedback (read, and held back while the bridge navigates).
    mavlink.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_GLOBAL_INT,
    mavlink.MAVLINK_MSG_ID_MISSION_ITEM_REACHED,
    # A proximity sensor's 8 sectors (simple avoidance): 80 a second at 10 Hz.
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,
})
PACK_IDS: Final = frozenset({
    mavlink.MAVLINK_MSG_ID_HEARTBEAT,
    mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE,
    mavlink.MAVLINK_MSG_ID_COMMAND_LONG,  # the servo output mode's per-tick command
    mavlink.MAVLINK_MSG_ID_TIMESYNC,
    mavlink.MAVLINK_MSG_ID_ODOMETRY,
})


def _mcrf4xx_slow(data: bytes, crc: int) -> int:
    """CRC-16/MCRF4XX continued from `crc`, with pymavlink's own code (no fastcrc installed)."""
    acc = mavlink.x25crc()
    acc.crc = crc
    acc.accumulate(data)
    value: int = acc.crc
    return value


# pymavlink's x25crc is fastcrc's mcrf4xx when fastcrc imports; the same function, without its wrapper.
_mcrf: Callable[[bytes, int], int] = getattr(mavlink, "mcrf4xx", None) or _mcrf4xx_slow


def can_decode_fast(mav: Any) -> bool:
    """True when `decode` gives what `mav.decode` would: the link has no signing key (else pymavlink
    checks signatures and counts them)."""
    return mav.signing.secret_key is None


def can_pack_fast(mav: Any) -> bool:
    """True when the packers give what `msg.pack(mav)` would: mav does not sign outgoing frames."""
    return not mav.signing.sign_outgoing


class FastMessage:
    """A decoded message that reads like pymavlink's: fields as attributes (subclass slots), its getters.

    Seq, source ids and the header are read from the frame when asked (only the frame and the fields
    are stored). Not a pymavlink MAVLink_message: isinstance checks and `==` with one do not hold.
    """

    __slots__ = ("_header", "_msgbuf")

    id: ClassVar[int]  # the message id, as pymavlink's class attribute (RAW_IMU has a field `id` instead)
    msgname: ClassVar[str] = ""
    fieldnames: ClassVar[list[str]] = []
    crc_extra: ClassVar[int] = 0
    _type: ClassVar[str] = ""
    _fieldnames: ClassVar[list[str]] = []
    _msg_id: ClassVar[int] = -1
    _signed: ClassVar[bool] = False  # decode is only used where pymavlink would not check signatures
    _link_id: ClassVar[int | None] = None

    _msgbuf: bytes | bytearray
    _header: Any

    def get_type(self) -> str:
        return self._type

    def get_msgId(self) -> int:  # noqa: N802 (pymavlink's name)
        return self._msg_id

    def get_seq(self) -> int:
        b = self._msgbuf
        return b[4] if b[0] == V2 else b[2]

    def get_srcSystem(self) -> int:  # noqa: N802
        b = self._msgbuf
        return b[5] if b[0] == V2 else b[3]

    def get_srcComponent(self) -> int:  # noqa: N802
        b = self._msgbuf
        return b[6] if b[0] == V2 else b[4]

    def get_msgbuf(self) -> bytes | bytearray:
        """The frame, as given to `decode` (header to CRC, and the signature if any)."""
        return self._msgbuf

    def get_header(self) -> Any:
        """A pymavlink MAVLink_header with the frame's values (built on first use, then kept)."""
        try:
            return self._header
        except AttributeError:
            pass
        b = self._msgbuf
        if b[0] == V2:
            header = mavlink.MAVLink_header(self._msg_id, b[2], b[3], b[1], b[4], b[5], b[6])
        else:
            header = mavlink.MAVLink_header(self._msg_id, 0, 0, b[1], b[2], b[3], b[4])
        self._header = header
        return header

    def _crc_at(self) -> int:
        b = self._msgbuf
        return len(b) - 2 - (_SIG_LEN if b[0] == V2 and b[2] & _SIGNED else 0)

    def get_payload(self) -> bytes | bytearray:
        """As pymavlink's: the frame from byte 6 to the CRC (for MAVLink 2 that includes 4 header bytes)."""
        return self._msgbuf[6 : self._crc_at()]

    def get_crc(self) -> int:
        b = self._msgbuf
        end = self._crc_at()
        return b[end] | b[end + 1] << 8

    def get_signed(self) -> bool:
        return self._signed

    def get_link_id(self) -> int | None:
        return self._link_id

    def get_fieldnames(self) -> list[str]:
        return self._fieldnames

    def format_attr(self, field: str) -> str | float | int:
        raw: Any = getattr(self, field)
        if isinstance(raw, bytes):
            return raw.decode(errors="backslashreplace").rstrip("\x00")
        value: str | float | int = raw
        return value

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"mavpackettype": self._type}
        for name in self._fieldnames:
            d[name] = self.format_attr(name)
        return d

    def __str__(self) -> str:
        return f"{self._type} {{" + ", ".join(f"{a} : {self.format_attr(a)}" for a in self._fieldnames) + "}"


# ---------------------------------------------------------------------------------------------------
# Code generation from pymavlink's class metadata (once, at import).

_ELEMENT = re.compile(r"(\d*)([a-zA-Z?])")


def _element_codes(fmt: str) -> list[str]:
    """One struct code per element of the unpacked tuple ("<Q16dB" -> Q, d x 16, B; "50s" is one)."""
    codes: list[str] = []
    for count, code in _ELEMENT.findall(fmt.lstrip("<")):
        codes.extend([code] if code in "sp" else [code] * int(count or 1))
    return codes


def _field_slices(pcls: Any) -> list[tuple[str, int, int, bool]]:
    """(name, first tuple index, array length or 0, is bytes) per field in pymavlink's fieldnames order,
    computed as pymavlink's decode does (orders, lengths; a char array is one bytes element)."""
    codes = _element_codes(pcls.unpacker.format)
    lengths: list[int] = list(pcls.lengths)
    if sum(lengths) != len(codes) or len(codes) != len(pcls.unpacker.unpack(bytes(pcls.unpacker.size))):
        raise ValueError(f"{pcls.msgname}: unexpected layout {pcls.unpacker.format} {lengths}")
    out = []
    for i, name in enumerate(pcls.fieldnames):
        order = pcls.orders[i]
        length = lengths[order]
        tip = sum(lengths[:order])
        is_bytes = codes[tip] in "sc"
        out.append((name, tip, 0 if length == 1 or is_bytes else length, is_bytes))
    return out


_CHAR_PROBE = b"\xffA\x00B"


def _char_modes(pcls: Any, fields: list[tuple[str, int, int, bool]]) -> dict[str, bool]:
    """Per char field: True when pymavlink's constructor turns it into str (text up to the first NUL,
    ASCII with replacement) and keeps the bytes as `_<name>_raw`, False when it keeps the bytes. Found by
    constructing one (the generated classes differ between pymavlink versions); anything else: ValueError."""
    modes: dict[str, bool] = {}
    zero = pcls.unpacker.unpack(bytes(pcls.unpacker.size))
    args = [zero[tip] if not n else list(zero[tip : tip + n]) for _, tip, n, _ in fields]
    for k, (name, _, _, is_bytes) in enumerate(fields):
        if not is_bytes:
            continue
        probe = pcls(*[_CHAR_PROBE if j == k else a for j, a in enumerate(args)])
        value, raw = getattr(probe, name), getattr(probe, f"_{name}_raw", None)
        if value == _CHAR_PROBE and raw is None:
            modes[name] = False
        elif raw == _CHAR_PROBE and value == _CHAR_PROBE.split(b"\x00", 1)[0].decode("ascii", errors="replace"):
            modes[name] = True
        else:
            raise ValueError(f"{pcls.msgname}.{name}: unknown char field handling")
    return modes


def _compile(source: str, namespace: dict[str, Any], name: str) -> Any:
    exec(compile(source, f"<fastcodec {name}>", "exec"), namespace)
    return namespace[name]


_Decoder = Callable[[bytes | bytearray, int, int, int], FastMessage | None]


def _message_class(pcls: Any) -> type[FastMessage]:
    names = list(pcls.fieldnames)
    raw = [f"_{name}_raw" for name, as_str in _char_modes(pcls, _field_slices(pcls)).items() if as_str]
    ns: dict[str, Any] = {
        "__slots__": tuple(names + raw), "__module__": __name__, "msgname": pcls.msgname,
        "fieldnames": pcls.fieldnames, "crc_extra": pcls.crc_extra, "_type": pcls.msgname,
        "_fieldnames": pcls.fieldnames, "_msg_id": pcls.id,
    }
    if "id" not in names:
        ns["id"] = pcls.id
    cls: type[FastMessage] = type(pcls.__name__.replace("MAVLink_", "Fast_"), (FastMessage,), ns)
    return cls


def _decoder(pcls: Any, cls: type[FastMessage]) -> _Decoder:
    """decode(frame, payload offset, payload length, CRC offset) -> message, or None on a bad CRC.

    The payload is zero-extended to the full layout (MAVLink 2 trims trailing zeros, MAVLink 1 and older
    senders lack the extension fields) or cut to it (a newer dialect's extensions), as pymavlink does."""
    size = pcls.unpacker.size
    fields = _field_slices(pcls)
    as_str = _char_modes(pcls, fields)
    lines = [
        "def decode(frame, off, plen, end):",
        "    if _mcrf(EXTRA, _mcrf(frame[1:end], 0xFFFF)) != frame[end] | frame[end + 1] << 8:",
        "        return None",
        f"    if plen >= {size}:",
        "        t = unpack_from(frame, off)",
        "    else:",
        "        t = unpack(frame[off:off + plen] + PAD[plen])",
        "    m = new(CLS)",
        "    m._msgbuf = frame",
    ]
    scalar = all(n == 0 and not b for _, _, n, b in fields)
    if scalar and sorted(tip for _, tip, _, _ in fields) == list(range(len(fields))):
        targets = [""] * len(fields)
        for name, tip, _, _ in fields:
            targets[tip] = f"m.{name}"
        lines.append(f"    {', '.join(targets)}, = t")
    else:
        for name, tip, n, is_bytes in fields:
            if n:
                lines.append(f"    m.{name} = list(t[{tip}:{tip + n}])")
            elif is_bytes and as_str[name]:  # as pymavlink: str, the bytes as _<name>_raw
                lines.append(f"    m._{name}_raw = r = t[{tip}].rstrip(b'\\x00')")
                lines.append(f"    m.{name} = r.split(b'\\x00', 1)[0].decode('ascii', errors='replace')")
            elif is_bytes:
                lines.append(f"    m.{name} = t[{tip}].rstrip(b'\\x00')")
            else:
                lines.append(f"    m.{name} = t[{tip}]")
    lines.append("    return m")
    ns: dict[str, Any] = {
        "_mcrf": _mcrf, "EXTRA": bytes((pcls.crc_extra,)), "unpack_from": pcls.unpacker.unpack_from,
        "unpack": pcls.unpacker.unpack, "PAD": [bytes(size - n) for n in range(size)], "new": object.__new__,
        "CLS": cls,
    }
    fn: _Decoder = _compile("\n".join(lines) + "\n", ns, "decode")
    return fn


MESSAGE_CLASSES: Final[dict[int, type[FastMessage]]] = {}
_DECODERS: dict[int, _Decoder] = {}
for _id in sorted(DECODE_IDS):
    _pcls = mavlink.mavlink_map[_id]
    MESSAGE_CLASSES[_id] = _message_class(_pcls)
    _DECODERS[_id] = _decoder(_pcls, MESSAGE_CLASSES[_id])


def decode(frame: bytes | bytearray) -> FastMessage | None:
    """The message of a delimited frame, as pymavlink's `mav.decode(bytearray(frame))` gives it, or None
    (use pymavlink): not one of DECODE_IDS, bad CRC, length not the header's, unknown incompat flags.

    get_msgbuf() returns `frame` itself (not a copy)."""
    n = len(frame)
    if n < 8:
        return None
    magic = frame[0]
    if magic == V2:
        flags = frame[2]
        if flags == 0:
            end = n - 2
        elif flags == _SIGNED:
            end = n - 2 - _SIG_LEN
        else:
            return None
        plen = frame[1]
        if end != 10 + plen:
            return None
        fn = _DECODERS.get(frame[7] | frame[8] << 8 | frame[9] << 16)
        return None if fn is None else fn(frame, 10, plen, end)
    if magic == V1:
        plen = frame[1]
        end = n - 2
        if end != 6 + plen:
            return None
        fn = _DECODERS.get(frame[5])
        return None if fn is None else fn(frame, 6, plen, end)
    return None


# ---------------------------------------------------------------------------------------------------
# Packing: pymavlink's MAVLink_message._pack for an unsigned MAVLink 2 frame.

_HEAD = struct.Struct("<BBBBBBHB")  # pymavlink's header without the magic: len, incompat, compat, seq, sys, comp, id
_CRC = struct.Struct("<H")
_MAGIC_V2 = bytes((V2,))


def _frame(payload: bytes, seq: int, src_system: int, src_component: int, msg_id: int, extra: bytes) -> bytes:
    """Header + payload without its trailing zeros (at least one byte is kept) + CRC with CRC_EXTRA."""
    body = payload.rstrip(b"\x00") or b"\x00"
    data = _HEAD.pack(len(body), 0, 0, seq, src_system, src_component, msg_id & 0xFFFF, msg_id >> 16) + body
    return b"".join((_MAGIC_V2, data, _CRC.pack(_mcrf(extra, _mcrf(data, 0xFFFF)))))


_Packer = Callable[[Any, int, int, int], bytes]


def _packer(pcls: Any) -> _Packer:
    """pack(msg, seq, src_system, src_component): the payload expression of pymavlink's generated pack()
    (fields in wire order, arrays element by element: msg.q[0], msg.q[1], ...)."""
    codes = _element_codes(pcls.unpacker.format)
    if any(c in "sc" for c in codes):
        raise ValueError(f"{pcls.msgname}: char fields are not packed here")
    args = []
    for w, name in enumerate(pcls.ordered_fieldnames):
        n = pcls.lengths[w]
        args.extend([f"m.{name}"] if n == 1 else [f"m.{name}[{k}]" for k in range(n)])
    source = (
        "def pack(m, seq, src_system, src_component):\n"
        f"    return frame(payload({', '.join(args)}), seq, src_system, src_component, {pcls.id}, EXTRA)\n"
    )
    ns: dict[str, Any] = {"frame": _frame, "payload": pcls.unpacker.pack, "EXTRA": bytes((pcls.crc_extra,))}
    fn: _Packer = _compile(source, ns, "pack")
    return fn


_PACKERS: dict[type, _Packer] = {mavlink.mavlink_map[i]: _packer(mavlink.mavlink_map[i]) for i in sorted(PACK_IDS)}


def pack(msg: Any, seq: int, src_system: int, src_component: int) -> bytes | None:
    """`msg.pack(mav)`'s bytes for a pymavlink message of PACK_IDS (MAVLink 2, unsigned), or None for
    another type (pack that one with pymavlink). `msg` itself is left untouched."""
    fn = _PACKERS.get(type(msg))
    return None if fn is None else fn(msg, seq, src_system, src_component)


_HEARTBEAT = mavlink.MAVLink_heartbeat_message
_TIMESYNC = mavlink.MAVLink_timesync_message
_RC_OVERRIDE = mavlink.MAVLink_rc_channels_override_message
_ODOMETRY = mavlink.MAVLink_odometry_message
_HEARTBEAT_PACK = _HEARTBEAT.unpacker.pack
_TIMESYNC_PACK = _TIMESYNC.unpacker.pack
_RC_OVERRIDE_PACK = _RC_OVERRIDE.unpacker.pack
_ODOMETRY_PACK = _ODOMETRY.unpacker.pack
_HEARTBEAT_EXTRA = bytes((_HEARTBEAT.crc_extra,))
_TIMESYNC_EXTRA = bytes((_TIMESYNC.crc_extra,))
_RC_OVERRIDE_EXTRA = bytes((_RC_OVERRIDE.crc_extra,))
_ODOMETRY_EXTRA = bytes((_ODOMETRY.crc_extra,))


def pack_heartbeat(seq: int, src_system: int, src_component: int, type: int, autopilot: int, base_mode: int,
                   custom_mode: int, system_status: int, mavlink_version: int) -> bytes:
    """HEARTBEAT (0), fields as MAVLink_heartbeat_message's."""
    return _frame(_HEARTBEAT_PACK(custom_mode, type, autopilot, base_mode, system_status, mavlink_version),
                  seq, src_system, src_component, 0, _HEARTBEAT_EXTRA)


def pack_timesync(seq: int, src_system: int, src_component: int, tc1: int, ts1: int) -> bytes:
    """TIMESYNC (111)."""
    return _frame(_TIMESYNC_PACK(tc1, ts1), seq, src_system, src_component, 111, _TIMESYNC_EXTRA)


def pack_rc_channels_override(seq: int, src_system: int, src_component: int, target_system: int,
                              target_component: int, chans: Sequence[int]) -> bytes:
    """RC_CHANNELS_OVERRIDE (70): `chans` is chan1_raw .. chan18_raw (exactly 18, else ValueError)."""
    c1, c2, c3, c4, c5, c6, c7, c8, c9, c10, c11, c12, c13, c14, c15, c16, c17, c18 = chans
    payload = _RC_OVERRIDE_PACK(c1, c2, c3, c4, c5, c6, c7, c8, target_system, target_component,
                                c9, c10, c11, c12, c13, c14, c15, c16, c17, c18)
    return _frame(payload, seq, src_system, src_component, 70, _RC_OVERRIDE_EXTRA)


def pack_odometry(seq: int, src_system: int, src_component: int, time_usec: int, frame_id: int,
                  child_frame_id: int, x: float, y: float, z: float, q: Sequence[float], vx: float, vy: float,
                  vz: float, rollspeed: float, pitchspeed: float, yawspeed: float,
                  pose_covariance: Sequence[float], velocity_covariance: Sequence[float], reset_counter: int = 0,
                  estimator_type: int = 0, quality: int = 0) -> bytes:
    """ODOMETRY (331), fields as MAVLink_odometry_message's; q has 4 elements, each covariance 21 (else
    ValueError: pymavlink would ignore extra elements)."""
    if len(q) != 4 or len(pose_covariance) != 21 or len(velocity_covariance) != 21:
        raise ValueError("ODOMETRY: q needs 4 elements, pose_covariance and velocity_covariance 21")
    payload = _ODOMETRY_PACK(time_usec, x, y, z, *q, vx, vy, vz, rollspeed, pitchspeed, yawspeed,
                             *pose_covariance, *velocity_covariance, frame_id, child_frame_id, reset_counter,
                             estimator_type, quality)
    return _frame(payload, seq, src_system, src_component, 331, _ODOMETRY_EXTRA)


__all__ = [
    "DECODE_IDS", "MESSAGE_CLASSES", "PACK_IDS", "FastMessage", "can_decode_fast", "can_pack_fast", "decode", "pack",
    "pack_heartbeat", "pack_odometry", "pack_rc_channels_override", "pack_timesync",
]
