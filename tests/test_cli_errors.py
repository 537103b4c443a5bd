"""Every mistake is one line: a damaged log is read without pymavlink's thousands of lines about it
(rover_bridge.app.chatter), in replay and in fleet's worker processes alike."""

from __future__ import annotations

import os
import random
import re
import subprocess
import sys
from pathlib import Path

import pytest

from rover_bridge.app.chatter import Chatter

REPO = Path(__file__).resolve().parents[1]
SITL_BIN = REPO / "tests" / "data" / "ardurover-skid-wenc.bin"  # a real ArduPilot Rover SITL log, 0.7 MB
DEFAULT = str(REPO / "params" / "default.toml")
NOISE = random.Random(44).randbytes(200_000)  # the "junk.bin": 200 kB of random bytes
# What pymavlink prints about a damaged DataFlash log (its C indexer, its Python reader).
PYMAVLINK_LINE = re.compile(r"bad header|Skipped \d+ bad bytes|unknown msg type|Failed to parse|bad msg at")


def run_cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The CLI as a user runs it: its own process, so whatever any library writes to fd 1 and 2 is seen."""
    return subprocess.run([sys.executable, "-m", "rover_bridge", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300, check=False)


def damaged_bin(path: Path) -> Path:
    """The SITL log with 20 kB of noise written over its middle: readable, with thousands of bytes skipped."""
    data = bytearray(SITL_BIN.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 20_000] = NOISE[:20_000]
    path.write_bytes(bytes(data))
    return path


# ---------------------------------------------------------------------------- a damaged log, quietly

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
