"""A kernel-level bandwidth cap for cross-checks: two network namespaces joined by a veth pair,
each end shaped by ``tbf``. Needs root and iproute2 (``ip``, ``tc``) on Linux.

    with NetnsLink(rate_mbps=20) as link:
        link.run("edge", ["python", "-m", "zoffload.lab.link.probe", "sink", "9000", "4", link.addr["edge"]])
        link.run("robot", [...])

The namespaces and addresses are this process's own test hosts (a /30 in 10.231.0.0/16 picked at
random); everything is removed on exit.
"""

from __future__ import annotations

import os
import random
import shutil
import subprocess
from types import TracebackType


class NetnsError(RuntimeError):
    pass


def available() -> str | None:
    """None when namespaces can be built here, else the reason they cannot."""
    if os.geteuid() != 0:
        return "needs root (network namespaces and tc)"
    if not shutil.which("ip") or not shutil.which("tc"):
        return "needs iproute2 (ip, tc)"
    return None


def _sh(*cmd: str) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise NetnsError(f"{' '.join(cmd)}: {r.stderr.strip()}")


class NetnsLink:
    """``robot`` and ``edge`` namespaces; the veth end in each is capped by tbf at ``rate_mbps``
    (so each direction is shaped on its way out), with a queue of ``latency_ms``."""

    def __init__(self, rate_mbps: float, latency_ms: float = 100.0) -> None:
        tag = f"{os.getpid() % 10000}{random.randint(0, 99)}"
        self.ns = {"robot": f"zo{tag}r", "edge": f"zo{tag}e"}
        self.dev = {"robot": f"zo{tag}vr", "edge": f"zo{tag}ve"}
        net = random.randint(0, 255)
        self.addr = {"robot": f"10.231.{net}.1", "edge": f"10.231.{net}.2"}
        self.rate_mbps = rate_mbps
        self.latency_ms = latency_ms

    def __enter__(self) -> NetnsLink:
        reason = available()
        if reason:
            raise NetnsError(reason)
        try:
            for side in ("robot", "edge"):
                _sh("ip", "netns", "add", self.ns[side])
            _sh("ip", "link", "add", self.dev["robot"], "type", "veth", "peer", "name", self.dev["edge"])
            burst = max(32_000, int(self.rate_mbps * 1e6 / 8 / 100))  # >= 10 ms of traffic
            for side in ("robot", "edge"):
                ns, dev = self.ns[side], self.dev[side]
                _sh("ip", "link", "set", dev, "netns", ns)
                _sh("ip", "-n", ns, "addr", "add", f"{self.addr[side]}/30", "dev", dev)
                _sh("ip", "-n", ns, "link", "set", dev, "up")
                _sh("ip", "-n", ns, "link", "set", "lo", "up")
                _sh("ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate",
                    f"{self.rate_mbps}mbit", "burst", str(burst), "latency", f"{self.latency_ms}ms")
        except NetnsError:
            self.close()
            raise
        return self

    def popen(self, side: str, cmd: list[str], **kw: object) -> subprocess.Popen[str]:
        return subprocess.Popen(["ip", "netns", "exec", self.ns[side], *cmd], text=True, **kw)  # type: ignore[call-overload]

    def close(self) -> None:
        for ns in self.ns.values():
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)

    def __exit__(self, et: type[BaseException] | None, e: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
