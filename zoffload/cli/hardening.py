"""``zoffload certs`` (a deployment's certificates and router config) and ``zoffload experiment
soak`` (robot + edge for a long time, their resources recorded)."""

from __future__ import annotations

import argparse
from typing import Any

from zoffload.runtime.errors import ConfigError, ExitCode


def _run_certs(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.runtime.certs import write_deployment

    if not a.robots or not a.edges:
        raise ConfigError("certs: name at least one robot (--robots) and one edge (--edges)")
    try:
        written = write_deployment(Path(a.out), a.robots, a.edges, a.monitors or [], a.router_names,
                                   a.listen, days=a.days, namespace=a.namespace, certs_path=a.certs_path,
                                   passwords=a.passwords, lease_ms=a.lease_ms, routers=a.routers,
                                   router_connect=a.router_connect)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    for name, path in written.items():
        print(f"{name:>14}  {path}")
    for router in a.routers:
        print(f"router: zoffload router -c {written[router + '.json5']}   (or zenohd -c ...)")
    print("daemons: --tls-ca ca.pem --tls-cert ID.pem --tls-key ID.key -m client -e tls/<router>:<port>")
    return ExitCode.OK


def add_certs(sub: Any) -> None:
    c = sub.add_parser("certs", help="a CA, certificates per robot/edge/monitor, the router TLS+ACL config",
                       description="Make (or extend: an existing ca.pem/ca.key in --out is reused) a private "
                       "CA, a certificate per identity (its common name is the identity the router's access "
                       "control sees), the router's certificate (SAN: --router-names) and router.json5: TLS "
                       "only, client certificates required, default-deny access control where each robot may "
                       "only publish its own data and each edge only answer.")
    c.add_argument("--out", required=True, help="folder for the files (keys are written mode 600)")
    c.add_argument("--robots", nargs="+", default=[], metavar="ID", help="robot ids")
    c.add_argument("--edges", nargs="+", default=[], metavar="ID", help="edge ids")
    c.add_argument("--monitors", nargs="*", default=[], metavar="ID",
                   help="read-only identities (status, maps, presence): lab runners, dashboards")
    c.add_argument("--router-names", nargs="+", default=["localhost", "127.0.0.1"], metavar="NAME",
                   help="every host name and IP address clients dial the router by (default: localhost "
                   "127.0.0.1; docker compose: router)")
    c.add_argument("--listen", nargs="+", default=["tls/0.0.0.0:7447"], metavar="ENDPOINT",
                   help="the router's endpoints (default tls/0.0.0.0:7447)")
    c.add_argument("--routers", nargs="+", default=["router"], metavar="NAME",
                   help="router names (default: one, 'router'): several make linked routers, e.g. one on "
                   "the robots' network and one in the edges' rack, each with its own certificate and "
                   "NAME.json5; the others connect to the first")
    c.add_argument("--router-connect", default=None, metavar="ENDPOINT",
                   help="where the other routers reach the first (default tls/FIRST:7447)")
    c.add_argument("--certs-path", default=None, metavar="DIR",
                   help="where the router finds these files at run time (default: --out; compose: "
                   "/etc/zoffload/certs)")
    c.add_argument("--days", type=int, default=365, help="validity of the certificates (default 365)")
    c.add_argument("--namespace", default="zoffload", help="key namespace (default zoffload)")
    c.add_argument("--passwords", action="store_true",
                   help="also a password per identity (ID.password) and the router's users.txt: Zenoh "
                   "user/password authentication, bound to the certificate in the ACL")
    c.add_argument("--lease-ms", type=int, default=2000,
                   help="the router's Zenoh lease: clients notice a dead router within it (default 2000)")
    c.add_argument("--log-level", default=None)
    c.set_defaults(func=_run_certs)


def _run_soak(a: argparse.Namespace) -> int:
    from pathlib import Path

    from zoffload.lab.soak import SoakOptions, run_soak

    summary = run_soak(SoakOptions(duration=a.duration, out=Path(a.out), period=a.period, rate_hz=a.rate,
                                   camera=a.camera, fps=a.fps, warmup=a.warmup, scans=a.scans,
                                   map_budget=a.map_budget))
    print(summary.line())
    return ExitCode.OK if summary.ok else ExitCode.FAILURE


def add_soak(sub: Any) -> None:
    """``zoffload experiment soak``: added to the ``experiment`` command's own subcommands."""
    experiment = sub.choices["experiment"]
    kinds = next(act for act in experiment._actions if isinstance(act, argparse._SubParsersAction))
    s = kinds.add_parser("soak", help="robot + edge (+ camera) for a long time: RSS, threads, CPU, fds and "
                         "counters every --period seconds, with a plot")
    s.add_argument("--duration", type=float, required=True, help="seconds to run (e.g. 3600)")
    s.add_argument("--out", required=True, help="results folder")
    s.add_argument("--period", type=float, default=10.0, help="seconds between samples (default 10)")
    s.add_argument("--warmup", type=float, default=300.0,
                   help="seconds before the growth figures start (map budget filling; default 300)")
    s.add_argument("--rate", type=float, default=10.0, help="scan rate in Hz (default 10)")
    s.add_argument("--scans", default="sim", help="'sim' (default) or a folder of scans, replayed in a loop")
    s.add_argument("--camera", default="auto", choices=["auto", "on", "off"],
                   help="also the camera pipeline (auto: when the detector models and COCO images exist)")
    s.add_argument("--fps", type=float, default=5.0, help="camera rate (default 5)")
    s.add_argument("--map-budget", type=int, default=None,
                   help="the edge's global map points per robot (default: the edge's, 2,000,000)")
    s.add_argument("--log-level", default="WARNING")
    s.set_defaults(func=_run_soak)
