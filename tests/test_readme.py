"""The README is part of the product: its parameter table and quick start are checked here."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

from rover_bridge.app.cli import build_parser
from rover_bridge.params import iter_params, markdown_table

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")


def test_parameter_table_is_generated_from_the_declarations() -> None:
    block = re.search(r"<!-- params:begin -->\n(.*?)<!-- params:end -->", README, re.S)
    assert block is not None, "README lost its generated parameter table markers"
    assert block.group(1) == markdown_table(), (
        "README parameter table is stale: regenerate with `rover-bridge check-params --table`")
    for info in iter_params():
        assert f"`{info.path}`" in block.group(1)


def quick_start() -> list[str]:
    section = README.split("## Quick start", 1)[1]
    block = re.search(r"```sh\n(.*?)```", section, re.S)
    assert block is not None
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_quick_start_is_two_commands_demo_then_tests() -> None:
    commands = quick_start()
    assert len(commands) == 2
    assert commands[0].rstrip().endswith("rover-bridge demo")
    assert "pytest" in commands[1]
    for cmd in commands:  # each works on a fresh machine: makes its own venv and installs the project
        assert cmd.startswith("python3 -m venv .venv && . .venv/bin/activate && pip install")


def test_ci_runs_the_quick_start_commands_as_written() -> None:
    script = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    extract = re.search(r"mapfile -t QUICK < <\((.*)\)\n", script)
    assert extract is not None, ".ci/run no longer extracts the quick start from the README"
    out = subprocess.run(["bash", "-c", extract.group(1)], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == quick_start()
    assert 'bash -euo pipefail -c "${QUICK[0]}"' in script and 'bash -euo pipefail -c "${QUICK[1]}"' in script


def test_every_subcommand_the_readme_shows_exists() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    known = set(sub.choices)  # type: ignore[arg-type]
    # Commands as the reader types them: in code blocks and code spans, not in prose.
    code = "\n".join(re.findall(r"```[a-z]*\n(.*?)```", README, re.S) + re.findall(r"`([^`\n]+)`", README))
    used = set(re.findall(r"(?:^|&& |\s)rover-bridge ([a-z][a-z-]+)", code, re.M))
    assert {"demo", "run", "check-params", "ik", "replay"} <= used
    assert used <= known, used - known
