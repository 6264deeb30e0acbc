"""The secure deployment's pure parts: certificates, the generated ACL, and the TLS/user session
settings turned into Zenoh config keys."""

from __future__ import annotations

import json
import stat
from pathlib import Path

import pytest
import zenoh

from zoffload.protocol.keys import Keys
from zoffload.runtime.acl import access_control, router_config
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.errors import ConfigError, ZenohSessionError
from zoffload.runtime.session import security_entries, zenoh_config


def rules_of(acl: dict, subject: str) -> list[dict]:
    policy = next(p for p in acl["policies"] if p["subjects"] == [subject])
    return [r for r in acl["rules"] if r["id"] in policy["rules"]]


def allowed(acl: dict, subject: str, flow: str, message: str, key: str) -> bool:
    """Whether a rule of the subject allows it (the rule key must include the message key: here
    checked for exact keys and trailing ``*``/``**`` chunks, all the generator uses)."""
    def includes(rule_key: str, k: str) -> bool:
        r, m = rule_key.split("/"), k.split("/")
        if r[-1] == "**":
            return m[:len(r) - 1] == r[:-1]
        return len(r) == len(m) and all(a in ("*", b) for a, b in zip(r, m, strict=True))

    return any(flow in r["flows"] and message in r["messages"]
               and any(includes(k, key) for k in r["key_exprs"]) for r in rules_of(acl, subject))


def test_each_robot_may_publish_only_its_own_keys_and_only_edges_may_answer() -> None:
    k = Keys()
    acl = access_control(k, ["robot1", "robot2"], ["edge1"], ["mon"])
    assert acl["default_permission"] == "deny" and acl["enabled"]
    assert allowed(acl, "robot_robot1", "ingress", "put", k.scan("robot1"))
    assert allowed(acl, "robot_robot1", "ingress", "put", k.frame("robot1"))
    assert allowed(acl, "robot_robot1", "ingress", "put", k.robot_status("robot1"))
    assert not allowed(acl, "robot_robot1", "ingress", "put", k.scan("robot2"))
    assert not allowed(acl, "robot_robot1", "ingress", "put", k.scan_ack("robot1", "edge1"))
    assert not allowed(acl, "robot_robot1", "ingress", "put", k.detections("robot2", "edge1"))
    assert not allowed(acl, "robot_robot1", "ingress", "liveliness_token", k.edge_alive("edge1"))
    assert allowed(acl, "robot_robot1", "ingress", "liveliness_token", k.robot_alive("robot1"))
    assert not allowed(acl, "robot_robot1", "egress", "put", k.scan_ack("robot2", "edge1"))  # no spying
    assert allowed(acl, "robot_robot1", "egress", "put", k.scan_ack("robot1", "edge1"))
    for key in (k.scan_acks("robot1"), k.detections_to("robot1"), k.checkpoints("robot1")):
        assert allowed(acl, "robot_robot1", "ingress", "declare_subscriber", key)  # every edge's answers
    # but only answers under an edge's id reach it: the key before per-edge answers, which no client
    # may put, does not come over a link from a router with an older ACL either
    for key in ("zoffload/data/robot1/scan_ack", "zoffload/data/robot1/checkpoint"):
        assert not allowed(acl, "robot_robot1", "egress", "put", key)
    assert allowed(acl, "robot_robot1", "ingress", "query", k.map("robot1", "edge1"))
    assert not allowed(acl, "robot_robot1", "ingress", "query", k.map("robot2", "edge1"))
    assert not allowed(acl, "robot_robot1", "ingress", "declare_queryable", k.all_maps("edge1"))
    # the edge answers everyone under its own id, and nothing else
    for key in (k.scan_ack("robot1", "edge1"), k.scan_ack("robot2", "edge1"), k.detections("robot2", "edge1"),
                k.checkpoint("robot2", "edge1"), k.edge_status("edge1")):
        assert allowed(acl, "edge_edge1", "ingress", "put", key)
    # not in another edge's name, nor on the key before per-edge answers (no edge chunk)
    for key in (k.scan_ack("robot1", "edge2"), k.detections("robot1", "edge2"),
                k.checkpoint("robot1", "edge2"), "zoffload/data/robot1/scan_ack",
                "zoffload/data/robot1/checkpoint"):
        assert not allowed(acl, "edge_edge1", "ingress", "put", key)
    assert not allowed(acl, "edge_edge1", "ingress", "put", k.scan("robot1"))
    assert allowed(acl, "edge_edge1", "ingress", "declare_subscriber", k.all_scans())
    assert allowed(acl, "edge_edge1", "ingress", "declare_queryable", k.all_pings("edge1"))
    assert not allowed(acl, "edge_edge1", "ingress", "declare_queryable", k.all_pings("edge2"))
    assert not allowed(acl, "edge_edge1", "ingress", "reply", k.ping("robot1", "edge2"))
    assert allowed(acl, "robot_robot1", "ingress", "query", k.ping("robot1", "edge1"))
    assert not allowed(acl, "robot_robot1", "ingress", "query", k.ping("robot2", "edge1"))
    assert allowed(acl, "edge_edge1", "ingress", "liveliness_token", k.edge_alive("edge1"))
    assert not allowed(acl, "edge_edge1", "ingress", "liveliness_token", k.edge_alive("edge2"))
    # the other edges' room and liveliness (an edge sheds a robot only to a live edge with room)
    assert allowed(acl, "edge_edge1", "ingress", "declare_subscriber", k.all_edge_status())
    assert allowed(acl, "edge_edge1", "egress", "put", k.edge_status("edge2"))
    assert allowed(acl, "edge_edge1", "ingress", "declare_liveliness_subscriber", k.any_edge_alive())
    assert allowed(acl, "edge_edge1", "egress", "liveliness_token", k.edge_alive("edge2"))
    assert not allowed(acl, "edge_edge1", "ingress", "put", k.edge_status("edge2"))
    # the monitor only reads
    assert allowed(acl, "monitor_mon", "egress", "put", k.edge_status("edge1"))
    assert not any("put" in r["messages"] and "ingress" in r["flows"] for r in rules_of(acl, "monitor_mon"))
    # declarations flow to every client (a Publisher would drop every put without them)
    assert all(allowed(acl, s["id"], "egress", "declare_subscriber", k.all_scans()) for s in acl["subjects"])


