"""The Zenoh session on the ROS side, set up as rmw_zenoh's own sessions are.

ROS 2 nodes on rmw_zenoh are peers of a router (``ros2 run rmw_zenoh_cpp rmw_zenohd``, listening
on ``tcp/localhost:7447``) with multicast scouting off and timestamping on. The rmw_zenohd
router does not forward between peers (``peers_failover_brokering: false``) but always to and from
clients, so a Python program joins as a **client** of that router (rmw_zenoh issues #625, #929).
``ZENOH_SESSION_CONFIG_URI`` (rmw_zenoh's variable for a session config file) and
``ROS_DOMAIN_ID`` are honoured as a ROS node honours them.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass

import zenoh

ROUTER = "tcp/localhost:7447"
CONFIG_ENV = "ZENOH_SESSION_CONFIG_URI"


class Ros2SessionError(RuntimeError):
    """The ROS-side session cannot be opened (bad config file, endpoint, domain)."""


def ros_domain(domain_id: int | None = None) -> int:
    """The configured domain, else ``ROS_DOMAIN_ID``, else 0."""
    if domain_id is not None:
        return int(domain_id)
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit():
        raise Ros2SessionError(f"ROS_DOMAIN_ID={text!r} is not a number")
    return int(text)


def ros_session_config(mode: str = "client", connect: Sequence[str] = (ROUTER,), listen: Sequence[str] = (),
                       config_file: str | None = None) -> zenoh.Config:
    """A config file (given, or ``$ZENOH_SESSION_CONFIG_URI``) is used as it is, with
    timestamping on; otherwise ``mode``, ``connect`` and ``listen`` with multicast scouting and
    shared memory off (as rmw_zenoh ships them) and timestamping on (a latched publisher's cache
    orders its samples by timestamp)."""
    path = config_file or os.environ.get(CONFIG_ENV) or None
    try:
        if path:
            conf = zenoh.Config.from_file(path)
        else:
            conf = zenoh.Config()
            conf.insert_json5("mode", json.dumps(mode))
            conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
            conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
            conf.insert_json5("scouting/multicast/enabled", "false")
            conf.insert_json5("transport/shared_memory/enabled", "false")
        conf.insert_json5("timestamping/enabled", "true")
    except Exception as exc:  # zenoh raises ZError and plain exceptions for config problems
        raise Ros2SessionError(f"invalid ROS-side Zenoh configuration ({path or mode}): {exc}") from exc
    return conf


def open_ros_session(mode: str = "client", connect: Sequence[str] = (ROUTER,), listen: Sequence[str] = (),
                     config_file: str | None = None) -> zenoh.Session:
    conf = ros_session_config(mode, connect, listen, config_file)
    try:
        return zenoh.open(conf)
    except Exception as exc:
        where = config_file or os.environ.get(CONFIG_ENV) or f"{mode}, connect={list(connect)}"
        raise Ros2SessionError(
            f"cannot open the ROS-side Zenoh session ({where}): {exc}. Is the rmw_zenoh router "
            "running (ros2 run rmw_zenoh_cpp rmw_zenohd)?") from exc


@dataclass(frozen=True)
class Ros2Link:
    """How a zoffload program joins the ROS graph: the session (mode, endpoints or a config file),
    the domain (None: ``ROS_DOMAIN_ID``), and the node it appears as."""

    domain_id: int | None = None
    mode: str = "client"
    connect: tuple[str, ...] = (ROUTER,)
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    node: str = "zoffload"
    namespace: str = "/"
    keyed_attachment: bool = False  # Jazzy 0.2.0-0.2.3 peers

    def domain(self) -> int:
        return ros_domain(self.domain_id)

    def open(self) -> zenoh.Session:
        return open_ros_session(self.mode, self.connect, self.listen, self.config_file)
