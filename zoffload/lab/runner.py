"""Running zoffload programs as child processes: shared by ``zoffload demo`` and the experiments."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from zoffload.protocol import wire
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import EdgeSettings, RobotSettings, ZenohSettings
from zoffload.runtime.lifecycle import wait_in_slices
from zoffload.runtime.loading import EDGE_ENV, ROBOT_ENV, environment_values, load_settings, write_effective
from zoffload.runtime.maps import fetch_map
from zoffload.runtime.session import free_tcp_port, loopback_endpoint, open_session


class Spawned:
    """A zoffload program in its own process, with its output in a log file."""

    def __init__(self, name: str, args: list[str], log_path: Path, cpus: set[int] | None = None) -> None:
        # ``cpus``: the cores it may run on, set by taskset (util-linux) before it starts Python,
        # so every thread it ever makes inherits them
        pin = ["taskset", "-c", ",".join(map(str, sorted(cpus)))] if cpus else []
        if pin and shutil.which("taskset") is None:
            raise StartError("taskset (util-linux) is needed to run processes on given cores")
        self.name = name
        self.log_path = log_path
        self._log = open(log_path, "w")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen([*pin, sys.executable, "-m", "zoffload.cli", *args],
                                     stdout=self._log, stderr=subprocess.STDOUT, env=env)

    def running(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return int(self.proc.returncode)

    def tail(self, n: int = 15) -> str:
        return "".join(self.log_path.read_text().splitlines(keepends=True)[-n:])


def connect_when_listening(z: ZenohSettings, owner: Spawned, timeout: float = 60) -> zenoh.Session | None:
    """Open a session once ``owner`` listens (its port opens a moment after it starts)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not owner.running():
            return None
        try:
            return open_session(z)
        except Exception:
            time.sleep(0.3)
    return None


def wait_token(session: zenoh.Session, key: str, timeout: float,
               alive: Callable[[], bool] | None = None) -> bool:
    """Wait for a liveliness token on ``key``; with ``alive``, give up as soon as it says the process
    that should declare it has gone (an edge that could not listen exits at once, and a peer session
    opens even when its connect is refused, so only the process's exit tells)."""
    seen = threading.Event()
    sub = session.liveliness().declare_subscriber(key, lambda s: seen.set(), history=True)
    try:
        return wait_in_slices(seen, timeout, 0.2, None if alive is None else lambda: not alive())
    finally:
        sub.undeclare()


class StatusWatcher:
    """Keeps the latest status values of one robot (or, with ``edge``, of that edge), for progress
    lines and soak samples. ``replace``: each status replaces the values (an edge's per-robot
    entries come and go) instead of updating them."""

    def __init__(self, session: zenoh.Session, keys: Keys, robot: str | None = None, edge: str | None = None,
                 replace: bool = False) -> None:
        if (robot is None) == (edge is None):
            raise ValueError("watch one robot or one edge")
        self.values: dict[str, float] = {}
        self.replace = replace
        key = keys.robot_status(robot) if robot is not None else keys.edge_status(edge or "")
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            msg = wire.decode(sample.payload.to_bytes(), expect=wire.Status)
        except wire.WireError:
            return
        if self.replace:
            self.values = dict(msg.values)
        else:
            self.values.update(msg.values)

    def close(self) -> None:
        self._sub.undeclare()


def progress_line(st: dict[str, float], elapsed: float, total: int) -> str:
    """A scan run's progress from the robot's status values; the robot's current voxel (status
    ``voxel``: the newest scan's grid, or a skip's), "raw" when 0 (no grid: the rate policy on a
    link that carries whole scans), "–" before the first scan sent."""
    voxel = st.get("voxel", 0.0)
    grid = "–" if not st.get("published") else f"{voxel:.2f} m" if voxel > 0 else "raw"
    return (
        f"[{elapsed:5.1f} s] scans {int(st.get('published', 0))}/{total} sent, "
        f"{int(st.get('acked', 0))} acked, {int(st.get('lost', 0))} lost | "
        f"voxel {grid} | T {st.get('last_T', 0):.3f} s | "
        f"CPU {st.get('cpu_ms', float('nan')):.1f} ms | "
        f"RTT {st.get('rtt_ms', float('nan')):.0f} ms | map {int(st.get('map_points', 0)):,} pts"
    )


def frames_line(st: dict[str, float], elapsed: float, total: int) -> str:
    """Progress of a camera run (the image offloader's status values)."""
    return (
        f"[{elapsed:5.1f} s] frames {int(st.get('frames_in', 0))}/{total} | local "
        f"{int(st.get('local_done', 0))}, edge {int(st.get('edge_done', 0))}, dropped "
        f"{int(st.get('dropped_camera', 0) + st.get('dropped_stale', 0) + st.get('dropped_window', 0))}, "
        f"lost {int(st.get('edge_lost', 0))} | "
        f"CPU {st.get('cpu_process', float('nan')):.0f} % | {st.get('mbps_out', float('nan')):.0f} Mbps"
        f"{' | FALLBACK' if st.get('fallback') else ''}"
    )