def test_an_edge_answers_map_queries_only_under_its_own_id() -> None:
    """Was: every edge declared and answered ``ctrl/*/map``, so an authorised edge answered map
    queries for robots it does not map, in another edge's name. Now edge E declares, is sent and
    answers only ``ctrl/*/map/E``; queriers ask each edge by name; the key before per-edge maps is
    nobody's."""
    k = Keys()
    acl = access_control(k, ["robot1", "robot2"], ["edge1", "edge2"], ["mon"], routers=["rack"])
    for e, other in (("edge1", "edge2"), ("edge2", "edge1")):
        subject = f"edge_{e}"
        assert allowed(acl, subject, "ingress", "declare_queryable", k.all_maps(e))
        assert allowed(acl, subject, "egress", "query", k.map("robot1", e))
        assert allowed(acl, subject, "ingress", "reply", k.map("robot1", e))
        for message, flow in (("declare_queryable", "ingress"), ("query", "egress"), ("reply", "ingress")):
            assert not allowed(acl, subject, flow, message, k.all_maps(other)), (e, message)
            assert not allowed(acl, subject, flow, message, k.map("robot1", other)), (e, message)
            assert not allowed(acl, subject, flow, message, k.map_before("robot1")), (e, message)
        assert not allowed(acl, subject, "ingress", "declare_queryable", "zoffload/ctrl/*/map/*")
        # a wildcard query is not within the edge's rule: a querier names the edge (runtime/maps.py)
        assert not allowed(acl, subject, "egress", "query", "zoffload/ctrl/robot1/map/*")
    # the monitor (the lab's runner, the viewer) asks any edge by name for any robot's map
    for key in (k.map("robot1", "edge1"), k.map("robot2", "edge2")):
        assert allowed(acl, "monitor_mon", "ingress", "query", key)
        assert allowed(acl, "monitor_mon", "egress", "reply", key)
    assert not allowed(acl, "monitor_mon", "ingress", "declare_queryable", k.all_maps("edge1"))
    # a robot asks for its own map only, of any edge by name
    assert allowed(acl, "robot_robot1", "ingress", "query", k.map("robot1", "edge2"))
    assert allowed(acl, "robot_robot1", "egress", "reply", k.map("robot1", "edge2"))
    assert not allowed(acl, "robot_robot1", "egress", "reply", k.map("robot2", "edge2"))
    # nobody asks or answers on the key before per-edge maps
    for subject in ("robot_robot1", "monitor_mon", "router_rack"):
        for flow, message in (("ingress", "query"), ("egress", "reply"), ("ingress", "reply")):
            assert not allowed(acl, subject, flow, message, k.map_before("robot1")), (subject, message)
    for flow in ("ingress", "egress"):  # a linked router carries every edge's map queries and replies
        for message in ("query", "reply"):
            assert allowed(acl, "router_rack", flow, message, k.map("robot1", "edge2"))


