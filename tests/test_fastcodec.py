"""rover_bridge.mavlink.fastcodec against pymavlink, differentially: the same values from every frame, the same bytes.

pymavlink is the reference. Decoding: frames packed by pymavlink (MAVLink 2 zero-trimmed, with extension
fields, MAVLink 1 from the v1.0 dialect and from force_mavlink1, signed) and frames built by hand from
arbitrary payload bytes (every bit pattern: NaN payloads, denormals, a newer dialect's longer payload)
decode to the same field values (float bits compared), getters and header. Packing: the same bytes as
`msg.pack(mav)`, or the same exception type, for any field values.
"""

from __future__ import annotations

import math
import os
import struct
import types
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rover_bridge.mavlink import fastcodec
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink, mavutil
from rover_bridge.mavlink.fastcodec import DECODE_IDS, PACK_IDS

SETTINGS = settings(derandomize=True, database=None, deadline=None, max_examples=300,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
KEY = bytes(range(32))
V1_DECODE_IDS = sorted(i for i in DECODE_IDS if i < 256)

_INT_RANGES = {
    "uint8_t": (0, 2**8 - 1), "int8_t": (-(2**7), 2**7 - 1), "uint16_t": (0, 2**16 - 1),
    "int16_t": (-(2**15), 2**15 - 1), "uint32_t": (0, 2**32 - 1), "int32_t": (-(2**31), 2**31 - 1),
    "uint64_t": (0, 2**64 - 1), "int64_t": (-(2**63), 2**63 - 1),
}
F32_MAX = struct.unpack("<f", b"\xff\xff\x7f\x7f")[0]


def _v10() -> Any:
    """pymavlink's MAVLink 1 dialect module, imported without touching the process's MAVLINK20 choice
    (it reads no environment; checked here anyway)."""
    before = os.environ.get("MAVLINK20")
    from pymavlink.dialects.v10 import ardupilotmega as v10

    assert os.environ.get("MAVLINK20") == before == "1"
    assert mavutil.mavlink is mavlink and mavlink.WIRE_PROTOCOL_VERSION == "2.0"
    return v10


V10 = _v10()


# ---------------------------------------------------------------------------------------------------
# Comparison


def same(a: object, b: object) -> bool:
    """Equal values of the same type; floats by their bits (NaN payloads, -0.0), lists element-wise."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float) and isinstance(b, float):
        return struct.pack("<d", a) == struct.pack("<d", b)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def assert_same_message(fast: Any, ref: MAVLinkMessage) -> None:
    assert fast is not None, f"fastcodec did not decode {ref.get_type()}"
    for name in ref.fieldnames:
        assert same(getattr(fast, name), getattr(ref, name)), (name, getattr(fast, name), getattr(ref, name))
    for name in vars(ref):
        if name.endswith("_raw"):  # a char field's bytes, where pymavlink's field is str
            assert same(getattr(fast, name), getattr(ref, name)), (name, getattr(fast, name), getattr(ref, name))
    assert fast.get_type() == ref.get_type()
    assert fast.get_msgId() == ref.get_msgId()
    assert fast.get_srcSystem() == ref.get_srcSystem()
    assert fast.get_srcComponent() == ref.get_srcComponent()
    assert fast.get_seq() == ref.get_seq()
    assert bytes(fast.get_msgbuf()) == bytes(ref.get_msgbuf())
    assert vars(fast.get_header()) == vars(ref.get_header())
    assert fast.get_header() is fast.get_header()
    assert bytes(fast.get_payload()) == bytes(ref.get_payload())
    assert fast.get_crc() == ref.get_crc()
    assert fast._signed is ref._signed is False
    assert fast.get_signed() is False and fast.get_link_id() is None
    assert fast.get_fieldnames() == ref.get_fieldnames()
    assert str(fast) == str(ref)
    assert fast.msgname == ref.msgname
    assert fast.id == ref.id  # the message id, or RAW_IMU's field `id` in both


def decode_both(frame: bytes) -> tuple[Any, MAVLinkMessage]:
    receiver = mavlink.MAVLink(None)
    ref = receiver.decode(bytearray(frame))
    assert fastcodec.can_decode_fast(receiver)
    return fastcodec.decode(frame), ref


# ---------------------------------------------------------------------------------------------------
# Field values over the full wire range


def _value(ftype: str) -> st.SearchStrategy[Any]:
    if ftype in _INT_RANGES:
        lo, hi = _INT_RANGES[ftype]
        return st.one_of(st.sampled_from([lo, hi, 0, lo + 1, hi - 1]), st.integers(lo, hi))
    if ftype == "float":
        extremes = [math.nan, -math.nan, math.inf, -math.inf, F32_MAX, -F32_MAX, 1.4e-45, -0.0, 0.0]
        return st.one_of(st.sampled_from(extremes), st.floats(width=32))
    if ftype == "double":
        extremes = [math.nan, math.inf, -math.inf, 1.7976931348623157e308, 5e-324, -0.0, 0.0]
        return st.one_of(st.sampled_from(extremes), st.floats())
    raise AssertionError(f"no strategy for {ftype}")


def _zero(ftype: str) -> Any:
    return 0.0 if ftype in ("float", "double") else 0


@st.composite
def field_values(draw: st.DrawFn, pcls: Any) -> dict[str, Any]:
    """Every field of `pcls` (pymavlink's names); the wire-order tail is zeroed sometimes, so that
    pymavlink's MAVLink 2 zero-trimming cuts the payload."""
    out: dict[str, Any] = {}
    zero_from = draw(st.one_of(st.just(len(pcls.ordered_fieldnames)), st.integers(0, len(pcls.ordered_fieldnames))))
    for i, name in enumerate(pcls.fieldnames):
        ftype = pcls.fieldtypes[i]
        wire = pcls.orders[i]
        n = pcls.array_lengths[wire]
        if wire >= zero_from:
            out[name] = [_zero(ftype)] * n if n else _zero(ftype)
        else:
            out[name] = draw(st.lists(_value(ftype), min_size=n, max_size=n)) if n else draw(_value(ftype))
    return out


ids_ = st.integers(0, 255)


def sender(seq: int, sysid: int, compid: int, module: Any = mavlink) -> Any:
    mav = module.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.seq = seq
    return mav


# ---------------------------------------------------------------------------------------------------
# Decoding


def test_decode_ids_are_the_hot_messages() -> None:
    assert {mavlink.mavlink_map[i].msgname for i in DECODE_IDS} == {
        "HEARTBEAT", "SYSTEM_TIME", "SCALED_IMU", "RAW_IMU", "ATTITUDE", "LOCAL_POSITION_NED",
        "GLOBAL_POSITION_INT", "COMMAND_ACK", "TIMESYNC", "WHEEL_DISTANCE", "COMMAND_LONG", "MISSION_ACK",
        "SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT", "MANUAL_CONTROL", "COMMAND_INT",
        "MISSION_ITEM_INT", "NAV_CONTROLLER_OUTPUT", "POSITION_TARGET_LOCAL_NED", "POSITION_TARGET_GLOBAL_INT",
        "MISSION_ITEM_REACHED", "DISTANCE_SENSOR"}


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(sorted(DECODE_IDS)), seq=ids_, sysid=ids_, compid=ids_)
def test_decode_mavlink2_as_pymavlink(data: st.DataObject, msg_id: int, seq: int, sysid: int, compid: int) -> None:
    pcls = mavlink.mavlink_map[msg_id]
    frame = pcls(**data.draw(field_values(pcls))).pack(sender(seq, sysid, compid))
    assert_same_message(*decode_both(frame))


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(sorted(DECODE_IDS)), seq=ids_, sysid=ids_, compid=ids_,
       link_id=ids_, timestamp=st.integers(0, 2**48 - 1))