def watch(robot_p: Spawned, status: StatusWatcher, total: int, limit_s: float,
          line: Callable[[dict[str, float], float, int], str] = progress_line) -> int:
    """Show progress until the robot process exits; returns its exit code."""
    tty = sys.stdout.isatty()
    start = time.monotonic()
    next_plain = start
    while robot_p.proc.poll() is None:
        time.sleep(0.25)
        elapsed = time.monotonic() - start
        text = line(status.values, elapsed, total)
        if tty:
            print("\r" + text.ljust(120), end="", flush=True)
        elif time.monotonic() >= next_plain:
            print(text, flush=True)
            next_plain = time.monotonic() + 5
        if elapsed > limit_s:
            print("\nthe robot did not finish in time; stopping it")
            robot_p.stop()
    if tty:
        print()
    return int(robot_p.proc.returncode)


def link_clock_start(log: Path) -> float | None:
    """Wall time at which ``zoffload link`` started its trace clock (its first connection)."""
    for line in log.read_text().splitlines() if log.exists() else []:
        if line.startswith("clock") and "wall_start=" in line:
            return float(line.split("wall_start=")[1])
    return None


# The robot's TCP send buffer behind the emulator: small, so a slow link reaches Zenoh's congestion
# control instead of hiding megabytes in the kernel.
ROBOT_SNDBUF = 65536


class StartError(RuntimeError):
    """The edge process did not start or did not announce itself."""


@dataclass
class OffloadRun:
    robot_code: int
    reply: wire.MapReply | None
    cut_short: bool


def loopback_zenoh(**kw: Any) -> ZenohSettings:
    """Session settings for local runs: explicit endpoints, no multicast scouting, no shared memory
    (same-host shared memory would carry payloads around any emulated link)."""
    return ZenohSettings(multicast_scouting=False, shared_memory=False, **kw)


START_ATTEMPTS = 3  # an edge that did not come up is started again, on other ports


def edge_apart_cores(cpus: set[int] | None = None) -> dict[str, set[int]]:
    """The cores of a run with the edge on one of its own (the highest) and the robot and the link
    emulator on the others, as on separate computers (``run_offload``'s ``cpus``); {} with fewer
    than two cores to split."""
    cores = sorted(cpus if cpus is not None else os.sched_getaffinity(0))
    if len(cores) < 2:
        return {}
    rest = set(cores[:-1])
    return {"edge": {cores[-1]}, "robot": rest, "link": rest}


def run_offload(out: Path, edge: EdgeSettings, robot: RobotSettings, trace: str | None,
                link_args: list[str], total: int, limit_s: float, keep_interrupted: bool = False,
                line: Callable[[dict[str, float], float, int], str] = progress_line,
                fetch: bool = True, on_watch: Callable[[zenoh.Session], None] | None = None,
                cpus: Mapping[str, set[int]] | None = None) -> OffloadRun:
    """Edge, link emulator (unless ``trace`` is None) and robot as separate processes on loopback,
    the edge started again on other ports (``START_ATTEMPTS`` in all) when it does not come up: the
    robot has not started then, so nothing of the run is lost (a port can be taken between the
    moment it is picked and the moment the edge listens). ``cpus``: the cores each process
    ("edge", "robot", "link") may run on (``edge_apart_cores``; a process not named: any). See
    ``run_offload_once``."""
    for attempt in range(1, START_ATTEMPTS + 1):
        try:
            return run_offload_once(out, edge, robot, trace, link_args, total, limit_s, keep_interrupted,
                                    line, fetch, on_watch, cpus)
        except StartError as exc:
            if attempt == START_ATTEMPTS:
                raise
            first = str(exc).splitlines()[0]
            print(f"start {attempt} of {START_ATTEMPTS} failed ({first}); again on other ports", flush=True)
    raise AssertionError("unreachable")


