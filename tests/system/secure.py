"""A TLS + ACL deployment as local processes for system tests: certificates from `zoffload certs`'
code, a `zoffload router` process with the generated router.json5, and the session settings or
flags of each identity."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from tests.system.procs import Proc, script
from zoffload.runtime.config import ZenohSettings
from zoffload.runtime.errors import ZenohSessionError
from zoffload.runtime.session import open_session


@dataclass
class Deployment:
    certs: Path
    port: int
    router: Proc
    linked: list[tuple[int, Proc]] = field(default_factory=list)  # other routers: (port, process)

    @property
    def endpoint(self) -> str:
        return f"tls/localhost:{self.port}"  # a name in the router certificate's SAN

    def settings(self, identity: str | None, **over: object) -> ZenohSettings:
        """A client session of ``identity`` (None: no certificate, only the CA)."""
        fields: dict[str, object] = dict(mode="client", connect=[self.endpoint], multicast_scouting=False,
                                         shared_memory=False, tls_ca=str(self.certs / "ca.pem"))
        if identity:
            fields.update(tls_cert=str(self.certs / f"{identity}.pem"),
                          tls_key=str(self.certs / f"{identity}.key"))
        fields.update(over)
        return ZenohSettings(**fields)  # type: ignore[arg-type]

    def args(self, identity: str, port: int | None = None) -> list[str]:
        """The daemons' command-line flags for a client session of ``identity`` (on the router
        listening on ``port``; default the first)."""
        endpoint = self.endpoint if port is None else f"tls/localhost:{port}"
        return ["-m", "client", "-e", endpoint, "--no-multicast-scouting", "--no-shm",
                "--tls-ca", str(self.certs / "ca.pem"),
                "--tls-cert", str(self.certs / f"{identity}.pem"),
                "--tls-key", str(self.certs / f"{identity}.key")]

    def stop(self) -> int:
        codes = [p.sigint() for _, p in reversed(self.linked)] + [self.router.sigint()]
        return next((c for c in codes if c != 0), 0)  # the first router that did not exit cleanly


def deploy(tmp: Path, port: int, robots: list[str], edges: list[str],
           monitors: tuple[str, ...] = ("monitor",), passwords: bool = False) -> Deployment:
    """Certificates and a running TLS + ACL router on ``port`` (returns once it accepts a session)."""
    from zoffload.runtime.certs import write_deployment

    certs = tmp / "certs"
    written = write_deployment(certs, robots, edges, monitors, listen=[f"tls/127.0.0.1:{port}"],
                               passwords=passwords)
    router = Proc(script("zoffload") + ["router", "-c", str(written["router.json5"])], tmp / "router.log")
    d = Deployment(certs, port, router)
    login = {"user": monitors[0], "password_file": str(certs / f"{monitors[0]}.password")}
    probe = d.settings(monitors[0], **(login if passwords else {}))
    deadline = time.monotonic() + 30
    while True:
        try:
            open_session(probe).close()
            return d
        except ZenohSessionError:
            if time.monotonic() > deadline or router.p.poll() is not None:
                router.sigint(5)
                raise AssertionError(f"the router did not come up:\n{router.text()}") from None
            time.sleep(0.2)


def deploy_linked(tmp: Path, ports: tuple[int, int], robots: list[str], edges: list[str],
                  monitors: tuple[str, ...] = ("monitor",)) -> Deployment:
    """Two linked TLS + ACL routers: ``rbt`` on ``ports[0]`` (the robots' network) and ``rack`` on
    ``ports[1]`` (the edges'), which connects to rbt, as `zoffload certs --routers rbt rack` makes
    them (each router's own certificate; each knows the other as a linked peer)."""
    from zoffload.runtime.certs import write_deployment

    certs = tmp / "certs"
    written = write_deployment(certs, robots, edges, monitors, routers=("rbt", "rack"),
                               router_listen={"rbt": [f"tls/127.0.0.1:{ports[0]}"],
                                              "rack": [f"tls/127.0.0.1:{ports[1]}"]},
                               router_connect=f"tls/localhost:{ports[0]}")
    rbt = Proc(script("zoffload") + ["router", "-c", str(written["rbt.json5"])], tmp / "rbt.log")
    rack = Proc(script("zoffload") + ["router", "-c", str(written["rack.json5"])], tmp / "rack.log")
    d = Deployment(certs, ports[0], rbt, [(ports[1], rack)])
    for port in ports:
        probe = d.settings(monitors[0], connect=[f"tls/localhost:{port}"])
        deadline = time.monotonic() + 30
        while True:
            try:
                open_session(probe).close()
                break
            except ZenohSessionError:
                if time.monotonic() > deadline:
                    d.stop()
                    raise AssertionError(f"a router did not come up:\n{rbt.text()}\n{rack.text()}") from None
                time.sleep(0.2)
    return d