def test_decode_signed_as_pymavlink(data: st.DataObject, msg_id: int, seq: int, sysid: int, compid: int,
                                    link_id: int, timestamp: int) -> None:
    """A signed frame decodes as pymavlink decodes it on a link without a key: not `_signed`."""
    pcls = mavlink.mavlink_map[msg_id]
    mav = sender(seq, sysid, compid)
    mavutil.mavfile.setup_signing(types.SimpleNamespace(mav=mav), KEY, sign_outgoing=True,
                                  initial_timestamp=timestamp, link_id=link_id)
    frame = pcls(**data.draw(field_values(pcls))).pack(mav)
    assert frame[2] == mavlink.MAVLINK_IFLAG_SIGNED
    fast, ref = decode_both(frame)
    assert_same_message(fast, ref)
    assert fast.get_header().incompat_flags == 1


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(V1_DECODE_IDS), seq=ids_, sysid=ids_, compid=ids_)
def test_decode_mavlink1_from_v10_dialect(data: st.DataObject, msg_id: int, seq: int, sysid: int,
                                          compid: int) -> None:
    """MAVLink 1 frames as a MAVLink 1 sender packs them (no extension fields: they decode as zero)."""
    v1cls = V10.mavlink_map[msg_id]
    values = data.draw(field_values(mavlink.mavlink_map[msg_id]))
    frame = v1cls(**{k: values[k] for k in v1cls.fieldnames}).pack(sender(seq, sysid, compid, V10))
    assert frame[0] == mavlink.PROTOCOL_MARKER_V1
    assert_same_message(*decode_both(frame))


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(V1_DECODE_IDS), seq=ids_, sysid=ids_, compid=ids_)
def test_decode_mavlink1_with_extensions(data: st.DataObject, msg_id: int, seq: int, sysid: int,
                                         compid: int) -> None:
    """MAVLink 1 frames as pymavlink's MAVLink 2 dialect packs them with force_mavlink1 (whole payload)."""
    pcls = mavlink.mavlink_map[msg_id]
    frame = pcls(**data.draw(field_values(pcls))).pack(sender(seq, sysid, compid), force_mavlink1=True)
    assert frame[0] == mavlink.PROTOCOL_MARKER_V1
    assert_same_message(*decode_both(frame))


