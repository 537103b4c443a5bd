"""What the demo's ground station collects (Series) and each go-here leg's result (GotoLeg): values the demo
fills and both its report (rover_bridge.app.demo) and its picture (rover_bridge.app.demo_picture) read, kept
here so that neither of those two imports the other.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class GotoLeg:
    north_m: float
    east_m: float
    sent_as: str
    arrival_m: float  # where the rover stopped, from the target (ground truth)
    seconds: float  # sent -> reached and stopped

    @staticmethod
    def table(legs: list[GotoLeg]) -> str:
        out = [f"{'go here':>14s} {'sent as':>17s} {'arrival error':>14s} {'time':>8s}"]
        out += [f"{leg.north_m:+6.2f} N {leg.east_m:+5.2f} E {leg.sent_as:>17s} {leg.arrival_m:12.3f} m "
                f"{leg.seconds:6.1f} s" for leg in legs]
        return "\n".join(out)


@dataclass
class Series:
    """Time series the GCS collected, each stamped on the autopilot's boot clock (seconds).

    Stamping by the senders' own clocks (LOCAL_POSITION_NED.time_boot_ms, WHEEL_DISTANCE and
    ODOMETRY time_usec) keeps transport delay out of the comparison.
    """

    truth: list[tuple[float, float, float, float]] = field(default_factory=list)  # t, north, east, yaw_cw
    # SIMSTATE (the true yaw) has no time field. The emulator sends it in the EXTRA1 group, with
    # WHEEL_DISTANCE in the same step right after it (the group runs in phase: the bridge asks for it, and
    # the demo does not ask for SIMSTATE on its own), so it takes that WHEEL_DISTANCE's time_usec. Stamping
    # it by its arrival (mapped through the smallest latency) put it as late as the demo read it: on a
    # busy machine up to a third of a second, 30 deg of spin; pairing it with the last position's stamp,
    # up to a period late.
    truth_yaw: list[tuple[float, float]] = field(default_factory=list)  # t, yaw_cw
    ekf: list[tuple[float, float, float, float]] = field(default_factory=list)  # t, x_fwd, y_right, yaw_cw
    wheel: list[tuple[float, float, float, float]] = field(default_factory=list)
    odometry_msgs: int = 0
    statustext: list[str] = field(default_factory=list)
    goto: list[GotoLeg] = field(default_factory=list)
    # The truth's speed along the rover's heading (+ forward) and the speed the GCS asked for, each stamped
    # with the last truth sample's time when it was sent (the requests carry no autopilot time).
    speed: list[tuple[float, float]] = field(default_factory=list)
    requested: list[tuple[float, float]] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)  # PARAM_VALUEs the GCS asked for (AVOID_MARGIN)
    # Where each segment of the route (or each go-here leg) began: its name and the boot-clock time of the
    # last ground truth then (the picture names the segments by these).
    segments: list[tuple[str, float]] = field(default_factory=list)

    def mark(self, name: str) -> None:
        self.segments.append((name, self.truth[-1][0] if self.truth else 0.0))
