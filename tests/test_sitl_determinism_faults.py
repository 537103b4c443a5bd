"""Lockstep determinism, seeded fault injection, and scenario events of the sitl emulator."""

from __future__ import annotations

import math
import socket

import pytest

from sitl import Emulator, FaultConfig, LinkFaults, Scenario, VehicleConfig
from sitl.faults import FaultyLink
from sitl.mav import mavlink
from sitl.scenario import LinkSilence, RebootEvent

_ENC = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)


def override(ch1: int, ch3: int) -> mavlink.MAVLink_message:
    return _ENC.rc_channels_override_encode(1, 1, ch1, 65535, ch3, 65535, 65535, 65535, 65535, 65535)


def scripted_run(seed: int, vehicle: VehicleConfig | None = None) -> Emulator:
    """A fixed input sequence injected without sockets: drive, turn, spin, stop."""
    emu = Emulator(vehicle=vehicle or VehicleConfig(start_armed=True), seed=seed, record_sent=True)
    script = {0: (1800, 1800), 100: (1800, 1600), 250: (1900, 1100), 400: (1500, 1500)}
    current = script[0]
    for i in range(500):
        if i in script or i % 50 == 0:  # refresh like a companion would
            current = script.get(i, current)
            emu.handle_message(override(*current), src_system=255)
        emu.step(0.01)
    return emu


def test_same_seed_gives_identical_ground_truth_and_sensors() -> None:
    a, b = scripted_run(seed=7), scripted_run(seed=7)
    assert a.truth == b.truth
    assert a.physics_state == b.physics_state
    assert math.hypot(a.truth.x_m, a.truth.y_m) > 0.5 and a.truth.yaw_rad != 0.0
    assert [m.get_msgbuf() for _, m in a.sent_log or []] == [m.get_msgbuf() for _, m in b.sent_log or []]


def test_different_seed_differs_only_where_noise_matters() -> None:
    a, b = scripted_run(seed=7), scripted_run(seed=8)
    assert a.truth == b.truth  # the robot is noise-free
    assert a.physics_state.ahrs_yaw_rad != b.physics_state.ahrs_yaw_rad  # the gyro is not


def test_fault_link_drops_about_the_configured_fraction_reproducibly() -> None:
    def pattern(seed: int) -> list[bool]:
        link = FaultyLink(LinkFaults(loss_rate=0.2), seed=seed)
        out = []
        for i in range(5000):
            link.push(i.to_bytes(2, "big"), 0.0)
            out.append(bool(link.pop_due(0.0)))
        return out

    first = pattern(11)
    assert 0.18 < first.count(False) / len(first) < 0.22
    assert pattern(11) == first
    assert pattern(12) != first


def test_fault_link_delay_jitter_reorder_duplicate_corrupt() -> None:
    link = FaultyLink(LinkFaults(delay_s=0.1, jitter_s=0.02), seed=1)
    link.push(b"abc", 1.0)
    assert link.pop_due(1.099) == []
    assert link.pop_due(1.121) == [b"abc"]

    link = FaultyLink(LinkFaults(reorder_rate=0.3, reorder_delay_s=0.05), seed=2)
    for i in range(100):
        link.push(bytes([i]), i * 0.01)
    order = [d[0] for d in link.pop_due(10.0)]
    assert sorted(order) == list(range(100)) and order != list(range(100))

    link = FaultyLink(LinkFaults(duplicate_rate=1.0, corrupt_rate=1.0), seed=3)
    link.push(b"\x00" * 8, 0.0)
    got = link.pop_due(0.0)
    assert len(got) == 2 and all(g != b"\x00" * 8 and len(g) == 8 for g in got)
    assert link.counters.duplicated == 1 and link.counters.corrupted == 2


def test_fault_config_validation() -> None:
    with pytest.raises(ValueError, match="loss_rate"):
        LinkFaults(loss_rate=1.5)
    with pytest.raises(ValueError, match="delay_s"):
        LinkFaults(delay_s=-1.0)
    assert FaultConfig.symmetric(loss_rate=0.1).inbound == FaultConfig.symmetric(loss_rate=0.1).outbound


def test_outbound_loss_through_emulator_is_seeded() -> None:
    def sent(seed: int) -> int:
        emu = Emulator(faults=FaultConfig(outbound=LinkFaults(loss_rate=0.5)), seed=seed, record_sent=True)
        for _ in range(1000):
            emu.step(0.01)
        return emu.counters["fault_out_dropped"]

    dropped = sent(5)
    pushed = Emulator().counters["fault_out_pushed"]  # 0 without traffic
    assert pushed == 0
    assert 40 < dropped < 120  # about half of ~160 packets in 10 s
    assert sent(5) == dropped


def test_scenario_reboot_and_link_silence() -> None:
    scenario = Scenario(reboots=(RebootEvent(1.0),), silences=(LinkSilence(3.0, 4.0),))
    emu = Emulator(vehicle=VehicleConfig(start_armed=True), scenario=scenario, record_sent=True)
    emu.handle_message(override(1800, 1800), src_system=255)
    for _ in range(100):
        emu.step(0.01)
    assert emu.wheel_distances_m[0] > 0.3
    emu.step(0.01)
    assert emu.rebooting
    for _ in range(200):
        emu.step(0.01)
    assert not emu.rebooting
    assert emu.wheel_distances_m == (0.0, 0.0)  # restarted, and overrides were cleared
    assert emu.rc_inputs[1] == 1500
    assert emu.counters["reboots"] == 1
    times = [t for t, _ in emu.sent_log or []]
    assert not [t for t in times if 1.0 < t < 2.5]  # silent while rebooting
    assert not [t for t in times if 3.0 <= t < 4.0]  # scripted link silence
    assert [t for t in times if t > 4.0] == []  # nothing yet: run on
    for _ in range(150):
        emu.step(0.01)
    assert [t for t, _ in emu.sent_log or [] if t > 4.0]
    assert emu.counters["tx_dropped_silence"] > 0


def test_a_withheld_message_is_not_sent_while_the_rest_streams_on() -> None:
    emu = Emulator(vehicle=VehicleConfig(start_armed=True), record_sent=True)
    emu.withheld.add(mavlink.MAVLINK_MSG_ID_HEARTBEAT)  # the autopilot's heartbeat silent, nothing else
    for _ in range(300):
        emu.step(0.01)
    kinds = {m.get_type() for _, m in emu.sent_log or []}
    assert "HEARTBEAT" not in kinds and "ATTITUDE" in kinds
    assert emu.counters["tx_withheld"] == 4  # at 0, 1, 2 and 3 s: built as always, not sent
    emu.withheld.clear()
    for _ in range(100):
        emu.step(0.01)
    assert any(m.get_type() == "HEARTBEAT" for _, m in emu.sent_log or [])


def test_corrupted_inbound_datagrams_are_counted_not_obeyed() -> None:
    emu = Emulator(
        vehicle=VehicleConfig(start_armed=True), faults=FaultConfig(inbound=LinkFaults(corrupt_rate=1.0))
    )
    emu.open("udpin:127.0.0.1:0")
    sender = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for _ in range(20):
            sock.sendto(override(1900, 1900).pack(sender), emu.local_address)
            emu.step(0.01)
    emu.close()
    # One flipped byte never passes MAVLink's CRC-16 (it catches every burst up to 16 bits).
    assert emu.counters.get("override_accepted", 0) == 0
    assert emu.rc_inputs[1] == 1500
