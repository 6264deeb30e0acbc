"""The interface every robot pipeline implements (the scan streamer, the camera offloader).

The robot server opens one Zenoh session, one edge-presence watcher and one status publisher,
and runs a list of pipelines over them: ``start`` declares the pipeline's publishers and
subscribers, ``run`` works until its source ends or the stop signal is set (on its own thread),
``status`` gives the values merged into the robot's 1 Hz status message, ``metrics`` and
``write_results`` report at the end, ``close`` undeclares what ``start`` declared.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import zenoh

from zoffload.robot.presence import EdgePresence


class Pipeline(Protocol):
    name: str

    def start(self, session: zenoh.Session, presence: EdgePresence) -> None: ...

    def run(self) -> None: ...

    def status(self) -> dict[str, float]: ...

    def metrics(self) -> dict[str, Any]: ...

    def write_results(self, out_dir: Path) -> None: ...

    def close(self) -> None: ...
