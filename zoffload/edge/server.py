"""zoffload-edge: one Zenoh session, presence and status, and the services that do the work.

Services (each in its own module, all on the server's session):
  mapping   ``<ns>/data/*/scan`` → ``<ns>/data/<robot>/scan_ack/<edge>``, ``<ns>/ctrl/<robot>/map/<edge>``
            (edge/mapping.py: one bounded KISS-ICP per robot on a fixed pool of workers, maps
            exported to ``map_dir`` on eviction and shutdown).
  detector  ``<ns>/data/*/frame`` → ``<ns>/data/<robot>/detections/<edge>`` (edge/detection.py), when the
            configured model can be found (or ``detector.enabled: true``, then a missing model is
            fatal).
The server itself: liveliness ``<ns>/alive/edge/<edge>``, ``<ns>/ctrl/<robot>/ping/<edge>`` (wire.Pong),
``<ns>/status/edge/<edge>`` (wire.Status, 1 Hz: every service's values in one message).

Both services share one ``Admission`` (edge/admission.py): only admitted robots get state, and the
main loop's housekeeping evicts robots idle for ``admission.idle_timeout`` from every service.
Every message is decoded within ``limits`` (the caps of ``wire.Limits``), and Zenoh's own
transport refuses any message larger than ``limits.max_bytes`` (plus framing) before it is
reassembled, unless the config file or ``--cfg`` sets that key.

Lifecycle as in uvicorn's Server: ``startup`` (session, ping, status publisher, services, then the
token), ``main_loop`` (status until stopped), ``shutdown`` (services in reverse, then the session).

Fleet (edge/fleet.py, fleet_contract.md): the status carries ``capacity``, ``robots`` and
``draining``. SIGTERM drains (``drain``): the status says so at once, attaches are refused, each
attached robot gets a final checkpoint, and the edge stops when every one of them has moved to
another edge or gone quiet, or after ``fleet.drain_timeout``. SIGINT, or a second SIGTERM, stops
at once (a third signal forces the exit, runtime/lifecycle.py).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from pathlib import Path
from types import FrameType

import zenoh

from zoffload.detect.detector import Detector
from zoffload.detect.models import ModelError
from zoffload.edge.admission import Admission
from zoffload.edge.detection import DetectorService
from zoffload.edge.fleet import Fleet
from zoffload.edge.isolate import MapperPool
from zoffload.edge.mapping import MappingService
from zoffload.edge.recipe import MapperRecipe
from zoffload.edge.robots import MapperFactory
from zoffload.edge.ros2 import ros2_service
from zoffload.edge.service import EdgeService
from zoffload.protocol import wire
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import EdgeSettings, LimitsSettings, ZenohSettings
from zoffload.runtime.drops import Drops
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.loading import write_effective
from zoffload.runtime.memory import HeapTrimmer
from zoffload.runtime.session import (
    DROP_WAIT_KEY,
    DROP_WAIT_US,
    MAX_MESSAGE_KEY,
    certificate_mismatch,
    open_session,
    with_defaults,
)

log = logging.getLogger("zoffload.edge")

TICK = 0.1  # seconds between the main loop's looks at a drain (status goes out every status_period)


def edge_zenoh(z: ZenohSettings, max_bytes: int | None = None) -> ZenohSettings:
    """The edge's session settings: acks and detections are small and published with DROP (a
    stalled robot must not block the mapper or the detector), but Zenoh's default 1 ms wait before
    dropping loses some of a burst of acks when the edge's CPU is busy. The edge waits up to 50 ms
    (two camera frames). With ``max_bytes``, the transport refuses larger messages (Zenoh's
    default is 1 GiB). Keys the user's ``--cfg`` or config file sets are left alone."""
    defaults = {DROP_WAIT_KEY: str(DROP_WAIT_US)}
    if max_bytes is not None:
        defaults[MAX_MESSAGE_KEY] = str(max_bytes + 64 * 1024)  # room for the message's framing
    return with_defaults(z, defaults)


def wire_limits(limits: LimitsSettings) -> wire.Limits:
    return wire.Limits(max_points=limits.max_points, max_pixels=limits.max_pixels,
                       max_bytes=limits.max_bytes)


def admission(settings: EdgeSettings) -> Admission:
    a = settings.admission
    return Admission(a.robots, max_robots=a.max_robots, idle_timeout=a.idle_timeout,
                     refusals_per_s=a.refusals_per_s)