def _crc(data: bytes, extra: int) -> bytes:
    crc = mavlink.x25crc(data)
    crc.accumulate(bytes((extra,)))
    return struct.pack("<H", crc.crc)


def hand_frame(msg_id: int, payload: bytes, seq: int, sysid: int, compid: int, *, v1: bool = False,
               compat: int = 0, signature: bytes | None = None) -> bytes:
    extra = mavlink.mavlink_map[msg_id].crc_extra
    if v1:
        head = bytes((mavlink.PROTOCOL_MARKER_V1, len(payload), seq, sysid, compid, msg_id))
        return head + payload + _crc(head[1:] + payload, extra)
    flags = 0 if signature is None else mavlink.MAVLINK_IFLAG_SIGNED
    head = bytes((mavlink.PROTOCOL_MARKER_V2, len(payload), flags, compat, seq, sysid, compid,
                  msg_id & 0xFF, msg_id >> 8 & 0xFF, msg_id >> 16))
    return head + payload + _crc(head[1:] + payload, extra) + (signature or b"")


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(sorted(DECODE_IDS)), seq=ids_, sysid=ids_, compid=ids_,
       compat=ids_, signed=st.booleans())
def test_decode_any_payload_bytes(data: st.DataObject, msg_id: int, seq: int, sysid: int, compid: int,
                                  compat: int, signed: bool) -> None:
    """Any payload bits, any length up to 10 bytes beyond the layout (a newer dialect's extensions),
    any compat flags, MAVLink 1 or 2: the same message."""
    size = mavlink.mavlink_map[msg_id].unpacker.size
    v1 = msg_id < 256 and data.draw(st.booleans(), "v1")
    payload = data.draw(st.binary(min_size=0, max_size=min(255, size + 10)), "payload")
    signature = data.draw(st.binary(min_size=13, max_size=13), "signature") if signed and not v1 else None
    frame = hand_frame(msg_id, payload, seq, sysid, compid, v1=v1, compat=compat, signature=signature)
    fast, ref = decode_both(frame)
    assert_same_message(fast, ref)
    assert_same_message(fastcodec.decode(bytearray(frame)), ref)  # a bytearray frame works too


@pytest.mark.parametrize("msg_id", sorted(DECODE_IDS))
def test_decode_all_zero_fields_trimmed_to_one_byte(msg_id: int) -> None:
    """The shortest MAVLink 2 payload: pymavlink keeps one zero byte; the rest decodes as zero."""
    pcls = mavlink.mavlink_map[msg_id]
    values = {name: ([0] * pcls.array_lengths[pcls.orders[i]] if pcls.array_lengths[pcls.orders[i]] else 0)
              for i, name in enumerate(pcls.fieldnames)}
    frame = pcls(**values).pack(sender(1, 2, 3))
    assert frame[1] == 1
    assert_same_message(*decode_both(frame))


def test_decode_wheel_distance_types() -> None:
    """What the estimate core reads: a list of 16 Python floats (doubles on the wire), int count."""
    dist = [0.1 * i for i in range(16)]
    frame = mavlink.MAVLink_wheel_distance_message(123, 2, dist).pack(sender(7, 1, 1))
    msg = fastcodec.decode(frame)
    assert msg is not None and msg.get_type() == "WHEEL_DISTANCE" and msg.get_msgId() == 9000
    assert type(msg.distance) is list and msg.distance == dist  # type: ignore[attr-defined]
    assert type(msg.count) is int and msg.count == 2  # type: ignore[attr-defined]
    assert msg.get_seq() == 7 and msg.to_dict()["distance"] == dist


