"""Opening Zenoh sessions from the session settings every program shares, and loopback helpers
for local runs and tests."""

from __future__ import annotations

import json
import logging
import socket
from typing import Any

import zenoh

from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.errors import ZenohSessionError


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (bind to port 0, read it back, release it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def zenoh_config(z: ZenohSettings) -> zenoh.Config:
    """Build a ``zenoh.Config`` from the session settings (file first, then flags, then --cfg)."""
    try:
        conf = zenoh.Config.from_file(z.config_file) if z.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(z.mode))
        if z.connect:
            conf.insert_json5("connect/endpoints", json.dumps(z.connect))
        if z.listen:
            conf.insert_json5("listen/endpoints", json.dumps(z.listen))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(z.multicast_scouting))
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(z.shared_memory))
        for item in z.cfg:
            key, value = item.split(":", 1)
            conf.insert_json5(key, value)
    except Exception as exc:  # zenoh raises ZError and plain exceptions for config problems
        raise ZenohSessionError(f"invalid Zenoh configuration: {exc}") from exc
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
