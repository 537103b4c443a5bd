"""Malformed input: >100,000 random, truncated and mutated MAVLink frames into both links.

Bulk: a seeded mutator starts from valid frames of every message type the bridge handles (both
links, signed and unsigned) and flips, overwrites, truncates, inserts, deletes and splices bytes.
Each mutated datagram goes through the real shell (Runner.step -> Endpoint.read -> pymavlink's
parser as the Endpoint configures it -> BridgeCore.handle -> forward / send), with the socket I/O of the
two Endpoints replaced by a byte queue (a few thousand also go through real UDP sockets).
Structure: Hypothesis builds messages field by field (any bit pattern, NaN and infinities included)
and random byte strings, fed the same way through a fresh parser and BridgeCore.

Checked on every datagram: nothing escapes the loop; every wheel output the bridge sends is
neutral (trim) unless the core holds a valid non-zero request (only possible when a mutation leaves
a frame valid, counted and bounded below); the estimate stays finite; and every byte and frame is
accounted for: bytes fed == bytes in decoded frames + bytes in bad data + bytes still buffered;
frames delimited by the parser == Endpoint.rx_frames + rx_bad; decoded frames == consumed + forwarded.
"""

from __future__ import annotations

import math
import random
import socket
from collections.abc import Callable
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from lockstep import free_udp_port

from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.loop import Runner
from rover_bridge.command.setpoints import BodyVelocity
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.links import Endpoint
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile

TRIM = Profile().output.pwm_trim
LEFT, RIGHT = Profile().output.left_channel, Profile().output.right_channel
KEY = bytes(range(32))
NAN = float("nan")


# ----------------------------------------------------------------------------------- seed frames

def _signed(sysid: int, compid: int) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.signing.secret_key, mav.signing.sign_outgoing, mav.signing.timestamp = KEY, True, 1000
    return mav


def gcs_messages() -> list[MAVLinkMessage]:
    """Everything a GCS sends that the bridge acts on (zero velocity: a valid seed must not drive)."""
    spt = mavlink.MAVLink_set_position_target_local_ned_message
    out: list[MAVLinkMessage] = [
        spt(0, 1, 1, frame, mask, 0, 0, 0, 0.0, 0.0, 0, 0, 0, 0, 0, 0.0)
        for frame in (1, 7, 8, 9, 12) for mask in (0b0000_0101_1100_0111, 0b0000_1101_1100_0111, 4039)
    ]
    out += [mavlink.MAVLink_set_position_target_global_int_message(0, 1, 1, frame, 0b0000_1101_1100_0111, 0, 0, 0,
                                                                   0.0, 0.0, 0, 0, 0, 0, 0, 0)
            for frame in (0, 3, 5, 6, 10, 11)]
    out += [
        mavlink.MAVLink_manual_control_message(1, 0, 0, 500, 0, 0),
        mavlink.MAVLink_manual_control_message(1, 0x7FFF, 0, 500, 0, 0),
        mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, NAN, NAN, NAN, 0, 0, 0, 0),
        mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3),
        mavlink.MAVLink_param_request_list_message(1, 1),
        mavlink.MAVLink_request_data_stream_message(1, 1, 0, 4, 1),
    ]
    return out


def autopilot_messages(i: int) -> list[MAVLinkMessage]:
    """Autopilot telemetry at step i (time stamps and distances move forward like a real stream)."""
    t_ms = 1000 + 20 * i
    return [
        mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                          mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, mavlink.MAV_STATE_ACTIVE, 3),
        mavlink.MAVLink_attitude_message(t_ms, 0.0, 0.0, 0.1, 0.0, 0.0, 0.01),
        mavlink.MAVLink_scaled_imu_message(t_ms, 0, 0, -1000, 0, 0, 10, 0, 0, 0, 0),
        mavlink.MAVLink_raw_imu_message(t_ms * 1000, 0, 0, -1000, 0, 0, 10, 0, 0, 0, 0, 0),
        mavlink.MAVLink_wheel_distance_message(t_ms * 1000, 2, [0.001 * i, 0.001 * i] + [0.0] * 14),
        mavlink.MAVLink_system_time_message(1_700_000_000_000_000 + t_ms * 1000, t_ms),
        mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0, 0, 1, 191),
        mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_SET_SERVO, 4, 0, 0, 255, 191),
    ]