@SETTINGS
@given(msg_id=st.sampled_from(sorted(set(mavlink.mavlink_map))), data=st.data())
def test_generator_exact_for_every_dialect_message(msg_id: int, data: st.DataObject) -> None:
    """The code generator behind decode, on every message of the dialect (char fields, arrays of every
    type): any payload bytes decode as pymavlink decodes them. Guards adding an id to DECODE_IDS."""
    pcls = mavlink.mavlink_map[msg_id]
    cls = fastcodec._message_class(pcls)
    decoder = fastcodec._decoder(pcls, cls)
    payload = data.draw(st.binary(max_size=min(255, pcls.unpacker.size + 3)))
    frame = hand_frame(msg_id, payload, 1, 2, 3)
    ref = mavlink.MAVLink(None).decode(bytearray(frame))
    assert_same_message(decoder(frame, 10, len(payload), len(frame) - 2), ref)


def test_decode_falls_back_to_pymavlink() -> None:
    """None (the caller uses pymavlink) where fastcodec cannot answer as pymavlink would."""
    mav = sender(1, 2, 3)
    good = mavlink.MAVLink_attitude_message(1, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6).pack(mav)
    assert fastcodec.decode(good) is not None
    # another id
    assert fastcodec.decode(mavlink.MAVLink_sys_status_message(*[1] * 13).pack(mav)) is None
    # bad CRC: pymavlink raises, so the caller's pymavlink fallback drops it as before
    bad = bytearray(good)
    bad[12] ^= 0x40
    assert fastcodec.decode(bytes(bad)) is None
    with pytest.raises(mavlink.MAVError):
        mavlink.MAVLink(None).decode(bad)
    # length not the header's, unknown incompatibility flag, not a frame
    assert fastcodec.decode(good[:-1]) is None
    assert fastcodec.decode(good + b"\x00") is None
    flagged = bytearray(good)
    flagged[2] = 0x02
    assert fastcodec.decode(bytes(flagged)) is None
    assert fastcodec.decode(b"") is None and fastcodec.decode(b"\x00" * 20) is None
    # a link with a signing key keeps pymavlink (signature checks, allow_unsigned_callback)
    keyed = mavlink.MAVLink(None)
    mavutil.mavfile.setup_signing(types.SimpleNamespace(mav=keyed), KEY, sign_outgoing=False,
                                  initial_timestamp=1, link_id=0)
    assert not fastcodec.can_decode_fast(keyed)


# ---------------------------------------------------------------------------------------------------
# Packing


def _outcome(fn: Callable[[], bytes | None]) -> bytes | type[BaseException] | None:
    try:
        return fn()
    except (struct.error, OverflowError, ValueError, TypeError, IndexError) as exc:
        return type(exc)


def _pack_value(ftype: str) -> st.SearchStrategy[Any]:
    """Wire-range values, plus Python values pymavlink cannot pack (out of range, beyond float32)."""
    if ftype in _INT_RANGES:
        lo, hi = _INT_RANGES[ftype]
        return st.one_of(_value(ftype), st.sampled_from([lo - 1, hi + 1]))
    if ftype == "float":
        return st.one_of(_value(ftype), st.floats(), st.sampled_from([1e39, -3.5e38, F32_MAX * (1 + 2**-25)]))
    return _value(ftype)


@st.composite
def pack_values(draw: st.DrawFn, pcls: Any, valid: bool) -> dict[str, Any]:
    if valid:
        return draw(field_values(pcls))
    out: dict[str, Any] = {}
    for i, name in enumerate(pcls.fieldnames):
        n = pcls.array_lengths[pcls.orders[i]]
        value = _pack_value(pcls.fieldtypes[i])
        out[name] = draw(st.lists(value, min_size=n, max_size=n)) if n else draw(value)
    return out


def test_pack_ids() -> None:
    assert {mavlink.mavlink_map[i].msgname for i in PACK_IDS} == {
        "HEARTBEAT", "RC_CHANNELS_OVERRIDE", "COMMAND_LONG", "TIMESYNC", "ODOMETRY"}


def _reference(pcls: Any, values: dict[str, Any], seq: int, sysid: int, compid: int) -> Any:
    mav = sender(seq, sysid, compid)
    assert fastcodec.can_pack_fast(mav)
    return _outcome(lambda: pcls(**values).pack(mav))


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(sorted(PACK_IDS)), seq=ids_, sysid=ids_, compid=ids_,
       valid=st.booleans())
