"""Simple avoidance (pure): cap the speed toward an obstacle or a fence edge so the rover stops at the margin.

ArduPilot Rover's rule (Rover/mode.cpp calc_throttle -> AC_Avoid::adjust_speed, BEHAVE 1 "stop"): the
velocity component toward each obstacle is limited to the speed from which the rover can still stop the margin
short of it, limit_velocity_2D with get_max_speed = sqrt(2 * accel * distance) (kP 0: Rover passes 0). A
differential-drive rover moves only along its body x, so for an obstacle at bearing theta from the direction
of travel the component is v * cos(theta) and the cap on v is v_stop(r - margin) / cos(theta); obstacles
behind or beside (cos <= 0) do not limit. The bridge adds what ArduPilot's 400 Hz loop can leave out: the
time the command takes to reach the wheels (`delay_s`): a rover that keeps going at v for delay_s and then
brakes at a covers v * delay_s + v^2 / (2 a), so v_stop(d) = -a * delay_s + sqrt((a * delay_s)^2 + 2 a d),
taken at d less a * delay_s^2 / 2 (see cap_speed_m_s: the commands already on their way).

A request is never increased and never flips sign; motion away from every obstacle passes untouched (so
backing away when asked always works). ArduPilot goes further in position-controlled modes: inside the
margin (beyond AVOID_BACKUP_DZ) it backs away by itself at up to AVOID_BACKUP_SPD. That is reported here as
`backup_m_s` (what ArduPilot would do) and not applied: the bridge only ever lowers a request.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from rover_bridge.command.fences import ALONG_COS, Fences, fence_clearance
from rover_bridge.command.obstacles import ObstacleView

BACKUP_ACCEL_FRACTION = 0.4  # AC_Avoid::calc_backup_velocity_2D backs away at 0.4 x the accel


class AvoidReason(enum.Enum):
    """Why a request was changed: a code for STATUSTEXT and --stats-json."""

    PASS = "pass"
    OBSTACLE_SLOW = "obstacle_slow"
    OBSTACLE_STOP = "obstacle_stop"
    FENCE_SLOW = "fence_slow"
    FENCE_STOP = "fence_stop"
    FENCE_BREACHED = "fence_breached"  # outside a fence: only the way back in passes
    FENCE_UNKNOWN = "fence_unknown"  # a fence is on but the rover cannot be placed on it: crawl
    BLIND_CRAWL = "blind_crawl"  # a proximity sensor went silent


@dataclass(frozen=True, slots=True)
class AvoidSettings:
    """AVOID_MARGIN, AVOID_BACKUP_SPD, AVOID_BACKUP_DZ (read from the autopilot), the profile's deceleration,
    the command's reaction delay and the crawl speed for a silent sensor."""

    margin_m: float = 2.0
    decel_m_s2: float = 1.0
    delay_s: float = 0.1
    crawl_speed_m_s: float = 0.2
    backup_speed_m_s: float = 0.75
    backup_deadzone_m: float = 0.10
    proximity: bool = True  # AVOID_ENABLE bit 1: obstacles are avoided (the caller passes them or not)


@dataclass(frozen=True, slots=True)
class FenceQuery:
    """The fences and where the rover is on them: local north/east from home, heading clockwise (ATTITUDE.yaw)."""

    fences: Fences
    north_m: float
    east_m: float
    heading_cw_rad: float


@dataclass(frozen=True, slots=True)
class Limited:
    """The velocity to drive, why it differs from the request, the binding cap, and ArduPilot's backup speed."""

    v_m_s: float
    omega_rad_s: float
    reason: AvoidReason = AvoidReason.PASS
    cap_m_s: float | None = None  # the tightest cap on |v| found (None: nothing in the way)
    backup_m_s: float = 0.0  # what ArduPilot would back away at (+ forward), not applied


def stopping_speed_m_s(distance_m: float, decel_m_s2: float, delay_s: float = 0.0) -> float:
    """The largest speed from which the rover, reacting after delay_s and braking at decel, stops within
    distance_m (0 at or below 0)."""
    if distance_m <= 0.0 or decel_m_s2 <= 0.0:
        return 0.0
    lag = decel_m_s2 * max(delay_s, 0.0)
    return -lag + math.sqrt(lag * lag + 2.0 * decel_m_s2 * distance_m)


