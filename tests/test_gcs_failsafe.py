"""The bridge lets ArduPilot's GCS failsafe see a silent ground station (rover_bridge.command.gcs_failsafe): the
pure pieces by hand and by property, then the command core with messages and times in, exact messages out.
End to end against the emulator's failsafe: tests/test_gcs_failsafe_e2e.py."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_command_core import Rig, overrides, profile, texts

from rover_bridge.command.core import CommandState
from rover_bridge.command.gcs_failsafe import PARAM_NAMES, FailsafeParams, GcsSilence, Phase
from rover_bridge.command.param_reader import PARAM_ATTEMPTS, ParamReader
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Link, Outgoing, Reaction

MANUAL, HOLD, AUTO, RTL, SMART_RTL, GUIDED = 0, 4, 10, 11, 12, 15


def params_of(r: ParamReader) -> FailsafeParams | None:
    return FailsafeParams.from_values(r.values)
ON = FailsafeParams(enable=1, timeout_s=5.0)


# -- the rules, by hand ------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("params", "mode", "acts"), [
    (FailsafeParams(0), MANUAL, False), (ON, MANUAL, True), (ON, GUIDED, True), (ON, AUTO, True),
    (ON, SMART_RTL, True), (ON, RTL, False), (ON, HOLD, False), (FailsafeParams(1, 5.0, 1), HOLD, True),
    (FailsafeParams(2), AUTO, False), (FailsafeParams(2), MANUAL, True),
])
def test_the_bridge_pauses_where_ardupilots_failsafe_would_act(params: FailsafeParams, mode: int, acts: bool) -> None:
    assert params.fails_safe_in(mode) is acts  # Rover/failsafe.cpp failsafe_trigger's conditions


def test_a_silence_begins_at_the_timeout_and_ends_when_the_gcs_or_the_autopilot_says_so() -> None:
    s = GcsSilence()
    assert not s.silent(100.0, MANUAL, ON)  # never seen: ArduPilot never fails safe for it either
    s.seen(10.0, ON)
    assert not s.silent(14.999, MANUAL, ON) and s.silent(15.0, MANUAL, ON) and s.phase is Phase.SILENT
    assert s.seen(15.5, ON) and s.phase is Phase.WATCHING and not s.silent(20.4, MANUAL, ON)
    assert s.silent(20.5, MANUAL, ON)
    assert not s.on_mode(MANUAL) and s.on_mode(RTL) and s.phase is Phase.SPENT  # the failsafe's mode change
    assert not s.silent(60.0, RTL, ON) and not s.silent(60.0, MANUAL, ON)  # RTL drives on: not again until seen
    s.seen(61.0, ON)
    assert s.silent(66.0, MANUAL, ON) and s.autopilot_acted() and not s.silent(66.1, MANUAL, ON)  # FS_ACTION 0


def test_params_read_late_or_changed_move_the_deadline() -> None:
    s = GcsSilence()
    s.seen(0.0, None)
    assert not s.silent(100.0, MANUAL, None)  # not read yet: nothing to watch
    s.rearm(FailsafeParams(1, 20.0))
    assert not s.silent(19.9, MANUAL, FailsafeParams(1, 20.0)) and s.silent(20.0, MANUAL, FailsafeParams(1, 20.0))
    s.seen(30.0, FailsafeParams(1, 20.0))
    s.rearm(FailsafeParams(0))
    assert s.due_s == math.inf and not s.silent(100.0, MANUAL, FailsafeParams(0))


def param_value(name: str, value: float) -> mavlink.MAVLink_param_value_message:
    return mavlink.MAVLink_param_value_message(name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, 1000, 1)


def test_the_reader_asks_for_what_is_missing_a_few_times_then_stops() -> None:
    r = ParamReader(PARAM_NAMES)
    assert not r.due(0.0)
    r.restart(1.0)
    first = r.requests(1.0, 1, 1)
    assert [m.param_id for m in first] == ["FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_OPTIONS"]
    assert all(m.param_index == -1 and (m.target_system, m.target_component) == (1, 1) for m in first)
    assert r.on_param_value(param_value("FS_GCS_ENABLE", 1.0), 1.1) and params_of(r) == FailsafeParams(1, 5.0, 0)
    assert not r.on_param_value(param_value("FS_GCS_TIMEOUT", math.nan), 1.1)
    assert not r.on_param_value(param_value("X", 1), 1.1)
    assert not r.due(2.9) and r.due(3.0)
    assert [m.param_id for m in r.requests(3.0, 1, 1)] == ["FS_GCS_TIMEOUT", "FS_OPTIONS"]
    for k in range(PARAM_ATTEMPTS):
        r.requests(5.0 + 2 * k, 1, 1)
    assert not r.due(1000.0)  # PX4 has no such parameters: asked PARAM_ATTEMPTS times, then left alone
    r.on_param_value(param_value("FS_GCS_TIMEOUT", 12.5), 1000.0)
    assert params_of(r) == FailsafeParams(1, 12.5, 0)


def test_a_value_that_changes_or_comes_unasked_is_asked_again_and_the_autopilots_answer_replaces_it() -> None:
    r = ParamReader(PARAM_NAMES)
    r.restart(0.0)
    r.requests(0.0, 1, 1)
    for name, value in (("FS_GCS_ENABLE", 1.0), ("FS_GCS_TIMEOUT", 5.0), ("FS_OPTIONS", 0.0)):
        r.on_param_value(param_value(name, value), 0.05)  # the answers: taken, nothing more to ask
    assert params_of(r) == FailsafeParams(1, 5.0, 0) and r.requests(2.0, 1, 1) == [] and not r.due(1000.0)
    r.on_param_value(param_value("FS_GCS_TIMEOUT", 0.0), 10.0)  # one frame (a corrupted one?) changes it
    assert params_of(r) == FailsafeParams(1, 0.0, 0)  # taken at once (a GCS's PARAM_SET must act) ...
    assert r.due(10.0) and [m.param_id for m in r.requests(10.0, 1, 1)] == ["FS_GCS_TIMEOUT"]  # ... and asked
    r.on_param_value(param_value("FS_GCS_TIMEOUT", 7.0), 10.01)  # another change before the answer
    assert not r.due(10.09) and r.due(10.1)  # asked again, no sooner than PARAM_CONFIRM_S after the last request
    assert [m.param_id for m in r.requests(10.1, 1, 1)] == ["FS_GCS_TIMEOUT"]
    r.on_param_value(param_value("FS_GCS_TIMEOUT", 5.0), 10.12)  # the autopilot's answer: a change, asked again
    assert [m.param_id for m in r.requests(10.22, 1, 1)] == ["FS_GCS_TIMEOUT"]
    r.on_param_value(param_value("FS_GCS_TIMEOUT", 5.0), 10.24)  # said twice: confirmed
    assert params_of(r) == FailsafeParams(1, 5.0, 0) and r.requests(12.22, 1, 1) == [] and not r.due(1000.0)


def test_a_value_the_autopilot_does_not_confirm_is_dropped() -> None:
    r = ParamReader(PARAM_NAMES)
    r.restart(0.0)
    for k in range(PARAM_ATTEMPTS + 1):
        r.requests(2.0 * k, 1, 1)  # an autopilot with no such parameters (PX4): no answer, asking stops
    assert params_of(r) is None and not r.due(1000.0)
    r.on_param_value(param_value("FS_GCS_ENABLE", 1.0), 100.0)  # unasked: a forged or corrupted frame
    assert params_of(r) == FailsafeParams(1, 5.0, 0) and r.due(100.0)
    for k in range(PARAM_ATTEMPTS):
        assert [m.param_id for m in r.requests(100.0 + 2.0 * k, 1, 1)] == ["FS_GCS_ENABLE", "FS_GCS_TIMEOUT",
                                                                          "FS_OPTIONS"]
    assert r.requests(106.0, 1, 1) == [] and params_of(r) is None and not r.due(1000.0)  # not said again: dropped


def test_a_silence_that_the_parameters_no_longer_call_for_ends() -> None:
    s = GcsSilence()
    s.seen(10.0, FailsafeParams(1, 0.0))  # a forged FS_GCS_TIMEOUT 0: silent at once
    assert s.silent(10.0, MANUAL, FailsafeParams(1, 0.0))
    assert not s.silent(10.2, MANUAL, ON) and s.phase is Phase.WATCHING  # the real 5 s: not due yet
    assert s.silent(15.0, MANUAL, ON)  # when due, silent as ever
    s.seen(20.0, ON)
    assert s.silent(25.0, MANUAL, ON) and not s.silent(25.1, MANUAL, FailsafeParams(0))  # FS_GCS_ENABLE 0
    assert s.due_s == math.inf and not s.silent(100.0, MANUAL, FailsafeParams(0))
    s.rearm(FailsafeParams(1, 5.0))  # on again (the watch rearms on every value read)
    assert s.silent(100.0, MANUAL, FailsafeParams(1, 5.0))  # the GCS still unheard since 20 s: due again


# -- a property: silent only when ArduPilot would fail safe -------------------------------------------------------

events = st.lists(st.tuples(st.floats(0.0, 3.0), st.sampled_from(["seen", "mode", "acted", "tick"]),
                            st.sampled_from([MANUAL, HOLD, AUTO, RTL, GUIDED])), max_size=60)


@settings(derandomize=True, max_examples=300)
@given(events, st.sampled_from([0, 1, 2]), st.floats(0.5, 10.0), st.sampled_from([0, 1]))
def test_silent_only_after_the_timeout_where_ardupilot_would_act(evs: list[tuple[float, str, int]], enable: int,
                                                                  timeout_s: float, options: int) -> None:
    params = FailsafeParams(enable, timeout_s, options)
    s, t, mode, last_seen = GcsSilence(), 0.0, MANUAL, None
    for dt, kind, m in evs:
        t += dt
        if kind == "seen":
            s.seen(t, params)
            last_seen = t
        elif kind == "mode":
            s.on_mode(m)
            mode = m
        elif kind == "acted":
            s.autopilot_acted()
        was = s.phase
        if s.silent(t, mode, params) and was is not Phase.SILENT:
            assert enable != 0 and last_seen is not None and t - last_seen >= timeout_s
            assert params.fails_safe_in(mode)
        if s.phase is Phase.SILENT:
            assert last_seen is not None and t - last_seen >= timeout_s  # the GCS said nothing since


# -- the command core -------------------------------------------------------------------------------------------

class FsRig(Rig):
    mode = MANUAL  # the autopilot's heartbeats (run_until's too) keep the last mode given

    def heartbeat(self, t: float, armed: bool = True, mode: int | None = None) -> Reaction:
        self.mode = self.mode if mode is None else mode
        return super().heartbeat(t, armed, self.mode)

    def gcs_heartbeat(self, t: float, src: mavlink.MAVLink | None = None) -> None:
        msg = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
        self.feed(Link.GCS, self.wire(src or self.gcs, msg), t)

    def param(self, t: float, name: str, value: float) -> list[Outgoing]:
        return list(self.feed(Link.AUTOPILOT, self.wire(self.ap, param_value(name, value)), t).out)

    def statustext(self, t: float, text: str) -> None:
        msg = mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_WARNING, text.encode())
        self.feed(Link.AUTOPILOT, self.wire(self.ap, msg), t)

    def answer(self, t: float, enable: int, timeout_s: float = 5.0, options: int = 0) -> list[Outgoing]:
        return self.param(t, "FS_GCS_ENABLE", enable) + self.param(t, "FS_GCS_TIMEOUT", timeout_s) \
            + self.param(t, "FS_OPTIONS", options)


def fs_read(o: Outgoing) -> bool:
    """A PARAM_REQUEST_READ of the failsafe's (avoidance reads AVOID_* and FENCE_* beside them)."""
    return o.msg.get_type() == "PARAM_REQUEST_READ" and o.msg.param_id in PARAM_NAMES


