"""Every mistake is one line: a path a command cannot use stops it before any work, with exit status 2, one line
on stderr that names the option, the path and what is wrong, and no traceback (rover_bridge.app.paths); a
damaged log is read without pymavlink's thousands of lines about it (rover_bridge.app.chatter), in replay and
in fleet's worker processes alike."""

from __future__ import annotations

import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from rover_bridge.app.chatter import Chatter
from rover_bridge.app.cli import main
from rover_bridge.app.log_frames import format_problem
from rover_bridge.app.loop import TlogWriter
from rover_bridge.app.paths import input_problem, output_folder_problem, output_problem
from rover_bridge.mavlink.dialect import mavlink

REPO = Path(__file__).resolve().parents[1]
SITL_BIN = REPO / "tests" / "data" / "ardurover-skid-wenc.bin"  # a real ArduPilot Rover SITL log, 0.7 MB
DEFAULT = str(REPO / "params" / "default.toml")
NOISE = random.Random(44).randbytes(200_000)  # the "junk.bin": 200 kB of random bytes
# What pymavlink prints about a damaged DataFlash log (its C indexer, its Python reader).
PYMAVLINK_LINE = re.compile(r"bad header|Skipped \d+ bad bytes|unknown msg type|Failed to parse|bad msg at")


def one_line(capsys: pytest.CaptureFixture[str], argv: list[str], code: int = 2) -> str:
    """Run the CLI in this process; the one line it printed on stderr (after checking that it is one)."""
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    return err.rstrip("\n")


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The CLI as a user runs it: its own process, so whatever any library writes to fd 1 and 2 is seen."""
    return subprocess.run([sys.executable, "-m", "rover_bridge", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300, check=False)


def small_tlog(path: Path, frames: int = 5, version: int = 2) -> Path:
    """A .tlog as `run --tlog` writes it: a few autopilot heartbeats."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    if version == 1:
        mav.WIRE_PROTOCOL_VERSION = "1.0"
    clock = iter(1.7e9 + 0.1 * i for i in range(frames))
    with path.open("wb") as f:
        writer = TlogWriter(f, wall_clock=lambda: next(clock))
        for _ in range(frames):
            writer.write(mav.heartbeat_encode(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 0, mavlink.MAV_STATE_ACTIVE).pack(mav))
    return path


def damaged_bin(path: Path) -> Path:
    """The SITL log with 20 kB of noise written over its middle: readable, with thousands of bytes skipped."""
    data = bytearray(SITL_BIN.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 20_000] = NOISE[:20_000]
    path.write_bytes(bytes(data))
    return path


# ---------------------------------------------------------------------------- the cases, one by one

