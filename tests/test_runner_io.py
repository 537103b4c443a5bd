"""The shell's I/O economy over real loopback sockets: forwarded frames share datagrams, the
autopilot's telemetry is read in batches, a ground station's request still wakes the loop at once."""

from __future__ import annotations

import dataclasses
import math
import socket
import time
from collections.abc import Callable, Iterator

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.demo import free_udp_port
from rover_bridge.app.loop import AP_BATCH_MAX_FRAMES, Runner, arrival_time
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.framing import Framer
from rover_bridge.mavlink.links import MAX_WRITE_BYTES, Endpoint
from rover_bridge.mavlink.wire import Incoming, Link, Reaction
from rover_bridge.params import Profile

LOCAL = "127.0.0.1"
BATCH_MS = 40.0


def _telemetry(n: int) -> list[bytes]:
    """VFR_HUD frames from the autopilot (no core reads them: forwarded raw), distinct payloads."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return [bytes(mavlink.MAVLink_vfr_hud_message(0.01 * i, 0.0, i % 360, 0, 0.0, 0.0).pack(mav)) for i in range(n)]


class Rig:
    def __init__(self, batch_ms: float = BATCH_MS) -> None:
        profile = Profile()
        batched = dataclasses.replace(profile.mavlink, autopilot_batch_ms=batch_ms)
        profile = dataclasses.replace(profile, mavlink=batched)
        self.ap_port, self.gcs_port = free_udp_port(), free_udp_port()
        self.runner = Runner(BridgeCore(profile), Endpoint(f"udpin:{LOCAL}:{self.ap_port}", Link.AUTOPILOT),
                             [Endpoint(f"udpin:{LOCAL}:{self.gcs_port}", Link.GCS)])
        self.ap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gcs.settimeout(1.0)
        # Both peers introduce themselves (udpin learns where to send).
        self.to_ap(_telemetry(1)[0])
        gcs_hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
        self.gcs.sendto(gcs_hb.pack(mavlink.MAVLink(None, 255, 190)), (LOCAL, self.gcs_port))
        time.sleep(0.05)
        self.runner.step(time.monotonic())
        self.drain_gcs()  # the introduction, forwarded, and the bridge's first messages

    def drain_gcs(self) -> None:
        self.gcs.setblocking(False)
        try:
            while self.gcs.recv(65536):
                pass
        except BlockingIOError:
            pass
        self.gcs.settimeout(1.0)

    def to_ap(self, frame: bytes) -> None:
        self.ap.sendto(frame, (LOCAL, self.ap_port))

    def close(self) -> None:
        self.runner.close()
        self.ap.close()
        self.gcs.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    yield r
    r.close()


def _frames_in(datagram: bytes) -> list[bytes]:
    framer = Framer()
    framer.feed(datagram)
    out = []
    while (item := framer.next()) is not None:
        assert item[0]
        out.append(item[1])
    assert framer.buffered == 0
    return out


def test_frames_forwarded_in_one_pass_share_datagrams_in_order(rig: Rig) -> None:
    frames = _telemetry(61)[1:]  # 60 frames (not the introduction's), 1724 bytes: two datagrams' worth
    for f in frames:
        rig.to_ap(f)
    time.sleep(0.05)
    tx_before = rig.runner.autopilot.tx_frames, rig.runner.gcs[0].tx_frames
    rig.runner.step(time.monotonic())
    received: list[bytes] = []
    datagrams = 0
    while len(received) < len(frames):
        data = rig.gcs.recv(65536)
        assert len(data) <= MAX_WRITE_BYTES
        received += [f for f in _frames_in(data) if f[7] == mavlink.MAVLINK_MSG_ID_VFR_HUD]
        datagrams += 1
    assert received == frames  # byte for byte, in order
    assert datagrams == -(-sum(map(len, frames)) // MAX_WRITE_BYTES)
    assert rig.runner.gcs[0].tx_frames - tx_before[1] >= len(frames)  # counted per frame, not per datagram


def test_autopilot_telemetry_waits_for_its_batch_but_a_gcs_frame_wakes_at_once(rig: Rig) -> None:
    clock = time.monotonic
    rig.to_ap(_telemetry(1)[0])
    time.sleep(0.02)
    rig.runner.step(clock())  # reads the autopilot link: its batch time starts now
    read_at = clock()
    rig.to_ap(_telemetry(2)[1])
    rig.runner.next_deadline_s = clock() + 10.0  # no tick in the way: only the links can end the wait
    ready = rig.runner.wait(clock)
    waited_s = clock() - read_at
    assert rig.runner.autopilot in ready
    assert waited_s >= 0.8 * BATCH_MS * 1e-3  # not woken by the autopilot's datagram
    rig.runner.step(clock())
    rig.to_ap(_telemetry(3)[2])
    start = clock()
    rig.gcs.sendto(_telemetry(1)[0], (LOCAL, rig.gcs_port))  # anything from the GCS side
    rig.runner.next_deadline_s = clock() + 10.0
    ready = rig.runner.wait(clock)
    assert clock() - start < 0.5 * BATCH_MS * 1e-3
    assert rig.runner.gcs[0] in ready and rig.runner.autopilot in ready  # the batch is read on this wake-up


def test_a_silent_autopilot_link_is_watched_not_polled(rig: Rig) -> None:
    clock = time.monotonic
    time.sleep(BATCH_MS * 1e-3)  # the introduction's batch is over
    rig.runner.step(clock())  # nothing to read: no batch starts
    time.sleep(0.002)
    rig.to_ap(_telemetry(1)[0])
    start = clock()
    rig.runner.next_deadline_s = clock() + 10.0
    ready = rig.runner.wait(clock)
    assert clock() - start < 0.5 * BATCH_MS * 1e-3
    assert ready == [rig.runner.autopilot]


def test_zero_batch_wakes_for_every_autopilot_datagram() -> None:
    r = Rig(batch_ms=0.0)
    try:
        clock = time.monotonic
        r.to_ap(_telemetry(1)[0])
        time.sleep(0.01)
        r.runner.step(clock())
        r.to_ap(_telemetry(2)[1])
        start = clock()
        r.runner.next_deadline_s = clock() + 10.0
        ready = r.runner.wait(clock)
        assert clock() - start < 0.01 and r.runner.autopilot in ready
    finally:
        r.close()


def test_a_listening_link_reads_its_socket_and_answers_every_peer_it_heard() -> None:
    """udpin goes to the socket directly (not through mavudp.recv/write): it must still learn each peer
    as mavudp does, write to every one of them, and read nothing (no error) from an empty socket."""
    port = free_udp_port()
    ep = Endpoint(f"udpin:{LOCAL}:{port}", Link.GCS)
    ep.decode_only(frozenset())  # nothing decoded: frames come back as their bytes
    peers = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    try:
        assert ep.read() == []  # an empty socket: nothing, not an exception
        frames = _telemetry(3)
        peers[0].sendto(frames[0], (LOCAL, port))
        peers[1].sendto(frames[1] + frames[2], (LOCAL, port))  # two frames in one datagram
        time.sleep(0.05)
        assert ep.read() == frames
        assert ep.conn.clients == {(LOCAL, p.getsockname()[1]) for p in peers}
        hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
        sent = ep.send(hb, 1, 191)
        ep.queue_frame(frames[0])
        ep.flush()
        for p in peers:
            p.settimeout(1.0)
            assert p.recv(65536) == sent
            assert p.recv(65536) == frames[0]
        assert ep.read() == []
        assert (ep.rx_frames, ep.tx_frames) == (3, 2)
    finally:
        ep.close()
        for p in peers:
            p.close()


def _attitude(time_boot_ms: int) -> bytes:
    """An ATTITUDE from the autopilot: a frame the cores read (decoded and handed to the core)."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return bytes(mavlink.MAVLink_attitude_message(time_boot_ms, 0.0, 0.0, 0.1, 0.0, 0.0, 0.2).pack(mav))


