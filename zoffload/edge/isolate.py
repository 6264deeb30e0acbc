"""Robots' mappers in processes of their own.

KISS-ICP's Python binding holds the GIL through each of its calls. On a thread of the edge's
process a registration (31 ms for an HDL-64 scan) stalls every other thread of it: the Zenoh
callbacks that stamp scans' arrival, the other robots' queues, the detector's service and the
fleet's status (``python -m benchmarks.bench_gil``: a thread sleeping 1 ms beside it woke 30 ms
late at p99, 86 ms at most), and however many cores the edge has, its robots are registered
one at a time. ``MapperPool`` (``mapper.processes``, by default one per two cores) keeps a
fixed set of worker processes that host the robots' mappers; the edge's worker thread that holds
a robot sends the scan down a pipe and waits for the registration with the GIL released.

* **Placement.** A robot's mapper lives in one process from its first scan to its eviction: the
  one hosting the fewest mappers when it was made. Each process answers one request at a time
  (a lock per pipe); two robots in one process wait for each other, as two robots on one core.
* **Interface.** ``ProcessMapper`` is the service's ``FleetMapper`` (edge/robots.py): every call
  is a request to the process; its counters (``map_points``, ``scans``, the backfills') come back
  with every reply, so reading them (the edge's status) never waits for a registration; poses
  the mapper trims from memory come back with the reply that trimmed them and go to the robot's
  spill (``map_dir``) in the edge's process.
* **Faults.** A process that dies (a crash inside KISS-ICP) or does not answer in time is killed and
  started again. In time: a scan's registration (and its prior's prediction) within
  ``register_timeout`` (5 s, a hundred times an HDL-64 scan's), any other call (an attach's backfill
  of 50 scans takes about a second, an export grows with the map) within ``call_timeout`` (30 s); a
  process that used CPU through the timeout (a busy host, not a hang) is waited for up to
  ``call_timeout`` (counted, ``mapper_slow_calls``), one that did not (stopped, deadlocked) is lost,
  and so is a registration that has used ``register_timeout`` seconds of CPU (a busy host stretches
  a call's wall time, not its CPU time: that one is running away, an endless loop; it is lost at the
  first timeout after it has used that much, not at ``call_timeout``). A request the process does
  not read from for 2 s (stopped, its socket's buffer full) loses it too. The robots it hosted lose
  their maps: their next call raises ``MapperLost``, and the service counts it (``mapper_lost``) and
  detaches an attached robot, which attaches again with its checkpoint (edge/mapping.py). Until then
  the robots in that process wait, as does a map query or an eviction's export that asks it. A
  process found dead when a new robot's mapper is made there is started again and asked once more
  (nothing was lost). Errors inside a call (a scan with no point in range, a checkpoint that does
  not fit its grid) come back as the exception they were.
* **Bounds.** The processes are fixed; a request carries one scan or one attach's backfill,
  which the codec's limits bound, and a reply one scan's registration or one map.

Each process is a fresh interpreter (``python -m zoffload.edge.isolate FD``, the same zoffload
the edge runs: forking a process that runs Zenoh's threads is not safe, and multiprocessing's
``spawn`` would import the caller's main script again) talking over a socket pair with
multiprocessing's ``Connection``. ``warm_up`` starts them in parallel; each loads KISS-ICP and the
map kernels before it says it is ready (about 0.8 s of CPU and 160 MB each). A process whose edge
died ends when its socket closes (one busy in a call, when it answers; Linux's parent-death signal
is not used: it fires when the *thread* that started the process ends, and restarts start them
from the edge's worker threads). Requests and replies are pickled: only between the edge and
its own children, over a socket pair no other process holds; nothing from the network is
unpickled (the scans reach the mapper decoded and checked by the codec).
"""

from __future__ import annotations

import itertools
import logging
import os
import pickle
import signal
import socket
import struct
import subprocess
import sys
import threading
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import psutil

