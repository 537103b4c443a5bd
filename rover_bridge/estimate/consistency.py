"""Do the wheels and the gyro agree, over the last second? (pure): what decides whether the filter
trusts the wheels' heading.

Wheel encoders count: the heading they accumulate has the error of one reading, however far the
rover drives, as long as the wheels roll on the ground with the geometry of the profile. A gyro's
heading drifts (its bias, its noise, its sampling of a rate that changes between samples). So the
filter holds the heading to the wheels, and learns the gyro's bias from them, for as long as the two
agree; it lets the gyro hold it while they do not (gyrodometry: Borenstein and Feng, 1996, use the
gyro only where gyro and odometry disagree).

They agree when, over a window of WINDOW_S, the heading the wheels turned is the one the gyro turned
(its bias removed) within AGREE_SIGMA times what the readings' noise, the gyro's noise and the bias's
and the geometry's uncertainty (at each interval's time: calibration learns it) allow. A wheel radius
2 % off shows at 0.5 m/s within a fifth of a second, a track 3 % off within a few degrees of turning;
slip, as the interval's own slip test (wheel_judge.py) sees it, interrupts the window.
"""

from __future__ import annotations

from collections import deque

WINDOW_S = 1.0
MIN_SPAN_S = 0.2  # a window shorter than this is not judged
AGREE_SIGMA = 5.0
MIN_DIST_M = 0.1
MIN_TURN_RAD = 0.2
AGREE_WINDOWS = 2


class ConsistencyWindow:
    """Running sums of the wheels' and the gyro's heading changes per interval over the last WINDOW_S."""

    def __init__(self) -> None:
        # (dt_s, wheels' turn - the turn they would read at the gyro's rate, gyro's noise variance, |distance| m,
        # |wheels' turn|, the geometry's share of the disagreement, 1 sigma)
        self._intervals: deque[tuple[float, float, float, float, float, float]] = deque()
        self._sums = [0.0] * 6
        self._agreed = 0  # windows in a row that agreed
        self.disagreement_rad = 0.0  # the wheels' turn minus the gyro's over the last window that disagreed

    def clear(self) -> None:
        self._intervals.clear()
        self._sums = [0.0] * 6

    def add(self, dt_s: float, wheels_turn_rad: float, disagreement_rad: float, gyro_var: float, dist_m: float,
            geometry_rad: float = 0.0) -> None:
        """One wheel interval: the wheels' turn, its difference to the turn they would read at the gyro's rate
        (bias removed) with the filter's geometry, that turn's noise variance, the distance driven, and how
        much of the difference the geometry's uncertainty at the time allows (1 sigma: while the filter
        learns the geometry, each interval's difference is the one with the geometry it had then)."""
        item = (dt_s, disagreement_rad, gyro_var, abs(dist_m), abs(wheels_turn_rad), geometry_rad)
        self._intervals.append(item)
        sums = self._sums
        for i, v in enumerate(item):
            sums[i] += v
        while self._intervals and sums[0] - self._intervals[0][0] >= WINDOW_S - 1e-9:
            for i, v in enumerate(self._intervals.popleft()):
                sums[i] -= v

    def agree(self, bias_var: float, reading_var: float) -> bool | None:
        """Whether they agree (module docstring): False at once when a window disagrees, True after
        AGREE_WINDOWS windows in a row agreed, each over at least MIN_DIST_M or MIN_TURN_RAD of motion (an
        agreement over too little motion proves nothing, and one window can hide a radius error against a
        track error that cancels it over a straight and a turn), and with the bias's uncertainty at most half the
        allowance (else it may hide their error, which trusted wheels would teach the gyro as a bias, the yaw
        moving with it over all the time the bias was unknown: accuracy.py --moving miscalibrated flipped 180 deg);
        else None (no new verdict). `reading_var` is one reading's heading variance. The geometry's shares add up
        as one error (fully correlated)."""
        span, d, gyro_var, dist, angle, geometry = self._sums
        if span < MIN_SPAN_S:
            return None
        var = 2.0 * reading_var + gyro_var + bias_var * span * span + geometry * geometry
        if d * d > AGREE_SIGMA ** 2 * var:
            self.disagreement_rad = d
            self.clear()
            self._agreed = 0
            return False
        if span < WINDOW_S - 1e-9 or (dist < MIN_DIST_M and angle < MIN_TURN_RAD):
            return None  # an agreement is judged over a whole window, with motion in it
        if bias_var * span * span > var - bias_var * span * span:
            return None  # the bias's uncertainty could hide a disagreement: that agreement proves nothing
        self.clear()
        self._agreed += 1
        return True if self._agreed >= AGREE_WINDOWS else None
