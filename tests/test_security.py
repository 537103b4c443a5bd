"""[security]: signed commands, replay protection, allow-list, key files, rate-limited reports and logs.

Frames are built with pymavlink's own signing (as a signing GCS would send them) and fed through the
parser of a real Endpoint with signing set up (the bytes the bridge would read), then into the whole
pure BridgeCore exactly as the Runner does (`Incoming(..., signed_ok=runner._signed_ok(ep, msg))`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from lockstep import Lockstep, free_udp_port

from rover_bridge.app import cli
from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.logs import LogRateLimit
from rover_bridge.app.loop import _signed_ok
from rover_bridge.errors import ConfigError
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.mavlink.gate import BAD_SIGNATURE, SOURCE_NOT_ALLOWED, UNSIGNED
from rover_bridge.mavlink.links import Endpoint
from rover_bridge.mavlink.signing import SignatureVerifier, carries_signature, key_from_bytes, load_key, passphrase_key
from rover_bridge.mavlink.wire import Incoming, Link, Outgoing
from rover_bridge.params import Profile, SecurityParams
from sitl import VehicleConfig

KEY = bytes(range(32))
WRONG_KEY = bytes(range(1, 33))
T0 = 100_000_000_000  # a signing timestamp (10 us units), the bridge's start
BODY_VEL = 0b0000_0101_1100_0111  # vx + yaw_rate
TRIM = 1500


def secured(require_signed: bool = True, allowed: tuple[str, ...] = ()) -> Profile:
    return dataclasses.replace(Profile(), security=SecurityParams(
        require_signed_commands=require_signed, key_file="/unused/in/the/pure/core", allowed_sources=allowed))


def signer(key: bytes | None, sysid: int = 255, compid: int = 190, timestamp: int = T0 + 1,
           link_id: int = 7) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = timestamp
        mav.signing.link_id = link_id
    return mav


def request(vx: float = 0.5) -> MAVLinkMessage:
    return mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, 8, BODY_VEL, 0, 0, 0, vx, 0, 0, 0, 0, 0,
                                                                 0, 0.0)


def vehicle_heartbeat() -> MAVLinkMessage:
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, mavlink.MAV_STATE_ACTIVE, 3)


class Rig:
    """The whole BridgeCore behind a GCS Endpoint with signing (parser only: bytes are fed, not received)."""

    def __init__(self, prof: Profile, key: bytes | None = KEY) -> None:
        self.core = BridgeCore(prof)
        self.ep = Endpoint(f"udpin:127.0.0.1:{free_udp_port()}", Link.GCS)
        self.verifier = SignatureVerifier(KEY, T0)
        if key is not None:
            self.ep.setup_signing(key, link_id=1, initial_timestamp=T0, verifier=self.verifier)
        self.ap = signer(None, 1, 1)
        self.t_s = 0.0
        self.out: list[Outgoing] = []
        self.core.handle(Incoming(Link.AUTOPILOT, self.decode_plain(vehicle_heartbeat().pack(self.ap))), 0.0)

    @staticmethod
    def decode_plain(frame: bytes) -> MAVLinkMessage:
        msg: MAVLinkMessage = mavlink.MAVLink(None).decode(bytearray(frame))
        return msg

    def feed(self, frame: bytes) -> list[bool]:
        """Feed GCS bytes; per decoded frame, whether the core consumed it (i.e. did not forward it)."""
        self.t_s += 0.01
        consumed = []
        for msg in self.ep.conn.mav.parse_buffer(frame) or []:
            assert msg.get_type() != "BAD_DATA"
            reaction = self.core.handle(Incoming(Link.GCS, msg, signed_ok=_signed_ok(self.ep, msg)), self.t_s)
            self.out += reaction.out
            consumed.append(reaction.consumed)
        return consumed

    def wheel_pwms(self) -> list[tuple[int, int]]:
        return [(o.msg.chan1_raw, o.msg.chan3_raw) for o in self.out if o.msg.get_type() == "RC_CHANNELS_OVERRIDE"]

    def statustexts(self) -> list[str]:
        return [o.msg.text for o in self.out if o.msg.get_type() == "STATUSTEXT"]

    @property
    def gate(self) -> dict[str, int]:
        return self.core.gate.counters

    def close(self) -> None:
        self.ep.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig(secured())
    yield r
    r.close()


def test_signed_request_is_accepted_and_drives(rig: Rig) -> None:
    assert rig.feed(request().pack(signer(KEY))) == [True]
    assert rig.core.command.counters.get("requests.accepted") == 1
    assert rig.wheel_pwms()[-1][0] > TRIM and rig.wheel_pwms()[-1][1] > TRIM
    assert rig.gate == {}


def test_unsigned_request_is_rejected_counted_reported_and_not_forwarded(rig: Rig) -> None:
    assert rig.feed(request().pack(signer(None))) == [True]  # consumed: never reaches the autopilot
    assert rig.gate == {f"rejected.{UNSIGNED}": 1}
    assert "requests.accepted" not in rig.core.command.counters
    assert all(p == (TRIM, TRIM) for p in rig.wheel_pwms())
    assert any("unsigned" in t for t in rig.statustexts())


def test_request_signed_with_the_wrong_key_is_rejected_as_bad_signature(rig: Rig) -> None:
    assert rig.feed(request().pack(signer(WRONG_KEY))) == [True]
    assert rig.gate == {f"rejected.{BAD_SIGNATURE}": 1}
    assert rig.verifier.counters["bad_signature"] == 1
    assert all(p == (TRIM, TRIM) for p in rig.wheel_pwms())


def test_a_tampered_signed_frame_is_rejected(rig: Rig) -> None:
    frame = bytearray(request().pack(signer(KEY)))
    frame[-1] ^= 0x01  # last signature byte
    rig.feed(bytes(frame))
    tampered_ts = bytearray(request().pack(signer(KEY, timestamp=T0 + 50)))
    tampered_ts[-8] ^= 0x01  # a timestamp byte: covered by the signature
    rig.feed(bytes(tampered_ts))
    assert rig.gate == {f"rejected.{BAD_SIGNATURE}": 2}
    assert "requests.accepted" not in rig.core.command.counters


def test_a_replayed_signed_frame_is_rejected(rig: Rig) -> None:
    frame = request().pack(signer(KEY))
    assert rig.feed(frame) == [True]
    assert rig.core.command.counters["requests.accepted"] == 1
    rig.feed(frame)  # the same bytes again: same timestamp
    older = request(0.9).pack(signer(KEY, timestamp=T0))  # a validly signed but older frame of the stream
    rig.feed(older)
    assert rig.core.command.counters["requests.accepted"] == 1
    assert rig.verifier.counters["replayed"] == 2
    assert rig.gate == {f"rejected.{BAD_SIGNATURE}": 2}


def test_a_frame_accepted_on_one_gcs_link_cannot_be_replayed_on_another() -> None:
    # One verifier for every GCS link (as `run` sets them up): the stream's timestamp is shared.
    first, second = Rig(secured()), Rig(secured(), key=None)
    try:
        second.verifier = first.verifier
        second.ep.setup_signing(KEY, link_id=2, initial_timestamp=T0, verifier=first.verifier)
        frame = request().pack(signer(KEY))
        assert first.feed(frame) == [True] and first.core.command.counters["requests.accepted"] == 1
        second.feed(frame)
        assert "requests.accepted" not in second.core.command.counters
        assert second.gate == {f"rejected.{BAD_SIGNATURE}": 1} and first.verifier.counters["replayed"] == 1
    finally:
        first.close()
        second.close()


def test_a_new_stream_more_than_a_minute_old_is_rejected(rig: Rig) -> None:
    rig.feed(request().pack(signer(KEY, timestamp=T0 - 61 * 100_000)))
    assert rig.verifier.counters["stale_new_stream"] == 1
    assert "requests.accepted" not in rig.core.command.counters


def test_a_forged_far_future_timestamp_does_not_lock_out_the_real_gcs(rig: Rig) -> None:
    # pymavlink's check_signature stores the timestamp before comparing the signature: one forged
    # frame stamped near 2^48 would make every later genuine frame "old". Ours checks the HMAC first.
    rig.feed(request().pack(signer(WRONG_KEY, timestamp=2**48 - 10)))
    assert rig.feed(request().pack(signer(KEY))) == [True]
    assert rig.core.command.counters["requests.accepted"] == 1

    stock = mavlink.MAVLink(None)  # the same two frames against pymavlink's own check: locked out
    stock.signing.secret_key, stock.signing.timestamp = KEY, T0
    stock.signing.allow_unsigned_callback = lambda _m, _i: True
    stock.decode(bytearray(request().pack(signer(WRONG_KEY, timestamp=2**48 - 10))))
    assert stock.decode(bytearray(request().pack(signer(KEY, timestamp=T0 + 5))))._signed is False


def _commands() -> list[MAVLinkMessage]:
    return [
        mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_command_int_message(1, 1, 0, mavlink.MAV_CMD_DO_SET_MODE, 0, 0, 1, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_set_mode_message(1, 1, 4),
        mavlink.MAVLink_rc_channels_override_message(1, 1, 2000, 65535, 2000, *[65535] * 5, *[0] * 10),
        mavlink.MAVLink_param_set_message(1, 1, b"ARMING_CHECK", 0.0, 9),
        mavlink.MAVLink_mission_item_int_message(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_mission_count_message(1, 1, 3, 0),
        mavlink.MAVLink_mission_clear_all_message(1, 1, 0),
        mavlink.MAVLink_request_data_stream_message(1, 1, 0, 0, 0),
        mavlink.MAVLink_manual_control_message(1, 800, 0, 500, 0, 0),
        mavlink.MAVLink_setup_signing_message(1, 1, [0] * 32, 0),
    ]


def test_every_command_type_from_the_gcs_needs_a_signature(rig: Rig) -> None:
    unsigned, signed_mav = signer(None), signer(KEY)
    for msg in _commands():
        assert rig.feed(msg.pack(unsigned)) == [True], msg.get_type()  # consumed: not forwarded
    assert rig.gate == {f"rejected.{UNSIGNED}": len(_commands())}
    for msg in _commands():
        if msg.get_type() in ("MANUAL_CONTROL",):
            continue  # a velocity request: consumed by the bridge itself
        assert rig.feed(msg.pack(signed_mav)) == [False], msg.get_type()  # signed: forwarded to the autopilot
    assert rig.gate == {f"rejected.{UNSIGNED}": len(_commands())}


def test_heartbeats_and_read_only_requests_may_stay_unsigned(rig: Rig) -> None:
    mav = signer(None)
    for msg in (mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3),
                mavlink.MAVLink_param_request_list_message(1, 1),
                mavlink.MAVLink_mission_request_list_message(1, 1, 0),
                mavlink.MAVLink_timesync_message(0, 123)):
        assert rig.feed(msg.pack(mav)) == [False], msg.get_type()
    assert rig.gate == {}


def test_unsigned_pose_reset_is_not_acted_on_signed_one_is(rig: Rig) -> None:
    reset = mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, 1.0, 2.0, 30.0, 0, 0, 0, 0)
    rig.feed(reset.pack(signer(None)))
    assert rig.core.estimate.reset_counter == 0
    rig.feed(reset.pack(signer(KEY)))
    assert rig.core.estimate.reset_counter == 1


def test_pose_reset_routed_through_the_unsigned_autopilot_link_is_refused(rig: Rig) -> None:
    reset = mavlink.MAVLink_command_long_message(1, 191, mavlink.MAV_CMD_USER_1, 0, 1.0, 2.0, 30.0, 0, 0, 0, 0)
    msg = rig.decode_plain(reset.pack(signer(None)))
    assert rig.core.handle(Incoming(Link.AUTOPILOT, msg, signed_ok=True), 1.0).consumed
    assert rig.core.estimate.reset_counter == 0
    assert rig.gate == {f"rejected.{UNSIGNED}": 1}


def test_badly_signed_frames_are_refused_even_when_signatures_are_not_required() -> None:
    r = Rig(secured(require_signed=False))
    try:
        assert r.feed(request().pack(signer(None))) == [True]  # unsigned: fine without require_signed
        assert r.core.command.counters["requests.accepted"] == 1
        r.feed(request().pack(signer(WRONG_KEY)))
        r.feed(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(signer(WRONG_KEY)))
        assert r.gate == {f"rejected.{BAD_SIGNATURE}": 2}
        assert r.core.command.counters["requests.accepted"] == 1
    finally:
        r.close()


def test_a_bad_signature_never_counts_as_signed_ok() -> None:
    # Whatever pymavlink's allow-unsigned callback lets through, signed_ok stays False unless verified.
    r = Rig(secured())
    try:
        for key in (WRONG_KEY, None):
            for msg in r.ep.conn.mav.parse_buffer(request().pack(signer(key))) or []:
                assert not _signed_ok(r.ep, msg)
        good = (r.ep.conn.mav.parse_buffer(request().pack(signer(KEY))) or [])[0]
        assert _signed_ok(r.ep, good) and carries_signature(good)
        good._signed = "yes"  # anything but the verifier's True is not trusted
        assert not _signed_ok(r.ep, good)
    finally:
        r.close()


def test_the_command_core_alone_is_as_strict() -> None:
    core = BridgeCore(secured())
    core.handle(Incoming(Link.AUTOPILOT, Rig.decode_plain(vehicle_heartbeat().pack(signer(None, 1, 1)))), 0.0)
    msg = Rig.decode_plain(request().pack(signer(None)))
    reaction = core.command.handle(Incoming(Link.GCS, msg, signed_ok=False), 0.1)  # bypassing the gate
    assert reaction.consumed and core.command.counters == {**core.command.counters, "rejected.unauthorised": 1}


# ------------------------------------------------------------------------------------ allow-list

def test_allowed_source_accepted_others_refused_and_reported_once_per_source() -> None:
    r = Rig(secured(require_signed=False, allowed=("255:190", "42:*")), key=None)
    try:
        assert r.feed(request().pack(signer(None, 255, 190))) == [True]
        assert r.feed(request().pack(signer(None, 42, 7))) == [True]
        assert r.core.command.counters["requests.accepted"] == 2
        for _ in range(50):
            r.feed(request().pack(signer(None, 255, 1)))  # right system, wrong component
            r.feed(request().pack(signer(None, 7, 190)))
            r.feed(mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(signer(None, 7, 190)))
        assert r.core.command.counters["requests.accepted"] == 2
        assert r.gate == {f"rejected.{SOURCE_NOT_ALLOWED}": 150}
        refused = [t for t in r.statustexts() if SOURCE_NOT_ALLOWED in t]
        assert len(refused) == 2 and any("255:1" in t for t in refused) and any("7:190" in t for t in refused)
        # Heartbeats from anyone still pass (the GCS must see the vehicle).
        assert r.feed(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(signer(None, 7, 190))) == [False]
    finally:
        r.close()


def test_rejection_reports_stay_bounded_under_a_flood_of_spoofed_sources() -> None:
    r = Rig(secured(require_signed=True), key=None)
    try:
        for sysid in range(1, 256):
            for compid in range(0, 256, 4):
                r.feed(request().pack(signer(None, sysid, compid)))
        assert r.gate[f"rejected.{UNSIGNED}"] == 255 * 64
        # The first 256 sources arrive within 2.56 s: at most the burst (3) plus 1 per second, then none.
        assert len(r.statustexts()) <= 3 + 3
        assert len(r.core.gate._reported) <= 256
        assert len(r.core.reporter.limiter._tokens) < 10
    finally:
        r.close()


def test_say_once_reports_stay_bounded_under_spoofed_sources_without_security() -> None:
    r = Rig(Profile(), key=None)
    try:
        for sysid in range(1, 256):
            for compid in range(0, 256, 8):
                r.feed(request(float("nan")).pack(signer(None, sysid, compid)))
        assert r.core.command.counters["rejected.non_finite"] == 255 * 32  # every one counted
        assert len(r.core.command._said) <= 1024
    finally:
        r.close()


# ------------------------------------------------------------------------------------- key files

def _write(path: Path, data: bytes, mode: int = 0o600) -> str:
    path.write_bytes(data)
    os.chmod(path, mode)
    return str(path)


def test_key_file_formats(tmp_path: Path) -> None:
    assert load_key(_write(tmp_path / "raw", KEY)) == KEY
    assert load_key(_write(tmp_path / "hex", KEY.hex().encode() + b"\n")) == KEY
    assert load_key(_write(tmp_path / "pass", b"correct horse battery\n")) == passphrase_key("correct horse battery")
    with pytest.raises(ConfigError):
        key_from_bytes(b"")
    with pytest.raises(ConfigError):
        key_from_bytes(b"two\nlines")


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o620, 0o602, 0o660])
def test_group_or_world_accessible_key_file_is_refused(tmp_path: Path, mode: int) -> None:
    path = _write(tmp_path / "key", KEY, mode)
    with pytest.raises(ConfigError, match="chmod 600"):
        load_key(path)


def test_missing_or_unreadable_key_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        load_key(str(tmp_path / "nope"))
    with pytest.raises(ConfigError):
        load_key(str(tmp_path))  # a directory
    if os.geteuid() != 0:  # root reads anything; the mode check above still applies to root
        with pytest.raises(ConfigError):
            load_key(_write(tmp_path / "locked", KEY, 0o000))


def test_run_refuses_to_start_with_an_exposed_key(tmp_path: Path, capsys: Any) -> None:
    path = _write(tmp_path / "key", KEY, 0o644)
    port = free_udp_port()
    code = cli.main(["run", "--params", "params/default.toml", "--autopilot", f"udpout:127.0.0.1:{port}",
                     "--gcs", "none", "--key-file", path, "--duration", "0.1"])
    assert code == 2
    assert "chmod 600" in capsys.readouterr().err
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o644  # never "fixed" behind the user's back
    # The CLI put the log rate limit on the handlers before anything ran.
    assert any(isinstance(f, LogRateLimit) for h in logging.getLogger().handlers for f in h.filters)


def test_frames_the_bridge_sends_to_the_gcs_are_signed() -> None:
    ep = Endpoint(f"udpin:127.0.0.1:{free_udp_port()}", Link.GCS, source_system=1, source_component=191)
    try:
        ep.setup_signing(KEY, link_id=3, initial_timestamp=T0, verifier=SignatureVerifier(KEY, T0))
        frame = ep.send(vehicle_heartbeat(), 1, 191)
        check = SignatureVerifier(KEY, T0)
        assert frame[2] & mavlink.MAVLINK_IFLAG_SIGNED and frame[-13] == 3
        assert check.check(frame, 1, 191)
        assert not SignatureVerifier(WRONG_KEY, T0).check(frame, 1, 191)
    finally:
        ep.close()


# ---------------------------------------------------------------------------------- log flooding

def test_log_rate_limit_bounds_a_flood_and_counts_what_it_dropped() -> None:
    flt = LogRateLimit(rate_per_s=2.0, burst=10.0)
    logger = logging.getLogger("rover_bridge.mavlink.links")
    passed = []
    for i in range(10_000):
        record = logger.makeRecord(logger.name, logging.DEBUG, __file__, 1, "%s: undecodable input dropped: %s",
                                   ("udpin", i), None)
        record.created = 1000.0 + i * 1e-3  # 10 s of a 1 kHz flood
        if flt.filter(record):
            passed.append(record.getMessage())
    assert len(passed) <= 10 + 2 * 10 + 1
    assert sum(flt.suppressed.values()) == 10_000 - len(passed)
    assert "similar suppressed" in passed[-1]
    for i in range(5000):  # distinct templates cannot grow the table without bound
        record = logger.makeRecord(logger.name, logging.INFO, __file__, 1, f"template {i}", (), None)
        record.created = 2000.0
        flt.filter(record)
    assert len(flt.limiter._last_s) <= flt.max_keys + 1


# ------------------------------------------------------------------------- end to end over loopback

def test_signed_gcs_drives_the_emulator_through_the_bridge_unsigned_one_cannot() -> None:
    ls = Lockstep(secured(), VehicleConfig(), seed=11)
    try:
        verifier = SignatureVerifier(KEY, T0)
        ls.gcs_endpoint.setup_signing(KEY, link_id=1, initial_timestamp=T0, verifier=verifier)
        ls.run_for(1.0)
        # Unsigned: the bridge refuses the requests, and forwards nothing the emulator would obey.
        ls.run_for(2.0, send=lambda: ls.send_body_velocity(0.5, 0.0))
        ls.gcs.mav.rc_channels_override_send(1, 1, 2000, 0, 2000, 0, 0, 0, 0, 0)
        ls.gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0)
        ls.run_for(0.5)
        assert abs(ls.emu.truth.v_m_s) < 1e-6
        assert ls.emu.armed  # the unsigned disarm never arrived
        assert ls.core.gate.counters[f"rejected.{UNSIGNED}"] >= 20
        assert ls.emu.counters.get("override_rejected_sysid", 0) == 0
        # The bridge's own frames to the GCS are signed.
        bridge_beats = [m for _, m in ls.view.of("HEARTBEAT") if m.get_srcComponent() == 191]
        assert bridge_beats and all(carries_signature(m) for m in bridge_beats)
        # The same GCS with the key: it drives.
        ls.gcs.setup_signing(KEY, sign_outgoing=True, allow_unsigned_callback=lambda _m, _i: True,
                             initial_timestamp=T0 + 1000, link_id=2)
        ls.run_for(3.0, send=lambda: ls.send_body_velocity(0.5, 0.0))
        assert ls.emu.truth.v_m_s == pytest.approx(0.5, abs=0.06)
        assert verifier.counters["good"] >= 25 and verifier.counters["bad_signature"] == 0
    finally:
        ls.close()
