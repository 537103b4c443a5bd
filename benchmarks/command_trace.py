"""A fingerprint of everything the command core says, per scenario, to prove a refactor changes nothing.

    python benchmarks/command_trace.py                       # this tree: one sha256 per scenario
    python benchmarks/command_trace.py --base /path/to/tree  # this tree against another: same or DIFF
    python benchmarks/command_trace.py --base DIR --soak-only # only the seeded random soaks (seconds)

Scenarios: every test (each parametrisation) of the protocol, fault and lockstep test files listed in
TEST_FILES, run by pytest with Hypothesis derandomised, plus seeded random message soaks of the command
core alone (SOAKS). Every call into a CommandCore (handle, tick, next_deadline_s, shutdown, set_direct,
emergency_stop, on_wheels, set_slipping) is recorded with its time and its answer: each Outgoing packed
to bytes (MAVLink 2, its source ids, sequence 0), the consumed flag, a deadline's value, and the core's
state after the call. A call that says nothing (no output, not consumed, no deadline) and leaves the state
as it was is not recorded: it is invisible outside the core (the shell forwards the frame either way), and a
tree that reads one more message type must not differ by the calls alone. The sha256 of that record is the
scenario's fingerprint; a test's pass/fail is shown beside it. Hypothesis runs derandomised and without
the literals it would otherwise collect from the code under test, so both trees get the same examples.
--dump NAME writes one scenario's record as
text for both trees and prints where they part.

With --base, both trees run the same scenarios: the test files are taken from the base tree (the
scenarios that existed before the change) unless --tests-from says otherwise, each tree's own code is
imported (PYTHONPATH; the worker is a script, so the working directory, the scenarios' tree, does not
shadow it), and the table lists every scenario whose fingerprint differs; the exit status is 1 if any
does. Run a tree against itself (--base pointing at an identical checkout) to see which scenarios are not
deterministic: on 2026-12-03 none were (543 of 543, the lockstep tests over UDP loopback included).
The soaks' "modes" variants use only modes whose meaning the change keeps (MANUAL, ACRO, STEERING,
HOLD, GUIDED); the "any mode" soak also drives in modes that change meaning on purpose (AUTO ...).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import hashlib
import json
import logging
import math
import os
import random
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve()
TREE = HERE.parent.parent

TEST_FILES = (
    "test_command_core.py", "test_goto.py", "test_stop_confirmed.py", "test_wheel_control.py", "test_outputs.py",
    "test_robustness_fields.py", "test_robustness_malformed.py", "test_robustness_sequences.py",
    "test_robustness_soak.py", "test_deadlines.py", "test_security.py", "test_calibration.py",
    "test_gyro_hand_over.py", "test_deferred_fusion.py", "test_odometry_wakeups.py",
)
# (name, seed, profile variant, modes, steps)
SAFE_MODES = (0, 1, 3, 4, 15)
ANY_MODES = (0, 1, 2, 3, 4, 5, 7, 10, 11, 12, 15, 16, 99)
SOAKS = tuple(
    (f"soak.{variant}.{kind}.{seed}", seed, variant, modes, 3000)
    for variant in ("open", "closed", "servo", "ramped")
    for kind, modes in (("modes", SAFE_MODES),)
    for seed in (1, 2, 3)
) + tuple((f"soak.{variant}.any_mode.{seed}", seed, variant, ANY_MODES, 3000)
          for variant in ("open", "closed") for seed in (1, 2))


# ----------------------------------------------------------------------------------------- recording

class Recorder:
    """Wraps CommandCore's public methods; hashes every call's time and answer per scenario."""

    def __init__(self, dump: str | None = None) -> None:
        self.results: dict[str, dict[str, Any]] = {}
        self.dump = dump
        self.lines: list[str] | None = None
        self._hash: Any = None
        self._cores: dict[int, int] = {}
        self._keep: list[Any] = []  # the cores, so that their ids are not reused within a scenario
        self.calls = 0

    def begin(self) -> None:
        self._hash = hashlib.sha256()
        self._cores, self._keep, self.calls = {}, [], 0
        self._lines: list[str] = []

    def end(self, name: str, outcome: str) -> None:
        self.results[name] = {"sha256": self._hash.hexdigest(), "calls": self.calls, "outcome": outcome}
        if self.dump is not None and self.dump == name:
            self.lines = self._lines
        self._hash = None
        self._keep = []

    def record(self, core: Any, method: str, args: tuple[Any, ...], result: Any, state_before: Any) -> None:
        h = self._hash
        if h is None:
            return
        silent = result is None or result == [] or (
            hasattr(result, "consumed") and not result.consumed and not result.out)
        if silent and getattr(core, "state", None) is state_before:
            return
        self.calls += 1
        index = self.index(core)
        parts = [str(index), method]
        for a in args:
            parts.append(_arg_text(a))
        parts.append(_result_text(result))
        state = getattr(core, "state", None)
        parts.append(getattr(state, "value", repr(state)))
        line = "|".join(parts)
        h.update(line.encode())
        h.update(b"\n")
        if self.dump is not None:
            self._lines.append(line)

    def index(self, core: Any) -> int:
        """The core's number in the scenario, in the order the cores were made (a silent core keeps its number)."""
        index = self._cores.get(id(core))
        if index is None:
            index = self._cores[id(core)] = len(self._cores)
            self._keep.append(core)
        return index

    def install(self) -> None:
        from rover_bridge.command.core import CommandCore

        made = CommandCore.__init__

        def init(core: Any, *args: Any, **kwargs: Any) -> None:
            made(core, *args, **kwargs)
            if self._hash is not None:
                self.index(core)

        CommandCore.__init__ = init  # type: ignore[method-assign]

        def wrap(name: str) -> None:
            original = getattr(CommandCore, name)

            def wrapper(core: Any, *args: Any, **kwargs: Any) -> Any:
                before = getattr(core, "state", None)
                result = original(core, *args, **kwargs)
                self.record(core, name, (*args, *kwargs.values()), result, before)
                return result

            wrapper.__name__ = name
            setattr(CommandCore, name, wrapper)

        for name in ("handle", "tick", "next_deadline_s", "shutdown", "set_direct", "emergency_stop",
                     "on_wheels", "set_slipping"):
            wrap(name)


