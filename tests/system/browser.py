"""A real headless browser for the live view's system test: Debian's chromium driven over the
DevTools protocol on a pipe (``--remote-debugging-pipe``: fd 3 in, fd 4 out, NUL-terminated JSON),
so no driver package is needed. ``chromium()`` is None where it is not installed
(``apt-get install -y chromium``)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run",
         "--enable-unsafe-swiftshader",  # WebGL on the CPU: the viewer renders without a GPU
         # a headless page counts as hidden: keep its timers and frames running (the viewer's
         # decoded images are painted on the next frame)
         "--disable-renderer-backgrounding", "--disable-background-timer-throttling",
         "--disable-backgrounding-occluded-windows"]


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


class Browser:
    """One headless chromium with one page; ``screenshot_until`` polls it."""

    def __init__(self, binary: str, size: tuple[int, int] = (1600, 1000)) -> None:
        self._profile = tempfile.mkdtemp(prefix="zoffload-chromium-")
        cmd_r, self._cmd = os.pipe()
        self._events, ev_w = os.pipe()

        def fds() -> None:  # in the child: the pipe ends as fds 3 and 4, inheritable through exec
            a, b = os.dup(cmd_r), os.dup(ev_w)  # away from 3 and 4 first (dup2 onto itself keeps CLOEXEC)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.proc = subprocess.Popen(
            [binary, *FLAGS, f"--user-data-dir={self._profile}", f"--window-size={size[0]},{size[1]}",
             "--remote-debugging-pipe", "about:blank"],
            preexec_fn=fds, close_fds=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(ev_w)
        self._buf = b""
        self._id = 0
        self._session: str | None = None

    def call(self, method: str, params: dict[str, Any] | None = None, page: bool = True,
             timeout: float = 60) -> dict[str, Any]:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if page and self._session:
            msg["sessionId"] = self._session
        os.write(self._cmd, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return dict(reply["result"])
            chunk = os.read(self._events, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed its DevTools pipe")
            self._buf += chunk
        raise TimeoutError(f"{method}: no answer in {timeout} s")

    def open(self, url: str) -> None:
        target = self.call("Target.createTarget", {"url": url}, page=False)["targetId"]
        self._session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                                  page=False)["sessionId"]

    def screenshot(self, out: Path) -> Path:
        out.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"]))
        return out

    def screenshot_until(self, out: Path, ready: Callable[[Path], bool], timeout: float,
                         every: float = 5.0) -> bool:
        """Screenshots every ``every`` s until ``ready(out)`` or ``timeout``; the last one stays."""
        deadline = time.monotonic() + timeout
        while True:
            time.sleep(every)
            if ready(self.screenshot(out)) or time.monotonic() > deadline:
                return ready(out)

    def close(self) -> None:
        try:
            self.call("Browser.close", page=False, timeout=10)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for fd in (self._cmd, self._events):
            os.close(fd)
        shutil.rmtree(self._profile, ignore_errors=True)
