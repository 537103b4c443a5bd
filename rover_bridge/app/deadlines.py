"""Deadline and budget accounting for the loop's periodic outputs (pure: times in, counts and texts out).

The outputs accounted: the wheel overrides (RC_CHANNELS_OVERRIDE, or DO_SET_SERVO in servo mode), ODOMETRY
and the bridge's HEARTBEAT, each with its period. For each output the shell gives the time its first frame
was written and the time the loop's pass that wrote it began (its wake-up), on one clock.

Scheduled time: each output has a grid, as the cores keep theirs. The first output starts it; the next
grid point is the previous one plus the period. An output written at w is grid point g's (the next point)
when w >= g - early_s (early_s: how far ahead an output may leave and still count as that point's: ODOMETRY
may leave half a period early in a pass made anyway, the others never). One written before that is off the
grid (an answer to a request, a state change): it starts a new grid at w + period and is never late. One
written a period or more after g is g's, and the grid restarts at w + period (the cores restart theirs
after a stall rather than bursting the missed outputs). Only written times count, so the same accounting
of the frames as they arrive (a benchmark, an autopilot's log, a .tlog's stamps) finds the same outputs late.

Late: an output written more than deadline_fraction of the period after its grid point. Not the loop's
lateness, and so not counted: an output that a pass begun after its grid point did not send (its core had
nothing to send then: ODOMETRY before the estimate is ready, or a pause): the loop was on time.
Over budget: the pass that wrote the output worked (wake-up to the written frame) longer than
budget_fraction of the period, whether or not the output was on the grid.

The ground station hears of late outputs when they start (at the first one), while they go on at most
once per report_window_s and only when more came (the count and the worst over the last window), and
when a whole window has passed without one: "RB: overrides late: 7 in 10 s, worst 31 ms" ...
"RB: overrides on time again: 12 late in 34 s".
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from rover_bridge.app.composition import HEARTBEAT_PERIOD_S
from rover_bridge.estimate.publish import EARLY_FRACTION
from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink
from rover_bridge.params import Profile

OVERRIDES, ODOMETRY, HEARTBEAT = "overrides", "odometry", "heartbeat"
# Grid points are sums of floats here and in the cores: an output within this of its point is that point's.
GRID_TOLERANCE_S = 1e-6
_BY_ID = {mavlink.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE: OVERRIDES, mavlink.MAVLINK_MSG_ID_ODOMETRY: ODOMETRY,
          mavlink.MAVLINK_MSG_ID_HEARTBEAT: HEARTBEAT}


def output_of(msg: MAVLinkMessage) -> str | None:
    """Which periodic output a message the bridge sends belongs to (None: not one). Only the bridge's own
    messages are asked about: a HEARTBEAT it sends is its own."""
    msg_id = msg.get_msgId()
    if msg_id == mavlink.MAVLINK_MSG_ID_COMMAND_LONG:
        return OVERRIDES if msg.command == mavlink.MAV_CMD_DO_SET_SERVO else None  # servo mode
    return _BY_ID.get(msg_id)


@dataclass(frozen=True, slots=True)
class Schedule:
    """One periodic output: its period, and how early one may leave and still be its grid point's."""

    name: str
    period_s: float
    early_s: float = 0.0


def schedules(profile: Profile) -> tuple[Schedule, ...]:
    """The bridge's periodic outputs under `profile` (ODOMETRY only where it goes somewhere)."""
    out = [Schedule(OVERRIDES, 1.0 / profile.command.rate_hz), Schedule(HEARTBEAT, HEARTBEAT_PERIOD_S)]
    if profile.odometry.targets != "none":
        period = 1.0 / profile.odometry.rate_hz
        out.append(Schedule(ODOMETRY, period, EARLY_FRACTION * period))
    return tuple(out)