def _packed(out: Any) -> str:
    from rover_bridge.mavlink.dialect import mavlink

    mav = mavlink.MAVLink(None, srcSystem=out.src_system, srcComponent=out.src_component)
    data = bytes(copy.copy(out.msg).pack(mav))
    return f"{out.dest.value}:{data.hex()}"


def _arg_text(a: Any) -> str:
    if isinstance(a, float):
        return repr(a)
    if hasattr(a, "msg") and hasattr(a, "link"):  # Incoming: the input; its type is enough to tell calls apart
        return f"{a.link.value}:{a.msg.get_type()}"
    if dataclasses.is_dataclass(a):
        return repr(a)
    return repr(a)


def _result_text(result: Any) -> str:
    if result is None:
        return "-"
    if isinstance(result, float):
        return repr(result)
    if hasattr(result, "consumed"):
        return f"c{int(result.consumed)}[" + ",".join(_packed(o) for o in result.out) + "]"
    if isinstance(result, list):
        return "[" + ",".join(_packed(o) for o in result) + "]"
    return repr(result)


class PytestPlugin:
    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder

    def pytest_configure(self, config: Any) -> None:
        from hypothesis import settings
        from hypothesis.internal.conjecture import providers

        settings.register_profile("command_trace", derandomize=True, database=None, print_blob=False)
        settings.load_profile("command_trace")
        # Hypothesis mixes literals it finds in the code under test into what it generates: the two trees would
        # get different examples from the same test. Without them, a test generates the same inputs on both.
        empty = providers.Constants()
        providers._get_local_constants = lambda: empty

    def pytest_runtest_setup(self, item: Any) -> None:
        self.recorder.begin()

    def pytest_runtest_logreport(self, report: Any) -> None:
        if report.when == "call" or (report.when == "setup" and report.outcome != "passed"):
            self.recorder.end(report.nodeid, report.outcome)


