"""Scenario: a TOML timeline of events in simulated seconds since the emulator started.

```toml
[[event]]
type = "slip"            # a slip window on one wheel ("left", "right" or "both")
wheel = "left"
start_s = 2.0
end_s = 4.0
ratio = 0.4              # ground contact covers 40 % less than the wheel turned

[[event]]
type = "slip_patch"      # slippery ground: applies to a wheel whose contact point is inside
x_min_m = 1.0            # NED metres (x north, y east)
x_max_m = 2.0
y_min_m = -1.0
y_max_m = 1.0
ratio = 0.5
wheel = "both"           # optional, default both

[[event]]
type = "encoder_dropout" # encoder counts of this wheel are lost during the window
wheel = "right"
start_s = 1.0
end_s = 1.5

[[event]]
type = "load"            # a slope or a payload: the wheel reaches only (1 - fraction) of its speed
wheel = "both"           # optional, default both
start_s = 2.0
end_s = 5.0
fraction = 0.25          # [0, 1); overlapping loads multiply: (1 - f1) * (1 - f2)

[[event]]
type = "stall"           # the wheel is held still: speed 0, no encoder counts; afterwards it
wheel = "left"           # spins up from rest through the motor lag ("left", "right" or "both")
start_s = 3.0
end_s = 3.5

[[event]]
type = "reboot"          # the autopilot reboots (link silent, WHEEL_DISTANCE restarts at 0)
at_s = 5.0

[[event]]
type = "link_silence"    # nothing in either direction (a cable pulled)
start_s = 6.0
end_s = 7.0

[[obstacles]]            # a wall, a box: a polygon in NED metres (sitl/obstacles.py)
polygon = [[10.0, -5.0], [10.0, 5.0], [10.5, 5.0], [10.5, -5.0]]

[[obstacles]]            # a post
circle = [4.0, 3.0]
radius_m = 0.5
```
Obstacles are what the emulator's range sensors see (sitl/range_sensors.py) and what the truth measures
against (``Emulator.nearest_obstacle_m``, ``Emulator.collided``); the rover drives through them (no contact
physics: a collision is detected, not simulated).

``kind`` is accepted for ``type``, and ``duration_s`` for ``end_s`` (end = start + duration).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from sitl.config import ConfigError, read_toml
from sitl.obstacles import Shape, parse_obstacle

WHEELS = ("left", "right", "both")


@dataclass(frozen=True)
class SlipWindow:
    wheel: str
    start_s: float
    end_s: float
    ratio: float


@dataclass(frozen=True)
class SlipPatch:
    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float
    ratio: float
    wheel: str = "both"


@dataclass(frozen=True)
class EncoderDropout:
    wheel: str
    start_s: float
    end_s: float


@dataclass(frozen=True)
class LoadWindow:
    start_s: float
    end_s: float
    fraction: float
    wheel: str = "both"


@dataclass(frozen=True)
class StallWindow:
    wheel: str
    start_s: float
    end_s: float


@dataclass(frozen=True)
class RebootEvent:
    at_s: float


@dataclass(frozen=True)
class LinkSilence:
    start_s: float
    end_s: float


def _applies(event_wheel: str, wheel: str) -> bool:
    return event_wheel in ("both", wheel)


@dataclass(frozen=True)
class Scenario:
    slips: tuple[SlipWindow, ...] = ()
    patches: tuple[SlipPatch, ...] = ()
    dropouts: tuple[EncoderDropout, ...] = ()
    reboots: tuple[RebootEvent, ...] = ()
    silences: tuple[LinkSilence, ...] = ()
    loads: tuple[LoadWindow, ...] = ()
    stalls: tuple[StallWindow, ...] = ()
    obstacles: tuple[Shape, ...] = ()

    def slip_ratio(self, wheel: str, time_s: float, x_m: float, y_m: float) -> float:
        """Largest slip ratio acting on ``wheel`` whose contact point is at (x_m, y_m)."""
        ratio = 0.0
        for s in self.slips:
            if _applies(s.wheel, wheel) and s.start_s <= time_s < s.end_s:
                ratio = max(ratio, s.ratio)
        for p in self.patches:
            if _applies(p.wheel, wheel) and p.x_min_m <= x_m <= p.x_max_m and p.y_min_m <= y_m <= p.y_max_m:
                ratio = max(ratio, p.ratio)
        return ratio

    def speed_scale(self, wheel: str, time_s: float) -> float:
        """Factor on ``wheel``'s achieved speed from the active loads (1.0 without any)."""
        scale = 1.0
        for ld in self.loads:
            if _applies(ld.wheel, wheel) and ld.start_s <= time_s < ld.end_s:
                scale *= 1.0 - ld.fraction
        return scale

    def stalled(self, wheel: str, time_s: float) -> bool:
        return any(_applies(st.wheel, wheel) and st.start_s <= time_s < st.end_s for st in self.stalls)

    def encoder_ok(self, wheel: str, time_s: float) -> bool:
        return not any(_applies(d.wheel, wheel) and d.start_s <= time_s < d.end_s for d in self.dropouts)

    def link_silent(self, time_s: float) -> bool:
        return any(s.start_s <= time_s < s.end_s for s in self.silences)

    def reboots_between(self, after_s: float, until_s: float) -> int:
        """Number of reboot events with after_s < at_s <= until_s."""
        return sum(1 for r in self.reboots if after_s < r.at_s <= until_s)

    @classmethod
    def from_events(cls, events: Sequence[Mapping[str, Any]], source: str = "scenario") -> Scenario:
        problems: list[str] = []
        slips: list[SlipWindow] = []
        patches: list[SlipPatch] = []
        dropouts: list[EncoderDropout] = []
        reboots: list[RebootEvent] = []
        silences: list[LinkSilence] = []
        loads: list[LoadWindow] = []
        stalls: list[StallWindow] = []
        for i, raw in enumerate(events):
            where = f"event[{i}]"
            ev = _normalise(raw)
            try:
                kind = ev.get("type")
                args = {k: v for k, v in ev.items() if k != "type"}
                if kind == "slip":
                    slips.append(SlipWindow(**args))
                elif kind == "slip_patch":
                    patches.append(SlipPatch(**args))
                elif kind == "encoder_dropout":
                    dropouts.append(EncoderDropout(**args))
                elif kind == "reboot":
                    reboots.append(RebootEvent(**args))
                elif kind == "link_silence":
                    silences.append(LinkSilence(**args))
                elif kind == "load":
                    loads.append(LoadWindow(**args))
                elif kind == "stall":
                    stalls.append(StallWindow(**args))
                else:
                    problems.append(f"{where}: unknown type {kind!r}")
                    continue
            except TypeError as exc:
                problems.append(f"{where} ({ev.get('type')}): {exc}")
                continue
            problems.extend(f"{where}: {p}" for p in _check(ev))
        if problems:
            raise ConfigError(source, problems)
        return cls(
            tuple(slips),
            tuple(patches),
            tuple(dropouts),
            tuple(reboots),
            tuple(silences),
            tuple(loads),
            tuple(stalls),
        )


