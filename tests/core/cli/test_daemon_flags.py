"""zoffload-robot / zoffload-edge: every flag they have always had still means the same setting,
and flags sit on top of the file and the environment."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel

from zoffload.cli.daemons import edge_parser, edge_settings, robot_parser, robot_settings, session_flags
from zoffload.cli.main import build_parser, edge_main, robot_main
from zoffload.cli.main import main as zoffload_main
from zoffload.runtime.config import EdgeSettings, RobotSettings
from zoffload.runtime.errors import ConfigError, ExitCode

# (flags, {key path: value}): the historical flags and what they set.
SESSION_FLAGS: list[tuple[list[str], dict[str, Any]]] = [
    (["-m", "client"], {"zenoh.mode": "client"}),
    (["--mode", "router"], {"zenoh.mode": "router"}),
    (["-e", "tcp/10.0.0.2:7447"], {"zenoh.connect": ["tcp/10.0.0.2:7447"]}),
    (["--connect", "tcp/a:1", "-e", "tcp/b:2"], {"zenoh.connect": ["tcp/a:1", "tcp/b:2"]}),
    (["-l", "tcp/0.0.0.0:7447"], {"zenoh.listen": ["tcp/0.0.0.0:7447"]}),
    (["--listen", "tcp/0.0.0.0:7447"], {"zenoh.listen": ["tcp/0.0.0.0:7447"]}),
    (["-c", "zenoh.json5"], {"zenoh.config_file": "zenoh.json5"}),
    (["--config", "zenoh.json5"], {"zenoh.config_file": "zenoh.json5"}),
    (["--no-multicast-scouting"], {"zenoh.multicast_scouting": False}),
    (["--no-shm"], {"zenoh.shared_memory": False}),
    (["--cfg", "transport/unicast/max_links:2", "--cfg", 'mode:"peer"'],
     {"zenoh.cfg": ["transport/unicast/max_links:2", 'mode:"peer"']}),
]
ROBOT_FLAGS: list[tuple[list[str], dict[str, Any]]] = [
    (["--namespace", "lab"], {"namespace": "lab"}),
    (["--robot-id", "r2"], {"robot_id": "r2"}),
    (["--scans", "/data/velodyne"], {"scans": "/data/velodyne"}),
    (["--replay", "pingpong"], {"replay": "pingpong"}),
    (["--rate", "10"], {"rate_hz": 10.0}),
    (["--max-scans", "50"], {"max_scans": 50}),
    (["--voxel", "0.1"], {"voxel": 0.1}),
    (["--voxel", "0"], {"voxel": 0.0}),
    (["--scale-policy", "dqn:model.onnx"], {"scale_policy": "dqn:model.onnx"}),
    (["--voxel-range", "0.02", "0.5"], {"voxel_range": (0.02, 0.5)}),
    (["--scan-coding", "f32"], {"scan_coding": "f32"}),
    (["--ack-timeout", "2.5"], {"ack_timeout": 2.5}),
    (["--max-in-flight", "0"], {"max_in_flight": 0}),
    (["--wait-edge", "30"], {"wait_edge": 30.0}),
    (["--out", "results/run1"], {"out_dir": "results/run1"}),
    (["-e", "tcp/EDGE:7447", "--no-multicast-scouting", "--scans", "/d", "--voxel", "0.1", "--out", "r"],
     {"zenoh.connect": ["tcp/EDGE:7447"], "zenoh.multicast_scouting": False, "scans": "/d", "voxel": 0.1,
      "out_dir": "r"}),  # the README's robot command line
    *SESSION_FLAGS,
]
EDGE_FLAGS: list[tuple[list[str], dict[str, Any]]] = [
    (["--namespace", "lab"], {"namespace": "lab"}),
    (["--edge-id", "e2"], {"edge_id": "e2"}),
    (["--map-dir", "maps/"], {"map_dir": "maps/"}),
    (["--map-format", "pcd"], {"map_format": "pcd"}),
    (["--no-mapping"], {"mapper.enabled": False}),
    (["-l", "tcp/0.0.0.0:7447", "--no-multicast-scouting", "--map-dir", "maps/"],
     {"zenoh.listen": ["tcp/0.0.0.0:7447"], "zenoh.multicast_scouting": False, "map_dir": "maps/"}),
    *SESSION_FLAGS,
]


def _expected(model: type[BaseModel], changes: dict[str, Any]) -> dict[str, Any]:
    """The defaults, with ``changes`` (by key path) applied: everything else must stay default."""
    out = model().model_dump()
    for path, value in changes.items():
        *sections, name = path.split(".")
        node = out
        for s in sections:
            node = node[s]
        node[name] = value
    return out


def _id(value: object) -> str:
    return " ".join(value) if isinstance(value, list) else ""


@pytest.mark.parametrize(("argv", "changes"), ROBOT_FLAGS, ids=_id)
def test_historical_robot_flags(argv: list[str], changes: dict[str, Any]) -> None:
    expected = _expected(RobotSettings, changes)
    for args in (robot_parser().parse_args(argv), build_parser().parse_args(["robot", *argv])):
        assert robot_settings(args, environ={}).model_dump() == expected


@pytest.mark.parametrize(("argv", "changes"), EDGE_FLAGS, ids=_id)
def test_historical_edge_flags(argv: list[str], changes: dict[str, Any]) -> None:
    expected = _expected(EdgeSettings, changes)
    for args in (edge_parser().parse_args(argv), build_parser().parse_args(["edge", *argv])):
        assert edge_settings(args, environ={}).model_dump() == expected


def test_settings_and_log_level_flags() -> None:
    a = robot_parser().parse_args(["--settings", "robot.yaml", "--log-level", "DEBUG"])
    assert a.settings == "robot.yaml" and a.log_level == "DEBUG"
    a = edge_parser().parse_args([])
    assert a.settings is None and a.log_level is None


def test_router_session_flags() -> None:
    a = build_parser().parse_args(["router", "-l", "tcp/0.0.0.0:7447", "--no-multicast-scouting", "--no-shm"])
    assert session_flags(a) == {"listen": ["tcp/0.0.0.0:7447"], "multicast_scouting": False,
                                "shared_memory": False}
    assert session_flags(build_parser().parse_args(["router"])) == {}


def test_nested_settings_are_flags_too() -> None:
    a = robot_parser().parse_args(["--perception.strategy", "edge", "--perception.encoding", "jpeg",
                                   "--perception.cpu-quota", "0.25", "--images", "coco-clips"])
    s = robot_settings(a, environ={})
    assert (s.perception.strategy, s.perception.encoding, s.perception.cpu_quota) == ("edge", "jpeg", 0.25)
    assert s.images == "coco-clips"
    a = edge_parser().parse_args(["--mapper.max-points-per-voxel", "10", "--mapper.deskew", "--no-detector",
                                  "--detector.model", "yolox-nano"])
    e = edge_settings(a, environ={})
    assert e.mapper.max_points_per_voxel == 10 and e.mapper.deskew is True
    assert e.detector.enabled is False and e.detector.model == "yolox-nano"


def test_precedence_default_file_env_flag(tmp_path: Path) -> None:
    f = tmp_path / "robot.yaml"
    f.write_text("voxel: 0.03\nrobot_id: from_file\nwait_edge: 9\nperception: {strategy: robot, fps: 5}\n"
                 "zenoh: {mode: client, connect: [tcp/file:1]}\n")
    env = {"ZOFFLOAD_ROBOT__ROBOT_ID": "from_env", "ZOFFLOAD_ROBOT__WAIT_EDGE": "12",
           "ZOFFLOAD_ROBOT__PERCEPTION__STRATEGY": "edge", "ZOFFLOAD_ROBOT__ZENOH__CONNECT": "[tcp/env:1]"}
    a = robot_parser().parse_args(["--settings", str(f), "--robot-id", "from_flag", "-e", "tcp/flag:1"])
    s = robot_settings(a, environ=env)
    assert s.ack_timeout == 1.0  # default
    assert s.voxel == 0.03 and s.zenoh.mode == "client" and s.perception.fps == 5  # file over default
    assert s.wait_edge == 12 and s.perception.strategy == "edge"  # environment over file
    assert s.robot_id == "from_flag" and s.zenoh.connect == ["tcp/flag:1"]  # flag over environment


def test_a_switch_flag_overrides_the_file_both_ways(tmp_path: Path) -> None:
    f = tmp_path / "edge.yaml"
    f.write_text("mapper: {enabled: false, queue: 3}\nzenoh: {shared_memory: false}\n")
    e = edge_settings(edge_parser().parse_args(["--settings", str(f), "--mapping", "--shm"]), environ={})
    assert e.mapper.enabled is True and e.mapper.queue == 3 and e.zenoh.shared_memory is True
    e = edge_settings(edge_parser().parse_args(["--settings", str(f)]), environ={})
    assert e.mapper.enabled is False and e.zenoh.shared_memory is False


def test_mistakes_are_named() -> None:
    with pytest.raises(ConfigError, match="ZOFFLOAD_ROBOT__VOXLE"):
        robot_settings(robot_parser().parse_args([]), environ={"ZOFFLOAD_ROBOT__VOXLE": "0.1"})
    with pytest.raises(ConfigError, match="voxel"):
        robot_settings(robot_parser().parse_args(["--voxel", "-1"]), environ={})
    with pytest.raises(ConfigError, match="robot_id"):
        robot_settings(robot_parser().parse_args(["--robot-id", "a/b"]), environ={})


def test_mistakes_in_a_file_or_a_variable_say_what_was_meant(tmp_path: Path) -> None:
    f = tmp_path / "robot.yaml"
    f.write_text("rate: 5\nfleet:\n  atach: true\n")
    with pytest.raises(ConfigError, match=r"fleet.atach: no such setting \(did you mean 'attach'\?\)") as err:
        robot_settings(robot_parser().parse_args(["--settings", str(f)]), environ={})
    assert "rate: no such setting (did you mean 'rate_hz'?)" in str(err.value)
    with pytest.raises(ConfigError, match="did you mean 'voxel'"):
        robot_settings(robot_parser().parse_args([]), environ={"ZOFFLOAD_ROBOT__VOXLE": "0.1"})
    f.write_text('"": 5\n')  # an empty key: no hint (every setting starts with "")
    with pytest.raises(ConfigError, match="no such setting") as err:
        robot_settings(robot_parser().parse_args(["--settings", str(f)]), environ={})
    assert "did you mean" not in str(err.value)


@pytest.mark.parametrize("argv", [["--voxle", "0.1"], ["--replay", "sideways"], ["--rate", "fast"],
                                  ["--voxel-rang", "0.1", "0.2"]])
def test_bad_flags_exit_with_the_config_code(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as err:
        robot_main(argv)
    assert err.value.code == 2  # ExitCode.CONFIG, argparse's own
    assert argv[0] in capsys.readouterr().err


def test_the_daemons_read_the_process_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ZOFFLOAD_EDGE__MAPPER__QUEUE", "5")
    assert edge_settings(edge_parser().parse_args([])).mapper.queue == 5
    monkeypatch.setenv("ZOFFLOAD_EDGE__MAPPER__QUEUEU", "3")
    with pytest.raises(ConfigError, match="ZOFFLOAD_EDGE__MAPPER__QUEUEU"):
        edge_settings(edge_parser().parse_args([]))


def test_help_reads_from_the_models(capsys: pytest.CaptureFixture[str]) -> None:
    for main, words in (
        (robot_main, ["--voxel-range LOW HIGH", "--perception.strategy", "ZOFFLOAD_ROBOT__KEY"]),
        (edge_main, ["--mapping, --no-mapping", "--mapper.queue INT", "ZOFFLOAD_EDGE__KEY"]),
    ):
        with pytest.raises(SystemExit):
            main(["--help"])
        text = " ".join(capsys.readouterr().out.split())
        for w in words:
            assert w in text


def test_a_flag_cut_short_is_not_taken_for_a_longer_one(capsys: pytest.CaptureFixture[str]) -> None:
    """Was: ``zoffload-edge --mapper.queu 7`` set ``mapper.queue`` (argparse's prefix matching)."""
    for run, argv in ((edge_main, ["--mapper.queu", "7"]), (robot_main, ["--voxel-rang", "0.1", "0.2"])):
        with pytest.raises(SystemExit) as err:
            run(argv)
        assert err.value.code == 2 and argv[0] in capsys.readouterr().err
    with pytest.raises(SystemExit):
        build_parser().parse_args(["edge", "--mapper.queu", "7"])


@pytest.mark.parametrize(("argv", "named"), [(["--trace", "nosuchtrace"], "nosuchtrace"),
                                             (["--scale-policy", "rat"], "unknown scale policy 'rat'")])
def test_a_demo_with_a_wrong_trace_or_policy_stops_before_it_starts(
        argv: list[str], named: str, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Named at once with the configuration code, before any folder or process (the trace used
    to surface as the robot failing to connect to an emulator that never started)."""
    out = tmp_path / "demo"
    assert zoffload_main(["demo", "--out", str(out), *argv]) == ExitCode.CONFIG
    assert named in caplog.text and not out.exists()
