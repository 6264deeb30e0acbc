"""Opening Zenoh sessions from the session settings every program shares (TLS and user/password
included), and loopback helpers for local runs and tests."""

from __future__ import annotations

import json
import logging
import os
import random
import socket
from pathlib import Path
from typing import Any

import zenoh

from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.errors import ConfigError, ZenohSessionError


def ephemeral_ports() -> tuple[int, int]:
    """The kernel's range of source ports for outgoing connections (Linux's default elsewhere)."""
    try:
        low, high = (int(x) for x in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return low, high
    except (OSError, ValueError):
        return 32768, 60999


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now, below the kernel's ephemeral range where there is room
    (from 20000). A port from ``bind(0)`` is an ephemeral one, and any outgoing connection may take
    it as its source port between the moment it is picked and the moment its server listens on it:
    a detection sweep's edge once failed to start so ("Address already in use")."""
    low = ephemeral_ports()[0]
    for _ in range(64) if low > 21000 else ():
        port = random.randint(20000, low - 1)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def security_entries(z: ZenohSettings) -> dict[str, Any]:
    """The Zenoh config keys of the TLS and user/password settings.

    ``tls_ca`` alone: TLS, the peer's certificate checked against that CA. With ``tls_cert`` and
    ``tls_key``: mutual TLS, this program presenting its certificate (its identity for the router's
    access control is the certificate's common name). Zenoh sends no client certificate unless
    ``enable_mtls`` is also set on the client, so it is set on every side; the certificate serves
    for both the connecting and the listening side of the session."""
    entries: dict[str, Any] = {}
    if z.tls_cert or z.tls_key or z.tls_ca:
        if not z.tls_ca:
            raise ConfigError("tls_cert and tls_key need tls_ca (the CA the other side's certificate "
                              "must chain to)")
        if bool(z.tls_cert) != bool(z.tls_key):
            raise ConfigError("tls_cert and tls_key go together")
        for path in (z.tls_ca, z.tls_cert, z.tls_key):
            if path and not os.access(path, os.R_OK):
                raise ZenohSessionError(f"cannot read the TLS file {path}")
        tls = "transport/link/tls/"
        entries[tls + "root_ca_certificate"] = z.tls_ca
        if z.tls_cert:
            entries[tls + "enable_mtls"] = True
            for side in ("connect", "listen"):
                entries[f"{tls}{side}_certificate"] = z.tls_cert
                entries[f"{tls}{side}_private_key"] = z.tls_key
        plain = [e for e in [*z.connect, *z.listen] if not e.startswith(("tls/", "quic/"))]
        if plain:
            logging.getLogger("zoffload.session").warning(
                "TLS is configured but %s %s not encrypted: use tls/HOST:PORT", ", ".join(plain),
                "is" if len(plain) == 1 else "are")
    if z.user:
        if not z.password_file:
            raise ConfigError("user needs password_file (the password's first line)")
        try:
            password = Path(z.password_file).read_text().splitlines()[0].strip()
        except (OSError, IndexError) as exc:
            raise ZenohSessionError(f"cannot read a password from {z.password_file}: {exc}") from exc
        entries["transport/auth/usrpwd/user"] = z.user
        entries["transport/auth/usrpwd/password"] = password
    return entries


def certificate_mismatch(z: ZenohSettings, identity: str) -> str | None:
    """A warning when this program's certificate (``tls_cert``) names another than ``identity``
    (its robot or edge id): a router's access control knows a client by its certificate's common
    name, and drops what it sends under another id without a word. None when the names agree, or
    when it cannot tell (no certificate; ``cryptography``, the ``security`` extra, not installed; a
    file Zenoh will report itself)."""
    if not z.tls_cert:
        return None
    try:
        from cryptography import x509
        from cryptography.x509.oid import NameOID
    except ImportError:
        return None
    try:
        cert = x509.load_pem_x509_certificate(Path(z.tls_cert).read_bytes())
    except (OSError, ValueError):
        return None
    names = [str(a.value) for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if identity in names:
        return None
    return (f"the certificate {z.tls_cert} names {', '.join(names) or 'no one'}, not {identity!r}: a "
            f"router's access control drops what this program sends as {identity!r} (its id must be its "
            f"certificate's common name)")


# Zenoh's own lease is 10 s: a SIGKILLed edge on a machine that stays up closes its sockets and is
# seen gone at once, but a machine that dies or leaves the Wi-Fi is seen gone only when its lease
# runs out. Each node announces its own lease (the time the others wait for a keep-alive from it),
# so robots, edges and the router all say 2 s, keep-alives every 0.5 s: an edge lost is an edge
# seen gone within 2 s, which bounds the robot's failover (issue 12). ``--cfg`` overrides these.
LEASE_MS = 2000
LINK_DEFAULTS = {"transport/link/tx/lease": str(LEASE_MS), "transport/link/tx/keep_alive": "4"}


def zenoh_config(z: ZenohSettings) -> zenoh.Config:
    """Build a ``zenoh.Config`` from the session settings: the config file first, then the session
    settings, then ``--cfg``. With a config file, the settings that have a default (mode, scouting,
    shared memory) override it only when they were given."""

    def given(name: str) -> bool:
        return not z.config_file or name in z.model_fields_set

    entries = security_entries(z)
    try:
        conf = zenoh.Config.from_file(z.config_file) if z.config_file else zenoh.Config()
    except Exception as exc:
        raise ZenohSessionError(f"invalid Zenoh configuration file {z.config_file}: {exc}") from exc
    try:
        if given("mode"):
            conf.insert_json5("mode", json.dumps(z.mode))
        if z.connect:
            conf.insert_json5("connect/endpoints", json.dumps(z.connect))
        if z.listen:
            conf.insert_json5("listen/endpoints", json.dumps(z.listen))
        if given("multicast_scouting"):
            conf.insert_json5("scouting/multicast/enabled", json.dumps(z.multicast_scouting))
        if given("shared_memory"):
            conf.insert_json5("transport/shared_memory/enabled", json.dumps(z.shared_memory))
        for key, value in entries.items():
            conf.insert_json5(key, json.dumps(value))
        if not z.config_file:
            for key, value in LINK_DEFAULTS.items():
                conf.insert_json5(key, value)
    except Exception as exc:  # zenoh raises ZError and plain exceptions for config problems
        raise ZenohSessionError(f"invalid Zenoh configuration: {exc}") from exc
    for item in z.cfg:
        key, value = item.split(":", 1)
        try:
            conf.insert_json5(key, value)
        except Exception as exc:  # which of several --cfg entries: named
            raise ZenohSessionError(f"invalid Zenoh configuration: cfg entry {item!r}: {exc}") from exc
    return conf


def open_session(z: ZenohSettings) -> zenoh.Session:
    """Open a Zenoh session, turning failures (port in use, bad endpoint) into a clear error."""
    conf = zenoh_config(z)
    try:
        return zenoh.open(conf)
    except Exception as exc:
        raise ZenohSessionError(
            f"cannot open the Zenoh session (mode={z.mode}, listen={z.listen}, "
            f"connect={z.connect}): {exc}"
        ) from exc


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches this publisher now. (zenoh-python 1.10's stub types
    ``matching_status`` as bool; at run time it is a ``MatchingStatus`` with ``.matching``.)"""
    status: Any = publisher.matching_status
    return bool(getattr(status, "matching", status))


def undeclare(*entities: Any) -> None:
    """Undeclare subscribers, publishers, queryables and tokens; None entries are skipped. A
    session already closing makes this fail, which at shutdown is no news."""
    for entity in entities:
        if entity is None:
            continue
        try:
            entity.undeclare()
        except Exception as exc:  # the session is closing
            logging.getLogger("zoffload.session").debug("%s not undeclared: %s", type(entity).__name__, exc)


MAX_MESSAGE_KEY = "transport/link/rx/max_message_size"
LISTEN_KEY = "listen/endpoints"
DROP_WAIT_KEY = "transport/link/tx/queue/congestion_control/drop/wait_before_drop"
DROP_WAIT_US = 50_000
"""How long a node's transport waits before it drops a message it cannot queue, in microseconds
(Zenoh's default: 1 ms). It also bounds the wait of a BLOCK_FIRST message (a scan) for its link's
block-first slot, which the previous one holds until a spawned task has queued it. On a busy CPU
that task can take longer than 1 ms to run: a router forwarding two robots' scans to one edge then
dropped the second scan, unseen by either side (``python -m benchmarks.bench_fanin``). The edge and
the router wait up to 50 ms (two camera frames) instead."""


def with_defaults(z: ZenohSettings, defaults: dict[str, str]) -> ZenohSettings:
    """``z`` with these ``KEY: JSON5 value`` Zenoh settings added, unless the user's ``--cfg`` or
    config file already sets them."""
    if z.config_file:
        return z
    given = {item.split(":", 1)[0] for item in z.cfg}
    extra = [f"{k}:{v}" for k, v in defaults.items() if k not in given]
    return z.model_copy(update={"cfg": [*extra, *z.cfg]}) if extra else z


def dialling_only(z: ZenohSettings) -> dict[str, str]:
    """The setting that keeps a peer without ``listen`` endpoints from listening at all (Zenoh's
    peers otherwise listen on a random port of every interface): a program that only dials, as a
    robot does, cannot then be dialled back. A peer that learns its address by gossip (an edge,
    told by a third peer) dials it while it dials the edge itself, and the two links make one
    Zenoh session; when one side's lease runs out first (an edge frozen past the 2 s lease), Zenoh
    can add the redial to the stale session on the other side and never send its declarations
    again (eclipse-zenoh/zenoh#2806, open). The frozen-edge test saw its like in CI
    (tests/system/test_vision.py): the robot saw the edge's token come back, and no frame or ping
    was answered for the rest of the run; Zenoh's log of that test shows the edge dialling the
    robot back. Nothing when the settings give endpoints to listen on, or in another mode (with a
    config file, ``with_defaults`` leaves every key to it)."""
    return {LISTEN_KEY: "[]"} if z.mode == "peer" and not z.listen else {}