def seed_frames() -> tuple[list[bytes], list[bytes]]:
    gcs_plain, gcs_signed = mavlink.MAVLink(None, 255, 190), _signed(255, 190)
    gcs = [m.pack(mav) for m in gcs_messages() for mav in (gcs_plain, gcs_signed)]
    ap_mav, ap_signed = mavlink.MAVLink(None, 1, 1), _signed(1, 1)
    ap = [m.pack(mav) for i in range(0, 200, 40) for m in autopilot_messages(i) for mav in (ap_mav, ap_signed)]
    return gcs, ap


# ------------------------------------------------------------------------------------- mutator

class Mutator:
    """Seeded byte-level mutations of MAVLink frames."""

    def __init__(self, seed: int, pool: list[bytes]) -> None:
        self.rng = random.Random(seed)
        self.pool = pool

    def _rand(self, n: int) -> bytes:
        return bytes(self.rng.randrange(256) for _ in range(n))

    def one(self, frame: bytes) -> bytes:
        r, b = self.rng, bytearray(frame)
        op = r.randrange(12)
        if op == 0 and b:  # flip 1-3 bits
            for _ in range(r.randint(1, 3)):
                b[r.randrange(len(b))] ^= 1 << r.randrange(8)
        elif op == 1 and b:  # overwrite bytes
            for _ in range(r.randint(1, 4)):
                b[r.randrange(len(b))] = r.randrange(256)
        elif op == 2:  # truncate
            del b[r.randrange(len(b) + 1):]
        elif op == 3:  # insert
            pos = r.randrange(len(b) + 1)
            b[pos:pos] = self._rand(r.randint(1, 20))
        elif op == 4 and b:  # delete a slice
            pos = r.randrange(len(b))
            del b[pos:pos + r.randint(1, 8)]
        elif op == 5 and len(b) > 2:  # payload length field
            b[1] = r.choice([0, 1, b[1] - 1, b[1] + 1, 255, r.randrange(256)]) & 0xFF
        elif op == 6 and len(b) > 3:  # incompat / compat flags
            b[r.choice([2, 3])] = r.choice([0, 1, 2, 0x80, 0xFF, r.randrange(256)])
        elif op == 7:  # splice with another frame
            other = r.choice(self.pool)
            b = b[:r.randrange(len(b) + 1)] + bytearray(other[r.randrange(len(other) + 1):])
        elif op == 8:  # garbage, sometimes starting like a frame
            b = bytearray(r.choice([b"", b"\xfd", b"\xfe"]) + self._rand(r.randrange(0, 300)))
        elif op == 9 and len(b) > 9:  # message id bytes
            b[7 + r.randrange(3)] = r.randrange(256)
        elif op == 10:  # MAVLink 1 / 2 marker swap
            if b:
                b[0] = 0xFE if b[0] == 0xFD else 0xFD
        else:  # several frames in one datagram, one of them mutated
            b = bytearray(r.choice(self.pool)) + b + bytearray(r.choice(self.pool))
            if b:
                b[r.randrange(len(b))] ^= 0xFF
        return bytes(b)

    def datagram(self, frame: bytes) -> bytes:
        data = frame
        for _ in range(self.rng.choice([1, 1, 1, 2, 3])):
            data = self.one(data)
        return data


# --------------------------------------------------------------------------------------- oracle

