"""rover_bridge.mavlink.framing against pymavlink's robust parser: the same frames and bad runs, any byte stream.

The shell delimits frames itself and decodes only what a core reads, so its counters and its
forwarding must agree with what pymavlink's parser would have made of the same bytes: every valid
frame (decoded or forwarded raw), every bad run, in the same order, however the bytes are chunked.
"""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.mavlink import framing
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.framing import Framer, crc_ok, msg_id

KEY = bytes(range(32))


def _sample_frames() -> list[bytes]:
    plain = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    signed = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    signed.signing.secret_key = KEY
    signed.signing.sign_outgoing = True
    signed.signing.link_id = 1
    v1 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    msgs: list[MAVLinkMessage] = [
        mavlink.MAVLink_heartbeat_message(10, 3, 0, 0, 4, 3),
        mavlink.MAVLink_wheel_distance_message(123456, 2, [1.5, 1.6] + [0.0] * 14),
        mavlink.MAVLink_attitude_message(1000, 0.1, 0.2, 0.3, 0.0, 0.0, -0.2),
        mavlink.MAVLink_sys_status_message(0x3F, 0x3F, 0x3F, 250, 12000, 150, 80, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_statustext_message(6, b"hello rover"),
        mavlink.MAVLink_param_value_message(b"RC1_MIN", 1000.0, 9, 900, 1),
    ]
    out = [m.pack(plain) for m in msgs] + [m.pack(signed) for m in msgs[:3]]
    out += [mavlink.MAVLink_heartbeat_message(10, 3, 0, 0, 4, 3).pack(v1)]
    # an id outside the dialect: pymavlink hands it on as MAVLink_unknown
    unknown = bytearray(msgs[0].pack(plain))
    unknown[7:10] = (0xFF, 0xFF, 0x00)
    return [*out, bytes(unknown)]


SAMPLES = _sample_frames()


def _reference(stream: bytes, cuts: list[int]) -> list[tuple[bool, bytes]]:
    """pymavlink's robust parser over the chunks: (valid, bytes) per frame or bad run."""
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True
    out: list[tuple[bool, bytes]] = []
    for chunk in _chunks(stream, cuts):
        m = mav.parse_char(chunk)
        while m is not None:
            if m.get_type() == "BAD_DATA":
                out.append((False, bytes(m.data)))
            else:
                out.append((True, bytes(m.get_msgbuf())))
            m = mav.parse_char(b"")
    return out


def _ours(stream: bytes, cuts: list[int]) -> tuple[list[tuple[bool, bytes]], Framer]:
    framer = Framer()
    out: list[tuple[bool, bytes]] = []
    for chunk in _chunks(stream, cuts):
        framer.feed(chunk)
        while (item := framer.next()) is not None:
            good, data = item
            out.append((good and crc_ok(data), data))
    return out, framer


def _chunks(stream: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    return [stream[a:b] for a, b in itertools.pairwise(points)]


@st.composite
def streams(draw: st.DrawFn) -> bytes:
    parts: list[bytes] = []
    for _ in range(draw(st.integers(1, 8))):
        kind = draw(st.sampled_from(["frame", "frame", "junk", "mutated", "truncated"]))
        frame = draw(st.sampled_from(SAMPLES))
        if kind == "frame":
            parts.append(frame)
        elif kind == "junk":
            parts.append(draw(st.binary(min_size=1, max_size=40)))
        elif kind == "truncated":
            parts.append(frame[: draw(st.integers(1, len(frame) - 1))])
        else:
            data = bytearray(frame)
            for _ in range(draw(st.integers(1, 3))):
                data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
            parts.append(bytes(data))
    return b"".join(parts)


@settings(max_examples=400, deadline=None)
@given(stream=streams(), cuts=st.lists(st.integers(0, 2000), max_size=6))
def test_same_frames_and_bad_runs_as_pymavlink(stream: bytes, cuts: list[int]) -> None:
    ours, framer = _ours(stream, cuts)
    assert ours == _reference(stream, cuts)
    assert framer.bytes_fed == len(stream) == framer.bytes_in_frames + framer.bytes_bad + framer.buffered


def test_every_sample_frame_is_valid_and_its_id_read() -> None:
    mav = mavlink.MAVLink(None)
    for frame in SAMPLES:
        assert crc_ok(frame)
        decoded = mav.decode(bytearray(frame))
        if frame is SAMPLES[-1]:
            assert msg_id(frame) == 0xFFFF and decoded.get_type().startswith("UNKNOWN")
        else:
            assert msg_id(frame) == decoded.get_msgId()


def test_a_flipped_payload_bit_fails_the_crc() -> None:
    for frame in SAMPLES[:-1]:  # the unknown id cannot be checked (no CRC_EXTRA), as in pymavlink
        bad = bytearray(frame)
        bad[len(bad) // 2] ^= 0x10
        assert not crc_ok(bytes(bad))


def test_the_pure_python_checksum_agrees_with_fastcrc(monkeypatch: pytest.MonkeyPatch) -> None:
    """fastcrc is a dependency, but a platform without its wheel falls back to pymavlink's own."""
    frames = SAMPLES[:-1] + [f[:10] + bytes([f[10] ^ 1]) + f[11:] for f in SAMPLES[:-1]]  # a payload bit
    fast = [crc_ok(f) for f in frames]
    monkeypatch.setattr(framing, "_mcrf4xx", None)
    assert [crc_ok(f) for f in frames] == fast
    assert fast.count(True) == len(SAMPLES) - 1  # the originals pass, every altered copy fails


@settings(max_examples=400, deadline=None)
@given(datagram=streams(), buffered=st.sampled_from([b"", b"\x00", SAMPLES[0][:5]]))
def test_a_whole_frame_datagram_skips_the_buffer_and_nothing_else(datagram: bytes, buffered: bytes) -> None:
    """Framer.whole (a listening UDP link's shortcut) takes a datagram exactly when feed() then next()
    would give that datagram back as one good frame and nothing left; it counts the same bytes."""
    fast, slow = Framer(), Framer()
    for framer in (fast, slow):
        framer.feed(buffered)
    frame = fast.whole(datagram)
    slow.feed(datagram)
    items = []
    while (item := slow.next()) is not None:
        items.append(item)
    one_good_frame = not buffered and items == [(True, datagram)] and slow.buffered == 0
    assert (frame is not None) == one_good_frame
    if frame is None:
        assert (fast.bytes_fed, fast.bytes_in_frames) == (len(buffered), 0)  # untouched: the caller feeds it
    else:
        assert frame is datagram
        assert (fast.bytes_fed, fast.bytes_in_frames, fast.bytes_bad, fast.buffered) == (
            slow.bytes_fed, slow.bytes_in_frames, slow.bytes_bad, slow.buffered)


def test_every_sample_frame_is_whole() -> None:
    for frame in SAMPLES:
        assert Framer().whole(frame) is frame
        assert Framer().whole(frame + b"\x00") is None and Framer().whole(frame[:-1]) is None