def test_replay_of_a_folder_says_so_and_points_at_fleet(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = one_line(capsys, ["replay", str(tmp_path)])
    assert line == (f"rover-bridge: {tmp_path}: a folder, not a log (replay reads one log; "
                    f"`rover-bridge fleet {tmp_path}` reads every log in it)")


@pytest.mark.parametrize("option", ["--csv", "--plot"])
def test_replay_to_a_missing_folder_stops_before_reading(option: str, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "missing" / "dir" / "x.out"
    others = ["--csv", str(tmp_path / "r.csv")] if option == "--plot" else []
    line = one_line(capsys, ["replay", str(SITL_BIN), *others, option, str(target)])
    assert line == f"rover-bridge: {option} {target}: folder {tmp_path / 'missing' / 'dir'} does not exist"
    assert list(tmp_path.iterdir()) == []  # nothing written: not even the CSV of a replay that did not run


@pytest.mark.parametrize("option", ["--tlog", "--stats-json"])
def test_run_with_an_output_in_a_missing_folder_does_not_start(option: str, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "missing" / "dir" / "a.out"
    t0 = time.monotonic()
    # --duration 30: had it started (and --stats-json failed at the exit, as it did), this would take 30 s.
    line = one_line(capsys, ["run", "--autopilot", "udpout:127.0.0.1:9", "--gcs", "none", "--duration", "30",
                             option, str(target)])
    assert time.monotonic() - t0 < 10.0
    assert line == f"rover-bridge: {option} {target}: folder {tmp_path / 'missing' / 'dir'} does not exist"


def test_replay_of_random_bytes_is_one_line_and_nothing_from_pymavlink(tmp_path: Path) -> None:
    (tmp_path / "junk.bin").write_bytes(NOISE)
    done = run_cli("replay", "junk.bin", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr == ("rover-bridge: junk.bin: not an ArduPilot DataFlash log (no DataFlash message in its "
                           "first 4096 bytes)\n")
    assert done.stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["junk.bin"]


def test_a_damaged_log_is_replayed_with_its_bad_bytes_in_one_summary_line(tmp_path: Path) -> None:
    damaged_bin(tmp_path / "damaged.bin")
    done = run_cli("replay", "damaged.bin", "--params", str(REPO / "params" / "ardupilot-sitl-skid.toml"),
                   cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    noise = [line for line in done.stderr.splitlines() + done.stdout.splitlines() if PYMAVLINK_LINE.search(line)]
    assert noise == []
    # Every line left on stderr is the bridge's own (its log lines, rate limited).
    assert all(" rover_bridge" in line for line in done.stderr.splitlines()), done.stderr[-2000:]
    note = [line for line in done.stdout.splitlines() if "unreadable data" in line]
    assert len(note) == 1
    found = re.fullmatch(r"WARNING: unreadable data in the log \(0 bad frames, (\d+) bad bytes\), skipped; "
                         r"pymavlink's (\d+) lines about it not shown", note[0])
    assert found is not None, note
    bad_bytes, hidden = int(found[1]), int(found[2])
    assert 19_000 <= bad_bytes <= 20_500  # the 20 kB written over, less the messages it happened to hold whole
    assert hidden > 0


def test_fleet_over_a_folder_with_damaged_logs_shows_only_its_own_lines(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "junk.bin").write_bytes(NOISE)
    damaged_bin(logs / "damaged.bin")
    # The progress bar on: in a log file it is a line at every tenth of the logs, each its own line.
    done = run_cli("fleet", "logs", "--workers", "1", "--out", "report", cwd=tmp_path)
    assert done.returncode == 1  # neither log is usable
    assert "Traceback" not in done.stderr
    lines = done.stderr.splitlines()
    assert [line for line in lines if not line.startswith(("fleet: ", "["))] == [], done.stderr[-2000:]
    assert sum(line.startswith("[") for line in lines) == 2
    summary = (tmp_path / "report" / "summary.txt").read_text()
    assert "junk.bin: corrupt: no readable frame in 200000 bytes" in summary
    assert "damaged.bin: corrupt: " in summary


# ---------------------------------------------------------------------------- their kind: what is read

@pytest.mark.parametrize(("name", "content", "problem"), [
    ("empty.bin", b"", "the log is empty"),
    ("junk.tlog", NOISE[:5000], "not a .tlog (it does not start with time-stamped MAVLink frames)"),
    ("log.csv", b"time,x\n0,1\n", "not a .tlog (it does not start with time-stamped MAVLink frames)"),
    ("gone.tlog", None, "no such log"),
])
def test_replay_of_what_is_not_a_log(name: str, content: bytes | None, problem: str, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / name
    if content is not None:
        log.write_bytes(content)
    assert one_line(capsys, ["replay", str(log), "--csv", str(tmp_path / "r.csv")]) == f"rover-bridge: {log}: {problem}"
    assert not (tmp_path / "r.csv").exists()


@pytest.mark.parametrize(("content", "problem"), [
    (None, "a folder, not a profile"),
    (b"", "the profile is empty (`rover-bridge init {path} --force` writes one to start from)"),
    (b"\x91\x00\xff" * 100, "not a TOML profile: not UTF-8 text (byte 0x91 at offset 0)"),
])
@pytest.mark.parametrize("command", [["check-params"], ["ik", "--params"], ["replay", str(SITL_BIN), "--params"]])
def test_a_profile_that_is_no_profile(command: list[str], content: bytes | None, problem: str, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "folder" if content is None else tmp_path / "p.toml"
    if content is None:
        path.mkdir()
    else:
        path.write_bytes(content)
    assert one_line(capsys, [*command, str(path)]) == f"rover-bridge: {path}: {problem.format(path=path)}"


def test_a_binary_key_file_that_is_no_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    key = tmp_path / "key"
    key.write_bytes(b"\xff\xfe" * 20)  # 40 bytes, not text: no kind of key
    key.chmod(0o600)
    line = one_line(capsys, ["run", "--autopilot", "udpout:127.0.0.1:9", "--gcs", "none", "--key-file", str(key)])
    assert line == (f"rover-bridge: security.key_file '{key}': expected 32 raw bytes, 64 hex characters or a "
                    "one-line passphrase")


# ---------------------------------------------------------------------------- their kind: what is written

def test_outputs_that_are_folders_or_under_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a_file = tmp_path / "a-file"
    a_file.write_text("x")
    tlog = str(small_tlog(tmp_path / "in.tlog"))
    cases = {
        f"--csv {tmp_path}: a folder: give the name of a file to write": ["replay", tlog, "--csv", str(tmp_path)],
        f"--plot {a_file}/x.png: {a_file} is a file, not a folder":
            ["replay", tlog, "--csv", str(tmp_path / "r.csv"), "--plot", f"{a_file}/x.png"],
        f"--out {a_file}/sub/p.toml: {a_file} is a file, not a folder":
            ["calibrate", "--yes", "--autopilot", "udpout:127.0.0.1:9", "--out", f"{a_file}/sub/p.toml"],
        f"--out {tmp_path}: a folder: give the name of a file to write":
            ["calibrate", "--yes", "--autopilot", "udpout:127.0.0.1:9", "--out", str(tmp_path)],
        f"--plot {tmp_path}/no/x.png: folder {tmp_path}/no does not exist":
            ["demo", "--quick", "--plot", f"{tmp_path}/no/x.png"],
        f"{a_file}/my.toml: {a_file} is a file, not a folder": ["init", f"{a_file}/my.toml"],
        f"{tmp_path}: a folder: give the name of a file to write": ["init", str(tmp_path), "--force"],
        f"--csv {tlog}: that is the log itself: give another path": ["replay", tlog, "--csv", tlog],
    }
    for message, argv in cases.items():
        assert one_line(capsys, argv) == f"rover-bridge: {message}", argv
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "in.tlog"]


def test_fleet_out_that_is_a_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("distributed")
    tlog = small_tlog(tmp_path / "in.tlog")
    for out, message in ((tlog, f"--out {tlog}: a file, not a folder"),
                         (tlog / "report", f"--out {tlog}/report: {tlog} is a file, not a folder")):
        assert one_line(capsys, ["fleet", str(tlog), "--out", str(out), "--no-progress"]) == f"rover-bridge: {message}"


def test_init_still_makes_the_folders_it_needs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["init", str(tmp_path / "new" / "rover" / "my.toml")]) == 0
    assert main(["check-params", str(tmp_path / "new" / "rover" / "my.toml")]) == 0


def test_a_write_that_fails_after_its_check_is_still_one_line(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    # /dev/full passes every check (a writable file in a writable folder) and fails at the write: a full disk.
    line = one_line(capsys, ["replay", str(small_tlog(tmp_path / "in.tlog")), "--csv", "/dev/full"], code=1)
    assert line == "rover-bridge replay: No space left on device"


# ---------------------------------------------------------------------------- permissions

@contextmanager
def as_an_ordinary_user() -> Iterator[None]:
    """File permissions as an ordinary user meets them. Root reads and writes anything, so as root the process's
    effective ids become nobody's for the while (open() and the checks' os.access both follow them)."""
    if os.geteuid() != 0:
        yield
        return
    os.setegid(65534)
    os.seteuid(65534)
    try:
        yield
    finally:
        os.seteuid(0)
        os.setegid(0)


@pytest.fixture
def shared_dir() -> Iterator[Path]:
    """A folder anyone may enter (pytest's own tmp_path is the user's alone)."""
    path = Path(tempfile.mkdtemp(prefix="rover-bridge-perm-"))
    path.chmod(0o755)
    try:
        yield path
    finally:
        for p in [path, *path.rglob("*")]:
            p.chmod(0o755)
        shutil.rmtree(path)


def test_what_the_user_may_not_read_or_write(shared_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = small_tlog(shared_dir / "locked.tlog")
    log.chmod(0o000)
    readable = small_tlog(shared_dir / "open.tlog")
    readable.chmod(0o644)
    read_only = shared_dir / "read-only"
    read_only.mkdir()
    existing = read_only / "old.csv"
    existing.write_text("x")
    existing.chmod(0o444)
    read_only.chmod(0o555)
    writable = shared_dir / "writable"
    writable.mkdir()
    writable.chmod(0o777)
    main(["check-params", DEFAULT])  # everything imported before the ids change (the venv may be root's only)
    capsys.readouterr()
    # The profile from the shared folder: the checkout itself may sit in a folder only its owner may enter.
    profile = shared_dir / "profile.toml"
    profile.write_text(Path(DEFAULT).read_text(encoding="utf-8"), encoding="utf-8")
    profile.chmod(0o644)
    p = ["--params", str(profile)]
    with as_an_ordinary_user():
        cases = {
            f"{log}: cannot read the log (Permission denied)": ["replay", str(log), *p, "--csv", str(writable / "r")],
            f"--csv {read_only}/x.csv: cannot create a file in folder {read_only} (permission denied)":
                ["replay", str(readable), *p, "--csv", f"{read_only}/x.csv"],
            f"--csv {existing}: cannot write the file (permission denied)":
                ["replay", str(readable), *p, "--csv", str(existing)],
            f"--tlog {read_only}/a.tlog: cannot create a file in folder {read_only} (permission denied)":
                ["run", *p, "--autopilot", "udpout:127.0.0.1:9", "--gcs", "none", "--tlog", f"{read_only}/a.tlog"],
        }
        lines = {message: one_line(capsys, argv) for message, argv in cases.items()}
        folder = output_folder_problem(read_only / "report", "--out")
        made = output_folder_problem(read_only, "--out")
    assert lines == {message: f"rover-bridge: {message}" for message in cases}
    assert folder == f"--out {read_only}/report: cannot create folders in {read_only} (permission denied)"
    assert made == f"--out {read_only}: cannot write in the folder (permission denied)"


# ---------------------------------------------------------------------------- the parts

def test_the_checks_pass_what_is_fine(tmp_path: Path) -> None:
    tlog = small_tlog(tmp_path / "a.tlog")
    assert input_problem(tlog, what="log") is None
    assert input_problem("/dev/null") is None  # a device: not opened to look
    assert output_problem(tmp_path / "new.csv", "--csv") is None
    assert output_problem(tlog, "--csv") is None  # replaced
    assert output_problem("/dev/null") is None
    assert output_problem(tmp_path / "a" / "b" / "c.toml", make_folders=True) is None
    assert output_folder_problem(tmp_path / "x" / "y") is None
    assert output_folder_problem(tmp_path) is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.tlog"]  # checking created nothing


@pytest.mark.parametrize("version", [1, 2])
def test_a_tlog_is_told_from_noise_by_its_first_bytes(version: int, tmp_path: Path) -> None:
    tlog = small_tlog(tmp_path / "a.tlog", version=version)
    assert format_problem(tlog) is None
    one = small_tlog(tmp_path / "one.tlog", frames=1, version=version)
    assert format_problem(one) is None
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(tlog.read_bytes()[:-3])  # a log cut mid-frame is a damaged log, not a wrong one
    assert format_problem(cut) is None
    rng = random.Random(7)
    refused = 0
    for i in range(200):
        noise = tmp_path / f"noise{i}.tlog"
        noise.write_bytes(rng.randbytes(600))
        refused += format_problem(noise) is not None
    assert refused == 200


def test_a_dataflash_log_is_told_from_noise_by_its_first_bytes(tmp_path: Path) -> None:
    assert format_problem(SITL_BIN) is None
    tlog_named_bin = tmp_path / "a.bin"
    tlog_named_bin.write_bytes(small_tlog(tmp_path / "a.tlog").read_bytes())
    assert format_problem(tlog_named_bin) == ("not an ArduPilot DataFlash log (no DataFlash message in its first "
                                              "4096 bytes)")


def test_chatter_counts_what_was_printed_at_either_level_and_shows_none(capfd: pytest.CaptureFixture[str]) -> None:
    chatter = Chatter()
    print("before", file=sys.stderr)
    with chatter.everything():
        os.write(2, b"from C, 1\nfrom C, 2\n")  # below Python, as pymavlink's indexer writes
        print("from Python", file=sys.stderr)
        print("to stdout")
    with chatter.python:
        print("one more", file=sys.stderr)
    print("after")
    captured = capfd.readouterr()
    assert (captured.out, captured.err) == ("after\n", "before\n")
    assert chatter.lines == 5