# ----------------------------------------------------------------------------------------- the soak

class SoakPose:
    """A pose source that follows the commanded twist (a perfect rover) with the autopilot's heading."""

    def __init__(self) -> None:
        from rover_bridge.odometry import Pose2D

        self.pose = Pose2D()
        self.now_s = 0.0
        self.reset_counter = 0
        self.fresh = True

    def nav_pose(self, now_s: float) -> Any:
        return self.pose if self.fresh else None

    def nav_pose_at(self, stamp_s: float) -> Any:
        return self.pose

    def autopilot_time_s(self, now_s: float) -> float:
        return now_s

    @property
    def position_fixes(self) -> list[Any]:
        return []

    @property
    def heading(self) -> tuple[float, float]:
        return self.now_s, -self.pose.yaw_rad

    @property
    def gps(self) -> tuple[float, float, float, float]:
        return self.now_s, self.now_s, -35.36 + self.pose.x_m * 9e-6, 149.16 - self.pose.y_m * 1.1e-5

    def move(self, twist: Any, dt_s: float) -> None:
        from rover_bridge.odometry import arc_step

        self.pose = arc_step(self.pose, twist.v_m_s * dt_s, twist.omega_rad_s * dt_s)


def _soak_profile(variant: str) -> Any:
    from rover_bridge.params import LimitsParams, Profile

    p = Profile()
    fast = LimitsParams(max_linear_accel_m_s2=100.0, max_linear_decel_m_s2=100.0, max_angular_accel_rad_s2=500.0)
    if variant == "open":
        return dataclasses.replace(p, limits=fast, control=dataclasses.replace(p.control, mode="open_loop"))
    if variant == "closed":
        return p
    if variant == "servo":
        return dataclasses.replace(p, output=dataclasses.replace(p.output, mode="servo"),
                                   control=dataclasses.replace(p.control, mode="open_loop"))
    jerk = dataclasses.replace(p.limits, max_linear_jerk_m_s3=5.0, max_angular_jerk_rad_s3=30.0)
    return dataclasses.replace(p, limits=jerk)


