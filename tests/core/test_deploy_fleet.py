"""deploy/fleet checked for consistency with the code (no Docker engine here): two linked routers
(the robots' and the edges'), two edges, three robots; each daemon's command parses with its
mounted settings, carries its own id and its own certificate (made by the `zoffload certs`
command the compose file documents); each router runs its own config, linked to the other."""

from __future__ import annotations

import re
import shlex
from pathlib import Path
from typing import Any

import pytest
import yaml

from zoffload.cli.daemons import edge_parser, edge_settings, robot_parser, robot_settings

FLEET = Path(__file__).resolve().parents[2] / "deploy" / "fleet"
TEXT = (FLEET / "docker-compose.fleet.yml").read_text()
COMPOSE = yaml.safe_load(TEXT)
EDGES = ("edge1", "edge2")
ROBOTS = ("robot1", "robot2", "robot3")
ROUTERS = ("router", "rack")  # the robots' router and the edges'


def _mounts(service: dict[str, Any]) -> dict[str, str]:
    return {v.split(":")[1]: v.split(":")[0] for v in service["volumes"] if v.startswith("./")}


def _host(certs: Path, src: str) -> Path:
    return certs / src.removeprefix("./certs/") if src.startswith("./certs/") else FLEET / src


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("cryptography")
    from zoffload.cli.main import build_parser

    text = " ".join(ln.lstrip("# ").rstrip() for ln in TEXT.splitlines() if ln.startswith("#"))
    m = re.search(r"zoffload (certs .*?--certs-path \S+)", text.replace("\\ ", " "))
    assert m, "the compose file documents its `zoffload certs` command"
    argv = shlex.split(m.group(1))
    out = tmp_path_factory.mktemp("certs")
    argv[argv.index("--out") + 1] = str(out)
    args = build_parser().parse_args(argv)
    assert args.func(args) == 0
    return out


def test_two_routers_two_edges_three_robots() -> None:
    import importlib.metadata

    services = COMPOSE["services"]
    assert set(services) == {*ROUTERS, *EDGES, *ROBOTS}
    for r in ROUTERS:
        assert services[r]["image"] == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"
    assert all(services[e]["depends_on"] == ["rack"] for e in EDGES)
    assert {services[s]["image"] for s in (*EDGES, *ROBOTS)} == {"zoffload:0.1.0"}
    assert services["edge1"]["build"]["dockerfile"] == "deploy/Dockerfile"
    assert all(services[e]["stop_signal"] == "SIGTERM" for e in EDGES)  # the planned drain
    assert all(set(EDGES) <= set(services[r]["depends_on"]) for r in ROBOTS)


def test_each_daemon_has_its_own_id_certificate_and_key(certs: Path) -> None:
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    services = COMPOSE["services"]
    seeds = set()
    for name in (*EDGES, *ROBOTS):
        cmd = services[name]["command"]
        is_edge = name in EDGES
        parser, settings_of = (edge_parser, edge_settings) if is_edge else (robot_parser, robot_settings)
        args = parser().parse_args(cmd[1:])
        mounts = _mounts(services[name])
        for dst, src in mounts.items():
            assert _host(certs, src).is_file(), f"{name}: {src} -> {dst}"
        args.settings = str(_host(certs, mounts[args.settings]))
        s = settings_of(args)  # raises ConfigError on a wrong key
        identity = s.edge_id if is_edge else s.robot_id  # type: ignore[union-attr]
        assert identity == name
        z = s.zenoh
        assert z.mode == "client" and not z.shared_memory and not z.multicast_scouting
        assert z.tls_cert in mounts and z.tls_key in mounts and z.tls_ca in mounts
        cert = x509.load_pem_x509_certificate(_host(certs, mounts[str(z.tls_cert)]).read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        assert not [k for k in mounts.values() if k.endswith(".key") and name not in k]
        if is_edge:
            assert s.fleet.capacity and s.fleet.capacity >= len(ROBOTS)  # type: ignore[union-attr]
            assert set(ROBOTS) <= set(s.admission.robots)  # type: ignore[union-attr]
        else:
            assert s.fleet.attach and s.fleet.local_odometry  # type: ignore[union-attr]
            seeds.add(s.sim_seed)  # type: ignore[union-attr]
    assert len(seeds) == len(ROBOTS)  # three different scenes
    ignore = (FLEET / "certs" / ".gitignore").read_text().splitlines()
    assert "*" in ignore and "!.gitignore" in ignore


def _json5(path: Path) -> Any:
    """A router config as `zoffload certs` writes it (JSON after // comment lines), checked with
    Zenoh's own parser too."""
    import json

    import zenoh

    text = path.read_text()
    zenoh.Config.from_json5(text)
    return json.loads("\n".join(ln for ln in text.splitlines() if not ln.startswith("//")))


def test_the_routers_run_their_own_config_and_certificate_and_are_linked(certs: Path) -> None:
    services = COMPOSE["services"]
    for r in ROUTERS:
        mounts = _mounts(services[r])
        conf_path = services[r]["command"][-1]
        conf = _json5(_host(certs, mounts[conf_path]))
        tls = conf["transport"]["link"]["tls"]
        for key in ("root_ca_certificate", "listen_certificate", "listen_private_key", "connect_certificate"):
            assert tls[key] in mounts and _host(certs, mounts[tls[key]]).is_file(), (r, key)
        assert tls["listen_certificate"].endswith(f"/{r}.pem") and tls["enable_mtls"]
        other = next(x for x in ROUTERS if x != r)
        subjects = {s["id"]: s for s in conf["access_control"]["subjects"]}
        assert subjects[f"router_{other}"]["cert_common_names"] == [other]  # the linked router
        assert {f"robot_{x}" for x in ROBOTS} | {f"edge_{x}" for x in EDGES} <= set(subjects)
    rack = _json5(_host(certs, _mounts(services["rack"])["/etc/zoffload/certs/rack.json5"]))
    assert rack["connect"]["endpoints"] == ["tls/router:7447"]  # the rack dials the robots' router
    # and each daemon dials its own router
    for name, router in [*((e, "rack") for e in EDGES), *((r, "router") for r in ROBOTS)]:
        cfg = yaml.safe_load((FLEET / ("edge.yaml" if name in EDGES else "robot.yaml")).read_text())
        assert cfg["zenoh"]["connect"] == [f"tls/{router}:7447"], name
