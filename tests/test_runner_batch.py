"""Runner.step with a frame budget (what run() uses so a flood cannot delay the control tick):
frames beyond the budget wait for the next pass, none is lost, and `backlog` says when to come back
without sleeping (frames already inside pymavlink's parser never wake select())."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest
from lockstep import free_udp_port

from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.loop import Runner
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.links import Endpoint
from rover_bridge.mavlink.wire import Link
from rover_bridge.params import Profile


def _frames(n: int) -> list[bytes]:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    out = []
    for i in range(n):
        out.append(bytes(mavlink.MAVLink_vfr_hud_message(0.1 * i, 0.0, 0, 0, 0.0, 0.0).pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    return out


@pytest.fixture
def rig() -> Iterator[tuple[Runner, socket.socket, int]]:
    port = free_udp_port()
    ap = Endpoint(f"udpin:127.0.0.1:{port}", Link.AUTOPILOT)
    runner = Runner(BridgeCore(Profile()), ap, [])
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield runner, sender, port
    sender.close()
    runner.close()


def test_frames_beyond_the_budget_wait_for_the_next_pass(rig: tuple[Runner, socket.socket, int]) -> None:
    runner, sender, port = rig
    for frame in _frames(5):
        sender.sendto(frame, ("127.0.0.1", port))  # loopback: queued before sendto returns
    seen = []
    for t in (0.0, 0.01, 0.02):
        runner.step(t, max_frames=2)
        seen.append((runner.autopilot.rx_frames, runner.backlog))
    assert seen == [(2, True), (4, True), (5, False)]


def test_frames_buffered_in_the_parser_are_not_stranded(rig: tuple[Runner, socket.socket, int]) -> None:
    runner, sender, port = rig
    sender.sendto(b"".join(_frames(5)), ("127.0.0.1", port))  # one datagram, five frames
    runner.step(0.0, max_frames=2)
    assert (runner.autopilot.rx_frames, runner.backlog) == (2, True)
    runner.step(0.01, max_frames=2)
    runner.step(0.02, max_frames=2)
    assert (runner.autopilot.rx_frames, runner.backlog, runner.autopilot.rx_bad) == (5, False, 0)


def test_without_a_budget_step_drains_everything(rig: tuple[Runner, socket.socket, int]) -> None:
    runner, sender, port = rig
    for frame in _frames(50):
        sender.sendto(frame, ("127.0.0.1", port))
    runner.step(0.0)
    assert (runner.autopilot.rx_frames, runner.backlog) == (50, False)
