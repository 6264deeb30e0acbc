"""The flag builder: forms derived from annotations, help and defaults from the fields."""

from __future__ import annotations

import argparse
from typing import Literal

import pytest
from pydantic import BaseModel, Field

from zoffload.cli.daemons import ROBOT_SPELLINGS, robot_parser
from zoffload.cli.flags import Spelling, add_settings_flags, flag_values, option_name
from zoffload.runtime.config import PerceptionSettings, RobotSettings
from zoffload.runtime.loading import load_settings


class Arm(BaseModel):
    """The arm."""

    speed: float = Field(default=0.5, gt=0, description="joint speed in rad/s")
    homed: bool = Field(default=True, description="home at start")


class Toy(BaseModel):
    """A model with one field of each form."""

    name: str = Field(default="t1", description="the toy's name")
    count: int | None = Field(default=None, description="how many; unset: all")
    gain: float = Field(default=1.5, description="the gain, 100% = 1")
    mode: Literal["a", "b"] = Field(default="a", description="the mode")
    verbose: bool = Field(default=False, description="say more")
    window: tuple[float, float] = Field(default=(0.1, 0.2), description="the window")
    peers: list[str] = Field(default_factory=list, description="peer to talk to")
    arm: Arm = Field(default_factory=Arm, description="the arm")


def _toy_parser(spellings: dict[str, Spelling] | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="toy")
    add_settings_flags(p, Toy, spellings, title="toy settings")
    return p


def test_option_names_follow_the_key_path() -> None:
    assert option_name("voxel") == "--voxel"
    assert option_name("perception.cpu_max") == "--perception.cpu-max"


def test_each_annotation_gets_its_form() -> None:
    argv = ["--name", "x", "--count", "3", "--gain", "2", "--mode", "b", "--verbose",
            "--window", "0.3", "0.4", "--peers", "tcp/a:1", "--peers", "tcp/b:2",
            "--arm.speed", "1.25", "--arm.no-homed"]
    values = flag_values(_toy_parser().parse_args(argv), Toy)
    assert values == {"name": "x", "count": 3, "gain": 2.0, "mode": "b", "verbose": True,
                      "window": [0.3, 0.4], "peers": ["tcp/a:1", "tcp/b:2"],
                      "arm": {"speed": 1.25, "homed": False}}
    toy = Toy.model_validate(values)
    assert toy.window == (0.3, 0.4) and toy.arm.homed is False


def test_flags_not_given_are_left_out() -> None:
    assert flag_values(_toy_parser().parse_args([]), Toy) == {}
    assert flag_values(_toy_parser().parse_args(["--no-verbose"]), Toy) == {"verbose": False}


def test_bad_values_are_refused_by_argparse() -> None:
    for argv in (["--mode", "c"], ["--count", "many"], ["--window", "0.1"]):
        with pytest.raises(SystemExit):
            _toy_parser().parse_args(argv)


def test_help_and_default_come_from_the_field() -> None:
    text = " ".join(_toy_parser().format_help().split())  # argparse wraps lines
    assert "--gain FLOAT the gain, 100% = 1 (default: 1.5)" in text  # a % in a description is kept
    assert "--count INT how many; unset: all" in text
    assert "unset: all (default" not in text  # nothing to show for None
    assert "--verbose, --no-verbose say more (default: off)" in text
    assert "--window FLOAT FLOAT the window (default: 0.1 0.2)" in text
    assert "--arm.homed, --arm.no-homed home at start (default: on)" in text
    assert "arm: The arm." in text  # a section is a group, described by its model


def test_spellings_rename_flags_and_keep_the_derived_parts() -> None:
    p = _toy_parser({"count": Spelling(("-n", "--number"), "N"), "verbose": Spelling(("-v", "--talk")),
                     "arm.speed": Spelling(("--speed",))})
    values = flag_values(p.parse_args(["-n", "4", "--no-talk", "--speed", "2"]), Toy)
    assert values == {"count": 4, "verbose": False, "arm": {"speed": 2.0}}
    assert flag_values(p.parse_args(["-v"]), Toy) == {"verbose": True}
    text = " ".join(p.format_help().split())
    assert "-n N, --number N how many" in text and "--speed FLOAT joint speed in rad/s" in text
    with pytest.raises(SystemExit):
        p.parse_args(["--count", "4"])  # renamed: the derived spelling is gone


def test_a_spelling_for_a_setting_that_does_not_exist_is_an_error() -> None:
    with pytest.raises(KeyError, match="cuont"):
        _toy_parser({"cuont": Spelling(("-n",))})


def test_a_field_without_a_command_line_form_is_named() -> None:
    class Odd(BaseModel):
        table: dict[str, int] = Field(default_factory=dict)

    with pytest.raises(TypeError, match="setting table"):
        add_settings_flags(argparse.ArgumentParser(), Odd)


def test_a_field_added_to_a_model_is_a_flag_without_more_code() -> None:
    class Tracker(PerceptionSettings):
        tracker: Literal["sort", "none"] = Field(default="sort", description="multi-object tracker")

    class GripperRobot(RobotSettings):
        gripper_force: float = Field(default=2.5, gt=0, description="gripper force in N")
        perception: Tracker = Field(default_factory=Tracker, description="the camera pipeline")

    p = argparse.ArgumentParser()
    add_settings_flags(p, GripperRobot, ROBOT_SPELLINGS)
    a = p.parse_args(["--gripper-force", "3", "--perception.tracker", "none", "--rate", "5", "-e", "tcp/x:1"])
    s = load_settings(GripperRobot, None, flag_values(a, GripperRobot))
    assert s.gripper_force == 3.0 and s.perception.tracker == "none"
    assert s.rate_hz == 5.0 and s.zenoh.connect == ["tcp/x:1"]
    text = " ".join(p.format_help().split())
    assert "--gripper-force FLOAT gripper force in N (default: 2.5)" in text
    assert "--perception.tracker {sort,none} multi-object tracker (default: sort)" in text


def test_the_daemon_help_is_the_field_descriptions() -> None:
    text = " ".join(robot_parser().format_help().split())
    fields = [RobotSettings.model_fields[n] for n in ("ack_timeout", "voxel", "scan_coding")]
    fields.append(PerceptionSettings.model_fields["reply_timeout"])
    for field in fields:
        assert field.description and field.description in text
    assert "--ack-timeout FLOAT seconds before an unanswered scan is lost (default: 1.0)" in text
