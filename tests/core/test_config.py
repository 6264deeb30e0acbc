from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from zoffload.runtime.config import (
    DetectorSettings,
    EdgeSettings,
    MapperSettings,
    PerceptionSettings,
    RobotSettings,
    ZenohSettings,
)
from zoffload.runtime.errors import ConfigError, ZenohSessionError
from zoffload.runtime.loading import load_settings, write_effective
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


def test_zenoh_config_error_is_clear(tmp_path: Path) -> None:
    """It names the entry of several ``--cfg`` that Zenoh refused, and a config file it cannot read."""
    with pytest.raises(ZenohSessionError, match="invalid Zenoh configuration: cfg entry 'no/such/key:1'"):
        zenoh_config(ZenohSettings(cfg=["transport/unicast/max_links:2", "no/such/key:1"]))
    missing = tmp_path / "nope.json5"
    with pytest.raises(ZenohSessionError, match=f"configuration file {missing}"):
        zenoh_config(ZenohSettings(config_file=str(missing)))


def test_edge_waits_longer_before_dropping_unless_told_otherwise() -> None:
    from zoffload.edge.server import edge_zenoh
    from zoffload.runtime.session import DROP_WAIT_KEY, zenoh_config

    z = edge_zenoh(ZenohSettings(cfg=['mode:"peer"']))
    assert z.cfg[0] == f"{DROP_WAIT_KEY}:50000" and z.cfg[1] == 'mode:"peer"'
    cc = zenoh_config(z).get_json("transport/link/tx/queue/congestion_control")
    assert '"wait_before_drop":50000' in cc
    mine = ZenohSettings(cfg=[f"{DROP_WAIT_KEY}:0"])
    assert edge_zenoh(mine) == mine


def test_router_waits_longer_before_dropping_unless_told_otherwise() -> None:
    """The router forwards several robots' BLOCK_FIRST scans to one edge; with Zenoh's 1 ms it
    dropped some under load (benchmarks/bench_fanin.py)."""
    from zoffload.runtime.router import router_zenoh
    from zoffload.runtime.session import DROP_WAIT_KEY, zenoh_config

    z = router_zenoh(ZenohSettings(mode="router", listen=["tcp/127.0.0.1:0"]))
    cc = zenoh_config(z).get_json("transport/link/tx/queue/congestion_control")
    assert '"wait_before_drop":50000' in cc
    mine = ZenohSettings(mode="router", cfg=[f"{DROP_WAIT_KEY}:2000"])
    assert router_zenoh(mine) == mine


def test_a_peer_robot_listens_only_where_told() -> None:
    """A robot peer without ``listen`` opens no listener, so no edge can dial it back (two links
    in one session: runtime/session.py ``dialling_only``); one told to listen, a client, a config
    file or the user's own ``listen/endpoints`` are left alone."""
    import psutil

    from zoffload.robot.server import robot_zenoh
    from zoffload.runtime.session import LISTEN_KEY, free_tcp_port, open_session

    def listening(z: ZenohSettings) -> list[int]:
        before = {c.laddr.port for c in psutil.Process().net_connections("tcp") if c.status == "LISTEN"}
        session = open_session(robot_zenoh(z))
        try:
            now = {c.laddr.port for c in psutil.Process().net_connections("tcp") if c.status == "LISTEN"}
        finally:
            session.close()
        return sorted(now - before)

    quiet = ZenohSettings(multicast_scouting=False, shared_memory=False)
    assert f"{LISTEN_KEY}:[]" in robot_zenoh(quiet).cfg
    assert listening(quiet) == []
    port = free_tcp_port()
    told = quiet.model_copy(update={"listen": [f"tcp/127.0.0.1:{port}"]})
    assert listening(told) == [port]
    for z in (told, quiet.model_copy(update={"mode": "client"}),
              quiet.model_copy(update={"cfg": [f'{LISTEN_KEY}:["tcp/127.0.0.1:{port}"]']})):
        added = [c for c in robot_zenoh(z).cfg if c not in z.cfg]
        assert not any(c.startswith(LISTEN_KEY) for c in added), added
    # Zenoh's own default for a peer (what the robot had before): a listener on a random port
    plain = open_session(quiet)
    try:
        assert any(c.status == "LISTEN" for c in psutil.Process().net_connections("tcp"))
    finally:
        plain.close()


ROBOT = "ZOFFLOAD_ROBOT__"
EDGE = "ZOFFLOAD_EDGE__"


