"""What Rover's driving modes do each loop (AUTO, RTL, SMART_RTL, GUIDED, HOLD), as behaviour.

Read in ArduPilot (Rover 4.7): Rover/mode.cpp (navigate_to_waypoint, calc_throttle, stop_vehicle,
calc_steering_from_turn_rate), mode_auto.cpp (_enter, update, start_command, verify_command,
do_nav_wp, verify_nav_wp, exit_mission), mode_rtl.cpp, mode_smart_rtl.cpp, mode_hold.cpp,
mode_guided.cpp (_enter: stop). What is kept:

- Driving to a point: AR_WPNav (sitl/wpnav.py) gives a speed and a turn rate; the speed goes through
  the acceleration limit to the speed controller (the stop controller when it is 0), the turn rate to
  the turn-rate controller; the results are the motors' throttle and steering (sitl/motors.py).
- AUTO: refused without a mission ("No Mission. Can't set AUTO."); starts stopped and starts or resumes
  the mission (MIS_RESTART 1: from item 1) on its first loop. NAV_WAYPOINT: drive there (with the next
  navigation item as the next destination unless param1, the hold time in seconds, is set), "Reached
  waypoint #N", then after the hold time MISSION_ITEM_REACHED N and the next item.
  NAV_RETURN_TO_LAUNCH: RTL inside AUTO. Other navigation items are skipped. At the end "Mission
  Complete" and MIS_DONE_BEHAVE: 0 (and 1, as no LOITER is emulated) stop in AUTO, 2 ACRO, 3 MANUAL.
- RTL: refused before home is set; drives to home at RTL_SPEED (WP_SPEED when 0), says "Reached
  destination" and stops.
- SMART_RTL: refused without an active path (sitl/smartrtl.py); cleans the path up, then drives back
  along it, newest point first, and stops at home ("Reached destination").
- GUIDED: stops (position targets are not navigated; the bridge drives them itself). HOLD and every
  other mode: throttle and steering 0, so motor outputs sit at trim and no controller runs.
"""

from __future__ import annotations

from collections.abc import Callable

from sitl.control import AttitudeControl, NavState, ParamGetter
from sitl.mission import CMD_NAV_RETURN_TO_LAUNCH, CMD_NAV_WAYPOINT, RUNNING, Mission, MissionItem
from sitl.modes import MODE_ACRO, MODE_AUTO, MODE_GUIDED, MODE_MANUAL, MODE_RTL, MODE_SMART_RTL
from sitl.motors import SkidMotors
from sitl.smartrtl import SmartRtlPath
from sitl.wpnav import WPNav

INFO, NOTICE = 6, 5  # MAV_SEVERITY
Vec = tuple[float, float]