def _warm_up_timestamps(sender: socket.socket, port: int, read: Callable[[], object]) -> None:
    """Linux turns receive timestamping on for the whole stack lazily (a static key, switched from a work
    queue after the first socket asks): a datagram that arrives before that is stamped when it is read.
    One datagram and a moment, so that what the test measures is the steady state the bridge runs in."""
    sender.sendto(b"\x00", (LOCAL, port))
    time.sleep(0.05)
    read()


def test_a_listening_link_knows_when_each_datagram_arrived() -> None:
    """The kernel's receive time of every frame, not the time it was read: a frame read 100 ms late
    carries its arrival, and frames of one datagram share it."""
    port = free_udp_port()
    ep = Endpoint(f"udpin:{LOCAL}:{port}", Link.AUTOPILOT)
    ep.decode_only(frozenset())
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert ep.receive_stamped
        _warm_up_timestamps(peer, port, ep.read)
        frames = _telemetry(3)
        # On loopback the kernel stamps the datagram inside the sender's sendto: between the clock read
        # before it and the one after (a host that stalls this process widens the window, never breaks it).
        first = time.time()
        peer.sendto(frames[0] + frames[1], (LOCAL, port))
        first_sent = time.time()
        time.sleep(0.1)
        second = time.time()
        peer.sendto(frames[2], (LOCAL, port))
        second_sent = time.time()
        time.sleep(0.05)
        read_wall = time.time()
        assert ep.read() == frames
        stamps = ep.rx_wall_s
        assert len(stamps) == 3 and stamps[0] == stamps[1]
        assert first - 0.001 <= stamps[0] <= first_sent + 0.001
        assert second - 0.001 <= stamps[2] <= second_sent + 0.001
        assert read_wall - stamps[2] >= 0.045  # the arrival, not the read
        assert ep.conn.clients == {(LOCAL, peer.getsockname()[1])}  # the peer learnt, as on recvfrom
        assert ep.read() == [] and ep.rx_wall_s == []
    finally:
        ep.close()
        peer.close()