def _normalise(raw: Mapping[str, Any]) -> dict[str, Any]:
    """Accept the aliases ``kind`` (for type) and ``duration_s`` (for end_s)."""
    ev = dict(raw)
    if "kind" in ev and "type" not in ev:
        ev["type"] = ev.pop("kind")
    if "duration_s" in ev and "end_s" not in ev:
        start, duration = ev.get("start_s"), ev.pop("duration_s")
        numbers = all(isinstance(x, int | float) and not isinstance(x, bool) for x in (start, duration))
        ev["end_s"] = start + duration if numbers else duration
    return ev


def _check(ev: Mapping[str, Any]) -> list[str]:
    out: list[str] = []
    for key, value in ev.items():
        if key in ("type", "wheel"):
            continue
        if not isinstance(value, int | float) or isinstance(value, bool) or not math.isfinite(value):
            out.append(f"{key} must be a number, got {value!r}")
    if "wheel" in ev and ev["wheel"] not in WHEELS:
        out.append(f"wheel must be one of {WHEELS}, got {ev['wheel']!r}")
    if "ratio" in ev and isinstance(ev["ratio"], int | float) and not 0.0 <= ev["ratio"] < 1.0:
        out.append(f"ratio must be in [0, 1), got {ev['ratio']!r}")
    if "fraction" in ev and isinstance(ev["fraction"], int | float) and not 0.0 <= ev["fraction"] < 1.0:
        out.append(f"fraction must be in [0, 1) (1 would stop the wheel: use a stall), got {ev['fraction']!r}")
    if "start_s" in ev and "end_s" in ev and not out and ev["end_s"] <= ev["start_s"]:
        out.append("end_s must be after start_s")
    return out


def load_scenario(path: str | Path) -> Scenario:
    """Load a scenario TOML file (a list of ``[[event]]`` tables and of ``[[obstacles]]``)."""
    p = Path(path)
    data = read_toml(p)
    unknown = [k for k in data if k not in ("event", "obstacles")]
    if unknown:
        raise ConfigError(str(p), [f"unknown top-level key {k!r}" for k in unknown])
    events, raw_obstacles = data.get("event", []), data.get("obstacles", [])
    if not isinstance(events, list):
        raise ConfigError(str(p), ["'event' must be an array of tables ([[event]])"])
    if not isinstance(raw_obstacles, list):
        raise ConfigError(str(p), ["'obstacles' must be an array of tables ([[obstacles]])"])
    shapes = [parse_obstacle(raw) for raw in raw_obstacles]
    problems = [f"obstacles[{i}]: {s}" for i, s in enumerate(shapes) if isinstance(s, str)]
    if problems:
        raise ConfigError(str(p), problems)
    scenario = Scenario.from_events(events, source=str(p))
    return replace(scenario, obstacles=tuple(s for s in shapes if not isinstance(s, str)))
