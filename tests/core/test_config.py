from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from zoffload.runtime.config import (
    EdgeSettings,
    RobotSettings,
    ZenohSettings,
    load_settings,
    write_effective,
)
from zoffload.runtime.errors import ConfigError, ZenohSessionError
from zoffload.runtime.session import zenoh_config


def test_precedence_defaults_file_env_flags(tmp_path: Path) -> None:
    f = tmp_path / "robot.yaml"
    f.write_text("voxel: 0.03\nrobot_id: from_file\nzenoh: {mode: client}\n")
    env = {"ZOFFLOAD_ROBOT__ROBOT_ID": "from_env", "ZOFFLOAD_ROBOT__ZENOH__LISTEN": "[tcp/127.0.0.1:1]"}
    s = load_settings(RobotSettings, f, {"robot_id": "from_flag"}, "ZOFFLOAD_ROBOT__", env)
    assert s.voxel == 0.03  # file over default
    assert s.zenoh.mode == "client"  # file
    assert s.zenoh.listen == ["tcp/127.0.0.1:1"]  # env, parsed as YAML
    assert s.robot_id == "from_flag"  # flag over env over file
    assert s.ack_timeout == 1.0  # default


def test_unknown_key_is_named(tmp_path: Path) -> None:
    f = tmp_path / "robot.yaml"
    f.write_text("voxle: 0.03\n")
    with pytest.raises(ConfigError, match="voxle"):
        load_settings(RobotSettings, f)
    with pytest.raises(ConfigError, match="mapper.max_points_per_voxle"):
        load_settings(EdgeSettings, None, {"mapper": {"max_points_per_voxle": 3}})


def test_bad_values_and_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="voxel"):
        load_settings(RobotSettings, None, {"voxel": -1})
    with pytest.raises(ConfigError, match="robot_id"):
        load_settings(RobotSettings, None, {"robot_id": "a/b"})
    with pytest.raises(ConfigError, match="does-not-exist"):
        load_settings(RobotSettings, tmp_path / "does-not-exist.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("voxel: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_settings(RobotSettings, bad)
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_settings(RobotSettings, bad)
    with pytest.raises(ConfigError, match="cfg"):
        load_settings(RobotSettings, None, {"zenoh": {"cfg": ["no-colon"]}})


def test_effective_config_round_trips(tmp_path: Path) -> None:
    s = load_settings(EdgeSettings, None, {"edge_id": "e7", "mapper": {"queue": 5}})
    path = write_effective(s, tmp_path / "out" / "edge.yaml")
    again = load_settings(EdgeSettings, path)
    assert again == s
    assert yaml.safe_load(path.read_text())["mapper"]["queue"] == 5


def test_zenoh_config_applies_the_session_flags() -> None:
    z = ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:7999"], connect=["tcp/127.0.0.1:7998"],
                      multicast_scouting=False, shared_memory=False,
                      cfg=["transport/unicast/max_links:2"])
    conf = zenoh_config(z)
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7999"]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7998"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(conf.get_json("transport/unicast/max_links")) == 2


def test_zenoh_config_error_is_clear() -> None:
    with pytest.raises(ZenohSessionError, match="invalid Zenoh configuration"):
        zenoh_config(ZenohSettings(cfg=["no/such/key:1"]))


def test_edge_waits_longer_before_dropping_unless_told_otherwise() -> None:
    from zoffload.edge.server import DROP_WAIT_KEY, edge_zenoh
    from zoffload.runtime.session import zenoh_config

    z = edge_zenoh(ZenohSettings(cfg=['mode:"peer"']))
    assert z.cfg[0] == f"{DROP_WAIT_KEY}:50000" and z.cfg[1] == 'mode:"peer"'
    cc = zenoh_config(z).get_json("transport/link/tx/queue/congestion_control")
    assert '"wait_before_drop":50000' in cc
    mine = ZenohSettings(cfg=[f"{DROP_WAIT_KEY}:0"])
    assert edge_zenoh(mine) == mine
