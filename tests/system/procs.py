"""Start zoffload's console scripts as real processes for system tests."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import zenoh

BIN = Path(sys.executable).parent


def script(name: str) -> list[str]:
    """The installed console script, or the module entry point when running from a checkout."""
    path = BIN / name
    if path.exists():
        return [str(path)]
    found = shutil.which(name)
    if found:
        return [found]
    sub = {"zoffload-robot": "robot", "zoffload-edge": "edge"}.get(name)
    return [sys.executable, "-m", "zoffload.cli"] + ([sub] if sub else [])


def session_args(listen: int | None = None, connect: int | None = None) -> list[str]:
    args = ["--no-multicast-scouting", "--no-shm"]
    if listen is not None:
        args += ["-l", f"tcp/127.0.0.1:{listen}"]
    if connect is not None:
        args += ["-e", f"tcp/127.0.0.1:{connect}"]
    return args


class Proc:
    def __init__(self, args: list[str], log: Path) -> None:
        self.log = log
        self._f = open(log, "w")
        # a daemon stuck in its stop dumps its stacks (runtime/lifecycle.py) before sigint() kills it
        env = dict(os.environ, PYTHONUNBUFFERED="1", ZOFFLOAD_SHUTDOWN_LIMIT="20")
        self.p = subprocess.Popen(args, stdout=self._f, stderr=subprocess.STDOUT, env=env)

    def sigint(self, timeout: float = 30) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
        return self.wait(timeout)

    def wait(self, timeout: float = 60) -> int:
        try:
            code = self.p.wait(timeout)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait()
            self._f.close()
        return code

    def text(self) -> str:
        return self.log.read_text()  # the child writes to the file itself


def edge_args(port: int, *extra: str, listen: bool = True) -> list[str]:
    """zoffload-edge listening on ``port`` (or connecting to it, ``listen=False``)."""
    return script("zoffload-edge") + session_args(**{"listen" if listen else "connect": port}) + list(extra)


def start_edge(session: zenoh.Session, args: list[str], log: Path, edge_id: str = "edge1",
               timeout: float = 60) -> Proc:
    """Start an edge process and return it once its liveliness token is seen through ``session``."""
    from tests.helpers import KEYS, wait_token

    edge = Proc(args, log)
    try:
        wait_token(session, KEYS.edge_alive(edge_id), timeout)
    except AssertionError:
        edge.sigint(5)
        raise AssertionError(f"the edge did not come up:\n{edge.text()}") from None
    return edge
