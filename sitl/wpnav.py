"""Rover's waypoint navigation (AR_WPNav), as behaviour: legs, pivots, arrival, cross-track error.

Read in ArduPilot (Rover 4.7): libraries/AR_WPNav/AR_WPNav.cpp (init, update, set_desired_location,
advance_wp_target_along_track, update_steering_and_speed, calc_crosstrack_error, get_stopping_location)
and Rover/mode.cpp (navigate_to_waypoint). What is kept:

- ``init(speed)``: the speed limit is ``speed`` or WP_SPEED (at least 0.05 m/s); acceleration WP_ACCEL
  or, when 0, min(ATC_ACCEL_MAX, ATC_DECEL_MAX); jerk WP_JERK or, when 0, the acceleration; origin and
  destination start at the vehicle's stopping point.
- A new destination continues from the previous one if that was reached while navigating; otherwise
  the leg starts at the vehicle's stopping point. A leg that does not follow a "fast" waypoint checks
  for a pivot first. With a next destination whose corner would not need a pivot, the waypoint is
  "fast": the leg ends at corner speed and the next one starts at it (see below).
- A target moves along the leg (sitl/scurve.py) on the leg's own clock, which runs slower when the
  vehicle falls behind: rate = clamp(0.05 + (along-track speed - 0.2 * along-track lag) / target speed,
  0, 1), smoothed with a time constant of accel / jerk; the target stands still while pivoting.
- Arrived: a fast waypoint when the target reaches it; otherwise when the target has reached it and
  the vehicle is within WP_RADIUS or past the line through the waypoint square to the leg.
- Simplified: ArduPilot blends a fast waypoint's corner into the next leg along an S-curve within
  WP_RADIUS; here the target takes the corner at min(speed, sqrt(ATC_TURN_MAX_G * g * r)) with r the
  radius of an arc tangent to both legs WP_RADIUS before the corner, no faster than the next leg can
  stop from in its own length, and the position controller cuts the corner.
"""

from __future__ import annotations

import math

from sitl.control import AttitudeControl, NavState, ParamGetter
from sitl.poscontrol import PivotTurn, PosControl, Vec, _norm, _sub
from sitl.scurve import LegProfile, stoppable_speed

SPEED_MIN_M_S = 0.05  # AR_WPNAV_SPEED_MIN
ACCEL_UNLIMITED = 20.0  # AR_WPNAV_ACCEL_MAX
TIMEOUT_MS = 100


def bearing_deg(frm: Vec, to: Vec) -> float:
    """Bearing 0..360 clockwise from north."""
    d = _sub(to, frm)
    return math.degrees(math.atan2(d[1], d[0])) % 360.0