def run_soak(recorder: Recorder, name: str, seed: int, variant: str, modes: tuple[int, ...], steps: int) -> None:
    """Random traffic from an autopilot and two ground stations into one CommandCore, on a random clock."""
    from rover_bridge.command.core import CommandCore
    from rover_bridge.command.outputs import WheelPwm
    from rover_bridge.kinematics import MeasuredWheels, WheelSpeeds
    from rover_bridge.mavlink.dialect import mavlink
    from rover_bridge.mavlink.identity import Identity
    from rover_bridge.mavlink.report import Reporter
    from rover_bridge.mavlink.wire import Incoming, Link

    logging.disable(logging.CRITICAL)  # the core's log lines: not part of the fingerprint
    rng = random.Random(seed)
    prof = _soak_profile(variant)
    identity = Identity.from_profile(prof)
    pose = SoakPose()
    core = CommandCore(prof, identity, Reporter(identity), pose_source=pose)
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    other = mavlink.MAVLink(None, srcSystem=200, srcComponent=1)
    recorder.begin()
    t = 0.0
    mode = 15
    armed = True
    heartbeats = True
    outcome = "passed"

    def feed(link: Any, mav: Any, msg: Any) -> None:
        wired = mav.decode(bytearray(msg.pack(mav)))
        core.handle(Incoming(link, wired), t)

    def heartbeat() -> None:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
        feed(Link.AUTOPILOT, ap, mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base, mode,
            mavlink.MAV_STATE_ACTIVE, 3))

    def gcs_heartbeat() -> None:
        feed(Link.GCS, gcs, mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                              0, 0, 0, 3))

    def velocity() -> Any:
        kind = rng.randrange(5)
        v, w = rng.uniform(-1.2, 1.2), rng.uniform(-3.5, 3.5)
        target = rng.choice(((1, 1), (1, 1), (1, 0), (2, 1)))
        if kind == 0:
            return mavlink.MAVLink_set_position_target_local_ned_message(
                0, *target, 8, 1479, 0, 0, 0, v, 0, 0, 0, 0, 0, 0, w)
        if kind == 1:
            return mavlink.MAVLink_set_position_target_local_ned_message(
                0, *target, 1, 3527, 0, 0, 0, v, rng.uniform(-1, 1), 0, 0, 0, 0, 0, 0)
        if kind == 2:
            return mavlink.MAVLink_set_position_target_local_ned_message(
                0, *target, 8, 2503, 0, 0, 0, v, 0, 0, 0, 0, 0, rng.uniform(-3, 3), 0)
        if kind == 3:
            return mavlink.MAVLink_manual_control_message(target[0], rng.randint(-1100, 1100), 0, 500,
                                                          rng.randint(-1000, 1000), 0)
        return mavlink.MAVLink_set_position_target_global_int_message(
            0, *target, 6, 3527, 0, 0, 0.0, v, rng.uniform(-1, 1), 0, 0, 0, 0, 0, 0)

    def goto() -> Any:
        kind = rng.randrange(4)
        if kind == 0:
            return mavlink.MAVLink_set_position_target_local_ned_message(
                0, 1, 1, rng.choice((1, 7, 8, 9)), 0x0DF8, rng.uniform(-8, 8), rng.uniform(-8, 8), 0,
                0, 0, 0, 0, 0, 0, 0, 0)
        if kind == 1:
            return mavlink.MAVLink_mission_item_int_message(
                1, 1, 0, 6, 16, 2, 1, 0, 0, 0, 0, int((-35.36 + rng.uniform(-5e-5, 5e-5)) * 1e7),
                int((149.16 + rng.uniform(-5e-5, 5e-5)) * 1e7), 0.0, 0)
        if kind == 2:
            return mavlink.MAVLink_command_int_message(
                1, 1, 0, mavlink.MAV_CMD_DO_REPOSITION, 0, 0, rng.choice((0.0, 0.4)), float(rng.randrange(2)), 0,
                rng.choice((math.nan, 1.0)), int((-35.36 + rng.uniform(-5e-5, 5e-5)) * 1e7),
                int((149.16 + rng.uniform(-5e-5, 5e-5)) * 1e7), 0.0)
        return mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_CHANGE_SPEED, 0, 1.0, rng.choice((0.3, -1.0, -2.0, 0.01)), 0, 0, 0, 0, 0)

    def mode_request() -> Any:
        wanted = rng.choice(modes)
        if rng.random() < 0.3:
            return mavlink.MAVLink_set_mode_message(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, wanted)
        return mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                                    float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(wanted),
                                                    0, 0, 0, 0, 0)

    try:
        heartbeat()
        for _ in range(steps):
            t = round(t + rng.choice((0.001, 0.01, 0.02, 0.05, 0.07, 0.2)), 6)
            if rng.random() < 0.004:
                t = round(t + rng.uniform(0.5, 4.0), 6)  # a stall: timeouts, link loss
            pose.now_s = t
            deadline = core.next_deadline_s(t)
            if deadline <= t:
                core.tick(t)
            pose.move(core.commanded, 0.01)
            r = rng.random()
            if r < 0.10 and heartbeats:
                if rng.random() < 0.08:
                    mode = rng.choice((*modes, 15, 15, 0))
                if rng.random() < (0.3 if not armed else 0.02):
                    armed = not armed
                heartbeat()
            elif r < 0.14:
                heartbeats = rng.random() < 0.9 if not heartbeats else rng.random() > 0.02
            elif r < 0.22:
                feed(Link.AUTOPILOT, ap, mavlink.MAVLink_attitude_message(int(t * 1000), 0, 0, -pose.pose.yaw_rad,
                                                                          0, 0, 0))
            elif r < 0.40:
                feed(Link.GCS, rng.choice((gcs, gcs, other)), velocity())
            elif r < 0.50:
                feed(Link.GCS, gcs, goto())
            elif r < 0.53:
                feed(Link.GCS, gcs, mode_request())
            elif r < 0.56:
                cmd = rng.choice((mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_DO_SET_SERVO))
                feed(Link.AUTOPILOT, ap, mavlink.MAVLink_command_ack_message(
                    cmd, rng.choice((0, 0, 2, 4)), 0, 0, *rng.choice(((255, 191), (1, 191), (0, 0), (255, 190)))))
            elif r < 0.62:
                gcs_heartbeat()
            elif r < 0.72:
                v = core.commanded
                speeds = WheelSpeeds((v.v_m_s - 0.15 * v.omega_rad_s) / 0.05 * rng.uniform(0.7, 1.2),
                                     (v.v_m_s + 0.15 * v.omega_rad_s) / 0.05 * rng.uniform(0.7, 1.2))
                if rng.random() < 0.01:
                    speeds = WheelSpeeds(-speeds.left_rad_s, speeds.right_rad_s)
                core.on_wheels(MeasuredWheels(t, speeds), t)
            elif r < 0.74:
                core.set_slipping(rng.random() < 0.3)
            elif r < 0.745:
                core.set_direct(rng.choice((WheelPwm(1600, 1400), None, None, None, None)), t)
            elif r < 0.75:
                pose.reset_counter += rng.random() < 0.3
                pose.fresh = rng.random() > 0.1
            elif r < 0.76:
                feed(Link.AUTOPILOT, ap, mavlink.MAVLink_nav_controller_output_message(0, 0, 90, 90, 5, 0, 0, 0.1))
            elif r < 0.765:
                core.emergency_stop()
        core.shutdown(t)
        for _ in range(10):
            t = round(t + 0.05, 6)
            if rng.random() < 0.3:
                feed(Link.AUTOPILOT, ap, mavlink.MAVLink_timesync_message(1, (0x5242_5354 << 32) + 1))
            core.tick(t)
    except Exception as exc:  # a crash is a result too: its type goes into the fingerprint
        outcome = f"raised {type(exc).__name__}"
        recorder._hash.update(outcome.encode())
    recorder.end(name, outcome)