def environment_settings(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The settings ``ZOFFLOAD_ROBOT__*`` / ``ZOFFLOAD_EDGE__*`` variables set (``environ``, else
    os.environ): the daemons a run starts inherit them over the settings the run writes, so a run's
    row records them, validated (``{"robot": {"perception": {"overflow": false}}}``: ``false``,
    ``False`` and ``0`` alike; {} for none). A variable naming no setting, or a value its setting
    refuses, is a ConfigError."""
    found: dict[str, Any] = {}
    for side, cls, prefix in (("robot", RobotSettings, ROBOT_ENV), ("edge", EdgeSettings, EDGE_ENV)):
        raw = environment_values(cls, prefix, environ)
        if raw:
            valid = load_settings(cls, env_prefix=prefix, environ=environ).model_dump(mode="json")
            found[side] = _pick(raw, valid)
    return found


def _pick(keys: Mapping[str, Any], values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` restricted to the nested keys of ``keys`` (a section set whole stays whole)."""
    return {k: _pick(v, values[k]) if isinstance(v, Mapping) and isinstance(values.get(k), Mapping)
            else values.get(k) for k, v in keys.items()}


def run_offload_once(out: Path, edge: EdgeSettings, robot: RobotSettings, trace: str | None,
                     link_args: list[str], total: int, limit_s: float, keep_interrupted: bool = False,
                     line: Callable[[dict[str, float], float, int], str] = progress_line,
                     fetch: bool = True,
                     on_watch: Callable[[zenoh.Session], None] | None = None,
                     cpus: Mapping[str, set[int]] | None = None) -> OffloadRun:
    """Edge, link emulator (unless ``trace`` is None) and robot as separate processes on loopback.

    The edge listens; the robot connects through the emulator in client mode (a peer could learn
    the edge's own address and connect around it); this process watches over a direct session and
    fetches the map at the end. The Zenoh settings of ``edge`` and ``robot`` are set here. With
    ``keep_interrupted``, Ctrl-C stops the robot gracefully (it writes its records) and the run
    returns with ``cut_short``; otherwise the interrupt propagates after the processes are stopped.
    """
    edge_port, link_port = free_tcp_port(), free_tcp_port()
    edge = edge.model_copy(update={"zenoh": loopback_zenoh(listen=[loopback_endpoint(edge_port)])})
    direct = loopback_zenoh(connect=[loopback_endpoint(edge_port)])
    robot_z = direct if trace is None else loopback_zenoh(
        mode="client", connect=[loopback_endpoint(link_port)],
        cfg=[f"transport/link/tcp/so_sndbuf:{ROBOT_SNDBUF}"])
    robot = robot.model_copy(update={"zenoh": robot_z})
    write_effective(edge, out / "edge.yaml")
    write_effective(robot, out / "robot.yaml")
    keys = Keys(robot.namespace)
    cpus = cpus or {}
    edge_p = Spawned("edge", ["edge", "--settings", str(out / "edge.yaml")], out / "edge.log",
                     cpus.get("edge"))
    link_p = None
    if trace is not None:
        link_p = Spawned("link", ["link", "--trace", trace, "--listen-port", str(link_port), "--target",
                                  f"127.0.0.1:{edge_port}", "--report", str(out / "link.csv"), *link_args],
                         out / "link.log", cpus.get("link"))
    robot_p: Spawned | None = None
    try:
        session = connect_when_listening(direct, edge_p)
        if session is None:
            raise StartError("the edge did not start:\n" + edge_p.tail())
        with session:
            status = StatusWatcher(session, keys, robot.robot_id)
            if on_watch is not None:  # e.g. the live view, on this watching session
                on_watch(session)
            if not wait_token(session, keys.any_edge_alive(), 30, alive=edge_p.running):
                raise StartError("the edge did not come up:\n" + edge_p.tail())
            robot_p = Spawned("robot", ["robot", "--settings", str(out / "robot.yaml")], out / "robot.log",
                              cpus.get("robot"))
            cut_short = False
            try:
                code = watch(robot_p, status, total, limit_s, line)
            except KeyboardInterrupt:
                if not keep_interrupted:
                    raise
                print("\ninterrupted: stopping the robot and writing what was measured", flush=True)
                cut_short = True
                code = robot_p.stop()
            if code != 0:
                print(f"\nthe robot exited with code {code}:\n" + robot_p.tail())
            # from the edge it started, by name (a wildcard query reaches no edge under the ACL)
            reply = (fetch_map(session, keys, robot.robot_id, [edge.edge_id], timeout=20.0)
                     if fetch and (code == 0 or keep_interrupted) else None)
            status.close()
    finally:
        if robot_p is not None:
            robot_p.stop()
        if link_p is not None:
            link_p.stop()
        edge_code = edge_p.stop()
    if edge_code != 0:
        print(f"the edge exited with code {edge_code}:\n" + edge_p.tail())
    return OffloadRun(code, reply, cut_short)


@contextlib.contextmanager
def sigterm_interrupts() -> Iterator[None]:
    """SIGTERM raises KeyboardInterrupt while the runs go (as Ctrl-C does), so the ``finally`` that
    stops the child processes runs; SIGTERM's default would leave them running. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
