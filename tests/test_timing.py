"""Deadlines and budgets of the periodic outputs (rover_bridge.app.deadlines), on a fake clock.

First the accounting alone (times in, counts and texts out), then through the shell in lockstep with the
emulator: a loop held back past an override's deadline is counted, said to the ground station when it
starts and when it stops, and shown in --stats-json and in a replay of the run's .tlog; outputs on time,
answers to requests and outputs a core held back are never counted late.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lockstep import Lockstep

from rover_bridge.app.commands.run import write_stats
from rover_bridge.app.deadlines import (
    HEARTBEAT,
    ODOMETRY,
    OVERRIDES,
    Deadlines,
    LateEpisodes,
    OutputTiming,
    Schedule,
    from_log,
    schedules,
)
from rover_bridge.app.replay import replay
from rover_bridge.errors import ConfigError
from rover_bridge.params import Profile, profile_from_dict
from sitl import VehicleConfig

P = 0.05  # the default override period (command.rate_hz = 20)


def timing(early_s: float = 0.0) -> OutputTiming:
    return OutputTiming(Schedule(OVERRIDES, P, early_s), budget_fraction=0.8, deadline_fraction=0.95)


def test_an_output_is_late_when_written_past_95_percent_of_the_period_after_its_grid_point() -> None:
    o = timing()
    assert o.record(1.0, 1.0) is None  # the first starts the grid: 1.05, 1.10, ...
    assert o.record(1.05 + 0.0474, 1.05) == pytest.approx(0.0474)  # just inside the 47.5 ms deadline
    assert o.late == 0
    # The grid does not move with a late output: the next point is 1.15, whatever 1.10's was.
    assert o.record(1.10 + 0.0476, 1.102) == pytest.approx(0.0476)
    assert o.late == 1 and o.on_grid == 2 and o.next_s == pytest.approx(1.15)
    assert o.record(1.151, 1.15) == pytest.approx(0.001) and o.late == 1
    assert o.worst_late_s == pytest.approx(0.0476)


def test_off_the_grid_outputs_start_a_new_grid_and_are_never_late() -> None:
    o = timing()
    o.record(1.0, 1.0)
    assert o.record(1.021, 1.02) is None  # an answer to a request, before 1.05: a new grid from it
    assert o.next_s == pytest.approx(1.071)
    assert o.record(1.08, 1.07) == pytest.approx(0.009) and o.on_grid == 1


def test_a_stall_longer_than_a_period_is_late_and_restarts_the_grid() -> None:
    o = timing()
    o.record(1.0, 1.0)
    assert o.record(1.301, 1.30) == pytest.approx(0.251)  # grid point 1.05, the loop stood for 0.25 s
    assert o.late == 1 and o.next_s == pytest.approx(1.351)  # restarted from the output, no burst
    assert o.record(1.351, 1.35) == 0.0 and o.late == 1


def test_an_output_a_pass_after_its_grid_point_did_not_send_was_held_back_not_late() -> None:
    o = timing()
    o.record(1.0, 1.0)
    # Passes ran at 1.06, 1.11, ... and sent nothing (ODOMETRY before the estimate was ready, say).
    assert o.record(1.40, 1.40, previous_pass_s=1.39) is None
    assert o.late == 0 and o.on_grid == 0 and o.next_s == pytest.approx(1.45)
    # Without a pass in between, the same output is the loop's lateness.
    o2 = timing()
    o2.record(1.0, 1.0)
    assert o2.record(1.40, 1.40, previous_pass_s=1.0) == pytest.approx(0.35) and o2.late == 1


def test_odometry_may_leave_early_in_its_window_and_stays_on_its_grid() -> None:
    o = OutputTiming(Schedule(ODOMETRY, 1 / 30, early_s=0.5 / 30), 0.8, 0.95)
    o.record(0.0, 0.0)
    assert o.record(0.025, 0.025) == 0.0  # 8 ms before 1/30: that grid point's, not late
    assert o.next_s == pytest.approx(2 / 30) and o.on_grid == 1
    assert o.record(0.045, 0.045) is None  # 22 ms early: off the grid
    assert o.next_s == pytest.approx(0.045 + 1 / 30)


def test_passes_that_work_longer_than_80_percent_of_the_period_are_over_budget() -> None:
    o = timing()
    o.record(1.0 + 0.039, 1.0)
    o.record(1.05 + 0.041, 1.05)  # 41 ms of work for a 40 ms budget
    assert o.record(1.099, 1.058) is None  # off the grid (before 1.10): the pass's work still counts
    assert o.over_budget == 2 and o.sent == 3 and o.worst_work_s == pytest.approx(0.041)


@settings(derandomize=True, max_examples=300, deadline=None)
@given(gaps=st.lists(st.floats(0.0, 0.2), min_size=1, max_size=60))
def test_late_means_written_past_the_deadline_after_the_previous_grid_point_plus_a_period(gaps: list[float]) -> None:
    """A restatement: each output's grid point is the previous point + P, or the output itself after a
    restart; the counter agrees with it output by output."""
    o = timing()
    t, g, late = 0.0, None, 0
    for gap in gaps:
        t += gap
        got = o.record(t, t)
        if g is None or t < g - 1e-6:
            assert got is None
            g = t + P
            continue
        assert got == pytest.approx(max(0.0, t - g))
        late += t - g > 0.95 * P
        g = g + P if t - g < P else t + P
    assert o.late == late


def test_late_episodes_are_said_when_they_start_while_they_go_on_and_when_they_stop() -> None:
    ep = LateEpisodes(window_s=10.0)
    assert ep.poll(OVERRIDES, 0.0) is None and ep.next_poll_s == math.inf
    ep.late(100.0, 0.031)
    assert ep.poll(OVERRIDES, 100.0) == "RB: overrides late: 1 in 10 s, worst 31 ms"  # at once
    for k in range(6):
        ep.late(101.0 + k, 0.02)
    assert ep.poll(OVERRIDES, 107.0) is None  # once per window at most
    assert ep.next_poll_s == pytest.approx(110.0)
    ep.late(109.0, 0.045)
    # The count and the worst of the last window: (100, 110].
    assert ep.poll(OVERRIDES, 110.0) == "RB: overrides late: 7 in 10 s, worst 45 ms"
    assert ep.poll(OVERRIDES, 118.9) is None
    # A whole window after the last one (at 109 s): over, with the episode's count.
    assert ep.poll(OVERRIDES, 119.0) == "RB: overrides on time again: 8 late in 19 s"
    assert ep.poll(OVERRIDES, 200.0) is None and ep.next_poll_s == math.inf
    assert all(len(text) <= 50 for text in ("RB: odometry late: 1234 in 600 s, worst 99999 ms",
                                            "RB: heartbeat on time again: 12345 late in 99999 s"))


def test_deadlines_log_a_line_per_interval_warning_only_when_something_was_late() -> None:
    profile = profile_from_dict({"timing": {"log_interval_s": 60.0}})
    d = Deadlines(profile, schedules(profile))
    assert set(d.outputs) == {OVERRIDES, HEARTBEAT, ODOMETRY}
    assert d.log_line(0.0) is None
    d.pass_began(1.0)
    d.sent(OVERRIDES, 1.0)
    d.pass_began(1.05)
    d.sent(OVERRIDES, 1.06)
    assert d.log_line(59.0) is None
    line = d.log_line(60.0)
    assert line is not None and not line[0]
    assert line[1].startswith("timing over 60 s: overrides 2 sent, 0 late (worst 10.0 ms past schedule), "
                              "0 over budget (worst 10.0 ms)")
    d.pass_began(61.0)
    d.sent(OVERRIDES, 61.01)  # 59.91 s after its grid point (1.10): late, said by the pass that wrote it
    assert d.poll(61.0) == [(4, "timing.overrides.late", "RB: overrides late: 1 in 10 s, worst 59910 ms")]
    assert d.poll(61.05) == []
    line = d.log_line(120.0)
    assert line is not None and line[0] and "overrides 1 sent, 1 late" in line[1]
    assert d.poll(71.0) == []  # a window after the late one: 71.01
    assert d.poll(71.01) == [(5, "timing.overrides.ok", "RB: overrides on time again: 1 late in 10 s")]
    assert d.log_line(170.0) is None
    off = profile_from_dict({"timing": {"log_interval_s": 0.0}})
    quiet = Deadlines(off, schedules(off))
    assert quiet.log_line(0.0) is None and quiet.log_line(1e6) is None


def test_the_profile_declares_the_fractions_and_checks_them() -> None:
    t = Profile().timing
    assert (t.budget_fraction, t.deadline_fraction) == (0.8, 0.95)
    with pytest.raises(ConfigError) as bad:
        profile_from_dict({"timing": {"budget_fraction": 0.9, "deadline_fraction": 0.5}})
    assert any("budget_fraction 0.9 is past deadline_fraction 0.5" in p for p in bad.value.problems)
    with pytest.raises(ConfigError) as bad:
        profile_from_dict({"timing": {"deadline_fraction": 1.5}})
    assert any("timing.deadline_fraction: 1.5 is out of range" in p for p in bad.value.problems)


# ------------------------------------------------------------------ through the shell, in lockstep


def _drive(lock: Lockstep, seconds: float) -> None:
    lock.run_for(seconds, send=lambda: lock.send_body_velocity(0.3, 0.0))


def _statustexts(lock: Lockstep) -> list[str]:
    return [m.text for _, m in lock.view.of("STATUSTEXT")]


def test_a_held_loop_is_counted_said_and_shown_in_the_stats_and_the_replay(tmp_path: Path) -> None:
    tlog = tmp_path / "run.tlog"
    lock = Lockstep(Profile(), VehicleConfig(start_armed=True), seed=3, tlog_path=str(tlog))
    try:
        _drive(lock, 3.0)
        before = lock.runner.timing.stats()
        assert before[OVERRIDES]["sent"] > 30 and before[ODOMETRY]["sent"] > 50 and before[HEARTBEAT]["sent"] >= 2
        assert all(s["late"] == 0 and s["over_budget"] == 0 for s in before.values()), before
        assert before[OVERRIDES]["on_grid"] > 20  # requests at 10 Hz, outputs at 20 Hz: both kinds were seen
        # The loop stands for 120 ms (a long computation elsewhere): the emulator and the GCS go on.
        for _ in range(12):
            lock.t_s = round(lock.t_s + lock.dt_s, 9)
            lock.emu.step(lock.dt_s)
        _drive(lock, 1.0)
        after = lock.runner.timing.stats()
        assert after[OVERRIDES]["late"] == 1 and after[OVERRIDES]["worst_late_ms"] > 47.5
        assert after[ODOMETRY]["late"] == 1 and after[HEARTBEAT]["late"] == 0
        texts = _statustexts(lock)
        said = [t for t in texts if t.startswith("RB: overrides late: 1 in 10 s, worst ")]
        assert len(said) == 1 and not any("on time again" in t for t in texts)
        # One pass works 45 ms by the loop's clock (over the 40 ms budget of a 20 Hz output).
        lock.runner._sent_clock = lambda: lock.t_s + 0.045
        lock.step()
        lock.runner._sent_clock = None
        assert lock.runner.timing.stats()[OVERRIDES]["over_budget"] + lock.runner.timing.stats()[ODOMETRY][
            "over_budget"] >= 1
        _drive(lock, 10.5)
        texts = _statustexts(lock)
        assert "RB: overrides on time again: 1 late in 10 s" in texts, texts
        assert sum(t.startswith("RB: overrides") for t in texts) == 2  # started, stopped: nothing in between
        stats_path = tmp_path / "stats.json"
        write_stats(str(stats_path), lock.runner)
        shown = json.loads(stats_path.read_text())["timing"]
        assert shown[OVERRIDES]["late"] == 1 and shown[OVERRIDES]["deadline_ms"] == pytest.approx(47.5)
    finally:
        lock.close()
    summary = replay(tlog, Profile()).summary()
    line = next(x for x in summary.splitlines() if x.startswith("timing (log stamps)"))
    # The log stamps the frames on the simulated clock: the same held pass, seen from the log alone.
    assert "overrides" in line and ", 1 late (worst" in line.split("overrides", 1)[1].split(";")[0], line


@pytest.mark.parametrize("every_s", [0.009, 0.03])
def test_answers_to_requests_are_off_the_grid_and_never_late(every_s: float) -> None:
    profile = dataclasses.replace(Profile(), command=dataclasses.replace(Profile().command, rate_hz=50.0))
    lock = Lockstep(profile, VehicleConfig(start_armed=True), seed=4, dt_s=0.003)
    try:
        # Outputs every 20 ms; a request every 9 ms (every override answers one: off the grid) or every 30 ms
        # (answers and periodic outputs alternate).
        lock.run_for(3.0, every_s=every_s, send=lambda: lock.send_body_velocity(0.4, 0.0))
        s = lock.runner.timing.stats()[OVERRIDES]
        assert s["sent"] == lock.core.command.counters["outputs.sent"] > 100
        assert s["late"] == 0 and s["worst_late_ms"] <= 3.0 + 1e-6, s  # a step of the simulated clock at most
        if every_s < 0.02:
            assert s["on_grid"] == 0
        else:
            assert 0.2 * s["sent"] < s["on_grid"] < 0.8 * s["sent"], s
    finally:
        lock.close()


def test_a_tlog_without_the_bridge_has_no_timing_line() -> None:
    assert from_log(Profile(), [])[OVERRIDES].sent == 0
