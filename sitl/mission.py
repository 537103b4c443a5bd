"""Rover's stored mission and how AUTO walks through it (AP_Mission), as behaviour.

Read in ArduPilot (Rover 4.7): libraries/AP_Mission/AP_Mission.cpp (read_cmd_from_storage, add_cmd,
replace_cmd, truncate, clear, start, stop, resume, update, advance_current_nav_cmd, set_current_cmd,
complete) and libraries/GCS_MAVLink/MissionItemProtocol_Waypoints.cpp. What is kept:

- Item 0 is home: it is never stored (an uploaded item 0 is accepted and dropped) and reads back as the
  current home. The mission is "present" with at least one item after home.
- Clearing is refused while armed with the mission running.
- start: from the first item; resume (entering AUTO, MIS_RESTART = 0): from the current navigation
  item, restarted, or from the first one when the mission had completed or never started; stop
  (leaving AUTO) keeps the current item.
- update (each loop in AUTO): start the next navigation item when none is loaded, else verify the
  loaded one and, once done, start the next; no further navigation item completes the mission.
  Navigation items the vehicle cannot start are skipped; "do" items are started and done at once.
  Each navigation item says "Mission: N WP" (N RTL, ...) as it starts.
- set_current: running, jump there; stopped or complete, make it where a resume starts (0 = item 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

CMD_NAV_WAYPOINT = 16
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAST = 95  # MAV_CMD_NAV_LAST: ids up to this are navigation items

STOPPED, RUNNING, COMPLETE = "stopped", "running", "complete"
_TYPE_NAMES = {CMD_NAV_WAYPOINT: "WP", CMD_NAV_RETURN_TO_LAUNCH: "RTL"}  # Mission_Command::type()
INFO = 6  # MAV_SEVERITY_INFO


def _start(runner: MissionRunner, index: int, item: MissionItem) -> bool:
    """AP_Mission::start_command: "Mission: N WP", then the vehicle's own start."""
    runner.say(INFO, f"Mission: {index} {_TYPE_NAMES.get(item.command, str(item.command))}")
    return runner.start_command(index, item)


@dataclass(frozen=True)
class MissionItem:
    """One stored item, in MISSION_ITEM_INT terms (x, y = lat, lon * 1e7)."""

    command: int
    frame: int = 6  # MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    x: int = 0
    y: int = 0
    z: float = 0.0
    autocontinue: int = 1

    @property
    def is_nav(self) -> bool:
        return self.command <= CMD_NAV_LAST


class MissionRunner(Protocol):
    """What the vehicle does with items (ModeAuto's start_command / verify_command / exit_mission)."""

    def say(self, severity: int, text: str) -> None: ...

    def start_command(self, index: int, item: MissionItem) -> bool: ...

    def verify_command(self, index: int, item: MissionItem) -> bool: ...

    def mission_complete(self) -> None: ...


class Mission:
    """The stored items (index 0 = home) and the execution cursor."""

    def __init__(self) -> None:
        self.items: list[MissionItem] = []  # index 1.. (home is index 0, not stored)
        self.total = 0  # AP_Mission's _cmd_total: items including home
        self.state = STOPPED
        self.nav_index: int | None = None
        self._nav_loaded = False
        self.changed = 0  # bumped on every change (uploads, clears)

    # ------------------------------------------------------------------ storage
    def count(self) -> int:
        """Items including home (AP_Mission::num_commands); 0 until home or an item was written."""
        return self.total

    def present(self) -> bool:
        return self.total > 1

    def item(self, index: int) -> MissionItem | None:
        return self.items[index - 1] if 1 <= index <= len(self.items) else None

    def write_home(self) -> None:
        """Setting home stores it as item 0 (AP_AHRS::set_home -> write_home_to_storage)."""
        self.total = max(self.total, 1)

    def truncate(self, count: int) -> None:
        if self.total > count:
            self.total = count
            del self.items[max(0, count - 1):]
            self.changed += 1

    def write(self, index: int, item: MissionItem) -> bool:
        """Replace (index < count; index 0, home, is accepted and dropped) or append (index == count).

        Appending to an empty store writes home first, as AP_Mission::add_cmd does, so the item lands
        at index 1 (a later item 1 then replaces it)."""
        if index < self.total:
            if index > 0:
                self.items[index - 1] = item
                self.changed += 1
            return True
        if index != self.total:
            return False
        self.write_home()
        self.items.append(item)
        self.total += 1
        self.changed += 1
        return True

    def clear(self, armed: bool) -> bool:
        if armed and self.state == RUNNING:
            return False
        self.truncate(0)
        self.nav_index, self._nav_loaded, self.state = None, False, STOPPED
        return True

    def next_nav_item(self, first: int) -> MissionItem | None:
        """The first navigation item at or after ``first`` (AP_Mission::get_next_nav_cmd)."""
        return next((it for it in self.items[max(first, 1) - 1:] if it.is_nav), None)

    def reset_cursor(self) -> None:
        """A reboot: the stored items stay, execution starts over."""
        self.state, self.nav_index, self._nav_loaded = STOPPED, None, False

    def current_nav_index(self) -> int:
        return self.nav_index or 0

    # ------------------------------------------------------------------ execution
    def start(self, runner: MissionRunner) -> None:
        self.state = RUNNING
        self.nav_index, self._nav_loaded = None, False
        if not self._advance(runner, 1):
            self._complete(runner)

    def stop(self) -> None:
        self.state = STOPPED

    def start_or_resume(self, runner: MissionRunner) -> None:
        if self.state == COMPLETE or self.nav_index is None or self.item(self.nav_index) is None:
            self.start(runner)
            return
        self.state = RUNNING
        item = self.item(self.nav_index)
        assert item is not None
        self._nav_loaded = _start(runner, self.nav_index, item)

    def update(self, runner: MissionRunner) -> None:
        if self.state != RUNNING or not self.items:
            return
        if not self._nav_loaded or self.nav_index is None:
            if not self._advance(runner, (self.nav_index or 0) + 1):
                self._complete(runner)
            return
        item = self.item(self.nav_index)
        if item is None or runner.verify_command(self.nav_index, item):
            self._nav_loaded = False
            if not self._advance(runner, self.nav_index + 1):
                self._complete(runner)

    def set_current(self, index: int, runner: MissionRunner) -> bool:
        if index >= self.count() or self.count() <= 1:
            return False
        self._nav_loaded = False
        if index == 0 or self.state == COMPLETE:
            index = max(index, 1)
        if self.state != RUNNING:
            for i in range(index, len(self.items) + 1):
                if self.items[i - 1].is_nav:
                    self.nav_index, self.state = i, STOPPED
                    return True
            self.nav_index = None
            return False
        if not self._advance(runner, index):
            self._complete(runner)
            return False
        return True

    def _advance(self, runner: MissionRunner, first: int) -> bool:
        for i in range(max(first, 1), len(self.items) + 1):
            item = self.items[i - 1]
            if not item.is_nav:
                continue  # "do" items: started and done at once (none is emulated)
            self.nav_index = i
            if _start(runner, i, item):
                self._nav_loaded = True
                return True
        return False

    def _complete(self, runner: MissionRunner) -> None:
        self.state = COMPLETE
        runner.mission_complete()