# ----------------------------------------------------------------------------------------- running

def worker(tests_dir: str, out_path: str, soak_only: bool, keyword: str | None, dump: str | None) -> None:
    """Inside the subprocess: this interpreter imports the tree on PYTHONPATH."""
    import rover_bridge

    recorder = Recorder(dump)
    recorder.install()
    for name, seed, variant, modes, steps in SOAKS:
        run_soak(recorder, name, seed, variant, modes, steps)
    if not soak_only:
        import pytest

        files = [str(Path(tests_dir) / f) for f in TEST_FILES if (Path(tests_dir) / f).exists()]
        args = [*files, "-q", "-p", "no:cacheprovider", "-m", "not e2e and not ardupilot_sitl",
                "-o", "addopts=", "-W", "ignore", "--rootdir", str(Path(tests_dir).parent)]
        if keyword:
            args += ["-k", keyword]
        pytest.main(args, plugins=[PytestPlugin(recorder)])
    Path(out_path).write_text(json.dumps({"code": str(Path(rover_bridge.__file__).parent.parent),
                                          "results": recorder.results, "dump": recorder.lines}, indent=1))


def run_tree(code: Path, tests_dir: Path, soak_only: bool, keyword: str | None,
             dump: str | None = None) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="command_trace_") as scratch:
        out = Path(scratch) / "trace.json"
        env = dict(os.environ, PYTHONPATH=str(code), PYTHONHASHSEED="0")
        cmd = [sys.executable, str(HERE), "--worker", str(tests_dir), str(out)]
        if soak_only:
            cmd.append("--soak-only")
        if keyword:
            cmd += ["-k", keyword]
        if dump:
            cmd += ["--dump", dump]
        # cwd: the scenarios' tree (tests open params/ relative to it); the script's own directory, not
        # cwd, heads sys.path, so the code still comes from PYTHONPATH (checked below).
        proc = subprocess.run(cmd, cwd=tests_dir.parent, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True)
        if not out.exists():
            sys.stdout.write(proc.stdout)
            raise SystemExit(f"the trace of {code} did not finish (exit {proc.returncode})")
        data: dict[str, Any] = json.loads(out.read_text())
        if Path(data["code"]).resolve() != code.resolve():
            raise SystemExit(f"imported {data['code']}, expected {code}: check PYTHONPATH / the editable install")
        tail = [line for line in proc.stdout.splitlines() if " passed" in line or " failed" in line]
        data["pytest"] = tail[-1] if tail else ""
        return data