class WPNav:
    """AR_WPNav for straight legs (see the module docstring). Positions are NED metres from the EKF origin."""

    def __init__(self, param: ParamGetter, atc: AttitudeControl) -> None:
        self._param = param
        self._atc = atc
        self.pos = PosControl(atc)
        self.pivot = PivotTurn(param, atc)
        self.origin: Vec = (0.0, 0.0)
        self.destination: Vec = (0.0, 0.0)
        self.valid = False
        self.reached = False
        self.fast = False
        self._pivot_at_next = False
        self._leg: LegProfile | None = None
        self._leg_time_s = 0.0
        self._track_scalar = 1.0
        self._last_ms: int | None = None
        self.speed_max = 0.0
        self.speed = 0.0  # outputs of the last update
        self.turn_rate_rad_s = 0.0
        self.crosstrack_m = 0.0
        self.distance_m = 0.0
        self.wp_bearing_deg = 0.0
        self.nav_bearing_deg = 0.0

    def active(self, now_ms: int) -> bool:
        return self._last_ms is not None and now_ms - self._last_ms < TIMEOUT_MS

    def stopping_point(self, nav: NavState) -> Vec:
        vel = (nav.vel_n_m_s, nav.vel_e_m_s)
        speed = _norm(vel)
        if speed <= 0.0:
            return nav.north_m, nav.east_m
        dist = self._atc.stopping_distance(speed)
        return nav.north_m + vel[0] / speed * dist, nav.east_m + vel[1] / speed * dist

    def init(self, nav: NavState, speed_max: float = 0.0) -> None:
        base = speed_max if speed_max > 0.0 else self._param("WP_SPEED")
        self.speed_max = max(SPEED_MIN_M_S, base)
        atc_accel = min(self._atc.accel_max, self._atc.decel_max)
        if atc_accel <= 0.0:
            atc_accel = ACCEL_UNLIMITED
        wp_accel = self._param("WP_ACCEL")
        accel = min(wp_accel, atc_accel) if wp_accel > 0.0 else atc_accel
        jerk = self._param("WP_JERK") if self._param("WP_JERK") > 0.0 else accel
        self.pos.set_limits(self.speed_max, accel, self._atc.turn_lat_accel_max, jerk)
        self._leg, self._track_scalar = None, 1.0
        self.reached = self.fast = self._pivot_at_next = False
        self.pivot.deactivate()
        self.origin = self.destination = self.stopping_point(nav)
        self.valid = True

    def set_turn_params(self, pivot_possible: bool) -> None:
        """Rover, every loop: a skid-steering rover can pivot; any other turns on TURN_RADIUS."""
        self.pivot.enabled = pivot_possible
        self.pos.turn_radius_m = 0.0 if pivot_possible else max(0.0, self._param("TURN_RADIUS"))
        if not pivot_possible:
            self.pivot.deactivate()

    def _corner_deg(self, a: Vec, b: Vec, c: Vec) -> float:
        return math.remainder(bearing_deg(b, c) - bearing_deg(a, b), 360.0)

    def _corner_speed(self, turn_deg: float) -> float:
        half = math.radians(abs(turn_deg)) / 2.0
        if half < 1e-6:
            return self.speed_max
        radius = max(self._param("WP_RADIUS"), self.pos.turn_radius_m, 0.0) / math.tan(half)
        return min(self.speed_max, math.sqrt(self._atc.turn_lat_accel_max * radius))

    def set_destination(self, dest: Vec, nav: NavState, now_ms: int, next_dest: Vec | None = None) -> None:
        start_m_s = self._leg.end_m_s if self._leg is not None and self.fast and self.reached else 0.0
        if not self.active(now_ms) or not self.reached:
            self.origin = self.destination = self.stopping_point(nav)
            start_m_s = 0.0
        self.origin, self.destination = self.destination, dest
        self.valid, self.reached = True, False
        self._update_distance(nav)
        if not self.fast:
            self.pivot.deactivate()
            self.pivot.check_activation(self.wp_bearing_deg, math.degrees(nav.yaw_rad), now_ms, self._pivot_at_next)
        self.fast = self._pivot_at_next = False
        end_m_s = 0.0
        if next_dest is not None:
            turn = self._corner_deg(self.origin, dest, next_dest)
            self._pivot_at_next = self.pivot.would_activate(turn)
            if not self._pivot_at_next:
                self.fast = True
                # ArduPilot overlaps two rest-to-rest S-curves at a corner, so the next leg can always
                # stop in its own length; the corner speed here is held to what allows that.
                end_m_s = min(self._corner_speed(turn), stoppable_speed(
                    _norm(_sub(next_dest, dest)), self.pos.accel_max, self.pos.jerk_max))
        p = self.pos
        self._leg = LegProfile(_norm(_sub(dest, self.origin)), self.speed_max, p.accel_max, p.jerk_max,
                               start_m_s, end_m_s)
        self._leg_time_s = 0.0

    def _update_distance(self, nav: NavState) -> None:
        here = (nav.north_m, nav.east_m)
        self.distance_m = _norm(_sub(self.destination, here))
        self.wp_bearing_deg = bearing_deg(here, self.destination)

    def _advance_target(self, nav: NavState, now_ms: int, dt_s: float) -> None:
        assert self._leg is not None
        p = self.pos
        target_speed = _norm(p.vel_desired)
        scaler = 1.0
        if target_speed > 0.0:
            direction = (p.vel_desired[0] / target_speed, p.vel_desired[1] / target_speed)
            err = p.pos_error(nav, now_ms)
            track_error = err[0] * direction[0] + err[1] * direction[1]
            track_velocity = nav.vel_n_m_s * direction[0] + nav.vel_e_m_s * direction[1]
            scaler = max(0.0, min(1.0, 0.05 + (track_velocity - 0.2 * track_error) / target_speed))
        tc = p.accel_max / p.jerk_max if p.jerk_max > 0.0 else 1.0
        self._track_scalar += (scaler - self._track_scalar) * (dt_s / tc)
        self._leg_time_s += self._track_scalar * dt_s
        s, v, a = self._leg.at(self._leg_time_s)
        leg = _sub(self.destination, self.origin)
        length = _norm(leg)
        u = (leg[0] / length, leg[1] / length) if length > 0.0 else (0.0, 0.0)
        if not p.active(now_ms):
            p.init(nav)
        p.set_target((self.origin[0] + u[0] * s, self.origin[1] + u[1] * s), (u[0] * v, u[1] * v), (u[0] * a, u[1] * a))
        if not self.reached and self._leg_time_s >= self._leg.duration_s:
            if self.fast:
                self.reached = True
            else:
                here = (nav.north_m, nav.east_m)
                near = _norm(_sub(self.destination, here)) <= self._param("WP_RADIUS")
                to_here = _sub(here, self.destination)
                past = length > 0.0 and to_here[0] * u[0] + to_here[1] * u[1] >= 0.0
                self.reached = near or past

    def update(self, nav: NavState | None, armed: bool, now_ms: int, dt_s: float) -> None:
        """One navigation step; results in speed, turn_rate_rad_s, crosstrack_m, distance_m."""
        if not armed or not self.valid or nav is None or self._leg is None:
            self.speed = self._atc.desired_speed_accel_limited(0.0, dt_s)
            self.turn_rate_rad_s = self.crosstrack_m = 0.0
            return
        if not self.active(now_ms):
            self.speed = nav.forward_speed_m_s
        self._last_ms = now_ms
        self._update_distance(nav)
        if not self.pivot.active:
            self._advance_target(nav, now_ms, dt_s)
        self.crosstrack_m = self._crosstrack(nav)
        self.pos.update(nav, now_ms, dt_s)
        if self.pivot.active:
            self.speed = self._atc.desired_speed_accel_limited(0.0, dt_s)
            self.nav_bearing_deg = self.wp_bearing_deg
            yaw_deg = math.degrees(nav.yaw_rad)
            pivoting = self.speed == 0.0  # turn on the spot only once stopped
            self.turn_rate_rad_s = self.pivot.turn_rate_rad_s(self.wp_bearing_deg, yaw_deg, now_ms) if pivoting else 0.0
        else:
            self.speed = self.pos.desired_speed
            self.turn_rate_rad_s = self.pos.turn_rate_rad_s

    def _crosstrack(self, nav: NavState) -> float:
        leg = _sub(self.destination, self.origin)
        here = _sub((nav.north_m, nav.east_m), self.origin)
        length = _norm(leg)
        if length < 1e-6:
            return _norm(_sub((nav.north_m, nav.east_m), self.destination))
        return (here[0] * leg[1] - here[1] * leg[0]) / length
