"""No Docker engine runs here, so the deployment is checked for consistency with the code: the
compose services, images, commands, mounted configs and endpoints."""

from __future__ import annotations

import json
import re
from pathlib import Path
from urllib.parse import urlparse

import yaml

from zoffload.cli.daemons import edge_parser, edge_settings, robot_parser, robot_settings
from zoffload.runtime.loading import load_settings

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
COMPOSE = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())


def _json5_listen(text: str) -> list[str]:
    return re.findall(r'"(tcp/[^"]+)"', text)


def _mounted(service: dict, target: str) -> Path:
    for vol in service["volumes"]:
        src, dst = vol.split(":")[:2]
        if dst == target:
            return DEPLOY / src
    raise AssertionError(f"{target} is not mounted")


def test_services_and_images() -> None:
    services = COMPOSE["services"]
    assert set(services) == {"router", "edge", "robot"}
    import importlib.metadata

    zenoh_version = importlib.metadata.version("eclipse-zenoh")
    assert services["router"]["image"] == f"eclipse/zenoh:{zenoh_version}"  # same protocol version
    assert services["edge"]["image"] == services["robot"]["image"]
    assert services["edge"]["build"]["dockerfile"] == "deploy/Dockerfile"
    assert "edge" in services["robot"]["depends_on"] and "router" in services["edge"]["depends_on"]


def test_commands_parse_with_the_cli_and_configs_load() -> None:
    services = COMPOSE["services"]
    for name, parser, settings_of in (("edge", edge_parser, edge_settings),
                                      ("robot", robot_parser, robot_settings)):
        cmd = services[name]["command"]
        assert cmd[0] == f"zoffload-{name}"
        args = parser().parse_args(cmd[1:])
        path = _mounted(services[name], args.settings)
        args.settings = str(path)
        s = settings_of(args)  # raises ConfigError on a wrong key
        assert s.zenoh.mode == "client" and s.zenoh.shared_memory is False
        # Each daemon connects to the router service on the port the router listens on
        router_cfg = _mounted(services["router"], services["router"]["command"][1]).read_text()
        urls = [urlparse("x://" + e.split("/", 1)[1]) for e in _json5_listen(router_cfg)]
        listen_ports = {u.port for u in urls if u.port}
        for ep in s.zenoh.connect:
            proto, addr = ep.split("/", 1)
            host, port = addr.rsplit(":", 1)
            assert proto == "tcp" and host == "router" and int(port) in listen_ports
        assert f"{min(listen_ports)}:{min(listen_ports)}" in services["router"]["ports"]


def test_robot_and_edge_share_a_namespace_and_write_to_volumes() -> None:
    from zoffload.runtime.config import EdgeSettings, RobotSettings

    edge = load_settings(EdgeSettings, DEPLOY / "edge.yaml")
    robot = load_settings(RobotSettings, DEPLOY / "robot.yaml")
    assert edge.namespace == robot.namespace
    services = COMPOSE["services"]
    assert any(v.endswith(f":{edge.map_dir}") for v in services["edge"]["volumes"])
    assert any(v.endswith(f":{robot.out_dir}") for v in services["robot"]["volumes"])


def test_dockerfile_installs_runtime_extras_without_torch() -> None:
    text = (DEPLOY / "Dockerfile").read_text()
    assert "libusb-1.0-0" in text
    assert '".[robot,edge]"' in text and "train" not in text.split("pip install")[1].split("\n")[0]
    assert "FROM python:3.11" in text
    json.dumps(COMPOSE)  # plain data, nothing exotic
