"""The README and docs/ are part of the product: the quick start, the generated parameter reference, the README's
length, line widths and links are checked here."""

from __future__ import annotations

import argparse
import re
import subprocess
from pathlib import Path

from rover_bridge.app.cli import build_parser
from rover_bridge.params import iter_params, markdown_table

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")
PARAMETERS = REPO / "docs" / "parameters.md"
README_MAX_LINES = 300
MARKDOWN_MAX_WIDTH = 120  # characters, outside tables


def markdown_files() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def test_parameter_table_is_generated_from_the_declarations() -> None:
    text = PARAMETERS.read_text(encoding="utf-8")
    block = re.search(r"<!-- params:begin -->\n(.*?)<!-- params:end -->", text, re.S)
    assert block is not None, "docs/parameters.md lost its generated parameter table markers"
    assert block.group(1) == markdown_table(), (
        "docs/parameters.md's table is stale: regenerate it with `rover-bridge check-params --table`")
    for info in iter_params():
        assert f"`{info.path}`" in block.group(1)


def test_the_readme_is_short() -> None:
    lines = README.splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move detail into docs/"


def test_no_markdown_line_is_wider_than_120_characters_outside_tables() -> None:
    wide = [f"{path.relative_to(REPO)}:{number}: {len(line)} characters"
            for path in markdown_files()
            for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
            if len(line) > MARKDOWN_MAX_WIDTH and not line.lstrip().startswith("|")]
    assert not wide, wide


def test_every_relative_link_in_the_readme_and_docs_exists() -> None:
    missing = []
    for path in markdown_files():
        text = path.read_text(encoding="utf-8")
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue  # http:, https:, mailto:
            file, _, fragment = target.partition("#")
            dest = (path.parent / file).resolve() if file else path
            if not dest.exists():
                missing.append(f"{path.relative_to(REPO)}: {target}")
            elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
                missing.append(f"{path.relative_to(REPO)}: {target} (no such heading)")
    assert not missing, missing


def anchors(path: Path) -> set[str]:
    """GitHub's anchors of a Markdown file's headings: lower case, punctuation dropped, spaces to hyphens."""
    headings = re.findall(r"^#+ (.+)$", path.read_text(encoding="utf-8"), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


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


def code_in(text: str) -> list[str]:
    """What a reader types: the lines of code blocks and the code spans, not the prose."""
    blocks = re.findall(r"```[a-z]*\n(.*?)```", text, re.S)
    return [line for block in blocks for line in block.splitlines()] + re.findall(r"`([^`\n]+)`", text)


def test_every_command_and_option_the_docs_show_exists() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    commands: dict[str, argparse.ArgumentParser] = sub.choices  # type: ignore[assignment]
    unknown, used = [], set()
    for path in markdown_files():
        for line in code_in(path.read_text(encoding="utf-8")):
            for name, rest in re.findall(r"(?:^|&& |\s|/)rover-bridge ([a-z][a-z-]+)([^#&;|`]*)", line):
                used.add(name)
                if name not in commands:
                    unknown.append(f"{path.name}: rover-bridge {name}")
                    continue
                options = commands[name]._option_string_actions
                unknown += [f"{path.name}: rover-bridge {name} {flag}"
                            for flag in re.findall(r"(?:^|\s)(--[a-z][a-z-]*)", rest) if flag not in options]
    assert {"demo", "init", "run", "check-params", "ik", "calibrate", "replay", "fleet"} <= used
    assert not unknown, unknown


def test_the_readme_leads_with_init_and_the_shipped_ardupilot_parameters() -> None:
    code = "\n".join(code_in(README))
    assert re.search(r"rover-bridge init (\S+)", code) is not None
    profile = re.search(r"rover-bridge init (\S+)", code).group(1)  # type: ignore[union-attr]
    assert f"--params {profile}" in code  # the commands after it use the profile init wrote
    assert "deploy/ardupilot-rover.parm" in README and (REPO / "deploy" / "ardupilot-rover.parm").exists()