from zoffload.edge.recipe import BoundedMapper, MapperRecipe, Spill
from zoffload.edge.robots import MapperLost
from zoffload.mapping.mapper import Registration
from zoffload.protocol import wire

log = logging.getLogger("zoffload.edge.mapping")

# What a reply carries of the mapper besides the call's result (read without a request)
STATS = ("map_points", "scans", "map_overflow", "backfilled", "backfill_unused", "backfill_posed",
         "priors_moved")
CALLS = frozenset({"register", "map_cloud", "trajectory", "continue_from", "checkpoint", "predict_from"})
GETS = frozenset({"backfilled_seqs"})
# A request goes to an idle process (one at a time): a write that makes no progress for this long
# (the process stopped with the socket's buffer full: a scan is larger) means the process is lost.
# (SO_SNDTIMEO bounds each write: a request whose first write got part of it in is lost after
# twice this at most.)
SEND_TIMEOUT_S = 2
# A reply: "ok" or "err", the result (or the exception), the mapper's STATS, the poses it trimmed
Reply = tuple[str, Any, "dict[str, int] | None", "list[tuple[np.ndarray, np.ndarray]]"]


def _stats(m: BoundedMapper) -> dict[str, int]:
    return {name: int(getattr(m, name)) for name in STATS}


def _sendable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError that names it."""
    try:
        back = pickle.loads(pickle.dumps(exc))
        return back if isinstance(back, BaseException) else RuntimeError(repr(exc))
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _serve(conn: Connection, recipe: MapperRecipe) -> None:
    """A mapper process: answers requests until its socket closes or it is told to exit."""
    # A Ctrl-C or a SIGTERM to the process group stops the edge, which exports its maps through
    # this process and then closes it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        try:
            recipe.warm_up()
        except Exception as exc:
            conn.send(("failed", f"{type(exc).__name__}: {exc}"))
            return
        conn.send(("ready", os.getpid()))
    except OSError:  # the edge went (or gave up on us) while we started
        return
    mappers: dict[int, BoundedMapper] = {}
    spilled: list[tuple[np.ndarray, np.ndarray]] = []

    def spill(seqs: np.ndarray, poses: np.ndarray) -> None:
        spilled.append((seqs, poses))

    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        op = msg[0]
        if op == "exit":
            return
        mid = msg[1] if len(msg) > 1 and isinstance(msg[1], int) else -1
        m = mappers.get(mid)
        status, result = "ok", None
        try:
            if op == "new":
                robot, max_range, voxel_max = msg[2:5]
                m = mappers[mid] = recipe.bounded(robot, max_range, voxel_max, spill)
            elif op == "drop":
                mappers.pop(mid, None)
                m = None
            elif m is None:
                raise MapperLost(f"no mapper {mid} in this process")
            elif op == "call" and msg[2] in CALLS:
                result = getattr(m, msg[2])(*msg[3], **msg[4])
            elif op == "get" and msg[2] in GETS:
                result = getattr(m, msg[2])
                result = list(result) if isinstance(result, Sequence) else result
            else:
                raise ValueError(f"unknown request {op!r} {msg[2:3]!r}")
        except Exception as exc:
            status, result = "err", _sendable(exc)
        reply = (status, result, _stats(m) if m is not None else None, list(spilled))
        spilled.clear()
        try:
            conn.send(reply)
        except (EOFError, OSError):
            return
        except Exception as exc:  # a result that does not pickle: say so, do not die
            conn.send(("err", RuntimeError(f"reply not sendable: {exc}"), None, []))


def _cpu_s(proc: psutil.Process | None) -> float | None:
    """A process's CPU seconds so far (user + system), None where unknown (it is gone)."""
    if proc is None:
        return None
    try:
        t = proc.cpu_times()
    except psutil.Error:
        return None
    return float(t.user + t.system)


