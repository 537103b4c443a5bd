"""A profile of one's own: `rover-bridge init` writes one the loader accepts, and `--params` finds the packaged
profiles from any working directory (one copy of each: params/ in a clone links to the package's)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from rover_bridge.app.cli import build_parser, main
from rover_bridge.app.commands.init import TODO, profile_template
from rover_bridge.params import (
    PROFILES_DIR,
    Profile,
    find_profile,
    iter_params,
    load_profile,
    packaged_profiles,
    profile_from_dict,
)

REPO = Path(__file__).resolve().parents[1]


def test_init_writes_a_profile_the_loader_accepts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "rovers" / "my-rover.toml"  # the folder is made too
    assert main(["init", str(path)]) == 0
    out = capsys.readouterr().out
    assert load_profile(path) == Profile()  # the declared defaults, nothing else
    # It says what to do next, with this path.
    for command in (f"check-params {path}", f"ik --params {path} --v 0 --omega 1", f"calibrate --params {path}"):
        assert command in out and command in path.read_text()
    assert main(["check-params", str(path)]) == 0


def test_init_names_every_value_to_measure_and_sets_it() -> None:
    text = profile_template("x.toml")
    data = tomllib.loads(text)
    declared = {info.path for info in iter_params()}
    assert set(TODO) <= declared  # no hint for a parameter that does not exist
    for key in ("robot.wheel_radius_m", "robot.track_width_m", "output.left_channel", "output.right_channel",
                "encoders.left_index", "encoders.right_index"):
        section, name = key.split(".")
        assert name in data[section], key  # present as a key, ready to edit
        assert TODO[key].startswith("MEASURE"), key
        # the hint comes right before the key's description and the key
        block = re.search(rf"# MEASURE[^\n]*\n(#[^\n]*\n)*{name} = ", text)
        assert block is not None, key
    assert all(len(line) <= 120 for line in text.splitlines())


def test_an_edited_init_profile_loads_with_the_edits(tmp_path: Path) -> None:
    path = tmp_path / "r.toml"
    assert main(["init", str(path)]) == 0
    text = path.read_text().replace("wheel_radius_m = 0.05", "wheel_radius_m = 0.0625")
    text = text.replace("left_index = 0", "left_index = 1").replace("right_index = 1", "right_index = 0")
    path.write_text(text)
    p = load_profile(path)
    assert (p.robot.wheel_radius_m, p.encoders.left_index, p.encoders.right_index) == (0.0625, 1, 0)


def test_init_never_overwrites_without_force(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "mine.toml"
    path.write_text("[robot]\nwheel_radius_m = 0.07\n")
    assert main(["init", str(path)]) == 2
    assert capsys.readouterr().err == f"rover-bridge: {path} exists: choose another PATH, or --force to overwrite it\n"
    assert load_profile(path).robot.wheel_radius_m == 0.07
    assert main(["init", str(path), "--force"]) == 0
    assert load_profile(path) == Profile()


# ------------------------------------------------------------------ the packaged profiles


def test_the_packaged_profiles_are_the_only_copies() -> None:
    assert packaged_profiles() == ["ardupilot-sitl-skid", "default"]
    for name in packaged_profiles():
        link = REPO / "params" / f"{name}.toml"  # the documented place in a clone: a link, not a copy
        assert link.is_symlink() and link.resolve() == (PROFILES_DIR / f"{name}.toml").resolve()
    assert load_profile("default") == Profile()


def test_find_profile_takes_a_path_first_then_a_packaged_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert find_profile("default") == PROFILES_DIR / "default.toml"
    assert find_profile("default.toml") == PROFILES_DIR / "default.toml"
    assert find_profile("ardupilot-sitl-skid") == PROFILES_DIR / "ardupilot-sitl-skid.toml"
    (tmp_path / "default.toml").write_text("[robot]\nwheel_radius_m = 0.07\n")
    assert find_profile("default.toml") == Path("default.toml")  # a file of that name here wins
    assert load_profile("default.toml").robot.wheel_radius_m == 0.07
    assert find_profile("params/default.toml") == Path("params/default.toml")  # a path is never a name


def test_a_missing_profile_says_what_exists_and_how_to_make_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["check-params", "params/my-rover.toml"]) == 2
    assert capsys.readouterr().err == (
        "rover-bridge: params/my-rover.toml: cannot read profile: No such file or directory (packaged profiles: "
        "ardupilot-sitl-skid, default; `rover-bridge init params/my-rover.toml` writes one to start from)\n")


@pytest.mark.parametrize("command", ["run", "replay", "calibrate"])
def test_every_command_with_params_defaults_to_the_packaged_profile(command: str) -> None:
    extra = ["x.tlog"] if command == "replay" else []
    args = build_parser().parse_args([command, *extra])
    assert args.params == "default" and load_profile(args.params) == profile_from_dict({})


def test_the_default_profile_is_found_from_any_directory(tmp_path: Path) -> None:
    """From a directory with no params/ (as after `pip install`): check-params, ik and replay find `default`."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    run = [sys.executable, "-m", "rover_bridge"]
    done = subprocess.run([*run, "ik", "--params", "default", "--v", "0.5", "--omega", "0"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 and "10.000" in done.stdout, done.stderr  # 0.5 m/s / 0.05 m on both wheels
    (tmp_path / "empty.tlog").write_bytes(b"")
    done = subprocess.run([*run, "replay", "empty.tlog"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=120, check=False)
    # The profile is loaded first: what stops the replay is the empty log, not the profile.
    assert done.stderr == "rover-bridge: empty.tlog: the log is empty\n" and done.returncode == 2, done.stderr
