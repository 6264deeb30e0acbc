"""No Docker engine runs here, so the deployment is checked for consistency with the code: the
compose services, images, commands, mounted configs and certificates, endpoints, and the router
config that `zoffload certs` makes with the command the compose file documents."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

from zoffload.cli.daemons import edge_parser, edge_settings, robot_parser, robot_settings
from zoffload.runtime.loading import load_settings

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
COMPOSE_TEXT = (DEPLOY / "docker-compose.yml").read_text()
COMPOSE = yaml.safe_load(COMPOSE_TEXT)


def _mounts(service: dict[str, Any]) -> dict[str, str]:
    """Container path -> host path (relative to deploy/) of a service's file mounts."""
    out = {}
    for vol in service["volumes"]:
        src, dst = vol.split(":")[:2]
        if src.startswith("./"):
            out[dst] = src
    return out


def _certs_command() -> list[str]:
    """The `zoffload certs ...` command the compose file's header documents."""
    lines = [ln.lstrip("# ").rstrip() for ln in COMPOSE_TEXT.splitlines() if ln.startswith("#")]
    text = " ".join(lines).replace("\\ ", " ")
    m = re.search(r"zoffload (certs .*?--certs-path \S+)", text)
    assert m, "the compose file documents its `zoffload certs` command"
    return shlex.split(m.group(1))


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The certificates and router config, made as the compose file says (into a temporary folder)."""
    pytest.importorskip("cryptography")
    from zoffload.cli.main import build_parser

    out = tmp_path_factory.mktemp("certs")
    argv = _certs_command()
    argv[argv.index("--out") + 1] = str(out)
    args = build_parser().parse_args(argv)
    assert args.func(args) == 0
    return out


def _host_file(certs: Path, src: str) -> Path:
    """A mount's host file: deploy/certs/* comes from `zoffload certs`, the rest is in deploy/."""
    return certs / src.removeprefix("./certs/") if src.startswith("./certs/") else DEPLOY / src


def test_services_and_images() -> None:
    services = COMPOSE["services"]
    assert set(services) == {"router", "edge", "robot"}
    import importlib.metadata

    zenoh_version = importlib.metadata.version("eclipse-zenoh")
    assert services["router"]["image"] == f"eclipse/zenoh:{zenoh_version}"  # same protocol version
    assert services["edge"]["image"] == services["robot"]["image"]
    assert services["edge"]["build"]["dockerfile"] == "deploy/Dockerfile"
    assert "edge" in services["robot"]["depends_on"] and "router" in services["edge"]["depends_on"]


def test_every_mount_exists_and_keys_stay_out_of_the_repository(certs: Path) -> None:
    for name, service in COMPOSE["services"].items():
        for dst, src in _mounts(service).items():
            assert _host_file(certs, src).is_file(), f"{name}: {src} -> {dst}"
    ignore = (DEPLOY / "certs" / ".gitignore").read_text().splitlines()
    assert "*" in ignore and "!.gitignore" in ignore  # whatever `zoffload certs` writes there


def test_the_router_speaks_tls_only_with_client_certificates_and_a_default_deny_acl(certs: Path) -> None:
    import zenoh

    router = COMPOSE["services"]["router"]
    cfg_path = router["command"][router["command"].index("-c") + 1]
    mounts = _mounts(router)
    text = _host_file(certs, mounts[cfg_path]).read_text()
    conf = json.loads("\n".join(ln for ln in text.splitlines() if not ln.startswith("//")))
    zenoh.Config.from_json5(text)  # zenohd's parser accepts it
    assert conf["mode"] == "router" and conf["scouting"]["multicast"]["enabled"] is False
    assert all(e.startswith("tls/") for e in conf["listen"]["endpoints"])
    link = conf["transport"]["link"]
    assert link["protocols"] == ["tls"] and link["tls"]["enable_mtls"] is True
    for key in ("root_ca_certificate", "listen_certificate", "listen_private_key"):
        assert link["tls"][key] in mounts, f"{key} {link['tls'][key]} is not mounted in the router"
    acl = conf["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    port = int(conf["listen"]["endpoints"][0].rsplit(":", 1)[1])
    assert f"{port}:{port}" in router["ports"]


def test_daemons_connect_over_tls_to_a_name_in_the_router_certificate_with_their_own_identity(
        certs: Path) -> None:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    services = COMPOSE["services"]
    router_cert = x509.load_pem_x509_certificate((certs / "router.pem").read_bytes())
    san = router_cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    router_names = set(san.get_values_for_type(x509.DNSName))
    conf = json.loads("\n".join(ln for ln in (certs / "router.json5").read_text().splitlines()
                                if not ln.startswith("//")))
    listen_ports = {int(e.rsplit(":", 1)[1]) for e in conf["listen"]["endpoints"]}
    subjects = {s["cert_common_names"][0] for s in conf["access_control"]["subjects"]}
    for name, parser, settings_of in (("edge", edge_parser, edge_settings),
                                      ("robot", robot_parser, robot_settings)):
        cmd = services[name]["command"]
        assert cmd[0] == f"zoffload-{name}"
        args = parser().parse_args(cmd[1:])
        mounts = _mounts(services[name])
        args.settings = str(_host_file(certs, mounts[args.settings]))
        s = settings_of(args)  # raises ConfigError on a wrong key
        z = s.zenoh
        assert z.mode == "client" and z.shared_memory is False and z.multicast_scouting is False
        for ep in z.connect:
            proto, addr = ep.split("/", 1)
            host, port = addr.rsplit(":", 1)
            assert proto == "tls" and host in router_names and int(port) in listen_ports
        for path in (z.tls_ca, z.tls_cert, z.tls_key):
            assert path in mounts, f"{name}: {path} is not mounted"
        identity = s.edge_id if name == "edge" else s.robot_id  # type: ignore[union-attr]
        assert z.tls_cert is not None
        cert = x509.load_pem_x509_certificate(_host_file(certs, mounts[z.tls_cert]).read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == identity
        assert identity in subjects
        assert not any(k.endswith(".key") for k in mounts.values() if identity not in k
                       and "router" not in k), f"{name} mounts another identity's key"


def test_robot_and_edge_share_a_namespace_and_the_edge_admits_the_robot() -> None:
    from zoffload.runtime.config import EdgeSettings, RobotSettings

    edge = load_settings(EdgeSettings, DEPLOY / "edge.yaml")
    robot = load_settings(RobotSettings, DEPLOY / "robot.yaml")
    assert edge.namespace == robot.namespace
    assert robot.robot_id in edge.admission.robots
    services = COMPOSE["services"]
    assert any(v.endswith(f":{edge.map_dir}") for v in services["edge"]["volumes"])
    assert any(v.endswith(f":{robot.out_dir}") for v in services["robot"]["volumes"])


def test_dockerfile_installs_runtime_extras_without_torch() -> None:
    text = (DEPLOY / "Dockerfile").read_text()
    assert "libusb-1.0-0" in text
    assert '".[robot,edge]"' in text and "train" not in text.split("pip install")[1].split("\n")[0]
    assert "FROM python:3.11" in text
    json.dumps(COMPOSE)  # plain data, nothing exotic