class Oracle:
    """Checks every Outgoing the core produces."""

    def __init__(self, core: BridgeCore) -> None:
        self.core = core
        self.outputs = 0
        self.driving_allowed = 0  # datagrams after which the core held a valid non-zero request

    def request_nonzero(self) -> bool:
        """The core holds a valid request that may move a wheel (anything but a body-frame stop)."""
        req = self.core.command.request
        if req is None:
            return False
        if isinstance(req, BodyVelocity):
            return req.v_m_s != 0.0 or req.omega_rad_s != 0.0
        return True  # a heading request turns towards its heading even at zero speed

    def check(self, out: list[Outgoing]) -> None:
        allowed = self.request_nonzero() or self.core.command.state.value == "braking"
        for item in out:
            msg = item.msg
            kind = msg.get_type()
            if kind == "RC_CHANNELS_OVERRIDE":
                self.outputs += 1
                assert item.dest is Link.AUTOPILOT and item.src_system == 255
                for ch in range(1, 19):
                    value = getattr(msg, f"chan{ch}_raw")
                    if ch in (LEFT, RIGHT):
                        assert value in (TRIM, 0) or allowed, (ch, value)
                    else:
                        assert value == (65535 if ch <= 8 else 0), (ch, value)
            elif kind == "COMMAND_LONG":
                assert int(msg.command) != mavlink.MAV_CMD_DO_SET_SERVO  # rc_override profile
            elif kind == "ODOMETRY":
                values = [msg.x, msg.y, msg.z, *msg.q, msg.vx, msg.vy, msg.vz, msg.rollspeed, msg.pitchspeed,
                          msg.yawspeed, *msg.pose_covariance, *msg.velocity_covariance]
                assert all(math.isfinite(v) for v in values), msg
        pose = self.core.estimate.pose
        assert all(math.isfinite(v) for v in (pose.x_m, pose.y_m, pose.yaw_rad)), pose


# ------------------------------------------------------------------------------- byte-queue rig

class QueueLink:
    """Replaces an Endpoint's socket I/O with a byte queue; spies on pymavlink's parser to account."""

    def __init__(self, ep: Endpoint) -> None:
        self.ep = ep
        self.queue: list[bytes] = []
        self.written: list[bytes] = []
        self.fed_bytes = 0
        self.good_bytes = 0
        self.bad_bytes = 0
        self.results = 0
        self.raised = 0
        ep._udp = None  # no direct socket I/O (a listening UDP link's fast path): all of it through conn
        ep.conn.recv = self._recv
        ep.conn.write = self.written.append
        framer = ep.framer
        original: Callable[[], Any] = framer.next

        def spy() -> Any:
            try:
                item = original()
            except Exception:
                self.raised += 1
                raise
            if item is not None:
                self.results += 1
                good, chunk = item
                if good:
                    self.good_bytes += len(chunk)
                else:
                    self.bad_bytes += len(chunk)
            return item

        framer.next = spy  # type: ignore[method-assign]

    def _recv(self, n: int | None = None) -> bytes:
        return self.queue.pop(0) if self.queue else b""

    def push(self, data: bytes) -> None:
        self.fed_bytes += len(data)
        self.queue.append(data)

    def check_accounting(self) -> None:
        assert self.raised == 0  # the framer returns bad runs rather than raising
        buffered = self.ep.framer.buffered
        assert self.fed_bytes == self.good_bytes + self.bad_bytes + buffered, (
            self.fed_bytes, self.good_bytes, self.bad_bytes, buffered)
        assert self.ep.rx_frames + self.ep.rx_bad == self.results


class Rig:
    def __init__(self) -> None:
        self.core = BridgeCore(Profile())
        ids = {"source_system": 1, "source_component": 191}
        self.ap = Endpoint(f"udpin:127.0.0.1:{free_udp_port()}", Link.AUTOPILOT, **ids)
        self.gcs = Endpoint(f"udpin:127.0.0.1:{free_udp_port()}", Link.GCS, **ids)
        self.runner = Runner(self.core, self.ap, [self.gcs])
        self.oracle = Oracle(self.core)
        self.t_s = 0.0
        original = self.runner.send_all

        def recording_send_all(out: Any) -> None:
            self.oracle.check(list(out))
            original(out)

        self.runner.send_all = recording_send_all  # type: ignore[method-assign]

    def step(self, dt_s: float = 0.001) -> None:
        self.t_s = round(self.t_s + dt_s, 9)
        self.runner.step(self.t_s)
        if self.oracle.request_nonzero():
            self.oracle.driving_allowed += 1

    def close(self) -> None:
        self.runner.begin_stop(self.t_s)
        self.runner.close()