class OutputTiming:
    """One output's grid and counters (see the module docstring for what is counted)."""

    def __init__(self, schedule: Schedule, budget_fraction: float, deadline_fraction: float) -> None:
        self.schedule = schedule
        self.period_s = schedule.period_s
        self.budget_s = budget_fraction * schedule.period_s
        self.deadline_s = deadline_fraction * schedule.period_s
        self.next_s: float | None = None  # the next grid point
        self.sent = 0
        self.on_grid = 0  # outputs of a grid point (the others: first, off the grid, held back by their core)
        self.late = 0
        self.over_budget = 0
        self.worst_late_s = 0.0  # largest time past the grid point (of any on-grid output, late or not)
        self.worst_work_s = 0.0
        self.interval_late_s = self.interval_work_s = 0.0  # the same since the last log line

    def record(self, sent_s: float, pass_s: float, previous_pass_s: float = -math.inf) -> float | None:
        """Account one output written at sent_s in a pass that began at pass_s (after one that began at
        previous_pass_s); returns how far past its grid point it was written (None: not a grid point's)."""
        self.sent += 1
        work_s = sent_s - pass_s
        self.worst_work_s = max(self.worst_work_s, work_s)
        self.interval_work_s = max(self.interval_work_s, work_s)
        if work_s > self.budget_s:
            self.over_budget += 1
        g = self.next_s
        period = self.period_s
        if g is None or sent_s < g - self.schedule.early_s - GRID_TOLERANCE_S:
            self.next_s = sent_s + period  # first, or off the grid: a new grid
            return None
        self.next_s = g + period if sent_s - g < period else sent_s + period
        if previous_pass_s >= g:
            return None  # a pass after its grid point did not send it: its core held it back, the loop was on time
        self.on_grid += 1
        late_s = max(0.0, sent_s - g)
        self.worst_late_s = max(self.worst_late_s, late_s)
        self.interval_late_s = max(self.interval_late_s, late_s)
        if late_s > self.deadline_s:
            self.late += 1
        return late_s

    def take_interval(self) -> tuple[float, float]:
        """The worst time past schedule and the worst work since the last call."""
        worst = (self.interval_late_s, self.interval_work_s)
        self.interval_late_s = self.interval_work_s = 0.0
        return worst

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent, "on_grid": self.on_grid, "late": self.late, "over_budget": self.over_budget,
                "worst_late_ms": round(self.worst_late_s * 1e3, 3), "worst_work_ms": round(self.worst_work_s * 1e3, 3),
                "period_ms": round(self.period_s * 1e3, 3), "deadline_ms": round(self.deadline_s * 1e3, 3),
                "budget_ms": round(self.budget_s * 1e3, 3)}


