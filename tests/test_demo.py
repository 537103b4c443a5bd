"""`rover-bridge demo` end to end: real processes on loopback, its table's numbers and its picture."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e


def test_demo_runs_reports_sane_numbers_and_draws_a_png(tmp_path: Path) -> None:
    png = tmp_path / "demo.png"
    summary_json = tmp_path / "summary.json"
    env = dict(os.environ, ROVER_BRIDGE_DEMO_JSON=str(summary_json))
    proc = subprocess.run([sys.executable, "-m", "rover_bridge", "demo", "--quick", "--plot", str(png)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "final position error" in proc.stdout and "EKF" in proc.stdout
    s = json.loads(summary_json.read_text())
    assert s["distance_m"] > 3.0  # the quick route is about 4.5 m
    # Clean scenario: both estimates stay close to the emulator's ground truth.
    assert s["ekf_final_m"] < 0.10
    assert s["ekf_max_m"] < 0.15
    assert s["ekf_heading_max_deg"] < 6.0
    assert s["wheel_final_m"] < 0.10
    assert 27.0 <= s["odometry_rate_hz"] <= 33.0  # [odometry] rate_hz = 30, +-10 %
    assert s["rejected"] == 0
    assert s["latency_p50_ms"] > 0.0  # measured from the bridge's own .tlog
    # A real PNG: signature, then an IHDR chunk with a non-empty image.
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    assert width > 200 and height > 200


def test_goto_demo_reaches_each_target_and_says_how_close(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "rover_bridge", "demo", "--scenario", "goto", "--quick"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # Its own picture, beside (never over) the clean route's demo.png.
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["demo-goto.png"]
    assert "picture: demo-goto.png" in proc.stdout
    rows = [line.split() for line in proc.stdout.splitlines() if line.strip().endswith(" s") and " N " in line]
    assert [r[4] for r in rows] == ["MISSION_ITEM_INT", "DO_REPOSITION", "LOCAL_NED", "GLOBAL_INT",
                                    "MISSION_ITEM_INT"]
    errors = [float(r[5]) for r in rows]
    assert all(e <= 0.15 for e in errors), proc.stdout  # navigation.arrival_radius_m, by ground truth


def test_demo_leaves_no_process_behind_when_interrupted(tmp_path: Path) -> None:
    import signal
    import time

    # SIGINT as a terminal leaves it (default): a harness started in the background (`cmd &` in a script)
    # passes SIGINT ignored to its children, and then the demo would never see the Ctrl-C below.
    proc = subprocess.Popen([sys.executable, "-m", "rover_bridge", "demo", "--quick", "--plot", "none"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        # Let it get the two children running, then Ctrl-C it as a terminal would.
        deadline = time.monotonic() + 60
        children: list[int] = []
        while time.monotonic() < deadline and len(children) < 2:
            children = _children(proc.pid)
            time.sleep(0.2)
        assert len(children) >= 2, "demo did not start the emulator and the bridge"
        time.sleep(1.0)
        os.killpg(proc.pid, signal.SIGINT)
        assert proc.wait(timeout=30) == 130
        out = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        assert "demo interrupted" in out and "Traceback" not in out
        for pid in children:
            assert not _alive(pid), f"child {pid} survived the demo's Ctrl-C"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_demo_killed_outright_takes_its_emulator_and_bridge_with_it(tmp_path: Path) -> None:
    """SIGKILL (or a SIGTERM / SIGHUP it does not catch) runs none of the demo's own clean-up; its
    children, in sessions of their own, must still not run on (a bridge and an emulator burning a
    laptop's CPU after its terminal closed)."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "rover_bridge", "demo", "--quick", "--plot", "none"],
                            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    children: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(children) < 2:
            children = _children(proc.pid)
            time.sleep(0.2)
        assert len(children) >= 2, "demo did not start the emulator and the bridge"
        time.sleep(1.0)
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.monotonic() + 15  # the bridge stops the rover first (at most a second or so)
        while time.monotonic() < deadline and any(_alive(pid) for pid in children):
            time.sleep(0.1)
        assert not [pid for pid in children if _alive(pid)], "the demo's children outlived it"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in children:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_the_demo_stamps_the_true_yaw_with_the_wheel_reading_of_its_step_whenever_it_is_read() -> None:
    # SIMSTATE has no time field. The emulator sends it in the EXTRA1 group, right before the WHEEL_DISTANCE
    # of the same step, so that reading's time_usec is its time. Stamping it by its arrival made it as late
    # as the demo read it (a busy machine: a third of a second, 30 deg of a spin); pairing it with the last
    # position stamp (another phase) up to a period late. A spin at 1.5 rad/s, positions at 20 Hz, the EXTRA1
    # step 25 ms out of their phase; the demo reads nothing for 0.3 s twice (no arrival time is used).
    from rover_bridge.app.demo import Demo, errors_over_time
    from rover_bridge.mavlink.dialect import mavlink
    from rover_bridge.odometry import WheelOdometry

    demo = Demo(progress=None)
    wheel = WheelOdometry(track_width_m=0.30)
    rate = 1.5
    for k in range(40):
        t = 10.0 + 0.05 * k
        demo._collect(mavlink.MAVLink_local_position_ned_message(round(t * 1000), 0, 0, 0, 0, 0, 0), wheel)
        ts = t + 0.025
        demo._collect(mavlink.MAVLink_simstate_message(0, 0, rate * ts, 0, 0, 0, 0, 0, 0, 0, 0), wheel)
        demo._collect(mavlink.MAVLink_wheel_distance_message(round(ts * 1e6), 2, [0.0] * 16), wheel)
        demo.series.ekf.append((t, 0.0, 0.0, rate * t))  # an estimate exactly right at its stamps
    demo.series.wheel = [(t, 0.0, 0.0, rate * t) for t, _ in demo.series.truth_yaw]
    errs = errors_over_time(demo.series)
    assert len(errs) > 30
    assert max(e[4] for e in errs) < 0.05  # degrees; pairing with the last position stamp gave 2.1 deg


def test_the_demo_judges_each_estimate_at_its_own_samples_not_between_them() -> None:
    # A turn whose rate changes (10 rad/s^2), the truth's yaw at 50 Hz (the wheels' stamps), positions at 20 Hz.
    # Both estimates are exact at their own stamps, the wheels at 50 Hz and the EKF at the 33-48 ms ODOMETRY of a
    # real-time run. A straight line across the EKF's gaps put 0.15 deg on it that no message carried.
    from rover_bridge.app.demo import errors_over_time
    from rover_bridge.app.demo_series import Series

    def yaw(t: float) -> float:
        return 5.0 * (t - 10.0) ** 2  # CW rad, from rest at 10 s

    series = Series()
    series.truth = [(10.0 + 0.05 * k, 0.0, 0.0, 0.0) for k in range(41)]
    series.truth_yaw = [(10.0 + 0.02 * k, yaw(10.0 + 0.02 * k)) for k in range(101)]
    series.wheel = [(t, 0.0, 0.0, y) for t, y in series.truth_yaw]
    stamps, t = [], 10.0
    while t <= 12.0:
        stamps.append(t)
        t += 0.048 if len(stamps) % 2 else 0.033
    series.ekf = [(s, 0.0, 0.0, yaw(s)) for s in stamps]
    errs = errors_over_time(series)
    assert len(errs) > 35
    assert max(e[3] for e in errs) < 1e-9  # the wheels, at the truth's own stamps
    # the EKF between the truth's 20 ms samples: at most their straight line's error (0.03 deg at 10 rad/s^2)
    assert max(e[4] for e in errs) < 0.03


def test_obstacles_demo_stops_short_of_the_wall_and_the_post_and_draws_it(tmp_path: Path) -> None:
    # The scenario as `rover-bridge demo --scenario obstacles` runs it (run_demo = Demo.run + report), in this
    # process so that the picture's panels can be read: GUIDED, 1.0 m/s at a wall 8 m ahead, then at a post,
    # the emulator's SITL proximity sensor (PRX1_TYPE 10), AVOID_MARGIN as the autopilot reports it (2 m).
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from rover_bridge.app.demo import Demo, report
    from rover_bridge.app.demo_obstacles import obstacle_legs
    from rover_bridge.app.demo_obstacles_picture import obstacles_figure

    demo = Demo(scenario="obstacles", progress=None, workdir=tmp_path / "run")
    try:
        summary, errs, stats = demo.run()
    finally:
        demo.stop_processes()
    png, lines = tmp_path / "demo-obstacles.png", []
    report(demo, summary, errs, png, lines.append)  # raises if the rover touched an obstacle
    margin = demo.series.params["AVOID_MARGIN"]
    assert margin == 2.0
    legs = obstacle_legs(demo.series, margin)
    assert [(leg.obstacle, leg.phase) for leg in legs] == [("wall", "to the wall"), ("post", "to the post")]
    for leg in legs:
        # The rover's centre, by ground truth: it stopped near the margin and never came much inside it.
        assert margin - 0.2 <= leg.rest_m <= margin + 0.6, leg
        assert leg.closest_m >= margin - 0.2 and not leg.touched, leg
        assert abs(leg.rest_speed_m_s) < 0.05, leg  # at rest, while the GCS still asks for 1.0 m/s
    # It was the bridge that stopped it: full speed on the way, then capped for an obstacle.
    assert max(v for _, v in demo.series.speed) > 0.9
    assert min(v for _, v in demo.series.speed) < -0.3  # and backing away from the post was not held back
    assert stats["command"]["avoid.obstacle_stop"] >= 2
    text = "\n".join(lines)
    assert "closest approach" in text and "at rest" in text and f"{legs[0].rest_m:.2f} m" in text
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    fig = obstacles_figure(demo.series, legs, "obstacles")
    try:
        panels = [(ax.get_title(), ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes]
        assert len(panels) == 4 and all(y for _, _, y in panels), panels
        assert [y for _, _, y in panels[2:]] == ["speed [m/s]", "distance [m]\n(rover's centre)"]
        assert panels[0][0] == "obstacles" and panels[1][0].startswith("zoom: the stop at the wall")
        assert [t.get_text() for t in fig.axes[2].get_legend().get_texts()] == ["requested by the GCS",
                                                                             "driven (ground truth)"]
        assert [t.get_text() for t in fig.axes[3].get_legend().get_texts()] == ["to the wall", "to the post",
                                                                             "AVOID_MARGIN"]
        map_texts = [t.get_text() for t in fig.axes[0].texts]
        assert f"stopped {legs[0].rest_m:.2f} m\nfrom the wall" in map_texts
        assert f"stopped {legs[1].rest_m:.2f} m\nfrom the post" in map_texts
        legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert "AVOID_MARGIN (2.00 m) from the obstacles" in legend and "ground truth" in legend
    finally:
        plt.close(fig)