def test_100k_mutated_frames_into_both_links_no_crash_no_unsafe_output_all_accounted() -> None:
    rig = Rig()
    ap_q, gcs_q = QueueLink(rig.ap), QueueLink(rig.gcs)
    gcs_seeds, ap_seeds = seed_frames()
    mutator = Mutator(20261122, gcs_seeds + ap_seeds)
    ap_live = mavlink.MAVLink(None, 1, 1)
    fed = 0
    for i in range(56_000):
        if i % 20 == 0:  # a valid vehicle heartbeat now and then keeps the link state realistic
            ap_q.push(autopilot_messages(i)[0].pack(ap_live))
        ap_q.push(mutator.datagram(mutator.rng.choice(ap_seeds)))
        gcs_q.push(mutator.datagram(mutator.rng.choice(gcs_seeds)))
        fed += 2
        rig.step()
    rig.step(0.1)
    for q in (ap_q, gcs_q):
        q.check_accounting()
    assert fed >= 100_000
    decoded = rig.ap.rx_frames + rig.gcs.rx_frames
    assert decoded == rig.runner.consumed + rig.runner.forwarded  # one peer per side: one write per forward
    assert rig.ap.rx_bad > 20_000 and rig.gcs.rx_bad > 20_000  # the mutations did break frames
    for i in range(40):  # the flood over, only the vehicle's heartbeat: any request times out, neutral
        ap_q.push(autopilot_messages(i)[0].pack(ap_live))
        rig.step(0.1)
    assert rig.core.command.state.value == "idle"
    assert rig.oracle.outputs > 1000  # the output loop kept running (neutral) through the flood
    # A mutation can leave a frame valid (inserted bytes after it, a signature byte with no key set,
    # a 1-in-65536 CRC collision); with zero-velocity seeds that almost never means a non-zero request.
    assert rig.oracle.driving_allowed <= 200
    rig.close()
    last = [m for w in ap_q.written[-3:] for m in (mavlink.MAVLink(None).parse_buffer(w) or [])]
    release = [m for m in last if m.get_type() == "RC_CHANNELS_OVERRIDE"]
    assert release and release[-1].chan1_raw == 0 and release[-1].chan3_raw == 0
    assert last[-1].get_type() == "TIMESYNC" and last[-1].tc1 == 0  # the probe that confirms the stop


def test_mutated_frames_through_real_udp_sockets() -> None:
    rig = Rig()
    gcs_seeds, ap_seeds = seed_frames()
    mutator = Mutator(7, gcs_seeds + ap_seeds)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ap_addr = ("127.0.0.1", int(rig.ap.url.rsplit(":", 1)[1]))
    gcs_addr = ("127.0.0.1", int(rig.gcs.url.rsplit(":", 1)[1]))
    ap_live = mavlink.MAVLink(None, 1, 1)
    sent = 0
    try:
        for i in range(3000):
            if i % 20 == 0:
                sender.sendto(autopilot_messages(i)[0].pack(ap_live), ap_addr)
            for addr, seeds in ((ap_addr, ap_seeds), (gcs_addr, gcs_seeds)):
                data = mutator.datagram(mutator.rng.choice(seeds))
                if data:  # an empty datagram is nothing on the wire
                    sender.sendto(data, addr)
                    sent += 1
            rig.step()
        rig.step(0.1)
    finally:
        sender.close()
    assert sent > 5000
    assert rig.ap.rx_frames + rig.gcs.rx_frames == rig.runner.consumed + rig.runner.forwarded
    assert rig.ap.rx_bad + rig.gcs.rx_bad > 2000
    assert rig.oracle.outputs > 50 and rig.oracle.driving_allowed <= 20
    rig.close()


# ---------------------------------------------------------------------------------- Hypothesis

_FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)