class _Host:
    """One mapper process and its pipe (one request at a time: ``lock``)."""

    def __init__(self, recipe: MapperRecipe, index: int, start_timeout: float) -> None:
        self.recipe = recipe
        self.index = index
        self.start_timeout = start_timeout
        self.lock = threading.Lock()
        self.generation = 0
        self.hosted = 0  # mappers of this generation not yet closed
        self.restarts = 0
        self.slow_calls = 0  # calls that outlasted their timeout but were still working
        self.closed = False
        self.pid: int | None = None
        self._proc: Any = None
        self._ps: psutil.Process | None = None  # the same process, for its CPU time
        self._conn: Connection | None = None
        self._ready = False

    def start(self) -> None:
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        if os.path.basename(root) not in ("site-packages", "dist-packages"):  # a source tree: the same one
            env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        try:
            with theirs:
                proc = subprocess.Popen([sys.executable, "-m", "zoffload.edge.isolate", str(theirs.fileno()),
                                         str(self.index)], pass_fds=(theirs.fileno(),),
                                        stdin=subprocess.DEVNULL, env=env)
        except OSError as exc:  # no process to be had (out of memory, pids): asked again next time
            ours.close()
            raise MapperLost(f"mapper process {self.index} not started: {exc}") from exc
        ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", SEND_TIMEOUT_S, 0))
        conn = Connection(ours.detach())
        try:
            conn.send(self.recipe)
        except OSError:  # it died at once: found by wait_ready
            pass
        try:
            ps: psutil.Process | None = psutil.Process(proc.pid)
        except psutil.Error:  # it died at once: found by wait_ready
            ps = None
        self._proc, self._ps, self._conn, self._ready, self.pid = proc, ps, conn, False, None
        self.generation += 1
        self.hosted = 0

    def wait_ready(self) -> None:
        """Block until the process has loaded its mapper (held lock or start-up)."""
        if self._ready:
            return
        assert self._conn is not None
        try:
            if not self._conn.poll(self.start_timeout):
                raise TimeoutError(f"no answer in {self.start_timeout:g} s")
            msg = self._conn.recv()
        except (EOFError, OSError, TimeoutError) as exc:
            self._stop()
            raise MapperLost(f"mapper process {self.index} did not start: {exc}") from exc
        if msg[0] != "ready":
            self._stop()
            raise MapperLost(f"mapper process {self.index} did not start: {msg[1]}")
        self._ready, self.pid = True, int(msg[1])

    def request(self, msg: tuple[Any, ...], timeout: float, patience: float | None = None,
                budget: float | None = None) -> Reply:
        """Send ``msg`` and wait for the reply (the caller holds ``lock``). A process that dies, or
        does not answer within ``timeout`` and has not used the CPU in that time (stopped,
        deadlocked), is started again, and MapperLost raised; one still working (a busy host) is
        waited for, ``timeout`` at a time, up to ``patience`` in all (counted: ``slow_calls``),
        unless the call has used ``budget`` seconds of CPU: then it is not slowed by a busy host
        (that stretches a call's wall time, not its CPU time) but running away (an endless loop),
        and lost too."""
        if self.closed:
            raise MapperLost("the mapper processes are closed (the edge is stopping)")
        if self._conn is None:
            self.restart("not running")
        self.wait_ready()
        assert self._conn is not None
        try:
            self._conn.send(msg)
            waited, cpu = 0.0, _cpu_s(self._ps)
            start = cpu
            while not self._conn.poll(timeout):
                waited += timeout
                now = _cpu_s(self._ps)
                idle = cpu is not None and now is not None and now <= cpu
                spent = now - start if now is not None and start is not None else 0.0
                runaway = budget is not None and spent >= budget
                if idle or runaway or cpu is None or now is None or waited >= (patience or timeout):
                    why = (", no CPU used meanwhile" if idle else
                           f", {spent:.2f} s of CPU used (its budget {budget:g} s)" if runaway else "")
                    raise TimeoutError(f"no answer in {waited:g} s{why}")
                cpu = now
            if waited:
                self.slow_calls += 1
                log.warning("mapper process %d answered after %g s (still working at %g s)", self.index,
                            waited, timeout)
            reply: Reply = self._conn.recv()
            return reply
        except (EOFError, OSError, TimeoutError) as exc:
            code = self._proc.poll() if self._proc is not None else None
            self.restart(f"{type(exc).__name__}: {exc}" + (f", exit code {code}" if code is not None else ""))
            raise MapperLost(f"mapper process {self.index} lost: {exc}") from exc

    def restart(self, why: str) -> None:
        log.error("mapper process %d (pid %s) lost (%s); its %d robots' maps start again", self.index,
                  self.pid, why, self.hosted)
        self._stop()
        self.restarts += 1
        self.start()

    def _stop(self) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = self._ps = None
        self._ready = False
        if conn is not None:
            conn.close()
        if proc is not None:
            try:
                proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5.0)

    def close(self) -> None:
        with self.lock:
            self.closed = True
            if self._conn is not None:
                try:
                    self._conn.send(("exit",))
                except (EOFError, OSError):
                    pass
            self._stop()