def test_pack_message_as_pymavlink(data: st.DataObject, msg_id: int, seq: int, sysid: int, compid: int,
                                   valid: bool) -> None:
    pcls = mavlink.mavlink_map[msg_id]
    values = data.draw(pack_values(pcls, valid))
    expected = _reference(pcls, values, seq, sysid, compid)
    if valid:
        assert isinstance(expected, bytes)
    msg = pcls(**values)
    assert _outcome(lambda: fastcodec.pack(msg, seq, sysid, compid)) == expected


def _field_packer(msg_id: int, values: dict[str, Any], seq: int, sysid: int, compid: int) -> bytes:
    if msg_id == mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE:
        chans = [values[f"chan{i}_raw"] for i in range(1, 19)]
        return fastcodec.pack_rc_channels_override(seq, sysid, compid, values["target_system"],
                                                   values["target_component"], chans)
    fn = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: fastcodec.pack_heartbeat,
          mavlink.MAVLINK_MSG_ID_TIMESYNC: fastcodec.pack_timesync,
          mavlink.MAVLINK_MSG_ID_ODOMETRY: fastcodec.pack_odometry}[msg_id]
    packed: bytes = fn(seq, sysid, compid, **values)  # type: ignore[operator]
    return packed


FIELD_PACK_IDS = sorted(PACK_IDS - {mavlink.MAVLINK_MSG_ID_COMMAND_LONG})


@SETTINGS
@given(data=st.data(), msg_id=st.sampled_from(FIELD_PACK_IDS), seq=ids_, sysid=ids_, compid=ids_,
       valid=st.booleans())
def test_field_packers_as_pymavlink(data: st.DataObject, msg_id: int, seq: int, sysid: int, compid: int,
                                    valid: bool) -> None:
    pcls = mavlink.mavlink_map[msg_id]
    values = data.draw(pack_values(pcls, valid))
    expected = _reference(pcls, values, seq, sysid, compid)
    if valid:
        assert isinstance(expected, bytes)
    assert _outcome(lambda: _field_packer(msg_id, values, seq, sysid, compid)) == expected


@pytest.mark.parametrize("msg_id", FIELD_PACK_IDS)
def test_pack_all_zero_is_one_payload_byte(msg_id: int) -> None:
    pcls = mavlink.mavlink_map[msg_id]
    values = {name: ([0] * pcls.array_lengths[pcls.orders[i]] if pcls.array_lengths[pcls.orders[i]] else 0)
              for i, name in enumerate(pcls.fieldnames)}
    frame = _field_packer(msg_id, values, 255, 1, 191)
    assert frame[1] == 1 and frame == pcls(**values).pack(sender(255, 1, 191))
    assert fastcodec.pack(pcls(**values), 255, 1, 191) == frame


def test_bridge_messages_pack_as_pymavlink() -> None:
    """The messages the bridge builds (rc_override, heartbeat, stop probe) as the cores build them."""
    from rover_bridge.command.outputs import rc_override

    msgs = [rc_override({1: 1500, 3: 1700}, 1, 1),
            mavlink.MAVLink_heartbeat_message(type=mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                              autopilot=mavlink.MAV_AUTOPILOT_INVALID, base_mode=0, custom_mode=0,
                                              system_status=mavlink.MAV_STATE_ACTIVE, mavlink_version=3),
            mavlink.MAVLink_timesync_message(tc1=0, ts1=123456789)]
    for seq, msg in enumerate(msgs):
        assert fastcodec.pack(msg, seq, 1, 191) == msg.pack(sender(seq, 1, 191))


def test_pack_falls_back_to_pymavlink() -> None:
    """Other types give None; a signing link is reported unfit (pymavlink signs)."""
    assert fastcodec.pack(mavlink.MAVLink_statustext_message(6, b"hi"), 0, 1, 1) is None
    mav = sender(0, 1, 1)
    assert fastcodec.can_pack_fast(mav)
    mavutil.mavfile.setup_signing(types.SimpleNamespace(mav=mav), KEY, sign_outgoing=True,
                                  initial_timestamp=1, link_id=0)
    assert not fastcodec.can_pack_fast(mav)
    with pytest.raises(ValueError):
        fastcodec.pack_rc_channels_override(0, 1, 1, 1, 1, [1500] * 8)
    with pytest.raises(ValueError):
        fastcodec.pack_odometry(0, 1, 1, 0, 0, 0, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.0, 0.0,
                                0.0, [0.0] * 21, [0.0] * 20)