def _fields(msg_class: Any) -> st.SearchStrategy[MAVLinkMessage]:
    """Any values the wire can carry for each field of `msg_class` (ints of their width, any float32)."""
    strategies = []
    for name, fmt in zip(msg_class.fieldnames, msg_class.fieldtypes, strict=True):
        length = msg_class.array_lengths[msg_class.ordered_fieldnames.index(name)]  # wire order
        if fmt == "float":
            base: st.SearchStrategy[Any] = _FLOATS
        elif fmt == "double":
            base = st.floats(allow_nan=True, allow_infinity=True)
        elif fmt == "char":
            base = st.binary(max_size=max(1, length))
        else:
            bits = int("".join(ch for ch in fmt if ch.isdigit()) or 8)
            signed = not fmt.startswith("uint")
            base = st.integers(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else st.integers(0, 2 ** bits - 1)
        if length and fmt != "char":
            strategies.append(st.lists(base, min_size=length, max_size=length))
        else:
            strategies.append(base)
    return st.tuples(*strategies).map(lambda values: msg_class(*values))


HANDLED = [mavlink.MAVLink_set_position_target_local_ned_message,
           mavlink.MAVLink_set_position_target_global_int_message, mavlink.MAVLink_manual_control_message,
           mavlink.MAVLink_command_long_message,
           mavlink.MAVLink_heartbeat_message, mavlink.MAVLink_attitude_message, mavlink.MAVLink_scaled_imu_message,
           mavlink.MAVLink_raw_imu_message, mavlink.MAVLink_wheel_distance_message,
           mavlink.MAVLink_system_time_message, mavlink.MAVLink_command_ack_message]


class PureRig:
    """A fresh BridgeCore behind a parser configured like the Endpoint's (robust parsing), no sockets."""

    def __init__(self) -> None:
        self.core = BridgeCore(Profile())
        self.oracle = Oracle(self.core)
        self.parsers = {link: mavlink.MAVLink(None) for link in Link}
        for p in self.parsers.values():
            p.robust_parsing = True
        ap = mavlink.MAVLink(None, 1, 1)
        self.feed(Link.AUTOPILOT, autopilot_messages(0)[0].pack(ap), 0.0)

    def feed(self, link: Link, data: bytes, now_s: float) -> int:
        msgs = self.parsers[link].parse_buffer(data) or []
        n = 0
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                continue
            n += 1
            self.oracle.check(list(self.core.handle(Incoming(link, msg), now_s).out))
        self.oracle.check(self.core.tick(now_s))
        return n


@settings(derandomize=True, max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.sampled_from(list(Link)), st.sampled_from(HANDLED).flatmap(_fields),
                          st.integers(0, 255), st.integers(0, 255)), min_size=1, max_size=6))
def test_any_field_values_of_handled_messages_never_crash_or_drive_unsafely(
        frames: list[tuple[Link, MAVLinkMessage, int, int]]) -> None:
    rig = PureRig()
    for i, (link, msg, sysid, compid) in enumerate(frames):
        data = msg.pack(mavlink.MAVLink(None, sysid, compid))  # every value here fits its wire type
        rig.feed(link, data, 0.05 * (i + 1))
        # Whatever arrived, a wheel may move only on a request the decoder accepted as finite.
        req = rig.core.command.request
        if req is not None:
            assert all(math.isfinite(float(v)) for v in (getattr(req, "v_m_s", 0.0), getattr(req, "omega_rad_s", 0.0),
                                                         getattr(req, "speed_m_s", 0.0),
                                                         getattr(req, "heading_cw_rad", 0.0)))


@settings(derandomize=True, max_examples=600, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(list(Link)), st.binary(max_size=300)), min_size=1, max_size=8))
def test_random_bytes_into_both_links_never_crash(chunks: list[tuple[Link, bytes]]) -> None:
    rig = PureRig()
    for i, (link, data) in enumerate(chunks):
        rig.feed(link, data, 0.01 * (i + 1))
    assert rig.core.command.state.value in ("idle", "waiting")