def kinds(out: list[tuple[float, Outgoing]]) -> list[str]:
    """The kinds sent, the failsafe's parameter reads among them (not avoidance's)."""
    return [o.msg.get_type() for _t, o in out if o.msg.get_type() != "PARAM_REQUEST_READ" or fs_read(o)]


def test_the_first_heartbeat_asks_for_the_failsafe_parameters_as_the_bridge_itself() -> None:
    rig = FsRig(profile())
    rig.heartbeat(0.0, mode=MANUAL)
    asked = [(t, o) for t, o in rig.run_until(0.2, 0.0) if fs_read(o)]
    assert [o.msg.param_id for _t, o in asked] == ["FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_OPTIONS"]
    assert all((o.dest, o.src_system, o.src_component) == (Link.AUTOPILOT, 1, 191) for _t, o in asked)
    assert rig.answer(0.3, 1) and "RB: GCS failsafe 1 (5 s): overrides pause for it" in texts(rig.sent)
    assert not [o for _t, o in rig.run_until(10.0, 0.3) if fs_read(o)]


def test_a_silent_gcs_gets_neutral_release_then_nothing_until_the_autopilot_acts() -> None:
    rig = FsRig(profile())
    rig.heartbeat(0.0, mode=MANUAL)
    rig.answer(0.01, 1)
    rig.gcs_heartbeat(0.5)
    before = rig.run_until(5.45, 0.5)
    assert overrides(before) and rig.core.state is CommandState.IDLE
    at = rig.run_until(5.55, 5.45)  # the GCS's last word was at 0.5 s: silent from 5.5 s
    assert rig.core.state is CommandState.GCS_SILENT
    assert overrides(at)[-2:] == [(1500, 1500), (0, 0)]  # neutral, then both channels released
    assert "RB: GCS silent, overrides released for failsafe" in texts(at)
    assert rig.local(6.0, vx=1.0).out == ()  # a request is no heartbeat (nor for ArduPilot): refused, nothing sent
    assert rig.core.counters["dropped.gcs_silent"] == 1
    quiet = rig.run_until(12.0, 6.0)
    assert kinds(quiet) == []  # not one message from the override's id: ArduPilot can count to its failsafe
    rig.statustext(12.0, "GCS Failsafe")  # ArduPilot acted (FS_ACTION 0: no mode change)
    assert overrides(rig.run_until(12.2, 12.0)) and rig.core.state is CommandState.IDLE
    assert kinds(rig.run_until(30.0, 12.2)).count("RC_CHANNELS_OVERRIDE") > 300  # and not again while silent
    rig.gcs_heartbeat(30.0)
    rig.run_until(36.0, 30.0)
    assert rig.core.state is CommandState.GCS_SILENT
    rig.statustext(36.0, "Radio Failsafe")  # the GCS failsafe as ArduPilot often words it (gcs_failsafe)
    assert rig.core.state is CommandState.IDLE


