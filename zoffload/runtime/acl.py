"""The Zenoh router's access control for a zoffload deployment, generated from the key layout.

Identities are certificate common names (mTLS): one per robot, per edge, per read-only monitor.
Default deny; what each may do, with flows seen from the router (ingress: from that client,
egress: to it) and every rule key including the message's key (Zenoh checks inclusion):

* robot R: put its own ``data/R/scan``, ``data/R/frame``, ``status/R``; hold ``alive/robot/R``;
  subscribe to (``data/R/scan_ack/**``, ...) and receive only its own answers, from every edge under
  its id (``data/R/scan_ack/*``, ``data/R/detections/*``, ``data/R/checkpoint/*``) and the edges'
  status (``status/edge/*``: their capacity and load, which the fleet assignment ranks by); query
  only its own ``ctrl/R/map/*`` (its map, from an edge by name), ``ctrl/R/ping/*`` (its round trip
  to an edge) and ``ctrl/R/attach/*`` (asking any edge to map it) and receive their replies; watch
  ``alive/edge/*``.
* edge E: subscribe to and receive every robot's scans and frames; put acks, detections and
  checkpoints for any robot under its own id only (``data/*/scan_ack/E``, ...: an edge cannot
  answer in another edge's name, and the robot checks the payload's edge against the key's) and its
  own ``status/edge/E``; declare and answer its own ``ctrl/*/map/E``, ``ctrl/*/ping/E`` and
  ``ctrl/*/attach/E`` queryables only (it cannot answer a map, attach or ping query in another
  edge's name, and a querier drops a map reply naming another edge than it asked); hold
  ``alive/edge/E``; watch ``alive/robot/*`` and ``alive/edge/*``, and receive the other edges'
  status (``status/edge/*``: whether one has room for a robot it sheds).
* monitor M (the lab's runner, a dashboard): receive ``status/**``, query ``ctrl/*/map/*`` (each
  edge by name: Zenoh checks the query's key against the edge's rule, so a wildcard query for
  ``ctrl/R/map/*`` reaches no edge), watch ``alive/**``; never put. Nobody may use the key before
  per-edge maps (``ctrl/R/map``), which any edge answered.
* router P (another router linked to this one, holding P's certificate): what its robots' and
  edges' traffic needs to cross the link, in both directions, for any robot and edge id: puts of
  scans, frames, answers and statuses; subscription, queryable and liveliness declarations;
  queries and replies on ``ctrl``; liveliness tokens under ``alive``. A router is trusted to hold
  its own clients to their rules (each router enforces the per-identity rules of the clients that
  connect to it), so P's key is worth every robot's and every edge's rights: keep it on P.
* everyone: the router may tell a client which subscriptions and queryables exist under the
  namespace (egress ``declare_subscriber``/``declare_queryable``: metadata, never data). Without it
  a ``declare_publisher`` sees no subscriber and drops every put inside the client, silently.

Zenoh has no templating by common name, so each robot and edge gets its own rules. With
``usernames``, a subject must also log in with the user of its own name (Zenoh's usrpwd), binding
the password to the certificate.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from zoffload.protocol.keys import Keys, check_id
from zoffload.runtime.session import DROP_WAIT_US

_PLACEHOLDER = "zoffload-acl-any"
RESERVED = (_PLACEHOLDER,)  # not an identity: the ACL's own wildcard placeholder


def _wild(key_of: Callable[[str], str]) -> str:
    """A per-id key with its id chunk as ``*`` (keys.py stays the only place that formats keys)."""
    parts = key_of(_PLACEHOLDER).split("/")
    i = len(parts) - 1 - parts[::-1].index(_PLACEHOLDER)
    parts[i] = "*"
    return "/".join(parts)


def _rule(rid: str, flow: str, messages: Sequence[str], keys: Sequence[str]) -> dict[str, Any]:
    return {"id": rid, "permission": "allow", "flows": [flow], "messages": list(messages),
            "key_exprs": list(keys)}


def _robot_rules(k: Keys, r: str) -> list[dict[str, Any]]:
    # subscribed with ``**`` (an older edge's answers on the key without an edge chunk, where no
    # ACL runs), received only under an edge's id (one chunk: never the key without one, which no
    # client may put and which must not reach a robot over a link from a router with an older ACL)
    subscribed = [*(k.answers(kind, r) for kind in k.ANSWERS), k.all_edge_status()]
    received = [*(k.answer(kind, r, "*") for kind in k.ANSWERS), k.all_edge_status()]
    ctrl = [_wild(lambda e: k.map(r, e)), _wild(lambda e: k.ping(r, e)), _wild(lambda e: k.attach(r, e))]
    return [
        _rule(f"robot_{r}_put", "ingress", ["put"], [k.scan(r), k.frame(r), k.robot_status(r)]),
        _rule(f"robot_{r}_sub", "ingress", ["declare_subscriber"], subscribed),
        _rule(f"robot_{r}_rx", "egress", ["put"], received),
        _rule(f"robot_{r}_token", "ingress", ["liveliness_token"], [k.robot_alive(r)]),
        _rule(f"robot_{r}_watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
              [k.any_edge_alive()]),
        _rule(f"robot_{r}_edges", "egress", ["liveliness_token"], [k.any_edge_alive()]),
        _rule(f"robot_{r}_get", "ingress", ["query"], ctrl),
        _rule(f"robot_{r}_replies", "egress", ["reply"], ctrl),
    ]


def _edge_rules(k: Keys, e: str) -> list[dict[str, Any]]:
    inputs = [k.all_scans(), k.all_frames()]
    ctrl = [k.all_maps(e), k.all_pings(e), k.all_attaches(e)]
    return [
        _rule(f"edge_{e}_sub", "ingress", ["declare_subscriber"], inputs),
        _rule(f"edge_{e}_rx", "egress", ["put"], inputs),
        _rule(f"edge_{e}_put", "ingress", ["put"],
              [*(k.answer(kind, "*", e) for kind in k.ANSWERS), k.edge_status(e)]),
        _rule(f"edge_{e}_queryable", "ingress", ["declare_queryable"], ctrl),
        _rule(f"edge_{e}_queries", "egress", ["query"], ctrl),
        _rule(f"edge_{e}_reply", "ingress", ["reply"], ctrl),
        _rule(f"edge_{e}_token", "ingress", ["liveliness_token"], [k.edge_alive(e)]),
        _rule(f"edge_{e}_watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
              [k.any_robot_alive(), k.any_edge_alive()]),
        _rule(f"edge_{e}_robots", "egress", ["liveliness_token"], [k.any_robot_alive(), k.any_edge_alive()]),
        # the other edges' room and liveliness: a robot is shed only when another live edge can take it
        _rule(f"edge_{e}_peers", "ingress", ["declare_subscriber"], [k.all_edge_status()]),
        _rule(f"edge_{e}_peers_rx", "egress", ["put"], [k.all_edge_status()]),
    ]


def _monitor_rules(k: Keys, m: str) -> list[dict[str, Any]]:
    status = f"{k.ns}/status/**"
    alive = f"{k.ns}/alive/**"
    return [
        _rule(f"monitor_{m}_sub", "ingress", ["declare_subscriber"], [status]),
        _rule(f"monitor_{m}_rx", "egress", ["put"], [status]),
        _rule(f"monitor_{m}_get", "ingress", ["query"], [_wild(k.all_maps)]),  # each edge by name
        _rule(f"monitor_{m}_replies", "egress", ["reply"], [_wild(k.all_maps)]),
        _rule(f"monitor_{m}_watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
              [alive]),
        _rule(f"monitor_{m}_tokens", "egress", ["liveliness_token"], [alive]),
    ]


def _router_rules(k: Keys, p: str) -> list[dict[str, Any]]:
    data = [_wild(k.scan), _wild(k.frame), *(k.answer(kind, "*", "*") for kind in k.ANSWERS),
            f"{k.ns}/status/**"]
    ctrl = [_wild(k.all_maps), _wild(k.all_pings), _wild(k.all_attaches)]
    alive = [k.any_robot_alive(), k.any_edge_alive()]
    rules = []
    for flow in ("ingress", "egress"):
        rules += [
            _rule(f"router_{p}_{flow}_put", flow, ["put"], data),
            _rule(f"router_{p}_{flow}_declare", flow, ["declare_subscriber", "declare_queryable"],
                  [f"{k.ns}/**"]),
            _rule(f"router_{p}_{flow}_ctrl", flow, ["query", "reply"], ctrl),
            _rule(f"router_{p}_{flow}_alive", flow, ["liveliness_token", "declare_liveliness_subscriber",
                                                     "liveliness_query"], alive),
        ]
    return rules


def access_control(keys: Keys, robots: Sequence[str], edges: Sequence[str], monitors: Sequence[str] = (),
                   usernames: bool = False, routers: Sequence[str] = ()) -> dict[str, Any]:
    """The ``access_control`` section of the router's config for these identities; ``routers``:
    the other routers linked to this one (their certificates' common names)."""
    names = [*robots, *edges, *monitors, *routers]
    for name in names:
        check_id(name, "identity")
        if name in RESERVED:
            raise ValueError(f"{name!r} is reserved (the ACL's placeholder), not an identity")
    if len(set(names)) != len(names):
        raise ValueError(f"identities must be distinct: {names}")
    rules: list[dict[str, Any]] = [
        _rule("declarations_out", "egress", ["declare_subscriber", "declare_queryable"], [f"{keys.ns}/**"])]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for kind, ids, make in (("robot", robots, _robot_rules), ("edge", edges, _edge_rules),
                            ("monitor", monitors, _monitor_rules), ("router", routers, _router_rules)):
        for name in ids:
            own = make(keys, name)
            rules += own
            subject: dict[str, Any] = {"id": f"{kind}_{name}", "cert_common_names": [name]}
            if usernames and kind != "router":  # routers authenticate by certificate alone
                subject["usernames"] = [name]
            subjects.append(subject)
            policies.append({"id": f"{kind}_{name}", "subjects": [subject["id"]],
                             "rules": [r["id"] for r in own] + ["declarations_out"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(listen: Sequence[str], ca: str, cert: str, key: str, acl: dict[str, Any],
                  lease_ms: int = 2000, users_file: str | None = None,
                  connect: Sequence[str] = ()) -> dict[str, Any]:
    """A router that speaks TLS only, requires client certificates and enforces ``acl``.

    ``lease_ms`` is the router's own lease: clients notice a dead router within it (each node
    announces its own lease, so robots and edges set theirs too). ``connect``: other routers to
    link to; the link presents ``cert`` (its common name is what their access control sees) and
    checks the other router's name against its certificate, as clients do."""
    link: dict[str, Any] = {
        "protocols": ["tls"],  # no plain tcp listener: unauthenticated clients cannot even connect
        "tls": {"root_ca_certificate": ca, "listen_certificate": cert, "listen_private_key": key,
                "connect_certificate": cert, "connect_private_key": key, "enable_mtls": True,
                "verify_name_on_connect": True},
        "tx": {"lease": lease_ms, "keep_alive": 4,
               # forwarding robots' scans (BLOCK_FIRST) to one edge: see runtime/session.py DROP_WAIT_US
               "queue": {"congestion_control": {"drop": {"wait_before_drop": DROP_WAIT_US}}}},
    }
    transport: dict[str, Any] = {"link": link}
    if users_file:
        transport["auth"] = {"usrpwd": {"dictionary_file": users_file}}
    return {"mode": "router", "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            "transport": transport, "access_control": acl}
