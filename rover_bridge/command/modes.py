"""Which driver holds the wheels in which autopilot mode (pure): the [modes] table, and saying when it changes.

As ArduPilot Rover picks one Mode class per mode (Rover/mode.h), the bridge picks its drivers by the
autopilot's mode (HEARTBEAT custom_mode, or a GCS's change the autopilot has accepted but not yet reported):

- `gcs`: a ground station's velocity requests and MANUAL_CONTROL (MANUAL, ACRO, STEERING, GUIDED);
- `targets`: the bridge's position targets (GUIDED);
- `autopilot`: the autopilot's own navigation, its per-wheel demand through the bridge's pipeline (LOITER,
  FOLLOW, DOCK, CIRCLE, AUTO, RTL, SMART_RTL): missions, return home, and the fence and failsafe actions that
  switch to them;
- `stop`: brake to a stop and hold neutral (HOLD: also what fence and failsafe actions may switch to).
A mode in no list stops too (SIMPLE, INITIALISING, anything unknown): the bridge drives only where it knows
who should. A driver whose mode no longer lists it loses the wheels and they brake through the limiter
until the driver the new mode lists takes them (from the limiter's state: no step).

When the autopilot's navigation takes the wheels, or gives them back, the log and a STATUSTEXT say so
(rate-limited); changes among the bridge's own modes say nothing new (their requests and states do).
"""

from __future__ import annotations

from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.report import Reporter
from rover_bridge.mavlink.wire import Outgoing
from rover_bridge.params import ModesParams

GCS, TARGETS, AUTOPILOT = "gcs", "targets", "autopilot"
_NAMES = {value: entry.name.removeprefix("ROVER_MODE_") for value, entry in mavlink.enums["ROVER_MODE"].items()
          if not entry.name.endswith("ENUM_END")}
_SAY = {
    AUTOPILOT: "the autopilot drives",
    GCS: "GCS requests drive",
    TARGETS: "position targets drive",
    GCS + TARGETS: "GCS requests and targets drive",
}


def mode_name(mode: int | None) -> str:
    """ArduPilot Rover's name of a mode number (e.g. AUTO), else `mode N`."""
    return _NAMES.get(mode, f"mode {mode}") if mode is not None else "no mode"


class ModeTable:
    """The [modes] table (see the module doc)."""

    def __init__(self, params: ModesParams, reporter: Reporter) -> None:
        self.gcs = frozenset(params.gcs)
        self.targets = frozenset(params.targets)
        self.autopilot = frozenset(params.autopilot)
        self.stop = frozenset(params.stop)
        self.of = {GCS: self.gcs, TARGETS: self.targets, AUTOPILOT: self.autopilot}  # driver -> its modes
        self.known = self.gcs | self.targets | self.autopilot | self.stop
        self.reporter = reporter
        self._said_owner: str | None = None
        self.said_mode: int | None = -1  # the mode announce() last looked at (-1: none yet)

    def allows(self, driver: str, mode: int | None) -> bool:
        return mode in self.of[driver]

    def listed(self, mode: int | None) -> bool:
        """Some driver (or the stop list) is named for this mode."""
        return mode in self.known

    def owner(self, mode: int | None) -> str:
        if mode in self.autopilot:
            return AUTOPILOT
        drivers = (GCS if mode in self.gcs else "") + (TARGETS if mode in self.targets else "")
        return drivers or "stop"

    def announce(self, mode: int | None, now_s: float) -> list[Outgoing]:
        """Say when the autopilot's navigation takes the wheels or gives them back to the bridge's drivers."""
        if mode == self.said_mode:
            return []  # the common case, every output: nothing changed
        self.said_mode = mode
        owner = self.owner(mode)
        before, self._said_owner = self._said_owner, owner
        if owner == before or AUTOPILOT not in (owner, before) or owner not in _SAY:
            return []  # a stop is said by the HOLD state; the bridge's own modes by their requests
        text = f"RB: {mode_name(mode)}: {_SAY[owner]}"
        return self.reporter.statustext(mavlink.MAV_SEVERITY_INFO, text, now_s, key="modes.owner")