def test_a_mode_change_ends_the_silence_and_the_gcs_coming_back_too() -> None:
    rig = FsRig(profile())
    rig.heartbeat(0.0, mode=MANUAL)
    rig.answer(0.01, 1)
    rig.gcs_heartbeat(0.5)
    rig.run_until(6.0, 0.5)
    assert rig.core.state is CommandState.GCS_SILENT
    rig.gcs_heartbeat(6.5)
    assert rig.core.state is CommandState.IDLE and overrides(rig.run_until(6.7, 6.5))
    rig.run_until(12.0, 6.7)
    assert rig.core.state is CommandState.GCS_SILENT
    rig.heartbeat(12.0, mode=HOLD)  # the failsafe's action
    assert rig.core.state is CommandState.HOLD and overrides(rig.run_until(12.5, 12.0))


def test_another_systems_heartbeat_is_not_the_gcs_and_enable_0_or_servo_mode_change_nothing() -> None:
    rig = FsRig(profile())
    rig.heartbeat(0.0, mode=MANUAL)
    rig.answer(0.01, 1)
    rig.gcs_heartbeat(0.5, src=mavlink.MAVLink(None, srcSystem=245, srcComponent=190))  # MAVSDK's id
    rig.run_until(20.0, 0.5)
    assert rig.core.state is CommandState.IDLE  # ArduPilot (MAV_GCS_SYSID 255) never saw a GCS either
    off = FsRig(profile())
    off.heartbeat(0.0, mode=MANUAL)
    off.answer(0.01, 0)
    off.gcs_heartbeat(0.5)
    assert kinds(off.run_until(20.0, 0.5)).count("RC_CHANNELS_OVERRIDE") == round(19.5 / 0.05)
    assert off.core.state is CommandState.IDLE and not texts(off.sent)[1:]  # said nothing new
    servo = FsRig(profile(output={"mode": "servo"}))
    servo.heartbeat(0.0, mode=MANUAL)
    assert "PARAM_REQUEST_READ" not in kinds(servo.run_until(1.0, 0.0))  # DO_SET_SERVO masks nothing