def cap_speed_m_s(distance_m: float, decel_m_s2: float, delay_s: float) -> float:
    """The cap for a stop within distance_m when commands reach the wheels delay_s late: the stopping speed with
    a * delay_s^2 / 2 kept in reserve, because the commands already on their way were sent for a farther
    obstacle (the cap falls at most at rate a, so they are at most a * delay_s higher: a * delay_s^2 / 2 more
    metres). Without it the delayed loop rings and ends inside the margin (measured: 18 cm at 3 m/s^2, 0.35 s)."""
    delay = max(delay_s, 0.0)
    return stopping_speed_m_s(distance_m - 0.5 * decel_m_s2 * delay * delay, decel_m_s2, delay)


def obstacle_cap_m_s(direction: float, view: ObstacleView, settings: AvoidSettings) -> float | None:
    """The cap on |v| for travel forward (direction +1) or in reverse (-1), or None if nothing is ahead."""
    cap: float | None = None
    for sector in view.obstacles:
        assert sector.distance_m is not None
        cos_theta = direction * math.cos(sector.bearing_ccw_rad)
        if cos_theta <= ALONG_COS:
            continue  # beside or behind the direction of travel
        limit = cap_speed_m_s(sector.distance_m - settings.margin_m, settings.decel_m_s2,
                              settings.delay_s) / cos_theta
        cap = limit if cap is None else min(cap, limit)
    return cap


def backup_speed_m_s(view: ObstacleView, settings: AvoidSettings) -> float:
    """ArduPilot's back-away speed along body x (+ forward) for obstacles inside margin - deadzone."""
    forward = backward = 0.0
    for sector in view.obstacles:
        assert sector.distance_m is not None
        breach_m = settings.margin_m - sector.distance_m
        if breach_m <= max(settings.backup_deadzone_m, 0.0):
            continue
        speed = stopping_speed_m_s(breach_m, BACKUP_ACCEL_FRACTION * settings.decel_m_s2)
        along_x = -math.cos(sector.bearing_ccw_rad) * speed
        forward, backward = max(forward, along_x), min(backward, along_x)
    total = forward + backward
    return max(-settings.backup_speed_m_s, min(settings.backup_speed_m_s, total))


def limit_velocity(v_m_s: float, omega_rad_s: float, settings: AvoidSettings, obstacles: ObstacleView | None = None,
                   fence: FenceQuery | None = None, with_backup: bool = True, fence_unplaced: bool = False) -> Limited:
    """The requested body velocity with its speed toward obstacles and fence edges capped. omega passes as is.
    `with_backup`: work out ArduPilot's back-away speed too (reported only; the command flow skips it).
    `fence_unplaced`: a fence is on but the rover cannot be placed on it: the crawl speed, as for a silent sensor."""
    backup = backup_speed_m_s(obstacles, settings) if obstacles is not None and with_backup else 0.0
    if v_m_s == 0.0 or not math.isfinite(v_m_s):
        return Limited(v_m_s, omega_rad_s, backup_m_s=backup)
    direction = 1.0 if v_m_s > 0.0 else -1.0
    caps: list[tuple[float, AvoidReason]] = []
    if obstacles is not None:
        cap = obstacle_cap_m_s(direction, obstacles, settings)
        if cap is not None:
            caps.append((cap, AvoidReason.OBSTACLE_STOP if cap <= 0.0 else AvoidReason.OBSTACLE_SLOW))
        if obstacles.blind:
            caps.append((settings.crawl_speed_m_s, AvoidReason.BLIND_CRAWL))
    if fence_unplaced:
        caps.append((settings.crawl_speed_m_s, AvoidReason.FENCE_UNKNOWN))
    if fence is not None:
        travel = fence.heading_cw_rad if direction > 0.0 else fence.heading_cw_rad + math.pi
        clearance = fence_clearance(fence.fences, fence.north_m, fence.east_m, travel)
        if clearance.distance_m is not None:
            cap = cap_speed_m_s(clearance.distance_m, settings.decel_m_s2, settings.delay_s)
            if clearance.breached and cap <= 0.0:
                reason = AvoidReason.FENCE_BREACHED
            else:
                reason = AvoidReason.FENCE_STOP if cap <= 0.0 else AvoidReason.FENCE_SLOW
            caps.append((cap, reason))
    if not caps:
        return Limited(v_m_s, omega_rad_s, backup_m_s=backup)
    cap, reason = min(caps, key=lambda c: c[0])
    cap = max(cap, 0.0)
    if abs(v_m_s) <= cap:
        return Limited(v_m_s, omega_rad_s, AvoidReason.PASS, cap, backup)
    return Limited(direction * cap, omega_rad_s, reason, cap, backup)
