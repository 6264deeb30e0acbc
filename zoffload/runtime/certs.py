"""Certificates for a TLS deployment, made with ``cryptography`` (``pip install 'zoffload[security]'``).

A private CA (ECDSA P-256, ``BasicConstraints(ca=True)``, ``keyCertSign``) signs one leaf per
identity: its common name is the identity the router's access control sees (robot, edge or
monitor id). The router's certificate carries a subject alternative name for every host name and
address clients dial (TLS checks names against the SAN only, never the CN). Private keys are
written readable by their owner only.

``write_deployment`` makes a whole set in a folder: ``ca.pem``/``ca.key`` (kept and reused when
present, so adding a robot later leaves the others' certificates valid), ``<id>.pem``/``<id>.key``
for every identity, ``router.pem``/``router.key``, the router's ``router.json5`` (TLS, mTLS and
the access control of runtime/acl.py), and, with ``passwords``, ``<id>.password`` per identity and
the router's ``users.txt`` for Zenoh's user/password authentication bound to the certificates.

Several routers (``routers``, e.g. one on the robots' network and one in the edges' rack): each
gets ``<name>.pem``/``.key`` (common name = its name, SAN = ``router_names`` plus its name) and
``<name>.json5``. Every router's access control knows every robot, edge and monitor (a client may
connect to any of them) and the other routers as linked peers; every router after the first
connects to ``router_connect`` (default ``tls/<first router>:7447``).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zoffload.protocol.keys import Keys
from zoffload.runtime.acl import access_control, router_config

HEADER = ("// zoffload's Zenoh router: TLS only, client certificates required (mTLS), default-deny\n"
          "// access control by certificate common name. Made by `zoffload certs`: run it again to\n"
          "// change it.\n")


def _crypto() -> Any:
    try:
        from cryptography import x509
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("making certificates needs cryptography: pip install 'zoffload[security]'") from exc
    return x509


@dataclass(frozen=True)
class Issuer:
    key: Any  # cryptography private key
    cert: Any  # cryptography x509.Certificate


def _new_key() -> Any:
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _write_key(path: Path, key: Any) -> None:
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def _write_cert(path: Path, cert: Any) -> None:
    from cryptography.hazmat.primitives import serialization

    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def make_ca(name: str = "zoffload CA", days: int = 3650) -> Issuer:
    x509 = _crypto()
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    key = _new_key()
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, encipher_only=False,
                                         decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return Issuer(key, cert)


def load_ca(cert_path: Path, key_path: Path) -> Issuer:
    x509 = _crypto()
    from cryptography.hazmat.primitives import serialization

    return Issuer(serialization.load_pem_private_key(key_path.read_bytes(), password=None),
                  x509.load_pem_x509_certificate(cert_path.read_bytes()))


def make_leaf(ca: Issuer, common_name: str, days: int = 365, names: Sequence[str] = (),
              valid_from: datetime.datetime | None = None) -> Issuer:
    """A certificate for ``common_name`` signed by ``ca``; ``names``: host names and IP addresses
    for the subject alternative name (a server's: every name clients dial)."""
    x509 = _crypto()
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = _new_key()
    start = valid_from or datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(minutes=5)
    builder = (x509.CertificateBuilder()
               .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
               .issuer_name(ca.cert.subject).public_key(key.public_key())
               .serial_number(x509.random_serial_number())
               .not_valid_before(start).not_valid_after(start + datetime.timedelta(days))
               .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
               .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                     ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
               .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.key.public_key()),
                              critical=False))
    alt: list[Any] = []
    for name in names:
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alt.append(x509.DNSName(name))
    if alt:
        builder = builder.add_extension(x509.SubjectAlternativeName(alt), critical=False)
    return Issuer(key, builder.sign(ca.key, hashes.SHA256()))


def write_pair(folder: Path, stem: str, issued: Issuer) -> tuple[Path, Path]:
    cert, key = folder / f"{stem}.pem", folder / f"{stem}.key"
    _write_cert(cert, issued.cert)
    _write_key(key, issued.key)
    return cert, key


def write_deployment(out: Path, robots: Sequence[str], edges: Sequence[str], monitors: Sequence[str] = (),
                     router_names: Sequence[str] = ("localhost", "127.0.0.1"),
                     listen: Sequence[str] = ("tls/0.0.0.0:7447",), days: int = 365,
                     namespace: str = "zoffload", certs_path: str | None = None, passwords: bool = False,
                     lease_ms: int = 2000, routers: Sequence[str] = ("router",),
                     router_listen: Mapping[str, Sequence[str]] | None = None,
                     router_connect: str | None = None) -> dict[str, Path]:
    """Write a deployment's certificates and router config to ``out`` (see the module docstring);
    ``certs_path``: where the router will find these files (default: ``out`` itself);
    ``router_listen``: a router's own endpoints instead of ``listen`` (several routers on one
    host). Returns the files written by name."""
    routers = list(routers)
    if not routers or len(set(routers)) != len(routers):
        raise ValueError(f"name one router or more, each once: {routers}")
    clash = set(routers) & {*robots, *edges, *monitors}
    if clash:
        raise ValueError(f"a router cannot share its name with a robot, edge or monitor: {sorted(clash)}")
    reserved = {"ca", "users"} & {*routers, *robots, *edges, *monitors}
    if reserved:
        raise ValueError(f"names kept for the CA and the users file: {sorted(reserved)}")
    if passwords and len(routers) > 1:
        # Zenoh's user/password check refuses a link that brings no credentials, and a router
        # dialling another has none: linked routers authenticate by certificate alone
        raise ValueError("passwords (usrpwd) work with one router; linked routers use certificates only")
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    ca_cert, ca_key = out / "ca.pem", out / "ca.key"
    if ca_cert.exists() and ca_key.exists():
        ca = load_ca(ca_cert, ca_key)
    else:
        ca = make_ca()
        write_pair(out, "ca", ca)
    written["ca"] = ca_cert
    for name in [*robots, *edges, *monitors]:
        written[name] = write_pair(out, name, make_leaf(ca, name, days))[0]
    for router in routers:
        names = [*router_names, *([router] if router not in router_names else [])]
        written[router] = write_pair(out, router, make_leaf(ca, router, days, names))[0]
    where = certs_path or str(out.resolve())
    users = None
    if passwords:
        lines = []
        for name in [*robots, *edges, *monitors]:
            secret = secrets.token_urlsafe(24)
            path = out / f"{name}.password"
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(secret + "\n")
            lines.append(f"{name}:{secret}")
        users_path = out / "users.txt"
        fd = os.open(users_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write("\n".join(lines) + "\n")
        written["users"] = users_path
        users = f"{where}/users.txt"
    first = routers[0]
    link = router_connect or f"tls/{first}:7447"
    for router in routers:
        peers = [r for r in routers if r != router]
        acl = access_control(Keys(namespace), robots, edges, monitors, usernames=passwords, routers=peers)
        conf = router_config((router_listen or {}).get(router, listen), f"{where}/ca.pem",
                             f"{where}/{router}.pem", f"{where}/{router}.key", acl, lease_ms=lease_ms,
                             users_file=users, connect=[link] if router != first else [])
        written[f"{router}.json5"] = out / f"{router}.json5"
        written[f"{router}.json5"].write_text(HEADER + json.dumps(conf, indent=2) + "\n")
    return written
