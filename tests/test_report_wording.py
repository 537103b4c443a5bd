"""What the programs say to a person: the demo's latency row names the samples it rests on, `run`'s own log
lines say which autopilot was found and how the run ended, and the emulator and the bridge share a default
address."""

from __future__ import annotations

import pytest

from rover_bridge.app.commands.run import DEFAULT_AUTOPILOT, found_line, stop_line
from rover_bridge.app.composition import BridgeCore
from rover_bridge.app.demo import Summary, latency_row, percentile
from rover_bridge.mavlink.dialect import mavlink
from rover_bridge.mavlink.wire import Incoming, Link
from rover_bridge.params import Profile
from sitl.cli import build_parser


def summary(latencies: list[float]) -> Summary:
    return Summary(distance_m=4.5, wheel_final_m=0.01, wheel_max_m=0.02, ekf_final_m=0.01, ekf_max_m=0.02,
                   wheel_heading_max_deg=1.0, ekf_heading_max_deg=0.5, latency_p50_ms=percentile(latencies, 50),
                   latency_p99_ms=percentile(latencies, 99), latency_samples=len(latencies), rejected=0,
                   odometry_rate_hz=30.0)


@pytest.mark.parametrize(("latencies", "row"), [
    ([], ("request->override latency", "no requests")),
    ([1.18], ("request->override latency, 1 sample", "1.18 ms")),  # the goto scenario's one request
    ([0.3, 0.2, 0.9, 0.25, 0.4], ("request->override latency p50/max, 5 samples", "0.30 / 0.90 ms")),
    ([0.01 * i for i in range(1, 201)], ("request->override latency p50/p99, 200 samples", "1.00 / 1.98 ms")),
])
def test_the_latency_row_says_how_many_samples_it_rests_on(latencies: list[float], row: tuple[str, str]) -> None:
    s = summary(latencies)
    assert latency_row(s.latency_p50_ms, s.latency_p99_ms, s.latency_samples) == row
    line = next(ln for ln in s.table().splitlines() if ln.startswith("request->override"))
    assert line.split() == [*row[0].split(), *row[1].split()]


def test_the_demo_table_stays_aligned_with_the_longer_latency_name() -> None:
    lines = summary([0.5] * 812).table().splitlines()
    assert "request->override latency p50/p99, 812 samples" in lines[5]
    # Every value ends in the same column as the header's "wheel odometry".
    header_end = lines[0].index("wheel odometry") + len("wheel odometry")
    assert all(len(ln.rstrip()) == header_end for ln in lines[1:] if not ln.startswith(("final", "max")))


def test_the_stop_line_says_why_and_what_became_of_the_outputs() -> None:
    assert stop_line("SIGTERM", True, "rc_override") == (
        "stopped (SIGTERM): neutral and release sent, confirmed by the autopilot")
    assert stop_line("--duration 5 s over", False, "rc_override") == (
        "stopped (--duration 5 s over): neutral and release sent, NOT confirmed by the autopilot")
    assert stop_line("an unexpected error, above", True, "servo") == (
        "stopped (an unexpected error, above): trim on both outputs sent, confirmed by the autopilot")
    assert stop_line("SIGINT", None, "rc_override") == "stopped (SIGINT): nothing sent (no vehicle was known)"


def test_the_found_line_names_the_autopilot_where_and_its_mode() -> None:
    core = BridgeCore(Profile())
    heartbeat = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                  mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                                                  | mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 15, 4, 3)
    heartbeat.pack(mavlink.MAVLink(None, srcSystem=7, srcComponent=1))  # sets its source ids
    core.handle(Incoming(Link.AUTOPILOT, heartbeat), 1.0)
    assert core.command.autopilot_alive
    assert found_line(core, "/dev/serial0,921600", again=False) == (
        "autopilot found: system 7, component 1 on /dev/serial0,921600, GUIDED, armed")
    assert found_line(core, "tcp:127.0.0.1:5760", again=True).startswith("autopilot back: system 7, ")


def test_the_emulator_listens_where_run_connects_by_default() -> None:
    sitl_default = build_parser().parse_args([]).connect
    assert sitl_default == "tcpin:127.0.0.1:5760"  # ArduPilot SITL's SERIAL0
    assert sitl_default.replace("tcpin:", "tcp:", 1) == DEFAULT_AUTOPILOT
