"""Robot profiles: every shipped profile loads; a bad file reports every problem at once."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

import pytest

from rover_bridge.errors import ConfigError
from rover_bridge.params import Profile, iter_params, load_profile, markdown_table, profile_from_dict, profile_to_toml

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
SHIPPED = sorted(PARAMS_DIR.glob("*.toml"))


def test_both_required_profiles_are_shipped() -> None:
    names = {p.name for p in SHIPPED}
    assert {"default.toml", "ardupilot-sitl-skid.toml"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_every_shipped_profile_loads_and_round_trips(path: Path) -> None:
    profile = load_profile(path)
    assert isinstance(profile, Profile)
    # The resolved TOML that check-params prints loads back to the same profile.
    assert profile_from_dict(tomllib.loads(profile_to_toml(profile))) == profile


LOOP_GAINS = {"kp", "ki_1_s", "reference_s", "turn_kp", "turn_ki_1_s", "turn_reference_s"}


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_no_shipped_profile_sets_loop_gains(path: Path) -> None:
    # Issue 42: the loop's defaults hold on every plant; gains come from `calibrate`, not from a profile.
    control = tomllib.loads(path.read_text(encoding="utf-8")).get("control", {})
    assert not LOOP_GAINS & set(control), sorted(LOOP_GAINS & set(control))


def test_default_profile_is_the_small_indoor_rover() -> None:
    r = load_profile(PARAMS_DIR / "default.toml").robot
    assert (r.wheel_radius_m, r.track_width_m, r.max_wheel_rpm) == (0.05, 0.30, 200.0)


def test_sitl_skid_profile_matches_the_sitl_model() -> None:
    p = load_profile(PARAMS_DIR / "ardupilot-sitl-skid.toml")
    # SIM_Rover skid: max_speed 4 m/s per side at full PWM, 140 deg/s yaw per unit of differential.
    assert p.robot.max_wheel_rad_s * p.robot.wheel_radius_m == pytest.approx(4.0, rel=1e-8)
    assert p.robot.track_width_m == pytest.approx(4.0 / (140.0 * math.pi / 180.0), rel=1e-9)
    assert (p.output.left_channel, p.output.right_channel) == (1, 3)
    assert (p.output.pwm_min, p.output.pwm_trim, p.output.pwm_max) == (1000, 1500, 2000)


def test_profile_is_frozen() -> None:
    p = load_profile(PARAMS_DIR / "default.toml")
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.robot.wheel_radius_m = 1.0  # type: ignore[misc]


BAD = """
[robot]
wheel_radius = 0.05            # unknown key
track_width_m = "wide"         # wrong type
max_wheel_rpm = -5.0           # out of range

[output]
pwm_min = 1600                 # cross-field: pwm_min >= pwm_trim
pwm_trim = 1500
left_channel = true            # bool where an integer belongs

[limts]                        # unknown section
max_linear_m_s = 1.0

[limits]
max_linear_accel_m_s2 = true   # bool where a number belongs
"""


def test_a_file_with_many_mistakes_lists_all_of_them(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(BAD, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_profile(f)
    problems = info.value.problems
    expected = [
        "robot.wheel_radius: unknown key (did you mean 'wheel_radius_m'?)",
        "robot.track_width_m: expected a number, got str 'wide'",
        "robot.max_wheel_rpm: -5.0 is out of range, expected a value in (0, 20000]",
        "output.left_channel: expected an integer, got bool True",
        "[limts]: unknown section (did you mean [limits]?)",
        "limits.max_linear_accel_m_s2: expected a number, got bool True",
        "output: expected pwm_min < pwm_trim < pwm_max, got 1600 / 1500 / 2000",
    ]
    assert len(problems) == len(expected), problems
    for want in expected:
        assert any(p.startswith(f"{f}: {want}") for p in problems), (want, problems)


def test_cross_field_check_is_skipped_when_its_own_key_is_bad() -> None:
    # pwm_min is rejected; comparing the default 1000 standing in for it would be misleading.
    with pytest.raises(ConfigError) as info:
        profile_from_dict({"output": {"pwm_min": "low", "pwm_trim": 900}}, source="x")
    assert info.value.problems == ["x: output.pwm_min: expected an integer, got str 'low'"]


def test_other_cross_field_checks() -> None:
    with pytest.raises(ConfigError) as info:
        profile_from_dict({"output": {"left_channel": 2, "right_channel": 2},
                           "encoders": {"left_index": 1, "right_index": 1},
                           "security": {"require_signed_commands": True,
                                        "allowed_sources": ["255:*", "x:1"]}})
    text = "\n".join(info.value.problems)
    assert "left_channel and right_channel are both 2" in text
    assert "left_index and right_index are both 1" in text
    assert "require_signed_commands = true needs key_file" in text
    assert "allowed_sources[1]" in text and "allowed_sources[0]" not in text
    assert len(info.value.problems) == 4


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"robot": {"wheel_radius_m": True}}, "robot.wheel_radius_m: expected a number, got bool True"),
        ({"robot": {"wheel_radius_m": 0.0}}, "robot.wheel_radius_m: 0.0 is out of range"),
        ({"robot": {"wheel_radius_m": math.nan}}, "robot.wheel_radius_m: expected a finite number"),
        ({"output": {"pwm_max": 2000.0}}, "output.pwm_max: expected an integer, got float 2000.0"),
        ({"output": {"mode": "rc_overide"}}, "did you mean 'rc_override'?"),
        ({"output": {"left_reversed": 1}}, "output.left_reversed: expected true or false, got int 1"),
        ({"robot": 5}, "robot: expected a table [robot], got int"),
        ({"command": {"accept_target_components": [1, 300]}},
         "command.accept_target_components[1]: 300 is out"),
    ],
)
def test_single_mistakes(doc: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        profile_from_dict(doc)
    assert len(info.value.problems) == 1
    assert message in info.value.problems[0]


def test_ints_are_accepted_for_floats_and_optional_keys_can_be_set() -> None:
    p = profile_from_dict({"robot": {"track_width_m": 1, "left_wheel_radius_m": 0.051}})
    assert p.robot.track_width_m == 1.0 and isinstance(p.robot.track_width_m, float)
    assert p.robot.left_radius_m == 0.051 and p.robot.right_radius_m == p.robot.wheel_radius_m


def test_unreadable_and_invalid_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read profile"):
        load_profile(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("[robot\nwheel_radius_m = ", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_profile(broken)


def test_markdown_table_has_one_row_per_declared_parameter() -> None:
    table = markdown_table().splitlines()
    infos = list(iter_params())
    assert len(table) == 2 + len(infos)
    for info in infos:
        assert any(row.startswith(f"| `{info.path}` |") for row in table)
    assert any("`robot.wheel_radius_m` | float | m | `0.05` | (0, 2]" in row for row in table)
