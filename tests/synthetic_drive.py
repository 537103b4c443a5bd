"""Deterministic synthetic drives for the estimator tests: a known trajectory -> WHEEL_DISTANCE + ATTITUDE.

Independent of the bridge's math on purpose: the truth is integrated with small Euler steps
(not the arc formula under test), and the wheels are generated from a *true* geometry that
may differ from the profile's nominal one (the miscalibration the estimator must live with).
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from dataclasses import dataclass

from rover_bridge.mavlink.dialect import MAVLinkMessage, mavlink

SIM_DT_S = 0.005
ACCEL_M_S2 = 1.0
ALPHA_RAD_S2 = 3.0


@dataclass(frozen=True)
class TrueGeometry:
    track_width_m: float = 0.30
    left_radius_m: float = 0.05
    right_radius_m: float = 0.05
    nominal_radius_m: float = 0.05  # what the autopilot integrates the distance with


@dataclass
class Truth:
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0  # CCW, unwrapped
    dist_m: float = 0.0


def route_a() -> list[tuple[float, float, float]]:
    """(duration_s, v_m_s, omega_rad_s) segments: straight runs, turns both ways, a spin, stops (~110 m)."""
    seg: list[tuple[float, float, float]] = [(2.0, 0.0, 0.0)]
    for _ in range(4):
        seg += [(25.0, 0.8, 0.0), (3.0, 0.5, 0.6), (10.0, 0.8, -0.1), (4.0, 0.0, -1.0), (2.0, 0.0, 0.0)]
    seg += [(8.0, 0.6, 0.8), (8.0, 0.6, -0.8), (2.0, 0.0, 0.0)]
    return seg


def drive(segments: list[tuple[float, float, float]], geometry: TrueGeometry, *, rate_hz: float = 20.0,
          gyro_bias_rad_s: float = 0.0, gyro_noise_rad_s: float = 0.003, seed: int = 1,
          latency_s: float = 0.004, slip: tuple[float, float, float] | None = None,
          boot_offset_s: float = 10.0) -> Iterator[tuple[float, MAVLinkMessage | None, Truth]]:
    """Yield (now_s, message or None, truth) in time order; None marks a pure time step (every 10 ms).

    `slip` = (start_s, end_s, fraction): in that window the left wheel spins (1 + fraction) times
    faster than the ground moves under it (the encoder sees it, the body does not).
    """
    rng = random.Random(seed)
    truth = Truth()
    ang_l = ang_r = 0.0  # wheel angles, rad
    period = 1.0 / rate_hz
    next_wheel = next_gyro = 0.0
    next_tick = 0.0
    t = 0.0
    g = geometry
    v = w = 0.0
    for duration, v_target, w_target in segments:
        end = t + duration
        while t < end - 1e-12:
            # The rover reaches each segment's speeds with bounded accelerations (as the limiter does).
            v += max(-ACCEL_M_S2 * SIM_DT_S, min(ACCEL_M_S2 * SIM_DT_S, v_target - v))
            w += max(-ALPHA_RAD_S2 * SIM_DT_S, min(ALPHA_RAD_S2 * SIM_DT_S, w_target - w))
            # truth (Euler, tiny steps)
            mid = truth.yaw_rad + 0.5 * w * SIM_DT_S  # midpoint rule: second order, not the arc formula
            truth.x_m += v * math.cos(mid) * SIM_DT_S
            truth.y_m += v * math.sin(mid) * SIM_DT_S
            truth.yaw_rad += w * SIM_DT_S
            truth.dist_m += abs(v) * SIM_DT_S
            ground_l = v - w * g.track_width_m / 2.0
            ground_r = v + w * g.track_width_m / 2.0
            if slip is not None and slip[0] <= t < slip[1]:
                ground_l *= 1.0 + slip[2]
            ang_l += ground_l / g.left_radius_m * SIM_DT_S
            ang_r += ground_r / g.right_radius_m * SIM_DT_S
            t += SIM_DT_S
            stamp = t + boot_offset_s
            if t >= next_wheel - 1e-9:
                next_wheel += period
                msg = mavlink.MAVLink_wheel_distance_message(
                    time_usec=round(stamp * 1e6), count=2,
                    distance=[ang_l * g.nominal_radius_m, ang_r * g.nominal_radius_m] + [0.0] * 14)
                msg._header = mavlink.MAVLink_header(msg.id, srcSystem=1, srcComponent=1)
                yield t + latency_s, msg, truth
            if t >= next_gyro - 1e-9:
                next_gyro += period
                rate_cw = -(w + gyro_bias_rad_s + rng.gauss(0.0, gyro_noise_rad_s))
                msg = mavlink.MAVLink_attitude_message(
                    time_boot_ms=round(stamp * 1e3), roll=0.0, pitch=0.0, yaw=-truth.yaw_rad, rollspeed=0.0,
                    pitchspeed=0.0, yawspeed=rate_cw)
                msg._header = mavlink.MAVLink_header(msg.id, srcSystem=1, srcComponent=1)
                yield t + latency_s, msg, truth
            if t >= next_tick - 1e-9:
                next_tick += 0.01
                yield t + latency_s, None, truth