def test_identities_must_be_ids_and_distinct() -> None:
    with pytest.raises(ValueError):
        access_control(Keys(), ["robot/1"], ["edge1"])
    with pytest.raises(ValueError, match="distinct"):
        access_control(Keys(), ["x"], ["x"])
    acl = access_control(Keys(), ["r1"], ["e1"], usernames=True)
    assert all(s["usernames"] == s["cert_common_names"] for s in acl["subjects"])


def test_router_config_speaks_tls_only() -> None:
    conf = router_config(["tls/0.0.0.0:7447"], "/c/ca.pem", "/c/router.pem", "/c/router.key",
                         {"enabled": True}, users_file="/c/users.txt")
    assert conf["transport"]["link"]["protocols"] == ["tls"]
    assert conf["transport"]["link"]["tls"]["enable_mtls"] is True
    assert conf["transport"]["auth"]["usrpwd"]["dictionary_file"] == "/c/users.txt"
    assert conf["scouting"]["multicast"]["enabled"] is False
    # forwarding several robots' BLOCK_FIRST scans to one edge without drops (bench_fanin)
    cc = zenoh.Config.from_json5(json.dumps(conf)).get_json("transport/link/tx/queue/congestion_control")
    assert '"wait_before_drop":50000' in cc


def test_certificates_chain_to_the_ca_with_the_identity_as_common_name(tmp_path: Path) -> None:
    pytest.importorskip("cryptography")
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    from zoffload.runtime.certs import write_deployment

    written = write_deployment(tmp_path, ["robot1"], ["edge1"], ["mon"], router_names=["router", "10.0.0.2"],
                               passwords=True)
    ca = x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name in ("robot1", "edge1", "mon", "router"):
        cert = x509.load_pem_x509_certificate((tmp_path / f"{name}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == name
        assert cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
        assert not cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
        assert stat.S_IMODE((tmp_path / f"{name}.key").stat().st_mode) == 0o600
    router = x509.load_pem_x509_certificate((tmp_path / "router.pem").read_bytes())
    san = router.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["router"]
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["10.0.0.2"]
    users = (tmp_path / "users.txt").read_text().split()
    assert sorted(u.split(":")[0] for u in users) == ["edge1", "mon", "robot1"]
    assert stat.S_IMODE((tmp_path / "users.txt").stat().st_mode) == 0o600
    text = written["router.json5"].read_text()
    conf = json.loads("\n".join(ln for ln in text.splitlines() if not ln.startswith("//")))
    assert conf["transport"]["link"]["tls"]["root_ca_certificate"] == f"{tmp_path.resolve()}/ca.pem"
    # Run again with one more robot: the CA is kept, so the others' certificates stay valid
    write_deployment(tmp_path, ["robot1", "robot2"], ["edge1"])
    assert x509.load_pem_x509_certificate((tmp_path / "ca.pem").read_bytes()) == ca


def test_linked_routers_each_get_a_certificate_a_config_and_the_other_as_a_peer(tmp_path: Path) -> None:
    pytest.importorskip("cryptography")
    from cryptography import x509

    from zoffload.runtime.certs import write_deployment

    written = write_deployment(tmp_path, ["robot1"], ["edge1"], routers=["router", "rack"],
                               router_names=["localhost"])
    confs = {}
    for r in ("router", "rack"):
        text = written[f"{r}.json5"].read_text()
        confs[r] = json.loads("\n".join(ln for ln in text.splitlines() if not ln.startswith("//")))
        cert = x509.load_pem_x509_certificate((tmp_path / f"{r}.pem").read_bytes())
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert san.get_values_for_type(x509.DNSName) == ["localhost", r]  # dialled by its own name too
        assert confs[r]["transport"]["link"]["tls"]["connect_certificate"].endswith(f"/{r}.pem")
    assert confs["router"]["connect"]["endpoints"] == []
    assert confs["rack"]["connect"]["endpoints"] == ["tls/router:7447"]
    for r, other in (("router", "rack"), ("rack", "router")):
        acl = confs[r]["access_control"]
        peer = next(p for p in acl["policies"] if p["id"] == f"router_{other}")
        rules = {rule["id"]: rule for rule in acl["rules"]}
        allowed = {(f, m) for rid in peer["rules"]
                   for f in rules[rid]["flows"] for m in rules[rid]["messages"]}
        # what crossed the link in the two-router check, both ways: data, declarations, queries, tokens
        for flow in ("ingress", "egress"):
            for message in ("put", "declare_subscriber", "declare_queryable", "query", "reply",
                            "liveliness_token"):
                assert (flow, message) in allowed, (r, flow, message)
        assert {s["id"] for s in acl["subjects"]} == {"robot_robot1", "edge_edge1", f"router_{other}"}
    with pytest.raises(ValueError, match="share its name"):
        write_deployment(tmp_path, ["robot1"], ["edge1"], routers=["router", "edge1"])


def test_tls_settings_become_zenoh_keys(tmp_path: Path) -> None:
    for name in ("ca.pem", "me.pem", "me.key", "pw"):
        (tmp_path / name).write_text("secret\n" if name == "pw" else "x")
    z = ZenohSettings(mode="client", connect=["tls/router:7447"], tls_ca=str(tmp_path / "ca.pem"),
                      tls_cert=str(tmp_path / "me.pem"), tls_key=str(tmp_path / "me.key"), user="me",
                      password_file=str(tmp_path / "pw"))
    e = security_entries(z)
    tls = "transport/link/tls/"
    assert e[tls + "enable_mtls"] is True  # without it on the client, Zenoh sends no certificate
    assert e[tls + "connect_certificate"] == e[tls + "listen_certificate"] == str(tmp_path / "me.pem")
    assert e["transport/auth/usrpwd/password"] == "secret"
    conf = zenoh_config(z)
    assert json.loads(conf.get_json(tls + "root_ca_certificate")) == str(tmp_path / "ca.pem")
    assert json.loads(conf.get_json("transport/auth/usrpwd/user")) == "me"
    assert security_entries(ZenohSettings()) == {}
    with pytest.raises(ConfigError, match="need tls_ca"):  # settings that cannot work: exit code 2
        security_entries(ZenohSettings(tls_cert="a", tls_key="b"))
    with pytest.raises(ConfigError, match="go together"):
        security_entries(ZenohSettings(tls_ca=str(tmp_path / "ca.pem"), tls_cert=str(tmp_path / "me.pem")))
    with pytest.raises(ZenohSessionError, match="cannot read"):
        security_entries(ZenohSettings(tls_ca=str(tmp_path / "missing.pem")))
    with pytest.raises(ConfigError, match="password_file"):
        security_entries(ZenohSettings(user="me"))


def test_a_config_file_keeps_its_mode_and_scouting_unless_they_are_given(tmp_path: Path) -> None:
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", scouting: { multicast: { enabled: false } } }')
    conf = zenoh_config(ZenohSettings(config_file=str(f)))
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    conf = zenoh_config(ZenohSettings(config_file=str(f), mode="router", multicast_scouting=True))
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True


def test_the_acl_placeholders_are_not_identities() -> None:
    """An edge named as the ACL's placeholder chunk would have had its id turned into ``*``."""
    from zoffload.runtime.acl import RESERVED

    for name in RESERVED:
        with pytest.raises(ValueError, match="reserved"):
            access_control(Keys(), ["robot1"], [name])
    linked = access_control(Keys(), ["robot1"], ["edge1"], routers=["rack"])
    assert allowed(linked, "router_rack", "ingress", "put", Keys().scan_ack("robot1", "edge1"))
    assert not allowed(linked, "router_rack", "ingress", "put", "zoffload/data/robot1/scan_ack")


def test_a_certificate_naming_another_than_the_programs_id_is_told(tmp_path: Path) -> None:
    """The router's ACL knows a client by its certificate's common name: a robot run as robot2
    with robot1's certificate is dropped without a word, so the daemons warn at start."""
    pytest.importorskip("cryptography")
    from zoffload.runtime.certs import make_ca, make_leaf, write_pair
    from zoffload.runtime.session import certificate_mismatch

    cert, key = write_pair(tmp_path, "robot1", make_leaf(make_ca(), "robot1"))
    z = ZenohSettings(tls_ca=str(cert), tls_cert=str(cert), tls_key=str(key))
    assert certificate_mismatch(z, "robot1") is None
    warning = certificate_mismatch(z, "robot2")
    assert warning is not None and "names robot1, not 'robot2'" in warning
    assert certificate_mismatch(ZenohSettings(), "robot2") is None  # no certificate: nothing to tell
    unreadable = ZenohSettings(tls_ca=str(cert), tls_cert=str(tmp_path / "gone.pem"), tls_key=str(key))
    assert certificate_mismatch(unreadable, "robot1") is None  # Zenoh reports the file itself