def test_the_core_is_given_each_autopilot_frame_at_its_arrival_time(rig: Rig) -> None:
    """With receive times on (as `run` has them), a frame read late reaches the core at its arrival on
    the runner's clock; without, at the pass's time."""
    seen: list[float] = []
    handle = rig.runner.core.handle

    def spy(inc: Incoming, now_s: float) -> Reaction:
        if inc.msg.get_type() == "ATTITUDE":
            seen.append(now_s)
        return handle(inc, now_s)

    _warm_up_timestamps(rig.ap, rig.ap_port, lambda: rig.runner.step(time.monotonic()))
    rig.runner.core.handle = spy  # type: ignore[method-assign]
    rig.runner.receive_times = True
    clock = time.monotonic
    sent: list[tuple[float, float]] = []  # the clock before and after each send (the stamp lies between)
    for stamp_ms in (1000, 1030):
        before = clock()
        rig.to_ap(_attitude(stamp_ms))
        sent.append((before, clock()))
        time.sleep(0.03)
    time.sleep(0.03)
    step_s = clock()
    rig.runner.step(step_s)
    assert len(seen) == 2
    for t, (before, after) in zip(seen, sent, strict=True):
        assert before - 0.001 <= t <= after + 0.001
    assert step_s - seen[1] >= 0.05
    rig.runner.receive_times = False
    rig.to_ap(_attitude(1100))
    time.sleep(0.03)
    step_s = clock()
    rig.runner.step(step_s)
    assert seen[2] == step_s


def test_the_batch_is_not_applied_where_the_link_has_no_receive_times() -> None:
    """udpout (as serial and TCP) has no kernel receive times: its frames are read as they arrive, so
    the estimator's clock mapping never counts a batch's wait as latency."""
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind((LOCAL, 0))
    peer.settimeout(1.0)
    profile = Profile()
    profile = dataclasses.replace(profile, mavlink=dataclasses.replace(profile.mavlink, autopilot_batch_ms=BATCH_MS))
    ap = Endpoint(f"udpout:{LOCAL}:{peer.getsockname()[1]}", Link.AUTOPILOT)
    runner = Runner(BridgeCore(profile), ap, [])
    try:
        assert not ap.receive_stamped
        clock = time.monotonic
        hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
        ap.send(hb, 1, 191)  # the autopilot learns where the bridge is
        _data, bridge_addr = peer.recvfrom(65536)
        peer.sendto(_telemetry(1)[0], bridge_addr)
        time.sleep(0.01)
        runner.step(clock())
        assert ap.rx_frames == 1
        peer.sendto(_telemetry(2)[1], bridge_addr)
        start = clock()
        runner.next_deadline_s = clock() + 10.0
        ready = runner.wait(clock)
        assert clock() - start < 0.5 * BATCH_MS * 1e-3 and ap in ready
    finally:
        runner.close()
        peer.close()


@settings(max_examples=300, deadline=None)
@given(
    now=st.floats(0.0, 1e6),
    age_s=st.lists(st.one_of(st.floats(-10.0, 10.0), st.just(math.nan)), max_size=12),
    floor_back=st.floats(0.0, 1.0),
)
def test_arrival_times_stay_ordered_and_within_the_pass(now: float, age_s: list[float], floor_back: float) -> None:
    wall = 1.7e9
    received = [0.0 if math.isnan(a) else wall - a for a in age_s]
    floor = now - floor_back
    out = []
    for r in received:  # as Runner.step: each frame's time is the next one's floor
        out.append(arrival_time(now, wall, r, out[-1] if out else floor))
    assert all(floor <= t <= now for t in out)
    assert out == sorted(out)
    lo = floor
    for t, r in zip(out, received, strict=True):
        want = now if r == 0.0 else now - (wall - r)
        # The frame's own arrival where it is within bounds, else the nearest bound.
        assert t == pytest.approx(min(now, max(lo, want)), abs=1e-6)
        lo = t


def test_the_batch_shortens_under_a_flood_so_the_kernel_buffer_never_overflows(rig: Rig) -> None:
    """A batch lets frames pile up in the kernel's receive buffer; at a flood's rate 40 ms would be
    thousands of datagrams (dropped). Beyond AP_BATCH_MAX_FRAMES' worth at the link's recent rate the
    link is not batched."""
    clock = time.monotonic
    frames = _telemetry(200)
    # 2000 frames in 10 ms of the runner's time: a flood. The passes are stamped 1 ms apart (ending now), not
    # by the clock: on a loaded machine pushing them takes longer, and the rate the runner measures would be
    # the machine's, not the flood's.
    t0 = clock() - 0.010
    for k in range(10):
        for f in frames:
            rig.to_ap(f)
        rig.runner.step(t0 + 0.001 * k)
    rate_hz = rig.runner._ap_rate_hz
    assert rate_hz * BATCH_MS * 1e-3 > 4 * AP_BATCH_MAX_FRAMES  # the full batch would pile up far more
    rig.to_ap(frames[0])
    start = clock()
    rig.runner.next_deadline_s = clock() + 10.0
    ready = rig.runner.wait(clock)
    assert clock() - start < 0.5 * BATCH_MS * 1e-3 and rig.runner.autopilot in ready