def test_nested_environment_variables_and_their_values() -> None:
    env = {
        f"{ROBOT}VOXEL": "0.03",  # a float from a string
        f"{ROBOT}PERCEPTION__STRATEGY": "edge",
        f"{ROBOT}PERCEPTION__CPU_QUOTA": "0.5",
        f"{ROBOT}VOXEL_RANGE": "[0.02, 0.5]",  # a pair, in YAML
        f"{ROBOT}ZENOH__CONNECT": "[tcp/10.0.0.2:7447, tcp/10.0.0.3:7447]",  # a list, unquoted YAML
        f"{ROBOT}ZENOH__MULTICAST_SCOUTING": "false",
        f"{ROBOT}ROBOT_ID": "123",  # stays a string: ids may be digits
        f"{ROBOT}RATE_HZ": "",  # empty: as if unset
        "ZOFFLOAD_EDGE__VOXEL": "7",  # another program's prefix: not ours to read
        "PATH": "/usr/bin",
    }
    s = load_settings(RobotSettings, None, None, ROBOT, env)
    assert s.voxel == 0.03 and s.voxel_range == (0.02, 0.5)
    assert s.perception.strategy == "edge" and s.perception.cpu_quota == 0.5
    assert s.perception.encoding == "auto"  # the rest of the section keeps its defaults
    assert s.zenoh.connect == ["tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447"]
    assert s.zenoh.multicast_scouting is False and s.zenoh.mode == "peer"
    assert s.robot_id == "123" and s.rate_hz is None

    e = load_settings(EdgeSettings, None, None, EDGE, {f"{EDGE}MAPPER__MAX_POINTS_PER_VOXEL": "10",
                                                        f"{EDGE}MAPPER": "{queue: 4}",
                                                        f"{EDGE}DETECTOR__ENABLED": "true"})
    assert e.mapper.max_points_per_voxel == 10 and e.mapper.queue == 4 and e.detector.enabled is True


def test_null_in_the_environment_unsets_what_the_file_set(tmp_path: Path) -> None:
    f = tmp_path / "robot.yaml"
    f.write_text("out_dir: /data/results\nperception: {fps: 10}\n")
    env = {f"{ROBOT}OUT_DIR": "null", f"{ROBOT}PERCEPTION__FPS": "null"}
    s = load_settings(RobotSettings, f, None, ROBOT, env)
    assert s.out_dir is None and s.perception.fps is None


@pytest.mark.parametrize(("name", "named"), [
    (f"{ROBOT}VOXLE", "'voxle'"),
    (f"{ROBOT}PERCEPTION__STRATEGI", "'perception.strategi'"),
    (f"{ROBOT}NO_SUCH__KEY", "'no_such'"),
    (f"{ROBOT}VOXEL__SIZE", "voxel is a value"),
    ("ZOFFLOAD_ROBOT_VOXEL", f"take {ROBOT}KEY"),  # one underscore: not silently ignored
])
def test_unknown_environment_variable_is_named(name: str, named: str) -> None:
    with pytest.raises(ConfigError, match=name) as err:
        load_settings(RobotSettings, None, None, ROBOT, {name: "1"})
    assert named in str(err.value)


def test_bad_environment_values_name_the_setting() -> None:
    with pytest.raises(ConfigError, match=f"{ROBOT}ZENOH__LISTEN: .* not valid YAML"):
        load_settings(RobotSettings, None, None, ROBOT, {f"{ROBOT}ZENOH__LISTEN": "[tcp/unclosed"})
    with pytest.raises(ConfigError, match="voxel"):
        load_settings(RobotSettings, None, None, ROBOT, {f"{ROBOT}VOXEL": "fine"})
    with pytest.raises(ConfigError, match="perception.strategy"):
        load_settings(RobotSettings, None, None, ROBOT, {f"{ROBOT}PERCEPTION__STRATEGY": "sideways"})


def test_only_load_settings_with_a_prefix_reads_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(f"{ROBOT}VOXEL", "0.2")
    monkeypatch.setenv(f"{EDGE}MAP_DIR", "/elsewhere")
    assert RobotSettings().voxel == 0.05  # building a model in Python: the shell has no say
    assert RobotSettings(scans="sim", voxel=0.1).voxel == 0.1
    assert EdgeSettings(map_dir="maps").map_dir == "maps"
    assert RobotSettings().model_copy(update={"max_scans": 3}).voxel == 0.05
    assert load_settings(RobotSettings).voxel == 0.05  # no prefix: no environment
    assert load_settings(RobotSettings, env_prefix=ROBOT).voxel == 0.2  # os.environ by default
    assert load_settings(RobotSettings, env_prefix=ROBOT, environ={}).voxel == 0.05


def test_every_setting_is_described_on_one_line() -> None:
    for model in (ZenohSettings, MapperSettings, DetectorSettings, PerceptionSettings, RobotSettings,
                  EdgeSettings):
        for name, field in model.model_fields.items():
            assert field.description, f"{model.__name__}.{name} has no description"
            assert "\n" not in field.description and len(field.description) <= 100, name
