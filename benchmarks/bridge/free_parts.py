"""`replay --without PART` and `cpu --without PART`: one part of the bridge's filter made to cost nothing in the
process that imports this (the cpu table's bridge under test imports only this module of the benchmarks)."""

from __future__ import annotations

from typing import Any

WITHOUT = ("judge", "update", "predict", "filterpy")  # replay/cpu --without: the filter's parts that can be made free


def make_free(part: str) -> None:
    """Make one part of the filter cost nothing in this process (replay and cpu --without): what trimming it could
    buy at most. judge: the first 50 wheel intervals are judged, every later one gets the 50th's verdict;
    update / predict: filterpy's update / prediction (with the models it runs) are skipped; filterpy: only
    filterpy's own predict and update are (the models still run, the state stays where it started)."""
    from rover_bridge.estimate import arc_ekf, wheel_judge

    if part == "judge":
        real = wheel_judge.WheelJudge.judge
        memo: list[Any] = []

        def judge(self: Any, t_s: float, w: Any, x: Any, P: Any) -> Any:  # noqa: N803
            if len(memo) < 50:
                memo.append(real(self, t_s, w, x, P))
            return memo[-1]
        wheel_judge.WheelJudge.judge = judge  # type: ignore[method-assign]
    elif part == "update":
        arc_ekf.ArcKalmanFilter.update_rows = lambda self, *a, **k: None  # type: ignore[method-assign]
    elif part == "predict":
        arc_ekf.ArcKalmanFilter.predict_arc = lambda self, dt_s: None  # type: ignore[method-assign]
    elif part == "filterpy":
        from filterpy.kalman import KalmanFilter

        KalmanFilter.predict = lambda self, *a, **k: None
        KalmanFilter.update = lambda self, *a, **k: None
