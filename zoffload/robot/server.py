"""zoffload-robot: one Zenoh session, one edge-presence watcher, one status publisher, and the
pipelines that share them (the scan streamer, the camera offloader).

Outputs of the server itself: liveliness ``<ns>/alive/robot/<robot>`` while it runs,
``<ns>/status/<robot>`` (wire.Status, every ``status_period``: the pipelines' values merged, plus
``edges`` present), ``robot_config.yaml`` in ``out_dir``. Each pipeline documents its own keys.

Phases, as uvicorn's Server: ``startup`` (session, token, presence, status publisher, pipelines
started, the edge waited for), ``main_loop`` (each pipeline on its own thread; status published
until they are all done or the stop signal is set), ``shutdown`` (pipelines closed, results
written, token and session released).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from zoffload.protocol import wire
from zoffload.protocol.keys import Keys
from zoffload.robot.pipeline import Pipeline
from zoffload.robot.presence import EdgePresence
from zoffload.runtime.config import RobotSettings, ZenohSettings
from zoffload.runtime.errors import ConfigError
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.loading import write_effective
from zoffload.runtime.memory import HeapTrimmer
from zoffload.runtime.session import (
    MAX_MESSAGE_KEY,
    certificate_mismatch,
    dialling_only,
    open_session,
    undeclare,
    with_defaults,
)

log = logging.getLogger("zoffload.robot")
ROBOT_MAX_MESSAGE = 64 * 1024 * 1024


def robot_zenoh(z: ZenohSettings) -> ZenohSettings:
    """The robot's session settings: it takes acks, detections and checkpoints, and a message of
    more than 64 MiB is no answer of an edge (Zenoh's own default is 1 GiB); as a peer it dials its
    edges and listens only where told, so no one dials it back (runtime/session.py
    ``dialling_only``). Keys the user's ``--cfg`` or config file sets are left alone."""
    return with_defaults(z, {MAX_MESSAGE_KEY: str(ROBOT_MAX_MESSAGE), **dialling_only(z)})


class RobotServer:
    def __init__(self, settings: RobotSettings, pipelines: list[Pipeline], stop: StopSignal | None = None,
                 session: zenoh.Session | None = None) -> None:
        """``session``: share an open session (the caller closes it) instead of opening one."""
        self.settings = settings
        self.pipelines = pipelines
        self.stop = stop or StopSignal()
        self.keys = Keys(settings.namespace)
        self.presence = EdgePresence(self.keys)
        self.session = session
        self._owns_session = session is None
        self._token: zenoh.LivelinessToken | None = None
        self._status_pub: zenoh.Publisher | None = None
        self.trimmer = HeapTrimmer(settings.heap_trim_period)

    # Startup
    def startup(self) -> None:
        s = self.settings
        if self.session is None:
            if warning := certificate_mismatch(s.zenoh, s.robot_id):
                log.warning("%s", warning)
            self.session = open_session(robot_zenoh(s.zenoh))
        self._token = self.session.liveliness().declare_token(self.keys.robot_alive(s.robot_id))
        self._status_pub = self.session.declare_publisher(
            self.keys.robot_status(s.robot_id), congestion_control=zenoh.CongestionControl.DROP)
        self.presence.start(self.session)
        for p in self.pipelines:
            p.start(self.session, self.presence)
        log.info("robot %s up: %s", s.robot_id, ", ".join(p.name for p in self.pipelines))
        if s.wait_edge > 0 and not self.presence.wait(s.wait_edge):
            log.warning("no edge after %.1f s (connecting to %s); running anyway (scans registered on the "
                        "robot where local odometry is on, else dropped; frames detected locally) until one "
                        "appears: check the address and that zoffload-edge listens there",
                        s.wait_edge, ", ".join(s.zenoh.connect) or "peers found by scouting")

    # Main loop
    def main_loop(self) -> None:
        threads = [threading.Thread(target=self._run_pipeline, args=(p,), name=p.name, daemon=True)
                   for p in self.pipelines]
        for t in threads:
            t.start()
        next_status = time.monotonic()
        while alive := [t for t in threads if t.is_alive()]:
            now = time.monotonic()
            if now >= next_status:
                self.publish_status()
                self.trimmer.maybe()  # fragmented arenas back to the system (runtime/memory.py)
                next_status = now + self.settings.status_period
            alive[0].join(timeout=max(0.0, min(0.05, next_status - now)))
        self.publish_status()

    def _run_pipeline(self, p: Pipeline) -> None:
        try:
            p.run()
        except Exception:  # a pipeline bug must not leave the others running forever
            log.exception("pipeline %s failed; stopping the robot", p.name)
            self.stop.set()

    def publish_status(self) -> None:
        values: dict[str, float] = {}
        for p in self.pipelines:
            values.update(p.status())
        values["edges"] = float(len(self.presence.edges))
        values["edge_messages_dropped"] = float(self.presence.drops.total())  # tokens and statuses
        values["edge_rechecked"] = float(self.presence.rechecked)  # a late "gone" undone
        msg = wire.Status(source="robot", id=self.settings.robot_id, stamp=time.time(), values=values)
        try:
            if self._status_pub is not None:
                self._status_pub.put(wire.encode(msg))
        except Exception as exc:  # status is best effort
            log.debug("status not published: %s", exc)

    # Shutdown
    def shutdown(self) -> None:
        with self.stop.bounded_shutdown():  # past its limit: stacks in the log, exit 1
            self._shutdown()

    def _shutdown(self) -> None:
        for p in self.pipelines:
            p.close()
        self.presence.stop()
        out = self.settings.out_dir
        if out:
            write_effective(self.settings, Path(out) / "robot_config.yaml")
            for p in self.pipelines:
                p.write_results(Path(out))
            # what the edges' tokens and statuses brought that was refused (counted, logged)
            (Path(out) / "presence_drops.json").write_text(json.dumps(self.presence.drops.snapshot()))
        undeclare(self._status_pub, self._token)
        if self._owns_session and self.session is not None:
            self.session.close()
        self.session = None

    def run(self) -> dict[str, Any]:
        """Startup, main loop, shutdown; returns every pipeline's metrics by name."""
        self.startup()
        try:
            self.main_loop()
        finally:
            self.shutdown()
        return {p.name: p.metrics() for p in self.pipelines}


def build_pipelines(settings: RobotSettings, stop: StopSignal,
                    quota_mode: str | None = None) -> list[Pipeline]:
    """The pipelines the settings ask for: scans unless ``scans: none``, the camera if ``images``."""
    pipelines: list[Pipeline] = []
    if settings.scans != "none":
        from zoffload.robot.scans import scan_streamer

        pipelines.append(scan_streamer(settings, stop))
    if settings.images:
        from zoffload.robot.camera import camera_offloader

        pipelines.append(camera_offloader(settings, stop, quota_mode))
    if not pipelines:
        raise ConfigError("nothing to do: scans is 'none' and no images are configured")
    return pipelines


def _apply_quota(settings: RobotSettings) -> tuple[RobotSettings, str | None]:
    """Put the process under ``perception.cpu_quota`` cores; where only a thread limit is
    possible, cap the local detector's threads instead."""
    cores = settings.perception.cpu_quota
    if not cores:
        return settings, None
    from zoffload.runtime.quota import apply_cpu_quota

    how = apply_cpu_quota(cores)
    if how == "threads":
        n = max(1, math.ceil(cores))
        perception = settings.perception.model_copy(
            update={"local_threads": min(settings.perception.local_threads or n, n)})
        settings = settings.model_copy(update={"perception": perception})
    return settings, how


def run(settings: RobotSettings, stop: StopSignal | None = None) -> dict[str, Any]:
    """The Python API of ``zoffload-robot``: start, run every pipeline until done or stopped,
    write results. Returns each pipeline's metrics by name (``scans``, ``camera``)."""
    stop = stop or StopSignal()
    settings, quota = _apply_quota(settings)
    if settings.out_dir:  # now, so that a folder it cannot write fails before the run, not after
        write_effective(settings, Path(settings.out_dir) / "robot_config.yaml")
    metrics = RobotServer(settings, build_pipelines(settings, stop, quota), stop).run()
    for name, m in metrics.items():
        log.info("%s done: %s", name, json.dumps(m.get("balance")))
    return metrics