class LateEpisodes:
    """When late outputs start, go on and stop, per output: the ground station's texts (module docstring)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._recent: deque[tuple[float, float]] = deque()  # (when, how late) within the last window
        self._since_s: float | None = None  # the episode's first late output
        self._count = 0  # late outputs in the episode
        self._next_report_s = math.inf  # inf: nothing new to say
        self._reported_s = -math.inf

    def late(self, now_s: float, late_s: float) -> None:
        self._recent.append((now_s, late_s))
        self._count += 1
        if self._since_s is None:
            self._since_s = now_s
            self._next_report_s = -math.inf  # said at the next poll
        elif self._next_report_s == math.inf:  # news since the last report: the next one a window after it
            self._next_report_s = self._reported_s + self.window_s

    def poll(self, name: str, now_s: float) -> str | None:
        recent = self._recent
        while recent and recent[0][0] <= now_s - self.window_s:
            recent.popleft()
        since = self._since_s
        if since is None:
            return None
        if not recent:  # a whole window without one
            text = f"RB: {name} on time again: {self._count} late in {now_s - since:.0f} s"
            self._since_s, self._count, self._next_report_s = None, 0, math.inf
            return text
        if now_s < self._next_report_s:
            return None
        self._reported_s, self._next_report_s = now_s, math.inf  # until another one comes
        worst_ms = max(late for _, late in recent) * 1e3
        return f"RB: {name} late: {len(recent)} in {self.window_s:.0f} s, worst {worst_ms:.0f} ms"

    @property
    def next_poll_s(self) -> float:
        """When poll may have something new to say without another late output."""
        if self._since_s is None:
            return math.inf
        end_of_quiet = self._recent[-1][0] + self.window_s if self._recent else -math.inf
        return min(self._next_report_s, end_of_quiet)


class Deadlines:
    """Every periodic output's accounting, the ground station's texts and the periodic log line."""

    def __init__(self, profile: Profile, outputs: tuple[Schedule, ...]) -> None:
        t = profile.timing
        self.outputs = {s.name: OutputTiming(s, t.budget_fraction, t.deadline_fraction) for s in outputs}
        self.episodes = {s.name: LateEpisodes(t.report_window_s) for s in outputs}
        self.log_interval_s = t.log_interval_s
        self._pass_s = -math.inf
        self._previous_pass_s = -math.inf
        self._next_poll_s = math.inf
        self._next_log_s: float | None = None
        self._logged: dict[str, tuple[int, int, int]] = {}  # (sent, late, over_budget) at the last log line

    def pass_began(self, now_s: float) -> None:
        self._previous_pass_s, self._pass_s = self._pass_s, now_s

    def sent(self, name: str, sent_s: float) -> None:
        out = self.outputs.get(name)
        if out is None:
            return
        late_s = out.record(sent_s, self._pass_s, self._previous_pass_s)
        if late_s is not None and late_s > out.deadline_s:
            self.episodes[name].late(sent_s, late_s)
            self._next_poll_s = -math.inf  # the pass that wrote it says so

    def poll(self, now_s: float) -> list[tuple[int, str, str]]:
        """The ground station's texts due now as (severity, rate-limit key, text); cheap when none is."""
        if now_s < self._next_poll_s:
            return []
        out = []
        for name, ep in self.episodes.items():
            text = ep.poll(name, now_s)
            if text is not None:
                ok = "on time" in text
                out.append((mavlink.MAV_SEVERITY_NOTICE if ok else mavlink.MAV_SEVERITY_WARNING,
                            f"timing.{name}.{'ok' if ok else 'late'}", text))
        self._next_poll_s = min(ep.next_poll_s for ep in self.episodes.values())
        return out

    def log_line(self, now_s: float) -> tuple[bool, str] | None:
        """Every log_interval_s: (any late since the last line, the line); None between them."""
        if self.log_interval_s <= 0.0:
            return None
        if self._next_log_s is None:
            self._next_log_s = now_s + self.log_interval_s
            return None
        if now_s < self._next_log_s:
            return None
        interval = now_s - self._next_log_s + self.log_interval_s
        self._next_log_s = now_s + self.log_interval_s
        parts = []
        any_late = False
        for name, out in self.outputs.items():
            sent0, late0, over0 = self._logged.get(name, (0, 0, 0))
            worst_late, worst_work = out.take_interval()
            late = out.late - late0
            any_late = any_late or late > 0
            parts.append(f"{name} {out.sent - sent0} sent, {late} late (worst {worst_late * 1e3:.1f} ms "
                         f"past schedule), {out.over_budget - over0} over budget (worst {worst_work * 1e3:.1f} ms)")
            self._logged[name] = (out.sent, out.late, out.over_budget)
        return any_late, f"timing over {interval:.0f} s: " + "; ".join(parts)

    def stats(self) -> dict[str, Any]:
        return {name: out.stats() for name, out in self.outputs.items()}


# A recorded log (.tlog) stamps every frame the bridge wrote, but not its passes: frames of one output
# closer than this are one output (written to each link, or servo mode's two commands, in one pass).
SAME_OUTPUT_S = 1e-3


class LogTiming:
    """The accounting of a recorded run from the bridge's own frames, fed one at a time in log order (a log
    streams: nothing is kept but the counters). Only deadlines: a log has no passes, so neither budgets nor
    held-back outputs (a pause of an output counts as late here)."""

    def __init__(self, profile: Profile) -> None:
        t = profile.timing
        self.outputs = {s.name: OutputTiming(s, t.budget_fraction, t.deadline_fraction) for s in schedules(profile)}
        self._last: dict[str, float] = {}

    def written(self, name: str, at_s: float) -> None:
        out = self.outputs.get(name)
        if out is None or at_s - self._last.get(name, -math.inf) < SAME_OUTPUT_S:
            return
        self._last[name] = at_s
        out.record(at_s, at_s)


def from_log(profile: Profile, written: Iterable[tuple[str, float]]) -> dict[str, OutputTiming]:
    """LogTiming over (output, time written) pairs in log order."""
    timing = LogTiming(profile)
    for name, at_s in written:
        timing.written(name, at_s)
    return timing.outputs


def summary_line(outputs: dict[str, OutputTiming]) -> str:
    """One line: per output, sent, late and the worst time past schedule."""
    return "; ".join(f"{name} {o.sent} sent, {o.late} late (worst {o.worst_late_s * 1e3:.1f} ms past schedule)"
                     for name, o in outputs.items() if o.sent)
