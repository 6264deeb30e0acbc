"""``zoffload experiment soak``: the edge and the robot (and its camera, when the models and images
are there) as separate processes for a long time, their resources sampled every ``period`` seconds.

Each sample: per process (psutil on the child's pid) RSS, threads, open file descriptors and CPU
(% of one core over the period), plus the counters both daemons publish in their status (robot:
produced, published, acked, lost, in flight, frames; edge: samples, registered, drops, robots, map
points). Written to ``soak.csv`` as they come, plotted to ``soak.png``, summarised in
``soak.json``: each process's RSS growth after ``warmup`` (the map budget filling) as a fraction
of its RSS then, and again from the time the robot's record rings are full (``rings_full_s``:
``keep_records`` scans, ``keep_frames`` frames: memory the robot is meant to fill); each RSS
figure is the median of a window of samples (up to 5 minutes), not one sample, because the
periodic heap trim makes RSS saw-toothed. Also the thread and fd ranges after warmup and the
robot's counters balanced. The
robot replays its scans forth and back (``pingpong``: a continuous drive, where a loop would jump
from the last scan to the first and derail the edge's odometry once a lap) at ``rate_hz``, and
the camera its images in a loop, so the run is as long as asked.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from zoffload.lab.proctree import TreeCpu, tree_resources
from zoffload.lab.runner import (
    Spawned,
    StatusWatcher,
    connect_when_listening,
    loopback_zenoh,
    sigterm_interrupts,
    wait_token,
)
from zoffload.protocol.keys import Keys
from zoffload.runtime.config import DetectorSettings, EdgeSettings, PerceptionSettings, RobotSettings
from zoffload.runtime.loading import write_effective
from zoffload.runtime.session import free_tcp_port, loopback_endpoint

PROCESS_FIELDS = ("rss_mb", "threads", "fds", "cpu_pct")
ROBOT_COUNTERS = ("produced", "published", "acked", "lost", "in_flight", "edge_dropped", "edge_error",
                  "frames_in", "edge_done", "local_done")
EDGE_COUNTERS = ("samples", "registered", "drops", "robots", "map_points", "detector.served")


@dataclass(frozen=True)
class SoakOptions:
    duration: float
    out: Path
    period: float = 10.0
    rate_hz: float = 10.0
    camera: str = "auto"  # "auto", "on", "off"
    fps: float = 5.0
    warmup: float = 300.0
    scans: str = "sim"
    map_budget: int | None = None  # the edge's global map budget per robot; None: its default


@dataclass
class SoakSummary:
    duration_s: float
    samples: int
    warmup_s: float
    camera: bool
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    rss_growth: dict[str, float] = field(default_factory=dict)  # fraction after warmup
    rss_mb: dict[str, tuple[float, float]] = field(default_factory=dict)  # at warmup, at the end
    rings_full_s: float | None = None  # when the robot's record rings are full (None: after the run)
    rss_growth_full: dict[str, float] = field(default_factory=dict)  # fraction after rings_full_s
    rss_mb_full: dict[str, tuple[float, float]] = field(default_factory=dict)
    rss_max_mb: dict[str, float] = field(default_factory=dict)  # after warmup
    threads: dict[str, tuple[int, int]] = field(default_factory=dict)  # min, max after warmup
    fds: dict[str, tuple[int, int]] = field(default_factory=dict)
    balanced: bool | None = None
    balance: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(c == 0 for c in self.exit_codes.values()) and self.balanced is not False

    def line(self) -> str:
        parts = [f"soak {self.duration_s:.0f} s, {self.samples} samples (growth after {self.warmup_s:.0f} s)"]
        for name in self.rss_growth:
            a, b = self.rss_mb[name]
            full = ""
            if name in self.rss_growth_full:
                fa, fb = self.rss_mb_full[name]
                full = (f" (rings full at {self.rings_full_s:.0f} s: {fa:.0f} -> {fb:.0f} MB, "
                        f"{100 * self.rss_growth_full[name]:+.1f} %)")
            parts.append(f"{name}: RSS {a:.0f} -> {b:.0f} MB ({100 * self.rss_growth[name]:+.1f} %){full}, "
                         f"threads {self.threads[name][0]}-{self.threads[name][1]}, "
                         f"fds {self.fds[name][0]}-{self.fds[name][1]}")
        parts.append(f"robot balanced: {self.balanced}; exit codes {self.exit_codes}")
        return " | ".join(parts)


def _camera_available() -> bool:
    try:
        from zoffload.detect.models import resolve
        from zoffload.sources.images import open_image_source

        resolve("nanodet-m")
        resolve("picodet-s")
        open_image_source("coco-clips")
    except Exception:  # any missing piece: the soak runs without the camera
        return False
    return True


class _Probe:
    """CPU, memory, threads and fds of one child process and the processes it started (the edge's
    mapper processes: lab/proctree.py)."""

    def __init__(self, pid: int) -> None:
        import psutil

        self.proc = psutil.Process(pid)
        self._tree = TreeCpu(self.proc)
        self._cpu = self._tree.read()
        self._t = time.monotonic()

    def sample(self) -> dict[str, float]:
        import psutil

        try:
            cpu = self._tree.read()
            values = tree_resources(self.proc)
        except psutil.Error:
            return {}
        now = time.monotonic()
        values["cpu_pct"] = 100.0 * (cpu - self._cpu) / max(now - self._t, 1e-6)
        self._cpu, self._t = cpu, now
        return values


def run_soak(opts: SoakOptions) -> SoakSummary:
    out = opts.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    camera = opts.camera == "on" or (opts.camera == "auto" and _camera_available())
    port = free_tcp_port()
    edge = EdgeSettings(map_dir=str(out / "maps"),
                        zenoh=loopback_zenoh(listen=[loopback_endpoint(port)]),
                        detector=DetectorSettings(enabled=True if camera else False))
    if opts.map_budget:
        mapper = edge.mapper.model_copy(update={"map_budget": opts.map_budget})
        edge = edge.model_copy(update={"mapper": mapper})
    robot = RobotSettings(scans=opts.scans, replay="pingpong", rate_hz=opts.rate_hz,
                          out_dir=str(out / "robot"), wait_edge=30,
                          zenoh=loopback_zenoh(connect=[loopback_endpoint(port)]))
    if camera:
        robot = robot.model_copy(update={"images": "coco-clips", "perception": PerceptionSettings(
            encoding="jpeg", fps=opts.fps, replay="loop")})
    write_effective(edge, out / "edge.yaml")
    write_effective(robot, out / "robot.yaml")
    keys = Keys(robot.namespace)
    warmup = opts.warmup if opts.warmup < opts.duration else opts.duration / 4
    print(f"soak: {opts.duration:g} s, robot at {opts.rate_hz:g} Hz{' + camera' if camera else ''}, "
          f"a sample every {opts.period:g} s, results in {out}", flush=True)
    edge_p = Spawned("edge", ["edge", "--settings", str(out / "edge.yaml")], out / "edge.log")
    robot_p: Spawned | None = None
    rows: list[dict[str, float]] = []
    codes: dict[str, int | None] = {}
    try:
        with sigterm_interrupts():  # SIGTERM stops the daemons and writes what was measured, as Ctrl-C
            session = connect_when_listening(loopback_zenoh(connect=[loopback_endpoint(port)]), edge_p)
            if session is None or not wait_token(session, keys.any_edge_alive(), 60, alive=edge_p.running):
                raise RuntimeError("the edge did not start:\n" + edge_p.tail())
            with session:
                robot_status = StatusWatcher(session, keys, robot.robot_id)
                edge_status = StatusWatcher(session, keys, edge=edge.edge_id, replace=True)
                robot_p = Spawned("robot", ["robot", "--settings", str(out / "robot.yaml")],
                                  out / "robot.log")
                probes = {"edge": _Probe(edge_p.proc.pid), "robot": _Probe(robot_p.proc.pid)}
                rows = _sample_loop(opts, out, probes, robot_status, edge_status, [edge_p, robot_p])
                robot_status.close()
    except KeyboardInterrupt:
        print("\ninterrupted: stopping the daemons and writing what was measured", flush=True)
    finally:
        if robot_p is not None:
            codes["robot"] = robot_p.stop(60)
        codes["edge"] = edge_p.stop(120)
    summary = _summarise(rows, opts, warmup, camera, codes, out)
    (out / "soak.json").write_text(json.dumps(asdict(summary), indent=2))
    if rows:
        plot_soak(out / "soak.png", rows, warmup)
    return summary


def _sample_loop(opts: SoakOptions, out: Path, probes: dict[str, _Probe], robot_status: StatusWatcher,
                 edge_status: StatusWatcher, procs: list[Spawned]) -> list[dict[str, float]]:
    columns = ["t"] + [f"{p}.{f}" for p in probes for f in PROCESS_FIELDS] + \
        [f"robot.{c}" for c in ROBOT_COUNTERS] + [f"edge.{c}" for c in EDGE_COUNTERS]
    rows: list[dict[str, float]] = []
    start = time.monotonic()
    with open(out / "soak.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        next_t = start + opts.period
        while True:
            time.sleep(max(0.0, min(1.0, next_t - time.monotonic())))
            if any(p.proc.poll() is not None for p in procs):
                print("a daemon exited early: " + ", ".join(f"{p.name} {p.proc.returncode}" for p in procs),
                      flush=True)
                break
            if time.monotonic() < next_t:
                continue
            row: dict[str, float] = {"t": round(time.monotonic() - start, 1)}
            for name, probe in probes.items():
                row.update({f"{name}.{k}": v for k, v in probe.sample().items()})
            robot_values, edge_values = dict(robot_status.values), dict(edge_status.values)
            edge_values["map_points"] = sum(v for k, v in edge_values.items() if k.endswith(".map_points"))
            row.update({f"robot.{c}": robot_values[c] for c in ROBOT_COUNTERS if c in robot_values})
            row.update({f"edge.{c}": edge_values[c] for c in EDGE_COUNTERS if c in edge_values})
            rows.append(row)
            w.writerow(row)
            f.flush()
            print(" | ".join(f"{k} {v:.0f}" if isinstance(v, float) else f"{k} {v}"
                             for k, v in row.items() if k.endswith(("t", "rss_mb", "threads", "acked"))),
                  flush=True)
            next_t += opts.period
            if row["t"] >= opts.duration:
                break
    return rows


def _summarise(rows: list[dict[str, float]], opts: SoakOptions, warmup: float, camera: bool,
               codes: dict[str, int | None], out: Path) -> SoakSummary:
    s = SoakSummary(duration_s=rows[-1]["t"] if rows else 0.0, samples=len(rows), warmup_s=warmup,
                    camera=camera, exit_codes=codes)
    after = [r for r in rows if r["t"] >= warmup] or rows
    full = rings_full(opts, camera)
    late = [r for r in rows if r["t"] >= full]
    s.rings_full_s = full if len(late) >= 4 else None
    for name in ("edge", "robot"):
        rss = [r[f"{name}.rss_mb"] for r in after if f"{name}.rss_mb" in r]
        if not rss:
            continue
        s.rss_mb[name] = growth_window(rss, opts.period)
        s.rss_growth[name] = (s.rss_mb[name][1] - s.rss_mb[name][0]) / s.rss_mb[name][0]
        s.rss_max_mb[name] = max(rss)
        late_rss = [r[f"{name}.rss_mb"] for r in late if f"{name}.rss_mb" in r]
        if s.rings_full_s is not None and len(late_rss) >= 4:
            s.rss_mb_full[name] = growth_window(late_rss, opts.period)
            a, b = s.rss_mb_full[name]
            s.rss_growth_full[name] = (b - a) / a
        threads = [int(r[f"{name}.threads"]) for r in after if f"{name}.threads" in r]
        fds = [int(r[f"{name}.fds"]) for r in after if f"{name}.fds" in r]
        s.threads[name] = (min(threads), max(threads))
        s.fds[name] = (min(fds), max(fds))
    metrics = out / "robot" / "robot_metrics.json"
    if metrics.exists():
        m = json.loads(metrics.read_text())
        s.balanced, s.balance = m.get("balanced"), m.get("balance", {})
    return s


def rings_full(opts: SoakOptions, camera: bool) -> float:
    """Seconds until the robot's in-memory record rings are full at the soak's rates (scans,
    and frames when the camera runs): its RSS is meant to grow until then."""
    from zoffload.robot.camera import CameraOptions
    from zoffload.robot.scans import StreamOptions

    full = StreamOptions.keep_records / opts.rate_hz
    if camera and opts.fps > 0:
        full = max(full, CameraOptions.keep_frames / opts.fps)
    return full


def growth_window(rss: list[float], period: float, window: float = 300.0) -> tuple[float, float]:
    """(median RSS of the first ``window`` seconds, of the last): RSS saw-tooths between heap
    trims, so one sample at each end would measure where in a tooth it fell. The window shrinks
    to a quarter of the series when that is shorter."""
    import statistics

    n = max(1, min(int(window / period), len(rss) // 4))
    return statistics.median(rss[:n]), statistics.median(rss[-n:])


def plot_soak(path: Path, rows: list[dict[str, float]], warmup: float) -> Path:
    """Six panels over time: RSS, threads, fds, CPU of each process, the robot's scan counters and
    the edge's map size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [r["t"] / 60 for r in rows]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8), sharex=True)
    labels = ("RSS [MB]", "threads", "open fds", "CPU [%]")
    for ax, field_, label in zip(axes.flat[:4], PROCESS_FIELDS, labels, strict=True):
        for name in ("edge", "robot"):
            ax.plot(t, [r.get(f"{name}.{field_}", float("nan")) for r in rows], label=name)
        ax.set_ylabel(label)
        ax.axvline(warmup / 60, color="0.7", ls="--", lw=1)
        ax.legend(loc="best")
    for c in ("published", "acked", "lost"):
        axes[1, 1].plot(t, [r.get(f"robot.{c}", float("nan")) for r in rows], label=c)
    axes[1, 1].set_ylabel("robot scans")
    axes[1, 1].legend(loc="best")
    axes[1, 2].plot(t, [r.get("edge.map_points", float("nan")) for r in rows])
    axes[1, 2].set_ylabel("edge map points")
    for ax in axes[1]:
        ax.set_xlabel("minutes")
    fig.suptitle("zoffload soak")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