class ProcessMapper:
    """A robot's mapper in a mapper process (see the module docstring)."""

    def __init__(self, host: _Host, mid: int, spill: Spill | None, call_timeout: float,
                 register_timeout: float) -> None:
        self._host = host
        self._mid = mid
        self._generation = host.generation
        self._spill = spill
        self.call_timeout = call_timeout
        # a scan's registration (and its prior's prediction): one scan, tens of ms
        self.register_timeout = register_timeout
        self._stats: dict[str, int] = dict.fromkeys(STATS, 0)
        self._closed = False

    # The counters of the last reply
    @property
    def map_points(self) -> int:
        return self._stats["map_points"]

    @property
    def scans(self) -> int:
        return self._stats["scans"]

    @property
    def map_overflow(self) -> int:
        return self._stats["map_overflow"]

    @property
    def backfilled(self) -> int:
        return self._stats["backfilled"]

    @property
    def backfill_unused(self) -> int:
        return self._stats["backfill_unused"]

    @property
    def backfill_posed(self) -> int:
        return self._stats["backfill_posed"]

    @property
    def priors_moved(self) -> int:
        return self._stats["priors_moved"]

    @property
    def backfilled_seqs(self) -> list[int]:
        seqs: list[int] = self._request("get", "backfilled_seqs")
        return seqs

    @property
    def pid(self) -> int | None:
        return self._host.pid

    def _request(self, op: str, *payload: Any, timeout: float | None = None) -> Any:
        host = self._host
        with host.lock:
            if self._closed:
                raise MapperLost("mapper closed")
            if host.generation != self._generation:
                raise MapperLost(f"mapper process {host.index} was restarted; this robot's map is gone")
            # a call with a timeout of its own (a scan's registration) has as many seconds of CPU
            status, result, stats, spilled = host.request(
                (op, self._mid, *payload), self.call_timeout if timeout is None else timeout,
                patience=self.call_timeout, budget=timeout)
            if stats is not None:  # (under the lock: a map query's reply must not undo a newer one's)
                self._stats = stats
        if self._spill is not None:
            for seqs, poses in spilled:
                self._spill(seqs, poses)
        if status != "ok":
            raise result
        return result

    def _call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self._request("call", method, args, kwargs)

    def _call_within(self, timeout: float, method: str, *args: Any) -> Any:
        return self._request("call", method, args, {}, timeout=timeout)

    def register(self, seq: int, points: np.ndarray, times: np.ndarray | None = None) -> Registration:
        reg: Registration = self._call_within(self.register_timeout, "register", seq, points, times)
        return reg

    def map_cloud(self) -> np.ndarray:
        cloud: np.ndarray = self._call("map_cloud")
        return cloud

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        seqs, poses = self._call("trajectory")
        return seqs, poses

    def continue_from(self, checkpoint: wire.Checkpoint | None, local_seqs: np.ndarray,
                      local_poses: np.ndarray, backfill: Sequence[tuple[int, np.ndarray]] = (),
                      backfill_poses: np.ndarray | None = None) -> bool:
        return bool(self._call("continue_from", checkpoint, local_seqs, local_poses, list(backfill),
                               backfill_poses))

    def checkpoint(self, robot: str, edge: str, epoch: int, stamp: float, resolution: float | None = None,
                   final: bool = False, coded: bool = True) -> wire.Checkpoint | None:
        cp: wire.Checkpoint | None = self._call("checkpoint", robot, edge, epoch, stamp, resolution, final,
                                                coded)
        return cp

    def predict_from(self, seq: int, prior_seq: int, pose: np.ndarray, delta: np.ndarray,
                     contest: bool = False, frame: int = -1) -> bool:
        return bool(self._call_within(self.register_timeout, "predict_from", seq, prior_seq, pose, delta,
                                      contest, frame))

    def close(self) -> None:
        """Free the mapper in its process (the robot was evicted; its map exported before)."""
        host = self._host
        with host.lock:
            if self._closed:
                return
            self._closed = True
            if host.generation != self._generation:
                return
            host.hosted -= 1
            try:
                host.request(("drop", self._mid), self.call_timeout)
            except MapperLost:
                pass