class Navigation:
    """The driving modes around one AR_WPNav, one AR_AttitudeControl and one motors object."""

    def __init__(self, param: ParamGetter, mission: Mission, say: Callable[[int, str], None],
                 item_reached: Callable[[int], None], set_mode: Callable[[int], bool],
                 item_position: Callable[[MissionItem], Vec]) -> None:
        self._param = param
        self._say = say
        self._item_reached = item_reached
        self._set_mode = set_mode
        self._item_position = item_position
        self.mission = mission
        self.atc = AttitudeControl(param)
        self.motors = SkidMotors(param)
        self.wp = WPNav(param, self.atc)
        self.smartrtl = SmartRtlPath(param, lambda text: say(4, text))
        self.home: Vec | None = None
        self.nav: NavState | None = None
        self.armed = False
        self.now_ms = 0
        self.dt_s = 0.02
        self.auto_sub = "stop"  # stop | wp | rtl
        self._waiting_to_start = False
        self._previously_reached = False
        self._hold_s = 0
        self._hold_start_ms = 0
        self._rtl_notify = False
        self._srtl_state = "cleanup"  # cleanup | follow | home
        self._load_point = False

    # ------------------------------------------------------------------ mode.cpp
    def _calc_throttle(self, speed: float) -> None:
        lim, dt = self.motors.limit, self.dt_s
        speed = self.atc.desired_speed_accel_limited(speed, dt)
        if speed == 0.0:
            throttle, _ = self.atc.throttle_out_stop(lim.throttle_lower, lim.throttle_upper, dt)
        else:
            throttle = self.atc.throttle_out_speed(speed, lim.throttle_lower, lim.throttle_upper, dt)
        self.motors.set_throttle(100.0 * throttle, self.armed)

    def _steer(self, rate_rad_s: float) -> None:
        lim = self.motors.limit
        self.motors.set_steering(4500.0 * self.atc.steering_out_rate(rate_rad_s, lim.steer_left, lim.steer_right,
                                                                     self.dt_s))

    def stop_vehicle(self) -> bool:
        lim = self.motors.limit
        throttle, stopped = self.atc.throttle_out_stop(lim.throttle_lower, lim.throttle_upper, self.dt_s)
        self.motors.set_throttle(100.0 * throttle, self.armed)
        if stopped:
            self.motors.set_steering(0.0)
        else:
            self._steer(0.0)
        return stopped

    def _navigate(self) -> None:
        self.wp.update(self.nav, self.armed, self.now_ms, self.dt_s)
        self._calc_throttle(self.wp.speed)
        self._steer(self.wp.turn_rate_rad_s)

    def _hold(self) -> None:
        self.motors.set_throttle(0.0, self.armed)
        self.motors.set_steering(0.0)

    # ------------------------------------------------------------------ entering and leaving
    def _rtl_speed(self) -> float:
        return max(0.0, self._param("RTL_SPEED"))

    def enter(self, mode: int, nav: NavState | None, now_ms: int) -> bool:
        """Mode::_enter of the driving modes; False refuses the mode."""
        self.nav, self.now_ms = nav, now_ms
        self.atc.tick(now_ms, nav)
        if mode == MODE_AUTO:
            if not self.mission.present():
                self._say(NOTICE, "No Mission. Can't set AUTO.")
                return False
            if nav is not None:
                self.wp.init(nav)
            self.auto_sub, self._waiting_to_start = "stop", True
            return True
        if mode == MODE_RTL:
            return self._enter_rtl()
        if mode == MODE_SMART_RTL:
            if nav is None or not self.smartrtl.active:
                return False
            self.wp.init(nav, self._rtl_speed())
            self.wp.set_destination(self.wp.stopping_point(nav), nav, now_ms)
            self._srtl_state = "cleanup"
            return True
        if mode == MODE_GUIDED and nav is not None:
            self.wp.init(nav)
        return True

    def _enter_rtl(self) -> bool:
        if self.home is None or self.nav is None:
            return False
        self.wp.init(self.nav, self._rtl_speed())
        self.wp.set_destination(self.home, self.nav, self.now_ms)
        self._rtl_notify = True
        return True

    def exit(self, mode: int) -> None:
        if mode == MODE_AUTO and self.mission.state == RUNNING:
            self.mission.stop()

    # ------------------------------------------------------------------ each loop
    def update(self, mode: int, nav: NavState | None, armed: bool, now_ms: int, dt_s: float) -> None:
        self.nav, self.armed, self.now_ms, self.dt_s = nav, armed, now_ms, dt_s
        self.atc.tick(now_ms, nav)
        if mode == MODE_AUTO:
            self._auto_update()
        elif mode == MODE_RTL:
            self._rtl_update()
        elif mode == MODE_SMART_RTL:
            self._smart_rtl_update()
        elif mode == MODE_GUIDED:
            self.stop_vehicle()
        elif mode != MODE_MANUAL:  # MANUAL's mix is the autopilot's (sitl/autopilot.py)
            self._hold()

    def _rtl_update(self) -> None:
        if not self.wp.reached:
            self._navigate()
            return
        if self._rtl_notify:
            self._rtl_notify = False
            self._say(INFO, "Reached destination")
        self.stop_vehicle()

    def _smart_rtl_update(self) -> None:
        if self._srtl_state == "cleanup":
            self.smartrtl.cleanup()
            self._srtl_state, self._load_point = "follow", True
            self.stop_vehicle()
        elif self._srtl_state == "follow":
            if self._load_point:
                dest = self.smartrtl.pop()
                if dest is None or self.nav is None:
                    self._say(INFO, "Reached destination")
                    self._srtl_state = "home"
                    return
                self.wp.set_destination(dest, self.nav, self.now_ms, self.smartrtl.peek())
                self._load_point = False
            self._navigate()
            if self.wp.reached:
                self._load_point = True
        else:
            self.stop_vehicle()

    # ------------------------------------------------------------------ AUTO
    def say(self, severity: int, text: str) -> None:
        self._say(severity, text)

    def _auto_update(self) -> None:
        if not self.armed and not self.mission.present():
            self.auto_sub = "stop"
        if self._waiting_to_start:
            if self.nav is not None:  # ArduPilot waits for an EKF origin
                self._waiting_to_start = False
                if self._param("MIS_RESTART") == 1:  # AP_Mission::start_or_resume: 1 restarts from item 1
                    self.mission.start(self)
                else:
                    self.mission.start_or_resume(self)
        else:
            self.mission.update(self)
        if self.auto_sub == "wp":
            self._navigate()
        elif self.auto_sub == "rtl":
            self._rtl_update()
        else:
            self.stop_vehicle()

    def start_command(self, index: int, item: MissionItem) -> bool:
        if item.command == CMD_NAV_RETURN_TO_LAUNCH:
            if self._enter_rtl():
                self.auto_sub = "rtl"
            return True
        if item.command != CMD_NAV_WAYPOINT or self.nav is None:
            return False  # not emulated: skipped, as Rover skips what it cannot start
        here = (self.nav.north_m, self.nav.east_m)
        dest = self._item_position(item) if (item.x, item.y) != (0, 0) else here
        self._hold_s = max(0, int(item.param1))
        nxt = None if self._hold_s > 0 else self.mission.next_nav_item(index + 1)
        next_dest = None
        if nxt is not None:
            next_dest = self._item_position(nxt) if (nxt.x, nxt.y) != (0, 0) else dest
        self.wp.set_destination(dest, self.nav, self.now_ms, next_dest)
        self.auto_sub, self._previously_reached = "wp", False
        return True

    def verify_command(self, index: int, item: MissionItem) -> bool:
        done = True
        if item.command == CMD_NAV_WAYPOINT:
            done = self._verify_waypoint(index)
        elif item.command == CMD_NAV_RETURN_TO_LAUNCH:
            done = self.wp.reached
        if done:
            self._item_reached(index)
        return done

    def _verify_waypoint(self, index: int) -> bool:
        if self.auto_sub == "wp" and not self.wp.reached:
            return False
        if not self._previously_reached:
            self._previously_reached = True
            if self._hold_s > 0:
                self._say(INFO, f"Reached waypoint #{index}. Loiter for {self._hold_s} seconds")
                self._hold_start_ms = self.now_ms
            else:
                self._say(INFO, f"Reached waypoint #{index}")
        return self._hold_s == 0 or (self.now_ms - self._hold_start_ms) // 1000 >= self._hold_s

    def mission_complete(self) -> None:
        self._say(NOTICE, "Mission Complete")
        behave = int(self._param("MIS_DONE_BEHAVE"))
        if behave in (2, 3) and self._set_mode(MODE_ACRO if behave == 2 else MODE_MANUAL):
            return
        self.auto_sub = "stop"

    # ------------------------------------------------------------------ reports
    def nav_output(self, mode: int) -> tuple[float, float, float, float]:
        """(nav bearing deg, target bearing deg, distance m, cross-track m) for NAV_CONTROLLER_OUTPUT."""
        stopped = (mode == MODE_AUTO and self.auto_sub == "stop") or mode == MODE_GUIDED
        if stopped or not self.wp.valid:
            return 0.0, 0.0, 0.0, 0.0
        w = self.wp
        return w.nav_bearing_deg, w.wp_bearing_deg, w.distance_m, w.crosstrack_m