# Factories: settings unpacked into each service's own arguments
def mapping_service(settings: EdgeSettings, keys: Keys, admitted: Admission | None = None) -> MappingService:
    m, f = settings.mapper, settings.fleet
    admitted = admitted or admission(settings)
    fleet = Fleet(settings.edge_id, capacity=f.capacity or admitted.max_robots,
                  require_attach=f.require_attach, shed=f.shed, shed_load=f.shed_load,
                  shed_late=f.shed_late)
    recipe = MapperRecipe(voxel_size=m.voxel_size, min_range=m.min_range, max_range=m.max_range,
                          max_points_per_voxel=m.max_points_per_voxel, deskew=m.deskew,
                          map_resolution=m.map_resolution, map_budget=m.map_budget,
                          trajectory_budget=m.trajectory_budget)
    # Unset: one mapper process per two cores (each KISS-ICP runs its threads over every core, and
    # each process costs 0.8 s of CPU and 160 MB to start), at most one per worker
    cores = os.cpu_count() or 1
    processes = max(1, min(m.workers or cores, cores // 2)) if m.processes is None else m.processes
    factory: MapperFactory = (MapperPool(recipe, processes, call_timeout=m.call_timeout,
                                         register_timeout=m.register_timeout) if processes else recipe)
    return MappingService(keys, factory if m.enabled else None, queue=m.queue,
                          map_dir=Path(settings.map_dir) if settings.map_dir else None,
                          map_format=settings.map_format, edge_id=settings.edge_id, workers=m.workers,
                          admission=admitted, limits=wire_limits(settings.limits), fleet=fleet,
                          checkpoint_every=f.checkpoint_every, checkpoint_resolution=f.checkpoint_resolution,
                          final_checkpoint_resolution=f.final_checkpoint_resolution)


def detector_service(settings: EdgeSettings, keys: Keys,
                     admitted: Admission | None = None) -> DetectorService | None:
    """The detector service, or None when it is off or (``enabled`` unset) its model is missing."""
    d = settings.detector
    if d.enabled is False:
        return None
    try:
        model = Detector(d.model, d.model_path, threads=d.threads, url=d.model_url)
    except ModelError as exc:
        if d.enabled:
            raise
        log.warning("object detector off: %s", exc)
        return None
    return DetectorService(model, keys, settings.edge_id, queue=d.queue, batch=d.batch, serve=d.serve,
                           admission=admitted or admission(settings), limits=wire_limits(settings.limits))


class EdgeServer:
    """The edge daemon: ``serve()`` runs it; tests drive ``startup``, ``main_loop`` and ``shutdown``."""

    def __init__(self, settings: EdgeSettings, stop: StopSignal | None = None) -> None:
        self.settings = settings
        self.keys = Keys(settings.namespace)
        self.stop = stop or StopSignal()
        self.session: zenoh.Session | None = None
        self.mapping: MappingService | None = None
        self.detector: DetectorService | None = None
        self.services: list[EdgeService] = []  # the started ones, in start order
        self.admission = admission(settings)
        self.drops = Drops(log)  # the server's own queryable (ping)
        self.trimmer = HeapTrimmer(settings.heap_trim_period)
        self._status_pub: zenoh.Publisher | None = None
        self._ping_q: zenoh.Queryable[None] | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._drain = threading.Event()  # asked for (SIGTERM, ``drain()``)
        self.drain_started: float | None = None  # monotonic, once the main loop began draining

    def serve(self) -> None:
        """Start, publish status until stopped, shut down (also after a failed start)."""
        self._install_drain()
        try:
            self.startup()
            self.main_loop()
        finally:
            self.shutdown()

    # Startup
    def startup(self) -> None:
        s = self.settings
        if warning := certificate_mismatch(s.zenoh, s.edge_id):
            log.warning("%s", warning)
        session = self.session = open_session(edge_zenoh(s.zenoh, s.limits.max_bytes))
        self._ping_q = session.declare_queryable(self.keys.all_pings(s.edge_id),
                                                 self.drops.guard(self._on_ping, "ping"))
        self._status_pub = session.declare_publisher(
            self.keys.edge_status(s.edge_id), congestion_control=zenoh.CongestionControl.DROP
        )
        # Services, each warmed up before it declares anything
        self.mapping = mapping_service(s, self.keys, self.admission)
        self.detector = detector_service(s, self.keys, self.admission)
        ros2 = ros2_service(s, self.keys)  # None unless ros2.enabled; last: it reads the others' answers
        for service in (self.mapping, self.detector, ros2):
            if service is not None:
                service.start(session)
                self.services.append(service)
        # Robots wait for this token before they send: declared last, it means every service listens
        self._token = session.liveliness().declare_token(self.keys.edge_alive(s.edge_id))
        log.info("edge %s up with %s (zenoh %s, listen=%s, connect=%s)", s.edge_id,
                 ", ".join(x.name for x in self.services), s.zenoh.mode, s.zenoh.listen, s.zenoh.connect)

    def _on_ping(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, wire.encode(wire.Pong(edge=self.settings.edge_id,
                                                          stamp=ping_stamp(query.parameters))))

    # Drain
    def drain(self) -> None:
        """Ask for a drain (from any thread or a signal handler); the main loop carries it out."""
        self._drain.set()

    def _install_drain(self) -> None:
        """SIGTERM drains; the handler found (the StopSignal's) takes the next signal."""
        if threading.current_thread() is not threading.main_thread():
            return
        previous = signal.getsignal(signal.SIGTERM)

        def on_sigterm(signum: int, frame: FrameType | None) -> None:
            if not self._drain.is_set() and not self.stop.is_set():
                log.info("SIGTERM received: draining (a second signal stops at once)")
                self._drain.set()
            elif callable(previous):
                previous(signum, frame)
            else:
                self.stop.set()

        signal.signal(signal.SIGTERM, on_sigterm)

    def _drain_step(self, now: float) -> None:
        """Start the drain when asked; stop when it is over."""
        mapping = self.mapping
        if self.drain_started is None:
            self.drain_started = now
            if mapping is not None:
                mapping.begin_drain()
            self._publish_status()  # the robots learn it now, not at the next period
            return
        timeout = self.settings.fleet.drain_timeout
        if mapping is None or mapping.drained(now) or now - self.drain_started >= timeout:
            log.info("drained after %.1f s%s", now - self.drain_started,
                     "" if mapping is None or mapping.drained(now) else " (timeout: robots still attached)")
            self.stop.set()

    # Main loop
    def status(self) -> wire.Status:
        values: dict[str, float] = {}
        for service in self.services:
            values.update(service.status())
        values.update(self.admission.status())
        values.update({f"ping.drop.{k}": float(v) for k, v in self.drops.snapshot().items()})
        values["heap_trims"] = float(self.trimmer.trims)
        # The newest codec version this edge reads (a robot sends newer fields only to an edge
        # that says it reads them: a scan's prior, a frame's arrival stamp)
        values[wire.READS_KEY] = float(max(wire.READS))
        return wire.Status(source="edge", id=self.settings.edge_id, stamp=time.time(), values=values)

    def main_loop(self) -> None:
        assert self._status_pub is not None, "main_loop() runs after startup()"
        period = self.settings.status_period
        due = time.monotonic()  # the first at once: a robot asks an edge once it knows what it reads
        while not self.stop.wait(min(TICK, max(0.0, due - time.monotonic()))):
            now = time.monotonic()
            if self._drain.is_set():
                self._drain_step(now)
                if self.stop.is_set():
                    return
            if now >= due:
                self.housekeeping(now)
                self._publish_status()
                due = now + period

    def _publish_status(self) -> None:
        assert self._status_pub is not None, "after startup()"
        self._status_pub.put(wire.encode(self.status()))

    def housekeeping(self, now: float | None = None) -> list[str]:
        """Evict the robots idle for longer than the admission's ``idle_timeout`` from every
        service (the mapping service exports their maps first); returns them."""
        gone = self.admission.expire(now)
        for robot in gone:
            for service in self.services:
                service.evict(robot)
        if self.mapping is not None:
            self.mapping.tick()  # its own clock: a test may pass a future ``now`` to expire robots
        self.trimmer.maybe()  # fragmented arenas back to the system (runtime/memory.py)
        return gone

    # Shutdown
    def shutdown(self) -> None:
        with self.stop.bounded_shutdown():  # past its limit: stacks in the log, exit 1
            self._shutdown()

    def _shutdown(self) -> None:
        self.stop.set()
        # Robots fall back to local processing the moment the token goes: tell them first
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        # Services in reverse order; one that fails to stop must not keep the others or the session
        errors: list[Exception] = []
        while self.services:
            service = self.services.pop()
            try:
                service.stop()
            except Exception as exc:
                log.error("%s service did not stop cleanly: %s", service.name, exc)
                errors.append(exc)
        if self.session is not None:
            self.session.close()
            self.session = None
        log.info("edge stopped")
        if errors:
            raise errors[0]


def run(settings: EdgeSettings, stop: StopSignal | None = None) -> None:
    """The Python API of ``zoffload-edge``: start, serve until stopped, shut down."""
    if settings.map_dir:
        write_effective(settings, Path(settings.map_dir) / "edge_config.yaml")
    EdgeServer(settings, stop).serve()


def ping_stamp(parameters: object) -> float:
    """The robot's stamp from a ping's ``stamp=`` parameter, NaN when absent or not a stamp (a
    pong echoes it, and must still be a valid message)."""
    try:
        value = float(parameters.get("stamp") or "nan")  # type: ignore[attr-defined]
    except (AttributeError, TypeError, ValueError):
        return float("nan")
    return value if abs(value) <= 1e12 else float("nan")