class MapperPool:
    """The edge's ``MapperFactory`` with every robot's mapper in one of ``processes`` processes
    (see the module docstring)."""

    def __init__(self, recipe: MapperRecipe, processes: int, call_timeout: float = 30.0,
                 start_timeout: float = 120.0, register_timeout: float = 5.0) -> None:
        if processes < 1:
            raise ValueError("a mapper pool needs at least one process")
        if min(call_timeout, register_timeout, start_timeout) <= 0:
            raise ValueError("a mapper pool's timeouts must be positive")
        self.recipe = recipe
        self.call_timeout = call_timeout
        self.register_timeout = register_timeout
        self.hosts = [_Host(recipe, i, start_timeout) for i in range(processes)]
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._started = False

    def warm_up(self) -> None:
        """Start every process and wait until each has loaded its mapper (in parallel)."""
        with self._lock:
            if self._started:
                return
            self._started = True
            for h in self.hosts:
                h.start()
        for h in self.hosts:
            with h.lock:
                try:
                    h.wait_ready()
                except MapperLost as exc:  # started again on its first request
                    log.error("%s", exc)
        log.info("%d mapper processes ready (pids %s)", len(self.hosts), [h.pid for h in self.hosts])

    def __call__(self, scan: wire.Scan, spill: Spill | None = None) -> ProcessMapper:
        self.warm_up()
        with self._lock:
            host = min(self.hosts, key=lambda h: (h.hosted, h.index))
            mid = next(self._ids)
        new = ("new", mid, scan.robot, scan.max_range, scan.voxel_max)
        with host.lock:
            try:
                status, result, _, _ = host.request(new, self.call_timeout)
            except MapperLost:  # found dead (it died idle): started again, nothing of ours was lost there
                status, result, _, _ = host.request(new, self.call_timeout)
            if status != "ok":
                raise result
            host.hosted += 1
            return ProcessMapper(host, mid, spill, self.call_timeout, self.register_timeout)

    def status(self) -> dict[str, float]:
        return {"mapper_processes": float(len(self.hosts)),
                "mapper_restarts": float(sum(h.restarts for h in self.hosts)),
                "mapper_slow_calls": float(sum(h.slow_calls for h in self.hosts))}

    def close(self) -> None:
        for h in self.hosts:
            h.close()



def main() -> None:
    """A mapper process: ``python -m zoffload.edge.isolate FD INDEX`` (started by ``_Host``)."""
    logging.basicConfig(level=logging.INFO,
                        format=f"%(asctime)s %(levelname)s %(name)s [mapper {sys.argv[2]}]: %(message)s")
    conn = Connection(int(sys.argv[1]))
    try:
        recipe = conn.recv()
    except (EOFError, OSError):
        return
    _serve(conn, recipe)


if __name__ == "__main__":
    main()