def _show_parting(base: list[str], this: list[str], context: int = 3, shown: int = 12) -> None:
    """The first records where the two trees part, with a little context."""
    first = next((i for i, (a, b) in enumerate(zip(base, this, strict=False)) if a != b), min(len(base), len(this)))
    print(f"records: {len(base)} base, {len(this)} here; first difference at record {first}")
    for i in range(max(0, first - context), min(max(len(base), len(this)), first + shown)):
        a = base[i] if i < len(base) else "-"
        b = this[i] if i < len(this) else "-"
        mark = "  " if a == b else "!!"
        print(f"{mark} {i:6d} base {a[:160]}")
        if a != b:
            print(f"{mark} {i:6d} this {b[:160]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, help="another source tree to compare with")
    parser.add_argument("--tests-from", type=Path, help="the tree whose tests/ are the scenarios "
                        "(default: the base tree's with --base, else this tree's)")
    parser.add_argument("--soak-only", action="store_true", help="only the seeded random soaks")
    parser.add_argument("-k", dest="keyword", help="pytest -k expression to select tests")
    parser.add_argument("--json", type=Path, help="also write the results here")
    parser.add_argument("--dump", metavar="SCENARIO", help="print where this scenario's records part")
    parser.add_argument("--worker", nargs=2, metavar=("TESTS_DIR", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(args.worker[0], args.worker[1], args.soak_only, args.keyword, args.dump)
        return
    tests_from = args.tests_from or args.base or TREE
    tests_dir = tests_from.resolve() / "tests"
    ours = run_tree(TREE, tests_dir, args.soak_only, args.keyword, args.dump)
    print(f"this tree: {TREE}  scenarios from {tests_dir}  pytest: {ours['pytest']}")
    if args.base is None:
        for name, r in ours["results"].items():
            print(f"{r['sha256'][:16]}  {r['calls']:8d}  {r['outcome']:7s}  {name}")
        if args.json:
            args.json.write_text(json.dumps(ours, indent=1))
        return
    base = run_tree(args.base.resolve(), tests_dir, args.soak_only, args.keyword, args.dump)
    print(f"base tree: {args.base.resolve()}  pytest: {base['pytest']}")
    a, b = ours["results"], base["results"]
    names = list(dict.fromkeys([*b, *a]))
    same = [n for n in names if n in a and n in b and a[n]["sha256"] == b[n]["sha256"]]
    print(f"{len(same)} of {len(names)} scenarios identical (calls recorded: "
          f"{sum(r['calls'] for r in a.values())} here, {sum(r['calls'] for r in b.values())} base)")
    print(f"{'scenario':90s} {'base':16s} {'this':16s} outcome (base / this)")
    for n in names:
        if n in same:
            continue
        ra, rb = a.get(n), b.get(n)
        print(f"{n[:90]:90s} {(rb or {}).get('sha256', '-')[:16]:16s} {(ra or {}).get('sha256', '-')[:16]:16s} "
              f"{(rb or {}).get('outcome', '-')} / {(ra or {}).get('outcome', '-')}")
    if args.json:
        args.json.write_text(json.dumps({"this": ours, "base": base}, indent=1))
    if args.dump:
        _show_parting(base.get("dump") or [], ours.get("dump") or [])
    if len(same) != len(names):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
