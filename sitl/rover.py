"""Rover's main loop and mode changes: what runs each loop, home, the fence and the GCS failsafe.

Read in ArduPilot (Rover 4.7): Rover/Rover.cpp (the scheduler table: the mode and the motors every
loop at SCHED_LOOP_RATE, read once at boot; fence_check and gcs_failsafe_check at 10 Hz; SmartRTL's
save_position at 3 Hz; ahrs_update sets home at the first position and, while disarmed, moves it when
the vehicle is 0.5 m away), Rover/system.cpp (set_mode), Rover/commands.cpp (set_home:
"Set HOME to LAT LON at ALTm"), Rover/AP_Arming_Rover.cpp (arming resets SmartRTL's path) and
libraries/AP_AHRS (a new home is sent as HOME_POSITION).

A mode change to the current mode does nothing. Armed, a mode that needs a position is refused without
one; a mode's own entry conditions (sitl/navigation.py) can refuse it too ("Flight mode change
failed"). A change that happens starts the fence's manual recovery when breached, leaves the old mode
and announces itself with a HEARTBEAT at once.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from sitl.control import NavState
from sitl.mav import mavlink
from sitl.mission import Mission, MissionItem
from sitl.modes import (
    ACTION_HOLD,
    ACTION_LOITER_HOLD,
    ACTION_NONE,
    ACTION_RTL,
    ACTION_SMART_RTL,
    ACTION_SMART_RTL_HOLD,
    ACTION_TERMINATE,
    MODE_HOLD,
    MODE_LOITER,
    MODE_MANUAL,
    MODE_NAMES,
    MODE_RTL,
    MODE_SMART_RTL,
    NO_POSITION_NEEDED,
)
from sitl.navigation import Navigation
from sitl.safety import GIVE_UP_DISTANCE_M, CircleFence, GcsFailsafe

_P = mavlink
INFO, NOTICE, WARNING = _P.MAV_SEVERITY_INFO, _P.MAV_SEVERITY_NOTICE, _P.MAV_SEVERITY_WARNING
HOME_MIN_CHANGE_M = 0.5  # DISTANCE_HOME_MINCHANGE
TASK_10HZ_MS = 100
Vec = tuple[float, float]


class Rover:
    """The vehicle side of the emulated autopilot: modes, the loop's tasks, home (see the module doc)."""

    def __init__(self, param: Callable[[str], float], mission: Mission, say: Callable[[int, str], None],
                 request: Callable[[int], None], item_reached: Callable[[int], None],
                 lat_lon_of: Callable[[float, float], tuple[float, float]],
                 item_position: Callable[[MissionItem], Vec], nav_now: Callable[[], NavState | None]) -> None:
        self._param = param
        self._say = say
        self._request = request
        self._lat_lon_of = lat_lon_of
        self._nav_now = nav_now  # the estimate as it is now (a mode change can come between loops)
        self.mission = mission
        self.nav = Navigation(param, mission, say, item_reached, self._mode_by_mission, item_position)
        self.fence = CircleFence(param, lambda text: say(INFO, text))
        self.failsafe = GcsFailsafe(param)
        self.mode = MODE_MANUAL
        rate = max(50.0, min(2000.0, param("SCHED_LOOP_RATE")))  # AP_Scheduler::init, at boot only
        self.loop_period_us = int(1_000_000 // rate)
        self.left = self.right = 0.0  # ThrottleLeft/Right demand of the last loop, [-1, 1]
        self.armed = False
        self.disarm_requested = False  # FENCE_ACTION / FS_ACTION 5 (terminate)
        self.clear_overrides_requested = False  # a GCS failsafe clears RC overrides
        self.skid_steering = False
        self._now_ms = 0
        self._next_loop_us: int | None = None
        self._next_10hz_ms = 0

    # ------------------------------------------------------------------ modes
    def set_mode(self, mode: int) -> bool:
        """Rover::set_mode; False when refused (see the module docstring)."""
        if mode == self.mode:
            return True
        if mode not in MODE_NAMES:
            self._say(WARNING, f"Mode change to {mode} failed: not emulated")
            return False
        nav = self._nav_now()
        refused = self.armed and mode not in NO_POSITION_NEEDED and nav is None
        if refused or not self.nav.enter(mode, nav, self._now_ms):
            self._say(WARNING, "Flight mode change failed")
            return False
        old, self.mode = self.mode, mode
        self.fence.manual_recovery_start(self._now_ms)
        self.nav.exit(old)
        self._request(_P.MAVLINK_MSG_ID_HEARTBEAT)  # announced at once, as Rover does
        return True

    def _mode_by_mission(self, mode: int) -> bool:
        return self.set_mode(mode)

    def _failsafe_action(self, action: int) -> None:
        """FENCE_ACTION / FS_ACTION (Rover's FailsafeAction)."""
        if action == ACTION_TERMINATE:
            self.disarm_requested = True
        elif action in (ACTION_SMART_RTL, ACTION_RTL, ACTION_HOLD):
            tries = {ACTION_SMART_RTL: (MODE_SMART_RTL, MODE_RTL), ACTION_RTL: (MODE_RTL,)}.get(action, ())
            if not any(self.set_mode(m) for m in tries):
                self.set_mode(MODE_HOLD)
        elif action in (ACTION_SMART_RTL_HOLD, ACTION_LOITER_HOLD):
            first = MODE_SMART_RTL if action == ACTION_SMART_RTL_HOLD else MODE_LOITER
            if not self.set_mode(first):
                self.set_mode(MODE_HOLD)

    # ------------------------------------------------------------------ home
    def set_home(self, pos: Vec, announce: bool) -> None:
        self.nav.home = pos
        self.mission.write_home()
        self._request(_P.MAVLINK_MSG_ID_HOME_POSITION)
        if announce:  # Rover::set_home_to_current_location (the first fix), also SmartRTL's home
            lat, lon = self._lat_lon_of(*pos)
            self._say(INFO, f"Set HOME to {lat:.6f} {lon:.6f} at 584.00m")
            self.nav.smartrtl.set_home(pos, self._now_ms)

    def _update_home(self, nav: NavState | None) -> None:
        if nav is None:
            return
        here = (nav.north_m, nav.east_m)
        home = self.nav.home
        if home is None:
            self.set_home(here, announce=True)
        elif not self.armed and math.hypot(here[0] - home[0], here[1] - home[1]) >= HOME_MIN_CHANGE_M:
            self.set_home(here, announce=False)

    # ------------------------------------------------------------------ the loop
    def update(self, now_us: int, boot_us: int, nav: NavState | None, armed: bool, skid_steering: bool) -> None:
        """Run the loop when one is due (call at least every few ms of simulated time)."""
        if self._next_loop_us is None or self._next_loop_us < boot_us:
            self._next_loop_us = boot_us
        if now_us < self._next_loop_us:
            return
        self._next_loop_us += self.loop_period_us
        if self._next_loop_us <= now_us:
            self._next_loop_us = now_us + self.loop_period_us
        self._now_ms = (now_us - boot_us) // 1000
        self.skid_steering = skid_steering
        if armed and not self.armed:  # AP_Arming_Rover::arm: SmartRTL starts its path here
            self.nav.smartrtl.set_home((nav.north_m, nav.east_m) if nav is not None else None, self._now_ms)
        self.armed = armed
        self._update_home(nav)
        self.nav.wp.set_turn_params(skid_steering)
        dt_s = self.loop_period_us / 1e6
        self.nav.update(self.mode, nav, armed, self._now_ms, dt_s)
        self.left, self.right = self.nav.motors.output(armed, dt_s)
        if self._now_ms >= self._next_10hz_ms:
            self._next_10hz_ms = self._now_ms + TASK_10HZ_MS
            self._fence_check(nav)
            self._failsafe_check()
        pos = (nav.north_m, nav.east_m) if nav is not None else None
        self.nav.smartrtl.save(pos, self._now_ms, saving=self.mode != MODE_SMART_RTL)

    def manual_mix(self, left: float, right: float) -> None:
        """MANUAL's outputs, given to the motors so their slew state follows (the PWM is the mix's)."""
        if self.mode == MODE_MANUAL:
            self.nav.motors.set_throttle(50.0 * (left + right), self.armed)
            self.nav.motors.set_steering(2250.0 * (left - right))

    def _fence_check(self, nav: NavState | None) -> None:
        pos = (nav.north_m, nav.east_m) if nav is not None else None
        if not self.fence.check(pos, self.nav.home, self._now_ms) or not self.armed:
            return
        action = int(self._param("FENCE_ACTION"))
        if action == ACTION_NONE:
            return
        if self.fence.breach_distance_m > GIVE_UP_DISTANCE_M:
            self.set_mode(MODE_HOLD)
        else:
            self._failsafe_action(action)

    def _failsafe_check(self) -> None:
        event = self.failsafe.check(self._now_ms, self.mode)
        if event == "cleared":
            self._say(INFO, "GCS Failsafe Cleared")
        elif event is not None:
            self._say(WARNING, "GCS Failsafe")
            self.clear_overrides_requested = True
            if event == "continue":
                self._say(WARNING, "Failsafe - Continuing Auto Mode")
            else:
                self._failsafe_action(int(self._param("FS_ACTION")))