def test_fs_gcs_enable_2_keeps_driving_in_auto_and_rtl_always() -> None:
    for enable, mode in ((2, AUTO), (1, RTL)):
        rig = FsRig(profile())
        rig.heartbeat(0.0, mode=mode)
        rig.answer(0.01, enable)
        rig.gcs_heartbeat(0.5)
        rig.run_until(20.0, 0.5)
        assert rig.core.state is not CommandState.GCS_SILENT
        assert "gcs_failsafe.silent" not in rig.core.counters


def test_a_corrupted_fs_gcs_timeout_pauses_only_until_the_autopilot_answers_then_a_fresh_request_drives() -> None:
    rig = FsRig(profile())
    rig.heartbeat(0.0, mode=MANUAL)
    rig.answer(0.01, 1)
    rig.gcs_heartbeat(0.5)
    assert rig.local(0.6, vx=1.0).out and rig.core.state is CommandState.ACTIVE
    rig.param(0.7, "FS_GCS_TIMEOUT", 0.0)  # one frame from the autopilot's ids: ArduPilot would fail safe at once
    released = rig.run_until(0.75, 0.7)
    assert rig.core.state is CommandState.GCS_SILENT and overrides(released)[-1] == (0, 0)
    asked = [(t, o.msg.param_id) for t, o in released if fs_read(o)]
    assert asked == [(0.7, "FS_GCS_TIMEOUT")]  # the autopilot is asked at once
    rig.param(0.72, "FS_GCS_TIMEOUT", 5.0)  # its answer
    assert rig.core.state is CommandState.GCS_SILENT
    again = rig.run_until(0.85, 0.75)
    assert [(t, o.msg.param_id) for t, o in again if fs_read(o)] == \
        [(0.8, "FS_GCS_TIMEOUT")]  # changed once more: asked once more, PARAM_CONFIRM_S after the last request
    assert rig.core.state is CommandState.IDLE and overrides(again)  # 5 s since the GCS's last word: not yet
    rig.param(0.86, "FS_GCS_TIMEOUT", 5.0)  # said twice: confirmed, nothing more to ask
    assert rig.local(0.9, vx=1.0).out and rig.core.state is CommandState.ACTIVE  # a fresh request drives
    assert not [o for _t, o in rig.run_until(5.0, 0.9) if fs_read(o)]
    assert rig.core.state is not CommandState.GCS_SILENT
    rig.run_until(5.6, 5.0)
    assert rig.core.state is CommandState.GCS_SILENT  # the real timeout still holds: 5 s after 0.5 s


def test_the_parameters_are_read_again_after_the_autopilot_comes_back() -> None:
    rig = FsRig(profile())
    rig.heartbeat(0.0, mode=MANUAL)
    rig.answer(0.01, 1)
    rig.run_until(1.0, 0.01)
    later = rig.run_until(10.0, 5.0, heartbeat_every_s=None)  # silent autopilot: link lost
    rig.heartbeat(10.0, mode=MANUAL)
    again = [o.msg.param_id for _t, o in rig.run_until(10.2, 10.0) if fs_read(o)]
    assert "PARAM_REQUEST_READ" not in kinds(later) and again == ["FS_GCS_ENABLE", "FS_GCS_TIMEOUT", "FS_OPTIONS"]
